// @vbusd/core's layered sockets (web/core/src/layers.js, spec/virtual-bones.md 8.4 with 8.6 and
// 23.4) on a plain scene `vbusd view` writes (vbusd/web/scene.py): for tests/test_layered_sockets.py.
// CASES.json is [{animation, bone, clip, tau, fade: {clip, tau, weight} | null, layers: [{clip, tau,
// weight, mask, mode, reference}] | null, streams: {clipMask, time, weight, sceneTime} | absent}] (streams:
// one instance's per-instance layer streams as the runtimes write them, decoded by layersOfStreams); prints {joints: [[16 numbers, column-major] per case]}, each
// the joint transform in animation space (no instance placement).
// Usage: node layered_sockets.mjs SCENE.json SCENE.bin CASES.json
import fs from 'node:fs';
import { parsePlainScene, layeredJointElements, layersOfStreams } from '../../web/core/src/index.js';

const [sceneFile, bufferFile, casesFile] = process.argv.slice(2);
const bytes = fs.readFileSync(bufferFile);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const scene = parsePlainScene(JSON.parse(fs.readFileSync(sceneFile, 'utf8')), buffer);
const cases = JSON.parse(fs.readFileSync(casesFile, 'utf8'));
const joints = cases.map((c) => {
  const animation = scene.animations[c.animation];
  const source = { name: animation.name, layout: animation.layout, texels: animation.texels };
  const layers = c.streams ? layersOfStreams(c.streams.clipMask, c.streams.time, c.streams.weight, 0, c.streams.sceneTime) : c.layers;
  return layeredJointElements(source, c.bone, c.clip, c.tau, c.fade, layers);
});
process.stdout.write(JSON.stringify({ joints }));
