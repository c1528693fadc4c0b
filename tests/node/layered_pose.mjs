// A masked override layer as three.js blends it (GLTFLoader + AnimationMixer + SkinnedMesh): the
// oracle of tests/test_layers.py for spec/virtual-bones.md 8.6 (layers and bone masks).
//
// The base clip plays at weight 1 on the bones outside the mask. On the masked bones three.js'
// PropertyMixer accumulates, by normalized weight, the base clip's tracks at weight 1 - w and the
// layer clip's tracks at weight w (the layer clip with every track outside the mask removed), so a
// masked bone's position and scale are lerped and its quaternion slerped by w: the override.
// Output: {joints: [node index...], poses: [{matrices: [[16 numbers, column-major]...],
//          meshes: [{positions: [x, y, z, ...]}]}]} with joint world matrices and skinned vertex
// positions in world space (SkinnedMesh.applyBoneTransform, then the mesh's world matrix).
// Usage: node layered_pose.mjs FILE.gltf|FILE.glb SKIN BASE_CLIP LAYER_CLIP MASKED_JOINTS WEIGHT
//        BASE_TIME:LAYER_TIME [...]   (MASKED_JOINTS: comma-separated indices into the skin's joints)
import fs from 'node:fs';
import path from 'node:path';
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';

globalThis.ProgressEvent ??= class ProgressEvent extends Event {
  constructor(type, init = {}) { super(type); Object.assign(this, init); }
};
globalThis.self ??= globalThis;
console.error = () => {};
console.warn = () => {};
const [fileArg, skinArg, baseName, layerName, maskedArg, weightArg, ...timeArgs] = process.argv.slice(2);
const file = path.resolve(fileArg);
const bytes = fs.readFileSync(file);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const gltf = await new GLTFLoader().parseAsync(buffer, 'file://' + path.dirname(file) + '/');
const joints = gltf.parser.json.skins[Number(skinArg)].joints;
const objects = await Promise.all(joints.map((node) => gltf.parser.getDependency('node', node)));
const masked = new Set(maskedArg === '' ? [] : maskedArg.split(',').map((i) => objects[Number(i)].uuid));
const weight = Number(weightArg);

function clipNamed(name) {
  const clip = gltf.animations.find((c) => c.name === name);
  if (!clip) throw new Error(`no animation ${name}`);
  return clip;
}
// A track's target object, resolved as the mixer resolves it (PropertyBinding on the scene).
function targetOf(track) {
  const parsed = THREE.PropertyBinding.parseTrackName(track.name);
  return THREE.PropertyBinding.findNode(gltf.scene, parsed.nodeName);
}
function part(clip, name, inMask) {
  const tracks = clip.tracks.filter((t) => masked.has(targetOf(t)?.uuid) === inMask);
  return new THREE.AnimationClip(name, clip.duration, tracks);
}
const base = clipNamed(baseName);
const layer = clipNamed(layerName);
const mixer = new THREE.AnimationMixer(gltf.scene);
const actions = [
  [mixer.clipAction(part(base, 'base.rest', false)), 1, 0],
  [mixer.clipAction(part(base, 'base.masked', true)), 1 - weight, 0],
  [mixer.clipAction(part(layer, 'layer.masked', true)), weight, 1],
];
for (const [action, w] of actions) {
  action.setLoop(THREE.LoopRepeat, Infinity);
  action.setEffectiveWeight(w);
  action.play();
}
const skinned = [];
gltf.scene.traverse((object) => { if (object.isSkinnedMesh && object.skeleton.bones.length === joints.length) skinned.push(object); });
const poses = [];
for (const pair of timeArgs) {
  const times = pair.split(':').map(Number);
  for (const [action, , which] of actions) action.time = times[which];
  mixer.update(0);
  gltf.scene.updateMatrixWorld(true);
  const meshes = skinned.map((mesh) => {
    mesh.skeleton.update();
    const position = mesh.geometry.attributes.position;
    const out = new Float64Array(position.count * 3);
    const v = new THREE.Vector3();
    for (let i = 0; i < position.count; i++) {
      v.fromBufferAttribute(position, i);
      mesh.applyBoneTransform(i, v);
      v.applyMatrix4(mesh.matrixWorld);
      out[3 * i] = v.x; out[3 * i + 1] = v.y; out[3 * i + 2] = v.z;
    }
    return { positions: Array.from(out) };
  });
  poses.push({ matrices: objects.map((object) => Array.from(object.matrixWorld.elements)), meshes });
}
process.stdout.write(JSON.stringify({ joints, poses }));
