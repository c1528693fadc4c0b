// A baked Virtual Bones animation on Babylon's engine: its texture (a RawTexture of the stored
// texels: NEAREST, no mipmaps, no flip, row r = scanline r), its clip table, ranges, rig texture
// and clock. The arrays come from @vbusd/core (checked against the layout there).

import { RawTexture, Constants } from '@babylonjs/core';
import {
  VirtualBonesError, checkLayout, widenWords, clipTable, unormRanges, compactRanges, rigTexels,
} from '@vbusd/core';

// Babylon's texture format and type per texel format. unorm16 is RGBA16_EXT of WebGL 2's
// EXT_texture_norm16 (Babylon's TEXTUREFORMAT_RGBA16_UNORM); the compact encoding's words are
// widened to RGBA32UI (A = 0) and read with texelFetch from a usampler2D.
const TEXTURES = {
  float16: { format: Constants.TEXTUREFORMAT_RGBA, type: Constants.TEXTURETYPE_HALF_FLOAT },
  float32: { format: Constants.TEXTUREFORMAT_RGBA, type: Constants.TEXTURETYPE_FLOAT },
  unorm16: { format: 32859, type: Constants.TEXTURETYPE_UNSIGNED_SHORT },  // Engine.TEXTUREFORMAT_RGBA16_UNORM
  uint32: { format: Constants.TEXTUREFORMAT_RGBA_INTEGER, type: Constants.TEXTURETYPE_UNSIGNED_INTEGER },
};

function rawTexture(scene, data, width, height, { format, type }, name) {
  // Data, not colour: NEAREST, no mipmaps, no flip (invertY false keeps row r at texel row r).
  const texture = new RawTexture(data, width, height, format, scene, false, false, Constants.TEXTURE_NEAREST_SAMPLINGMODE, type);
  texture.name = name;
  texture.wrapU = texture.wrapV = Constants.TEXTURE_CLAMP_ADDRESSMODE;
  return texture;
}

/**
 * One Virtual Bones texture on a Babylon scene.
 *
 * `layout` is the layout metadata (spec "Layout metadata"); `texels` the stored values, scanline
 * 0 first (Uint16Array of float16 bits or unorm16 integers, Float32Array, or the compact
 * encoding's Uint32Array of three words per texel). Every encoding and texel format; unorm16 needs
 * EXT_texture_norm16, and where the browser lacks it the constructor says so in one line, naming
 * the alternative.
 */
export class VirtualBonesAnimation {
  constructor(scene, { layout, texels, clipExtents = null, name = '' }) {
    const facts = checkLayout(layout, texels, name);
    if (layout.texelFormat === 'unorm16' && !scene.getEngine().getCaps().textureNorm16) {
      throw new VirtualBonesError(`${name || 'animation'}: this unorm16 texture needs the WebGL extension `
        + 'EXT_texture_norm16, which this browser does not offer; convert the asset with --texel-format float16 or float32');
    }
    this.name = name;
    this.layout = layout;
    this.encoding = facts.encoding;
    this.texelFormat = facts.texelFormat;
    this.texelsPerBone = facts.texelsPerBone;
    this.maxClips = facts.maxClips;
    this.maxBones = facts.maxBones;
    this.masks = facts.masks;
    this.clips = layout.clips;
    this.clipExtents = clipExtents;
    this.texels = texels;  // as stored: the CPU decoder (sockets) reads them
    const data = layout.texelFormat === 'uint32' ? widenWords(layout, texels) : texels;
    this.texture = rawTexture(scene, data, layout.width, layout.height, TEXTURES[layout.texelFormat], `${name} (Virtual Bones)`);
    this.clipTable = clipTable(this.clips, this.maxClips);
    if (layout.texelFormat === 'unorm16') this.ranges = unormRanges(layout);
    if (layout.texelFormat === 'uint32') this.compactRanges = compactRanges(layout, this.maxBones);
    const rig = rigTexels(layout);  // format 1.2 layers: bind transforms, parents, masks
    this.rigTexture = rig ? rawTexture(scene, rig.data, rig.width, rig.height, TEXTURES.float32, `${name} (rig)`) : null;
    /** Scene time in seconds (vb_time): every material skinned from this animation reads it. */
    this.time = 0;
    /** Scene time of the previous frame (vb_previousTime, spec 21): VirtualBonesCrowd.updatePrevious sets it. */
    this.previousTime = -1 / 60;
  }

  /** Index of the clip named `name`, or -1. */
  clipIndex(name) { return this.clips.findIndex((clip) => clip.name === name); }

  /** Index of the bone mask called `name` (format 1.2), or -1. */
  maskIndex(name) { return this.masks.indexOf(name); }

  dispose() {
    this.texture.dispose();
    this.rigTexture?.dispose();
  }
}
