// Loads a mesh file with three.js's own loaders (GLTFLoader; OBJLoader with MTLLoader) and says what it got, so
// tests can hold splatzoo's mesh files to what three.js-based web viewers read.
//   await window.loadMesh({url, mtl}) -> {meshes, vertices, triangles, uvs, textured, textureSize, meanTexel}
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OBJLoader } from "three/addons/loaders/OBJLoader.js";
import { MTLLoader } from "three/addons/loaders/MTLLoader.js";

// The mean colour of a texture image (0..1 per channel), read back through a 2D canvas.
function meanColour(image) {
  const canvas = document.createElement("canvas");
  canvas.width = image.width;
  canvas.height = image.height;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(image, 0, 0);
  const data = ctx.getImageData(0, 0, image.width, image.height).data;
  const sum = [0, 0, 0];
  for (let i = 0; i < data.length; i += 4) for (let c = 0; c < 3; c++) sum[c] += data[i + c];
  const n = data.length / 4;
  return sum.map((s) => s / n / 255);
}

// Waits until every texture's image has arrived (OBJ materials load their maps after the OBJ resolves).
async function texturesLoaded(root, timeoutMs = 20000) {
  const start = performance.now();
  for (;;) {
    let pending = false;
    root.traverse((o) => {
      if (!o.isMesh) return;
      for (const m of [].concat(o.material)) {
        if (m && m.map && !(m.map.image && m.map.image.width > 0)) pending = true;
      }
    });
    if (!pending) return;
    if (performance.now() - start > timeoutMs) throw new Error("texture image did not load");
    await new Promise((r) => setTimeout(r, 20));
  }
}

function summary(root) {
  const out = { meshes: 0, vertices: 0, triangles: 0, uvs: true, textured: false, textureSize: null, meanTexel: null };
  root.traverse((o) => {
    if (!o.isMesh) return;
    const g = o.geometry;
    out.meshes += 1;
    out.vertices += g.attributes.position.count;
    out.triangles += (g.index ? g.index.count : g.attributes.position.count) / 3;
    out.uvs = out.uvs && Boolean(g.attributes.uv);
    for (const m of [].concat(o.material)) {
      if (m && m.map && m.map.image) {
        out.textured = true;
        out.textureSize = [m.map.image.width, m.map.image.height];
        out.meanTexel = meanColour(m.map.image);
      }
    }
  });
  return out;
}

window.loadMesh = async ({ url, mtl }) => {
  let root;
  if (url.toLowerCase().endsWith(".glb") || url.toLowerCase().endsWith(".gltf")) {
    root = (await new GLTFLoader().loadAsync(url)).scene;
  } else {
    const loader = new OBJLoader();
    if (mtl) {
      const materials = await new MTLLoader().loadAsync(mtl);
      materials.preload();
      loader.setMaterials(materials);
    }
    root = await loader.loadAsync(url);
  }
  await texturesLoaded(root);
  return summary(root);
};
window.meshReady = true;
void THREE;
