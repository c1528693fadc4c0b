// Check a vbusd runtime package (.glb or .gltf) with the Khronos glTF-Validator and load it with
// three.js's GLTFLoader, then print what each found as JSON for tests/test_gltf_package.py.
// Usage: node gltf_check.mjs FILE.glb|FILE.gltf
import crypto from 'node:crypto';
import fs from 'node:fs';
import path from 'node:path';
import validator from 'gltf-validator';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { KTX2Loader } from 'three/examples/jsm/loaders/KTX2Loader.js';

const file = path.resolve(process.argv[2]);
const folder = path.dirname(file);
const bytes = new Uint8Array(fs.readFileSync(file));
const result = {};

result.validator = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 0,
  externalResourceFunction: (uri) => new Promise((resolve, reject) => {
    try { resolve(new Uint8Array(fs.readFileSync(path.join(folder, decodeURIComponent(uri))))); }
    catch (error) { reject(error.toString()); }
  }),
});

// GLTFLoader fetches external buffers; Node's fetch has no file: scheme, so serve the folder (and
// give FileLoader the DOM's ProgressEvent, which Node lacks).
globalThis.ProgressEvent ??= class ProgressEvent extends Event {
  constructor(type, init = {}) { super(type); Object.assign(this, init); }
};
const nodeFetch = globalThis.fetch;
globalThis.fetch = async (request, ...rest) => {
  const url = typeof request === 'string' ? request : request.url;
  if (!url.startsWith('file:')) return nodeFetch(request, ...rest);  // zstddec's data: URL wasm
  const name = decodeURIComponent(new URL(url).pathname);
  const data = fs.readFileSync(name);
  return new Response(data, { status: 200 });
};

const sha256 = (u8) => crypto.createHash('sha256').update(u8).digest('hex');
const attributeInfo = (attribute) => ({
  arrayType: attribute.array.constructor.name, itemSize: attribute.itemSize, count: attribute.count,
  normalized: attribute.normalized, instanced: !!attribute.isInstancedBufferAttribute,
  sha256: sha256(new Uint8Array(attribute.array.buffer, attribute.array.byteOffset, attribute.array.byteLength)),
});

const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const gltf = await new GLTFLoader().parseAsync(buffer, 'file://' + folder + '/');
const meshes = [];
gltf.scene.updateMatrixWorld(true);
gltf.scene.traverse((object) => {
  if (!object.isMesh) return;
  const attributes = {};
  for (const [name, attribute] of Object.entries(object.geometry.attributes)) attributes[name] = attributeInfo(attribute);
  meshes.push({
    name: object.name, parent: object.parent ? object.parent.name : null, isInstancedMesh: !!object.isInstancedMesh,
    count: object.isInstancedMesh ? object.count : 1, attributes,
    index: object.geometry.index ? attributeInfo(object.geometry.index) : null,
    userData: object.userData, matrixWorld: object.matrixWorld.elements,
    instanceMatrix0: object.isInstancedMesh ? Array.from(object.instanceMatrix.array.slice(0, 16)) : null,
  });
});
const root = gltf.userData.gltfExtensions || {};
const textures = [];
for (const animation of (root.VBUSD_virtual_bones || {}).animations || []) {
  const view = await gltf.parser.getDependency('bufferView', animation.texture.bufferView);
  const u8 = new Uint8Array(view);
  const loader = new KTX2Loader();
  loader.workerConfig = { astcSupported: false, astcHDRSupported: false, etc1Supported: false,
    etc2Supported: false, dxtSupported: false, bptcSupported: false, pvrtcSupported: false };
  let texture = null;
  try {
    const t = await loader._createTexture(u8.slice().buffer);
    const data = t.mipmaps[0].data;
    texture = { width: t.image.width, height: t.image.height, type: t.type,
      sha256: sha256(new Uint8Array(data.buffer, data.byteOffset, data.byteLength)) };
  } catch (error) { texture = { error: String(error.message || error) }; }
  textures.push({ byteLength: u8.byteLength, sha256: sha256(u8), texture });
}
result.three = { rootExtensions: root, meshes, textures, sceneChildren: gltf.scene.children.map((c) => c.name) };
process.stdout.write(JSON.stringify(result));
