// A baked Virtual Bones animation on the GPU: its texture, clip table and the shader uniforms that
// every material skinned from it shares (spec/shaders.md, "Resources").

import {
  DataTexture, RGBAFormat, RGBAIntegerFormat, HalfFloatType, FloatType, UnsignedShortType, UnsignedIntType,
  NearestFilter, ClampToEdgeWrapping, NoColorSpace, Vector4, Box3, Vector3, Matrix4,
} from 'three';

import { BASE_MAX_CLIPS } from './shader-modules.js';

const TEXEL_TYPES = {
  float16: { type: HalfFloatType, array: Uint16Array, bytes: 2, channels: 4, format: RGBAFormat },
  float32: { type: FloatType, array: Float32Array, bytes: 4, channels: 4, format: RGBAFormat },
  unorm16: { type: UnsignedShortType, array: Uint16Array, bytes: 2, channels: 4, format: RGBAFormat },
  // Format 1.2 (spec 9.4): the compact encoding's three words per texel, read with texelFetch from
  // a usampler2D, never filtered; uploaded widened to RGBA32UI (A = 0): three's RGB32UI upload read
  // back as zeros in Chromium (measured, SwiftShader WebGL 2), RGBA32UI is color-renderable and
  // sampled everywhere.
  uint32: { type: UnsignedIntType, array: Uint32Array, bytes: 4, channels: 3, format: RGBAIntegerFormat },
};

const ENCODINGS = { crossMatrix: 3, affineMatrix: 3, quatTranslation: 2, dualQuat: 2, compactQuatTranslation: 1 };

/** Bones the compact module's range uniforms hold unless an animation needs more (VB_MAX_BONES). */
export const BASE_MAX_BONES = 64;

/** An error in the data handed to the runtime, or a browser that cannot run it. */
export class VirtualBonesError extends Error {
  constructor(message) {
    super(`vbusd: ${message}`);
    this.name = 'VirtualBonesError';
  }
}

/**
 * One Virtual Bones texture with its layout metadata.
 *
 * `layout` is the layout metadata dict (the texture's sidecar JSON, spec "Layout metadata");
 * `texels` holds the stored texel values, scanline 0 first: a Uint16Array of float16 bits
 * (float16), a Float32Array (float32) or a Uint16Array of 16-bit integers (unorm16).
 * `clipExtents` is optional: per clip [[minX, minY, minZ], [maxX, maxY, maxZ]] of the skinned
 * meshes (vb:clipExtents), used for frustum culling.
 */
export class VirtualBonesAnimation {
  constructor({ layout, texels, clipExtents = null, name = '' }) {
    const texelType = TEXEL_TYPES[layout.texelFormat];
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
    this.name = name;
    this.layout = layout;
    this.encoding = layout.encoding;
    this.texelFormat = layout.texelFormat;
    this.texelsPerBone = texelsPerBone;
    this.clips = layout.clips;
    this.clipExtents = clipExtents;

    let data = texels;
    if (layout.texelFormat === 'uint32') {  // widen R, G, B words to RGBA with A = 0
      data = new Uint32Array(layout.width * layout.height * 4);
      for (let i = 0, n = layout.width * layout.height; i < n; ++i) {
        data[4 * i] = texels[3 * i];
        data[4 * i + 1] = texels[3 * i + 1];
        data[4 * i + 2] = texels[3 * i + 2];
      }
    }
    const texture = new DataTexture(data, layout.width, layout.height, texelType.format, texelType.type);
    if (layout.texelFormat === 'uint32') texture.internalFormat = 'RGBA32UI';
    // Data, not colour: no colour conversion, no mipmaps, no filtering, no flip (row r = scanline r).
    texture.colorSpace = NoColorSpace;
    texture.generateMipmaps = false;
    texture.minFilter = texture.magFilter = NearestFilter;
    texture.wrapS = texture.wrapT = ClampToEdgeWrapping;
    texture.flipY = false;
    texture.unpackAlignment = 1;
    texture.normalized = layout.texelFormat === 'unorm16';  // unorm16: RGBA16_EXT of EXT_texture_norm16
    texture.needsUpdate = true;
    this.texture = texture;

    this.maxClips = Math.max(BASE_MAX_CLIPS, this.clips.length);
    const clipTable = [];
    for (let i = 0; i < this.maxClips; ++i) {
      const clip = this.clips[i];
      clipTable.push(clip ? new Vector4(clip.firstRow, clip.rowCount, clip.rowsPerSecond, clip.loop ? 1 : 0)
        : new Vector4(0, 1, 1, 0));
    }
    // Shared by reference with every patched material: setting `time` moves them all.
    this.uniforms = {
      vb_texture: { value: texture },
      vb_time: { value: 0 },
      vb_clips: { value: clipTable },
    };
    this.masks = (layout.masks ?? []).map((mask) => mask.name);
    if (layout.masks && layout.boneParents && layout.bindTransforms) {
      this.rigTexture = rigTexture(layout);
      this.uniforms.vb_rig = { value: this.rigTexture };
    }
    if (layout.texelFormat === 'unorm16') {
      const ranges = layout.unormRanges;  // [slot][channel] = [min, max]
      this.uniforms.vb_rangeMin = { value: ranges.map((slot) => new Vector4(...slot.map((r) => r[0]))) };
      this.uniforms.vb_rangeMax = { value: ranges.map((slot) => new Vector4(...slot.map((r) => r[1]))) };
    }
    this.maxBones = Math.max(BASE_MAX_BONES, layout.boneCount);
    if (layout.texelFormat === 'uint32') {
      // Per bone (spec 5.6.3): q min, q max, (t min, 0), (t max, 0); the array is VB_MAX_BONES long.
      const ranges = layout.compactRanges;  // [bone][k][min, max], k = qx qy qz qw tx ty tz
      const value = [];
      for (let b = 0; b < this.maxBones; ++b) {
        const r = ranges[b];
        if (!r) { value.push(new Vector4(), new Vector4(), new Vector4(), new Vector4()); continue; }
        value.push(new Vector4(r[0][0], r[1][0], r[2][0], r[3][0]), new Vector4(r[0][1], r[1][1], r[2][1], r[3][1]),
          new Vector4(r[4][0], r[5][0], r[6][0], 0), new Vector4(r[4][1], r[5][1], r[6][1], 0));
      }
      this.uniforms.vb_compactRange = { value };
    }
  }

  /** Scene time in seconds: instance clip-local time is timeOffset + playbackRate * time. */
  get time() { return this.uniforms.vb_time.value; }

  set time(seconds) { this.uniforms.vb_time.value = seconds; }

  /** Index of the clip called `name`, or -1. */
  clipIndex(name) { return this.clips.findIndex((clip) => clip.name === name); }

  /**
   * Bounds covering every pose of the given clips (union of their vb:clipExtents), or null when
   * the asset has no extents.
   */
  boundsOfClips(clipIndices) {
    if (!this.clipExtents) return null;
    const box = new Box3();
    for (const index of clipIndices) {
      const extent = this.clipExtents[index];
      if (!extent) return null;
      box.expandByPoint(new Vector3(...extent[0]));
      box.expandByPoint(new Vector3(...extent[1]));
    }
    return box;
  }

  /**
   * Throw a clear error where the browser cannot sample this texture: unorm16 needs WebGL 2's
   * EXT_texture_norm16 (16-bit normalized formats are not core WebGL 2).
   */
  checkSupport(renderer) {
    if (!renderer.capabilities.isWebGL2) throw new VirtualBonesError('Virtual Bones needs WebGL 2 (texelFetch, integer attributes)');
    if (this.texelFormat === 'unorm16' && !renderer.extensions.has('EXT_texture_norm16')) {
      throw new VirtualBonesError(`${this.name || 'animation'}: this unorm16 texture needs the WebGL extension `
        + 'EXT_texture_norm16, which this browser does not offer; convert the asset with --texel-format float16 or float32');
    }
  }

  /** Index of the bone mask called `name` (format 1.2), or -1. */
  maskIndex(name) { return this.masks.indexOf(name); }

  dispose() {
    this.texture.dispose();
    this.rigTexture?.dispose();
  }
}

/**
 * The rig texture of the layer functions (spec/shaders.md, "Layers"; vbusd.decoders.shaders.rig_texels):
 * RGBA32F, 8 texels per bone in row 0 (rows of B, rows of B^-1, (parent, 0, 0, 0), 0), then one row
 * per mask (texel b = (weight of bone b, 0, 0, 0)).
 */
export function rigTexture(layout) {
  const bones = layout.boneCount;
  const width = 8 * bones;
  const data = new Float32Array(width * (1 + layout.masks.length) * 4);
  const inverse = new Matrix4();
  layout.bindTransforms.forEach((columnMajor, b) => {
    const bind = new Matrix4().fromArray(columnMajor);
    inverse.copy(bind).invert();
    for (const [slot, m] of [[0, bind], [3, inverse]]) {
      const e = m.elements;  // column-major: row i is e[i], e[4 + i], e[8 + i], e[12 + i]
      for (let i = 0; i < 3; ++i) data.set([e[i], e[4 + i], e[8 + i], e[12 + i]], 4 * (8 * b + slot + i));
    }
    data[4 * (8 * b + 6)] = layout.boneParents[b];
  });
  layout.masks.forEach((mask, m) => mask.weights.forEach((w, b) => { data[4 * ((1 + m) * width + b)] = w; }));
  const texture = new DataTexture(data, width, 1 + layout.masks.length, RGBAFormat, FloatType);
  texture.colorSpace = NoColorSpace;
  texture.generateMipmaps = false;
  texture.minFilter = texture.magFilter = NearestFilter;
  texture.wrapS = texture.wrapT = ClampToEdgeWrapping;
  texture.flipY = false;
  texture.unpackAlignment = 1;
  texture.needsUpdate = true;
  return texture;
}
