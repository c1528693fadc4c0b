// The layout metadata of a Virtual Bones texture (spec "Layout metadata") as the arrays every
// runtime uploads: the texels checked against the layout, widened where an API needs it, the clip
// table, the unorm16 and compact ranges, and the rig texture of the layer functions.

import { BASE_MAX_CLIPS } from './shader-modules.js';
import { BASE_MAX_BONES } from './assemble.js';
import { VirtualBonesError } from './errors.js';

/** Per texel format: the typed array of its stored values and the channels a file stores. */
export const TEXEL_FORMATS = {
  float16: { array: Uint16Array, channels: 4 },
  float32: { array: Float32Array, channels: 4 },
  unorm16: { array: Uint16Array, channels: 4 },
  uint32: { array: Uint32Array, channels: 3 },  // format 1.2: the compact encoding's three words
};

/** Texels per bone of each encoding (spec "Encodings"). */
export const ENCODINGS = { crossMatrix: 3, affineMatrix: 3, quatTranslation: 2, dualQuat: 2, compactQuatTranslation: 1 };

/**
 * Check `texels` against `layout` (one clear line when they disagree) and return the facts the
 * runtimes need: {encoding, texelFormat, texelsPerBone, maxClips, maxBones, masks}.
 */
export function checkLayout(layout, texels, name = '') {
  const texelType = TEXEL_FORMATS[layout.texelFormat];
  if (!texelType) throw new VirtualBonesError(`${name}: unknown texel format ${JSON.stringify(layout.texelFormat)}`);
  const texelsPerBone = ENCODINGS[layout.encoding];
  if (!texelsPerBone) throw new VirtualBonesError(`${name}: unknown encoding ${JSON.stringify(layout.encoding)}`);
  const expected = layout.width * layout.height * texelType.channels;
  if (!(texels instanceof texelType.array) || texels.length !== expected) {
    throw new VirtualBonesError(`${name}: texels must be a ${texelType.array.name} of ${expected} values `
      + `(${layout.width} x ${layout.height} ${'RGBA'.slice(0, texelType.channels)}), got ${texels?.constructor?.name} of ${texels?.length}`);
  }
  if ((layout.encoding === 'compactQuatTranslation') !== (layout.texelFormat === 'uint32')) {
    throw new VirtualBonesError(`${name}: encoding compactQuatTranslation and texel format uint32 go together, `
      + `got ${layout.encoding} with ${layout.texelFormat}`);
  }
  return {
    encoding: layout.encoding,
    texelFormat: layout.texelFormat,
    texelsPerBone,
    maxClips: Math.max(BASE_MAX_CLIPS, layout.clips.length),
    maxBones: Math.max(BASE_MAX_BONES, layout.boneCount),
    masks: (layout.masks ?? []).map((mask) => mask.name),
  };
}

/** The compact encoding's R, G, B words widened to RGBA with A = 0 (RGBA32UI is sampled everywhere). */
export function widenWords(layout, texels) {
  const n = layout.width * layout.height;
  const data = new Uint32Array(n * 4);
  for (let i = 0; i < n; ++i) {
    data[4 * i] = texels[3 * i];
    data[4 * i + 1] = texels[3 * i + 1];
    data[4 * i + 2] = texels[3 * i + 2];
  }
  return data;
}

/** vb_clips: (firstRow, rowCount, rowsPerSecond, loop) per clip, padded to `maxClips` with (0, 1, 1, 0). */
export function clipTable(clips, maxClips) {
  const table = new Float32Array(4 * maxClips);
  for (let i = 0; i < maxClips; ++i) {
    const clip = clips[i];
    table.set(clip ? [clip.firstRow, clip.rowCount, clip.rowsPerSecond, clip.loop ? 1 : 0] : [0, 1, 1, 0], 4 * i);
  }
  return table;
}

/** vb_rangeMin / vb_rangeMax of a unorm16 texture: per slot a vec4 of channel minima and maxima. */
export function unormRanges(layout) {
  const slots = layout.unormRanges;  // [slot][channel] = [min, max]
  const min = new Float32Array(4 * slots.length);
  const max = new Float32Array(4 * slots.length);
  slots.forEach((slot, s) => slot.forEach((range, c) => { min[4 * s + c] = range[0]; max[4 * s + c] = range[1]; }));
  return { min, max };
}

/**
 * vb_compactRange (format 1.2, spec 5.6.3): per bone q min, q max, (t min, 0), (t max, 0), four
 * vec4 for each of `maxBones` bones (zeros past the layout's).
 */
export function compactRanges(layout, maxBones) {
  const ranges = layout.compactRanges;  // [bone][k][min, max], k = qx qy qz qw tx ty tz
  const out = new Float32Array(16 * maxBones);
  ranges.forEach((r, b) => {
    out.set([r[0][0], r[1][0], r[2][0], r[3][0], r[0][1], r[1][1], r[2][1], r[3][1],
      r[4][0], r[5][0], r[6][0], 0, r[4][1], r[5][1], r[6][1], 0], 16 * b);
  });
  return out;
}

/** Rows [a0, a1, a2] (three rows of four) of the inverse of an affine transform given as rows. */
export function affineInverseRows([a0, a1, a2]) {
  const cross = (u, v) => [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
  const c0 = cross(a1, a2);
  const c1 = cross(a2, a0);
  const c2 = cross(a0, a1);
  const det = a0[0] * c0[0] + a0[1] * c0[1] + a0[2] * c0[2];
  const t = [a0[3], a1[3], a2[3]];
  return [0, 1, 2].map((i) => {
    const r = [c0[i] / det, c1[i] / det, c2[i] / det];
    return [...r, -(r[0] * t[0] + r[1] * t[1] + r[2] * t[2])];
  });
}

/**
 * The rig texture of the layer functions (spec/shaders.md, "Layers"; vbusd.decoders.shaders.rig_texels):
 * RGBA32F, 8 texels per bone in row 0 (rows of B, rows of B^-1, (parent, 0, 0, 0), 0), then one row
 * per mask (texel b = (weight of bone b, 0, 0, 0)). Returns {width, height, data}, or null when the
 * layout stores no masks, parents or bind transforms.
 */
export function rigTexels(layout) {
  if (!((layout.masks || layout.blendSpaces) && layout.boneParents && layout.bindTransforms)) return null;
  const bones = layout.boneCount;
  const width = 8 * bones;
  const masks = layout.masks ?? [];
  // Format 1.3: with blend spaces, mask index masks.length weighs every bone (spec 23.1, 23.7).
  const height = 1 + masks.length + (layout.blendSpaces ? 1 : 0);
  const data = new Float32Array(width * height * 4);
  layout.bindTransforms.forEach((e, b) => {  // column-major: row i is e[i], e[4 + i], e[8 + i], e[12 + i]
    const rows = [0, 1, 2].map((i) => [e[i], e[4 + i], e[8 + i], e[12 + i]]);
    const inverse = affineInverseRows(rows);
    rows.forEach((row, i) => data.set(row, 4 * (8 * b + i)));
    inverse.forEach((row, i) => data.set(row, 4 * (8 * b + 3 + i)));
    data[4 * (8 * b + 6)] = layout.boneParents[b];
  });
  masks.forEach((mask, m) => mask.weights.forEach((w, b) => { data[4 * ((1 + m) * width + b)] = w; }));
  if (layout.blendSpaces) for (let b = 0; b < bones; ++b) data[4 * ((1 + masks.length) * width + b)] = 1;
  return { width, height, data };
}
