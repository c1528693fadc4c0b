// The three.js runtime's CPU sockets and root motion (web/src/sockets.js) on a conformance vector,
// for tests/test_conformance_browser.py: prints {sockets: [time][instance][bone][16 column-major]}
// and, when a root-track JSON is given, {rootMotion: [[16 numbers] per (t0, t1) pair]}.
// Usage: node runtime_sockets.mjs VECTOR.json [ROOT_TRACK.json]
import fs from 'node:fs';
import { VirtualBonesAnimation } from '../../web/src/animation.js';
import { socketMatrix, rootMotionMatrix } from '../../web/src/sockets.js';

const vector = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
const layout = { ...vector.layout };
layout.bindTransforms = vector.bindTransforms.map((m) => [0, 1, 2, 3].flatMap((c) => m.map((row) => row[c])));
const arrays = { float16: Uint16Array, float32: Float32Array, unorm16: Uint16Array };
let texels = vector.texels;
if (layout.texelFormat === 'float16') {
  const half = new Uint16Array(new Float32Array(texels).length);
  const f32 = new Float32Array(1);
  const u32 = new Uint32Array(f32.buffer);
  texels.forEach((value, i) => {  // exact: every stored value is a binary16
    f32[0] = value;
    const bits = u32[0];
    const sign = (bits >>> 16) & 0x8000;
    const exponent = ((bits >>> 23) & 0xff) - 127 + 15;
    const mantissa = bits & 0x7fffff;
    if (value === 0) half[i] = sign;
    else if (exponent <= 0) half[i] = sign | ((mantissa | 0x800000) >> (14 - exponent));
    else half[i] = sign | (exponent << 10) | (mantissa >> 13);
  });
  texels = half;
} else if (layout.texelFormat === 'uint32') {  // format 1.2: the three words per texel
  texels = new Uint32Array(texels);
} else {
  texels = new arrays[layout.texelFormat](texels);
}
const animation = new VirtualBonesAnimation({ layout, texels, name: vector.vector });
const sockets = vector.expected.map(({ time }) => vector.instances.map((inst) => layout.bones.map((_, bone) => Array.from(
  socketMatrix(animation, bone, inst.clip, inst.timeOffset + inst.playbackRate * time,
    { clip: inst.fadeClip, tau: inst.fadeTimeOffset + inst.fadePlaybackRate * time, weight: inst.fadeWeight }).elements))));
const out = { sockets };
if (process.argv[3]) {
  const root = JSON.parse(fs.readFileSync(process.argv[3], 'utf8'));
  const rootAnimation = { clips: root.clips };
  out.rootMotion = root.pairs.map(([t0, t1]) => Array.from(rootMotionMatrix(rootAnimation, root.rootMotion, 0, t0, t1).elements));
}
process.stdout.write(JSON.stringify(out));
