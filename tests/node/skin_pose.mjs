// Pose a glTF with three.js (GLTFLoader + AnimationMixer + SkinnedMesh CPU skinning) and print
// every mesh's world-space vertex positions at given times, as JSON, for
// tests/test_real_characters_gltf.py. What three.js shows: GLTFLoader renormalizes skin weights
// (SkinnedMesh.normalizeSkinWeights), meshes of nodes under joints follow them through the scene
// graph, morph targets are applied with their weights.
// Output: {animations, poses: [{time, meshes: {name: [x, y, z, ...]}, byNode: {"node:primitive": [...]}}]}.
// Usage: node skin_pose.mjs FILE.gltf|FILE.glb ANIMATION_NAME|#INDEX|- T0 [T1 ...]
import fs from 'node:fs';
import path from 'node:path';
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';

// GLTFLoader decodes data: URIs with fetch and reports progress with the DOM's ProgressEvent,
// which Node lacks.
globalThis.ProgressEvent ??= class ProgressEvent extends Event {
  constructor(type, init = {}) { super(type); Object.assign(this, init); }
};
const file = path.resolve(process.argv[2]);
const clipName = process.argv[3];
const times = process.argv.slice(4).map(Number);
const bytes = fs.readFileSync(file);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
// Geometry only: Node has no image decoder, so textures are not loaded (a plugin answering
// loadTexture first, as GLTFLoader's own extensions do).
const loader = new GLTFLoader().register(() => ({ name: 'vbusd_no_textures', loadTexture: () => Promise.resolve(null) }));
const gltf = await loader.parseAsync(buffer, 'file://' + path.dirname(file) + '/');
const scene = gltf.scene;
const mixer = new THREE.AnimationMixer(scene);
if (clipName !== '-') {
  const clip = clipName.startsWith('#') ? gltf.animations[Number(clipName.slice(1))]
    : gltf.animations.find((c) => c.name === clipName);
  if (!clip) throw new Error(`no animation ${clipName}`);
  const action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;
  action.play();
}
const poses = [];
const vertex = new THREE.Vector3();
for (const t of times) {
  mixer.setTime(t);
  scene.updateMatrixWorld(true);
  const meshes = {};
  const byNode = {};
  scene.traverse((object) => {
    if (!object.isMesh) return;
    const count = object.geometry.attributes.position.count;
    const out = new Array(count * 3);
    for (let i = 0; i < count; i++) {
      object.getVertexPosition(i, vertex);   // morph targets and (SkinnedMesh) bone transforms
      vertex.applyMatrix4(object.matrixWorld);
      out[3 * i] = vertex.x; out[3 * i + 1] = vertex.y; out[3 * i + 2] = vertex.z;
    }
    meshes[object.name] = out;
    // "node:primitive" of the glTF (GLTFLoader's associations; a multi-primitive mesh is a group
    // of meshes under the node's object).
    const own = gltf.parser.associations.get(object) || {};
    const parent = object.parent ? gltf.parser.associations.get(object.parent) || {} : {};
    const node = own.nodes !== undefined ? own.nodes : parent.nodes;
    byNode[`${node}:${own.primitives !== undefined ? own.primitives : 0}`] = out;
  });
  poses.push({ time: t, meshes, byNode });
}
process.stdout.write(JSON.stringify({ animations: gltf.animations.map((c) => c.name), poses }));
