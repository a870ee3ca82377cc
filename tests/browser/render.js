// Render one splat PLY in a third-party three.js viewer (Spark or GaussianSplats3D) from a splatzoo camera and return
// the frame as a PNG data URL. Used by tests/browser_viewers.py; one render per page load keeps the viewers' global
// state (workers, caches) from leaking between renders.
//
// camera: {world_to_camera: 4x4 (nested rows or 16 numbers, row-major), fx, fy, cx, cy, width, height, near?, far?}
//   in splatzoo's (OpenCV) convention: camera axes +x right, +y down, +z forward; pixel (i, j) covers [j, j+1] x
//   [i, i+1], so cx = width / 2 is the image centre. three.js cameras look down -z with +y up: the camera's world
//   matrix is the inverse of world_to_camera times diag(1, -1, -1), and the projection matrix is built from the
//   intrinsics (off-centre cx, cy included), never from a field of view.
// background: [r, g, b] in [0, 1], written to the canvas as is (display values, no colour-space conversion).
// options: viewer settings. spark: SparkRenderer options (blurAmount, preBlurAmount, sortRadial, enable2DGS, ...)
//   plus `mesh` (SplatMesh options, e.g. {extSplats: true}). gs3d: DropInViewer options (antialiased, kernel2DSize,
//   splatRenderMode, ...) plus `scene` (addSplatScene options).
import * as THREE from "three";

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function rows4(m) {
  const flat = Array.isArray(m[0]) ? m.flat() : Array.from(m);
  if (flat.length !== 16 || flat.some((v) => !Number.isFinite(v))) {
    throw new Error("camera.world_to_camera must be a 4x4 matrix of finite numbers");
  }
  return flat;
}

export function makeCamera(cam) {
  const { fx, fy, cx, cy, width: W, height: H } = cam;
  for (const [k, v] of Object.entries({ fx, fy, cx, cy, width: W, height: H })) {
    if (!Number.isFinite(v)) throw new Error(`camera.${k} must be a finite number, got ${v}`);
  }
  const near = cam.near ?? 0.01;
  const far = cam.far ?? 1000.0;
  const camera = new THREE.PerspectiveCamera();
  camera.near = near;
  camera.far = far;
  // OpenCV pixel u = fx x / z + cx with the GL view (x, -y, -z): ndc_x = 2 u / W - 1, ndc_y = 1 - 2 v / H
  camera.projectionMatrix.set(
    2 * fx / W, 0, 1 - 2 * cx / W, 0,
    0, 2 * fy / H, 2 * cy / H - 1, 0,
    0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, -1, 0);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  // what viewers read besides the matrix (GaussianSplats3D culls with fov): the vertical field of view and aspect
  camera.fov = THREE.MathUtils.radToDeg(2 * Math.atan(H / (2 * fy)));
  camera.aspect = W / H;
  camera.updateProjectionMatrix = () => {};  // a viewer must not rebuild it from fov / aspect

  const worldToCamera = new THREE.Matrix4().set(...rows4(cam.world_to_camera));
  const flip = new THREE.Matrix4().makeScale(1, -1, -1);
  const cameraToWorld = worldToCamera.clone().invert().multiply(flip);
  cameraToWorld.decompose(camera.position, camera.quaternion, camera.scale);
  camera.scale.set(1, 1, 1);
  camera.updateMatrixWorld(true);
  return camera;
}

function makeRenderer(width, height, background) {
  const canvas = document.createElement("canvas");
  canvas.width = width;
  canvas.height = height;
  canvas.style.width = `${width}px`;
  canvas.style.height = `${height}px`;
  document.body.appendChild(canvas);
  const renderer = new THREE.WebGLRenderer({
    canvas, antialias: false, alpha: false, premultipliedAlpha: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(width, height, false);
  renderer.outputColorSpace = THREE.SRGBColorSpace;  // splat colours are display values: written unconverted
  const [r, g, b] = background ?? [1, 1, 1];
  renderer.setClearColor(new THREE.Color().setRGB(r, g, b, THREE.SRGBColorSpace), 1);
  return renderer;
}

async function renderSpark(url, renderer, scene, camera, options) {
  const { SparkRenderer, SplatMesh } = await import("@sparkjsdev/spark");
  const { mesh: meshOptions = {}, ...sparkOptions } = options;
  const spark = new SparkRenderer({ renderer, ...sparkOptions });
  scene.add(spark);
  const mesh = new SplatMesh({ url, ...meshOptions });
  await mesh.initialized;
  scene.add(mesh);
  // sorting runs in a worker after a frame asks for it: render until it has settled for a few frames
  let settled = 0;
  for (let i = 0; i < 400 && settled < 4; i++) {
    renderer.render(scene, camera);
    await sleep(15);
    settled = (!spark.sorting && !spark.sortDirty && spark.activeSplats > 0) ? settled + 1 : 0;
  }
  if (settled < 4) throw new Error("spark: the splats were not sorted in time");
  renderer.render(scene, camera);
  return { splats: mesh.packedSplats?.numSplats ?? mesh.numSplats };
}

async function renderGs3d(url, renderer, scene, camera, options) {
  const GS3D = await import("@mkkellogg/gaussian-splats-3d");
  const { scene: sceneOptions = {}, ...viewerOptions } = options;
  const dropIn = new GS3D.DropInViewer({
    sharedMemoryForWorkers: false,  // needs cross-origin isolation; changes nothing on screen
    sceneRevealMode: GS3D.SceneRevealMode.Instant,  // no fade-in animation
    logLevel: GS3D.LogLevel.None,
    ...viewerOptions,
  });
  await dropIn.addSplatScene(url, { showLoadingUI: false, progressiveLoad: false, ...sceneOptions });
  scene.add(dropIn);
  const viewer = dropIn.viewer;
  renderer.render(scene, camera);  // hands the camera to the viewer
  let settled = 0;
  for (let i = 0; i < 400 && settled < 4; i++) {
    if (i === 1) await viewer.runSplatSort(true, true);  // the first sort may be skipped for an unmoved camera
    if (viewer.sortPromise) await viewer.sortPromise;
    renderer.render(scene, camera);
    await sleep(15);
    settled = (i >= 1 && !viewer.sortRunning && viewer.splatRenderReady) ? settled + 1 : 0;
  }
  if (settled < 4) throw new Error("gs3d: the splats were not sorted in time");
  renderer.render(scene, camera);
  return { splats: viewer.splatMesh.getSplatCount(), rendered: viewer.splatRenderCount };
}

const VIEWERS = { spark: renderSpark, gs3d: renderGs3d };

export async function renderSplat({ url, viewer = "spark", camera, background = [1, 1, 1], options = {} }) {
  if (!VIEWERS[viewer]) throw new Error(`unknown viewer ${viewer}; known: ${Object.keys(VIEWERS).join(", ")}`);
  if (!url) throw new Error("no PLY url given");
  const threeCamera = makeCamera(camera);
  const renderer = makeRenderer(camera.width, camera.height, background);
  const scene = new THREE.Scene();
  const info = await VIEWERS[viewer](url, renderer, scene, threeCamera, options);
  const image = renderer.domElement.toDataURL("image/png");
  return { image, ...info };
}

window.renderSplat = renderSplat;
window.makeCamera = makeCamera;

const params = new URLSearchParams(window.location.search);
if (params.has("ply")) {
  window.splatResult = null;
  renderSplat({
    url: params.get("ply"),
    viewer: params.get("viewer") ?? "spark",
    camera: JSON.parse(params.get("camera")),
    background: (params.get("background") ?? "1,1,1").split(",").map(Number),
    options: JSON.parse(params.get("options") ?? "{}"),
  }).then((r) => { window.splatResult = r; }, (e) => { window.splatResult = { error: String(e && e.stack || e) }; });
}
window.splatReady = true;
