// A baked Virtual Bones animation on Babylon's engine: its texture (a RawTexture of the stored
// texels: NEAREST, no mipmaps, no flip, row r = scanline r), its clip table and its clock.

import { RawTexture, Constants } from '@babylonjs/core';

import { VirtualBonesError } from './skinning.js';
import { BASE_MAX_CLIPS } from '@vbusd/three/shader-modules';

const TEXEL_TYPES = {
  float16: { type: Constants.TEXTURETYPE_HALF_FLOAT, array: Uint16Array },
  float32: { type: Constants.TEXTURETYPE_FLOAT, array: Float32Array },
};
const ENCODINGS = { crossMatrix: 3, affineMatrix: 3, quatTranslation: 2, dualQuat: 2 };

/**
 * One Virtual Bones texture on a Babylon scene.
 *
 * `layout` is the layout metadata (spec "Layout metadata"); `texels` the stored values, scanline
 * 0 first (Uint16Array of float16 bits, or Float32Array). The Babylon runtime reads the float
 * encodings in float16 and float32; unorm16 and the compact uint32 encoding are refused with a
 * message (three.js' runtime reads them).
 */
export class VirtualBonesAnimation {
  constructor(scene, { layout, texels, name = '' }) {
    const texelType = TEXEL_TYPES[layout.texelFormat];
    if (!texelType) throw new VirtualBonesError(`${name}: texel format ${JSON.stringify(layout.texelFormat)}: the Babylon.js runtime reads float16 and float32`);
    if (!ENCODINGS[layout.encoding]) throw new VirtualBonesError(`${name}: encoding ${JSON.stringify(layout.encoding)}: the Babylon.js runtime reads ${Object.keys(ENCODINGS).join(', ')}`);
    const expected = layout.width * layout.height * 4;
    if (!(texels instanceof texelType.array) || texels.length !== expected) {
      throw new VirtualBonesError(`${name}: texels must be a ${texelType.array.name} of ${expected} values, got ${texels?.constructor?.name} of ${texels?.length}`);
    }
    this.name = name;
    this.layout = layout;
    this.encoding = layout.encoding;
    this.texelFormat = layout.texelFormat;
    this.clips = layout.clips;
    this.texels = texels;
    // Data, not colour: NEAREST, no mipmaps, no flip (invertY false keeps row r at texel row r).
    this.texture = new RawTexture(texels, layout.width, layout.height, Constants.TEXTUREFORMAT_RGBA, scene,
      false, false, Constants.TEXTURE_NEAREST_SAMPLINGMODE, texelType.type);
    this.texture.name = `${name} (Virtual Bones)`;
    this.texture.wrapU = this.texture.wrapV = Constants.TEXTURE_CLAMP_ADDRESSMODE;
    this.maxClips = Math.max(BASE_MAX_CLIPS, this.clips.length);
    this.clipTable = new Float32Array(4 * this.maxClips);
    for (let i = 0; i < this.maxClips; ++i) {
      const clip = this.clips[i];
      this.clipTable.set(clip ? [clip.firstRow, clip.rowCount, clip.rowsPerSecond, clip.loop ? 1 : 0] : [0, 1, 1, 0], 4 * i);
    }
    /** Scene time in seconds (vb_time): every material skinned from this animation reads it. */
    this.time = 0;
  }

  /** Index of the clip named `name`, or -1. */
  clipIndex(name) { return this.clips.findIndex((clip) => clip.name === name); }

  dispose() { this.texture.dispose(); }
}
