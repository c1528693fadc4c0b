// The world matrices of a glTF skin's joints at given times, as three.js computes them (GLTFLoader +
// AnimationMixer + Object3D.matrixWorld): the oracle of tests/test_sockets.py for sockets.
// Output: {joints: [node index...], poses: [{time, matrices: [[16 numbers, column-major]...]}]}.
// Usage: node joint_world.mjs FILE.gltf|FILE.glb SKIN_INDEX ANIMATION_NAME|- T0 [T1 ...]
import fs from 'node:fs';
import path from 'node:path';
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';

globalThis.ProgressEvent ??= class ProgressEvent extends Event {
  constructor(type, init = {}) { super(type); Object.assign(this, init); }
};
// Textures are irrelevant here and cannot load without a DOM: GLTFLoader reports and skips them.
globalThis.self ??= globalThis;
console.error = () => {};
console.warn = () => {};
const file = path.resolve(process.argv[2]);
const skinIndex = Number(process.argv[3]);
const clipName = process.argv[4];
const times = process.argv.slice(5).map(Number);
const bytes = fs.readFileSync(file);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const gltf = await new GLTFLoader().parseAsync(buffer, 'file://' + path.dirname(file) + '/');
const joints = gltf.parser.json.skins[skinIndex].joints;
const objects = await Promise.all(joints.map((node) => gltf.parser.getDependency('node', node)));
const mixer = new THREE.AnimationMixer(gltf.scene);
if (clipName !== '-') {
  const clip = gltf.animations.find((c) => c.name === clipName);
  if (!clip) throw new Error(`no animation ${clipName}`);
  const action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;
  action.play();
}
const poses = [];
for (const t of times) {
  mixer.setTime(t);
  gltf.scene.updateMatrixWorld(true);
  poses.push({ time: t, matrices: objects.map((object) => Array.from(object.matrixWorld.elements)) });
}
process.stdout.write(JSON.stringify({ joints, poses }));
