// Weighted, phase-synchronized and additive actions as three.js blends them (GLTFLoader +
// AnimationMixer + SkinnedMesh): the oracle of tests/test_blend_spaces.py for spec/virtual-bones.md
// section 23 (blend spaces, phase sync, additive layers).
//
// Each pose is a list of actions, started in the order given (the order PropertyMixer accumulates
// them), then the mixer advances by `advance` seconds (0: the actions' own times are the pose):
//   {clip, time, weight, timeScale?, mask?: [joint indices], additive?: {clip, time}}
// An additive action plays AnimationUtils.makeClipAdditive(clip, time, referenceClip, 1) (fps 1, so
// the reference frame is the reference time in seconds); a mask keeps only the tracks of those joints.
// Output: {poses: [{matrices: [[16 numbers, column-major] per joint], positions: [x, y, z, ...]}]}:
// joint world matrices and skinned vertex positions (SkinnedMesh.applyBoneTransform) in world space.
// Usage: node blend_pose.mjs FILE.gltf|FILE.glb SKIN POSES.json
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
const [fileArg, skinArg, posesArg] = process.argv.slice(2);
const file = path.resolve(fileArg);
const bytes = fs.readFileSync(file);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const gltf = await new GLTFLoader().parseAsync(buffer, 'file://' + path.dirname(file) + '/');
const joints = gltf.parser.json.skins[Number(skinArg)].joints;
const objects = await Promise.all(joints.map((node) => gltf.parser.getDependency('node', node)));
const poses = JSON.parse(fs.readFileSync(posesArg, 'utf8'));

function clipNamed(name) {
  const clip = gltf.animations.find((c) => c.name === name);
  if (!clip) throw new Error(`no animation ${name}`);
  return clip;
}
function targetOf(track) {
  const parsed = THREE.PropertyBinding.parseTrackName(track.name);
  return THREE.PropertyBinding.findNode(gltf.scene, parsed.nodeName);
}
const skinned = [];
gltf.scene.traverse((object) => { if (object.isSkinnedMesh && object.skeleton.bones.length === joints.length) skinned.push(object); });
const mixer = new THREE.AnimationMixer(gltf.scene);
const out = [];
let serial = 0;
for (const pose of poses) {
  const actions = pose.actions.map((spec) => {
    let clip = clipNamed(spec.clip).clone();
    if (spec.mask) {
      const keep = new Set(spec.mask.map((i) => objects[i].uuid));
      clip = new THREE.AnimationClip(clip.name, clip.duration, clip.tracks.filter((t) => keep.has(targetOf(t)?.uuid)));
    }
    if (spec.additive) {
      THREE.AnimationUtils.makeClipAdditive(clip, spec.additive.time, clipNamed(spec.additive.clip), 1);
    }
    clip.name = `${spec.clip}#${serial++}`;
    const action = mixer.clipAction(clip);
    action.setLoop(THREE.LoopRepeat, Infinity);
    action.play();
    action.setEffectiveWeight(spec.weight);
    action.setEffectiveTimeScale(spec.timeScale ?? 1);
    action.time = spec.time;
    return action;
  });
  mixer.update(pose.advance ?? 0);
  gltf.scene.updateMatrixWorld(true);
  const positions = [];
  for (const mesh of skinned) {
    mesh.skeleton.update();
    const position = mesh.geometry.attributes.position;
    const v = new THREE.Vector3();
    for (let i = 0; i < position.count; i++) {
      v.fromBufferAttribute(position, i);
      mesh.applyBoneTransform(i, v);
      v.applyMatrix4(mesh.matrixWorld);
      positions.push(v.x, v.y, v.z);
    }
  }
  out.push({ matrices: objects.map((object) => Array.from(object.matrixWorld.elements)), positions,
             times: actions.map((a) => a.time) });
  mixer.stopAllAction();
  for (const action of actions) mixer.uncacheClip(action.getClip());
}
process.stdout.write(JSON.stringify({ joints, poses: out }));
