// Render a glTF binary holding KHR_gaussian_splatting splats in the PlayCanvas engine (its own glb parser and gsplat
// renderer, WebGL2) from a splatzoo camera and return the frame as a PNG data URL. Used by tests/browser_viewers.py;
// one render per page load keeps the engine's global state (workers, caches) from leaking between renders.
//
// camera: as render.js takes it: {world_to_camera: 4x4 (row-major, OpenCV axes), fx, fy, cx, cy, width, height,
//   near?, far?}. PlayCanvas cameras look down -z with +y up, like three.js: the camera entity's world transform is
//   the inverse of world_to_camera times diag(1, -1, -1), and the projection matrix is built from the intrinsics (an
//   off-centre principal point included) through CameraComponent#calculateProjection, never from a field of view.
// background: [r, g, b] in [0, 1], the camera's clear colour, written as display values.
// options: fields of app.scene.gsplat (GSplatParams: antiAlias, minPixelSize, alphaClipForward, radialSorting, ...)
//   set before loading, plus `unified` (false: the engine's deprecated non-unified renderer).
// Colours go out as the splats hold them: gamma-space output, no tone mapping, no fog (a splat's colour is a display
// value; gsplatOutput decodes it only for tone mapping, fog or linear output).
import * as pc from "playcanvas";

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function rows4(m) {
  const flat = Array.isArray(m[0]) ? m.flat() : Array.from(m);
  if (flat.length !== 16 || flat.some((v) => !Number.isFinite(v))) {
    throw new Error("camera.world_to_camera must be a 4x4 matrix of finite numbers");
  }
  return flat;
}

// the camera's projection (column-major, as pc.Mat4 holds it): OpenCV pixel u = fx x / z + cx with the GL view
// (x, -y, -z) gives ndc_x = 2 u / W - 1, ndc_y = 1 - 2 v / H
function projection(cam, near, far) {
  const { fx, fy, cx, cy, width: W, height: H } = cam;
  const rows = [
    2 * fx / W, 0, 1 - 2 * cx / W, 0,
    0, 2 * fy / H, 2 * cy / H - 1, 0,
    0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, -1, 0];
  const m = new pc.Mat4();
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) m.data[c * 4 + r] = rows[r * 4 + c];
  return m;
}

function cameraEntity(app, cam, background) {
  const { fx, fy, cx, cy, width: W, height: H } = cam;
  for (const [k, v] of Object.entries({ fx, fy, cx, cy, width: W, height: H })) {
    if (!Number.isFinite(v)) throw new Error(`camera.${k} must be a finite number, got ${v}`);
  }
  const near = cam.near ?? 0.01;
  const far = cam.far ?? 1000.0;
  const [r, g, b] = background ?? [1, 1, 1];
  const entity = new pc.Entity("splatzoo camera");
  entity.addComponent("camera", {
    clearColor: new pc.Color(r, g, b, 1),
    nearClip: near,
    farClip: far,
    // what the engine reads besides the matrix (culling, LOD): the vertical field of view and the aspect
    fov: 2 * Math.atan(H / (2 * fy)) * 180 / Math.PI,
    aspectRatioMode: pc.ASPECT_MANUAL,
    aspectRatio: W / H,
    gammaCorrection: pc.GAMMA_SRGB,
    toneMapping: pc.TONEMAP_NONE,
  });
  const proj = projection(cam, near, far);
  entity.camera.calculateProjection = (mat) => { mat.copy(proj); };

  const w2c = rows4(cam.world_to_camera);
  const worldToCamera = new pc.Mat4();
  for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) worldToCamera.data[j * 4 + i] = w2c[i * 4 + j];
  const flip = new pc.Mat4().setScale(1, -1, -1);
  const cameraToWorld = new pc.Mat4().copy(worldToCamera).invert().mul(flip);
  entity.setPosition(cameraToWorld.getTranslation());
  entity.setRotation(new pc.Quat().setFromMat4(cameraToWorld));
  app.root.addChild(entity);
  return entity;
}

function loadContainer(app, url) {
  return new Promise((resolve, reject) => {
    app.assets.loadFromUrl(url, "container", (err, asset) => (err ? reject(new Error(String(err))) : resolve(asset)));
  });
}

export async function renderGltfSplat({ url, camera, background = [1, 1, 1], options = {} }) {
  if (!url) throw new Error("no glTF url given");
  const { unified = true, ...params } = options;
  const canvas = document.createElement("canvas");
  canvas.width = camera.width;
  canvas.height = camera.height;
  canvas.style.width = `${camera.width}px`;
  canvas.style.height = `${camera.height}px`;
  document.body.appendChild(canvas);
  const app = new pc.Application(canvas, {
    graphicsDeviceOptions: { deviceTypes: ["webgl2"], antialias: false, alpha: false, preserveDrawingBuffer: true },
  });
  app.graphicsDevice.maxPixelRatio = 1;
  app.setCanvasFillMode(pc.FILLMODE_NONE);
  app.setCanvasResolution(pc.RESOLUTION_FIXED, camera.width, camera.height);
  for (const [k, v] of Object.entries(params)) {
    if (!(k in app.scene.gsplat)) throw new Error(`unknown PlayCanvas gsplat option ${k}`);
    app.scene.gsplat[k] = v;
  }
  const cameraNode = cameraEntity(app, camera, background);
  const asset = await loadContainer(app, url);
  const splats = asset.resource.gsplats.length;
  if (!splats) {
    throw new Error("the file holds no Gaussian splats the engine reads (no KHR_gaussian_splatting primitive)");
  }
  const count = asset.resource.gsplats.reduce((n, a) => n + (a.resource?.numSplats ?? 0), 0);
  const entity = asset.resource.instantiateRenderEntity();
  entity.findComponents("gsplat").forEach((c) => { c.unified = unified; });
  app.root.addChild(entity);

  // the engine sorts in a worker and says when a frame shows everything sorted (frame:ready, unified renderer; the
  // non-unified one fires gsplat:sorted on the scene): render until that has held for a few frames
  let ready = false;
  app.systems.gsplat.on("frame:ready", (cam, layer, isReady, loading) => { ready = isReady && !loading; });
  app.scene.on("gsplat:sorted", () => { if (!unified) ready = true; });
  app.autoRender = false;
  app.start();
  let settled = 0;
  for (let i = 0; i < 400 && settled < 4; i++) {
    app.renderNextFrame = true;
    await sleep(20);
    settled = ready ? settled + 1 : 0;
  }
  if (settled < 4) throw new Error("playcanvas: the splats were not sorted in time");
  app.renderNextFrame = true;
  await sleep(40);
  const image = canvas.toDataURL("image/png");
  app.destroy();
  return { image, splats: count, primitives: splats, camera: cameraNode.name };
}

window.renderGltfSplat = renderGltfSplat;
window.gltfSplatReady = true;
