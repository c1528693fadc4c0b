// A baked Virtual Bones animation on the GPU: its texture, clip table and the shader uniforms that
// every material skinned from it shares (spec/shaders.md, "Resources").

import {
  DataTexture, RGBAFormat, RGBAIntegerFormat, HalfFloatType, FloatType, UnsignedShortType, UnsignedIntType,
  NearestFilter, ClampToEdgeWrapping, NoColorSpace, Vector4, Box3, Vector3,
} from 'three';
import {
  VirtualBonesError, BASE_MAX_BONES, checkLayout, widenWords, clipTable, unormRanges, compactRanges, rigTexels,
} from '@vbusd/core';

export { VirtualBonesError, BASE_MAX_BONES };

// three's texture type per texel format (@vbusd/core checks the texels against the layout).
const TEXTURE_TYPES = {
  float16: { type: HalfFloatType, format: RGBAFormat },
  float32: { type: FloatType, format: RGBAFormat },
  unorm16: { type: UnsignedShortType, format: RGBAFormat },
  // Format 1.2 (spec 9.4): the compact encoding's three words per texel, read with texelFetch from
  // a usampler2D, never filtered; uploaded widened to RGBA32UI (A = 0): three's RGB32UI upload read
  // back as zeros in Chromium (measured, SwiftShader WebGL 2), RGBA32UI is color-renderable and
  // sampled everywhere.
  uint32: { type: UnsignedIntType, format: RGBAIntegerFormat },
};

function dataTexture(data, width, height, format, type) {
  const texture = new DataTexture(data, width, height, format, type);
  // Data, not colour: no colour conversion, no mipmaps, no filtering, no flip (row r = scanline r).
  texture.colorSpace = NoColorSpace;
  texture.generateMipmaps = false;
  texture.minFilter = texture.magFilter = NearestFilter;
  texture.wrapS = texture.wrapT = ClampToEdgeWrapping;
  texture.flipY = false;
  texture.unpackAlignment = 1;
  texture.needsUpdate = true;
  return texture;
}

const vectors = (array) => Array.from({ length: array.length / 4 }, (_, i) => new Vector4().fromArray(array, 4 * i));

/**
 * One Virtual Bones texture with its layout metadata.
 *
 * `layout` is the layout metadata dict (the texture's sidecar JSON, spec "Layout metadata");
 * `texels` holds the stored texel values, scanline 0 first: a Uint16Array of float16 bits
 * (float16), a Float32Array (float32), a Uint16Array of 16-bit integers (unorm16) or a Uint32Array
 * of three words per texel (uint32, the compact encoding). `clipExtents` is optional: per clip
 * [[minX, minY, minZ], [maxX, maxY, maxZ]] of the skinned meshes (vb:clipExtents), used for
 * frustum culling.
 */
export class VirtualBonesAnimation {
  constructor({ layout, texels, clipExtents = null, name = '' }) {
    const facts = checkLayout(layout, texels, name);
    this.name = name;
    this.layout = layout;
    this.texels = texels;  // as stored: the CPU decoder (sockets) reads them
    this.encoding = facts.encoding;
    this.texelFormat = facts.texelFormat;
    this.texelsPerBone = facts.texelsPerBone;
    this.clips = layout.clips;
    this.clipExtents = clipExtents;
    this.maxClips = facts.maxClips;
    this.maxBones = facts.maxBones;
    this.masks = facts.masks;

    const { type, format } = TEXTURE_TYPES[layout.texelFormat];
    const data = layout.texelFormat === 'uint32' ? widenWords(layout, texels) : texels;
    const texture = dataTexture(data, layout.width, layout.height, format, type);
    if (layout.texelFormat === 'uint32') texture.internalFormat = 'RGBA32UI';
    texture.normalized = layout.texelFormat === 'unorm16';  // unorm16: RGBA16_EXT of EXT_texture_norm16
    this.texture = texture;

    // Shared by reference with every patched material: setting `time` moves them all.
    this.uniforms = {
      vb_texture: { value: texture },
      vb_time: { value: 0 },
      // The previous frame's scene time (spec 21; velocity materials and the probe read it).
      vb_previousTime: { value: -1 / 60 },
      vb_clips: { value: vectors(clipTable(this.clips, this.maxClips)) },
    };
    const rig = rigTexels(layout);
    if (rig) {
      this.rigTexture = dataTexture(rig.data, rig.width, rig.height, RGBAFormat, FloatType);
      this.uniforms.vb_rig = { value: this.rigTexture };
    }
    if (layout.texelFormat === 'unorm16') {
      const { min, max } = unormRanges(layout);
      this.uniforms.vb_rangeMin = { value: vectors(min) };
      this.uniforms.vb_rangeMax = { value: vectors(max) };
    }
    if (layout.texelFormat === 'uint32') {
      // Per bone (spec 5.6.3): q min, q max, (t min, 0), (t max, 0); the array is VB_MAX_BONES long.
      this.uniforms.vb_compactRange = { value: vectors(compactRanges(layout, this.maxBones)) };
    }
  }

  /** Scene time in seconds: instance clip-local time is timeOffset + playbackRate * time. */
  get time() { return this.uniforms.vb_time.value; }

  set time(seconds) { this.uniforms.vb_time.value = seconds; }

  /** Scene time of the previous frame (time - dt; VirtualBonesCrowd.updatePrevious sets it). */
  get previousTime() { return this.uniforms.vb_previousTime.value; }

  set previousTime(seconds) { this.uniforms.vb_previousTime.value = seconds; }

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
