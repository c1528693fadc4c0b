/**
 * VBUSD_virtual_bones for glTF-Transform (spec/runtime-package.md, proposal:
 * spec/extensions/VBUSD_virtual_bones/README.md).
 *
 * The extension reads the root object into typed properties (one `VirtualBonesAnimation` per
 * animation: name, path, layout, clip extents and the KTX2 file's bytes) and each bound mesh
 * primitive's object into a `VirtualBonesBinding` (a reference to its animation, influences,
 * path), and writes them back. Because the texture is a property holding its own bytes (not a
 * buffer view index) and the binding holds a reference (not an animation index), the standard
 * transforms (dedup, prune, weld, reorder, join, flatten, resample, instance, meshopt and Draco
 * compression) renumber accessors, buffer views and meshes freely and the extension still
 * writes a consistent package. The per-vertex skin travels as the primitive's `_VB_JOINTS_n` /
 * `_VB_WEIGHTS_n` attributes, which every glTF-Transform transform keeps in step with POSITION.
 *
 * What a transform can break, the writer refuses with one clear error naming the mesh and
 * primitive (never a silently broken skin): a quantized POSITION (quantize() and meshopt() move
 * the dequantization into the node or instance transform, which a Virtual Bones runtime would
 * apply after skinning, not before), quantized or missing skin attributes, and a crowd node
 * (EXT_mesh_gpu_instancing, e.g. made by instance()) without the per-instance `_VB_` attributes.
 * `vbusdQuantize()` and `vbusdMeshopt()` are the safe forms; `vbusdInstanceDefaults()` completes
 * batches made by instance().
 *
 *   import { NodeIO } from '@gltf-transform/core';
 *   import { VBUSDVirtualBones } from '@vbusd/gltf-transform';
 *   const io = new NodeIO().registerExtensions([VBUSDVirtualBones]);
 */

import { Extension, ExtensionProperty, PropertyType, Accessor, Format, RefMap } from '@gltf-transform/core';
import { KHRMeshQuantization } from '@gltf-transform/extensions';
import { join, quantize, reorder } from '@gltf-transform/functions';

export const VBUSD_VIRTUAL_BONES = 'VBUSD_virtual_bones';
/** The version of the extension's structure this implementation reads and writes. */
export const EXTENSION_VERSION = 1;
/** Alignment of a texture's buffer view in a GLB's BIN chunk (spec/runtime-package.md 3). */
export const TEXTURE_ALIGNMENT = 16;
const KTX2_SIGNATURE = [0xab, 0x4b, 0x54, 0x58, 0x20, 0x32, 0x30, 0xbb, 0x0d, 0x0a, 0x1a, 0x0a];
/**
 * The instance attributes a crowd node must have (spec/runtime-package.md 5), with the values of
 * a character node drawn alone (at its node, clip 0 from time 0 at rate 1).
 */
export const INSTANCE_DEFAULTS = {
  TRANSLATION: ['VEC3', [0, 0, 0]],
  ROTATION: ['VEC4', [0, 0, 0, 1]],
  _VB_CLIP: ['SCALAR', [0]],
  _VB_TIME_OFFSET: ['SCALAR', [0]],
  _VB_PLAYBACK_RATE: ['SCALAR', [1]],
};
/** quantize() pattern that leaves the attributes Virtual Bones skinning reads exact. */
export const VBUSD_QUANTIZE_PATTERN = /^(?!POSITION$|_VB_)/;

/** Raised for a document this extension cannot read or write as a working package. */
export class VirtualBonesError extends Error {
  constructor(message) {
    super(`${VBUSD_VIRTUAL_BONES}: ${message}`);
    this.name = 'VirtualBonesError';
  }
}

/** One Virtual Bones animation: its KTX2 texture (bytes), layout metadata and clip extents. */
export class VirtualBonesAnimation extends ExtensionProperty {
  init() {
    this.extensionName = VBUSD_VIRTUAL_BONES;
    this.propertyType = 'VirtualBonesAnimation';
    this.parentTypes = [];
  }

  getDefaults() {
    return Object.assign(super.getDefaults(), {
      path: null, texture: null, layout: null, clipExtents: null, buffer: null,
    });
  }

  /** The USD prim path it came from (informative), or null. */
  getPath() { return this.get('path'); }
  setPath(path) { return this.set('path', path); }
  /** The whole KTX 2.0 file, byte for byte (spec/ktx2.md). */
  getTexture() { return this.get('texture'); }
  setTexture(bytes) { return this.set('texture', bytes); }
  /** The layout metadata document (JSON object), equal to the KTX2 file's vbusd.layout. */
  getLayout() { return this.get('layout'); }
  setLayout(layout) { return this.set('layout', layout); }
  /** The layout's clips ({name, firstRow, rowCount, rowsPerSecond, loop, startTime}), in order. */
  listClips() { return this.get('layout')?.clips ?? []; }
  /** Per clip [[minX, minY, minZ], [maxX, maxY, maxZ]] in mesh space, or null. */
  getClipExtents() { return this.get('clipExtents'); }
  setClipExtents(extents) { return this.set('clipExtents', extents); }
  /** The buffer the texture's buffer view is written to (default: the document's first buffer). */
  getBuffer() { return this.getRef('buffer'); }
  setBuffer(buffer) { return this.setRef('buffer', buffer); }
}

/** The binding of one mesh primitive to an animation (meshes[m].primitives[p].extensions). */
export class VirtualBonesBinding extends ExtensionProperty {
  init() {
    this.extensionName = VBUSD_VIRTUAL_BONES;
    this.propertyType = 'VirtualBonesBinding';
    this.parentTypes = [PropertyType.PRIMITIVE];
  }

  getDefaults() {
    return Object.assign(super.getDefaults(), { animation: null, influences: 4, path: null, part: null });
  }

  getAnimation() { return this.getRef('animation'); }
  setAnimation(animation) { return this.setRef('animation', animation); }
  /** K, the bone influences per vertex: ceil(K / 4) _VB_JOINTS_n / _VB_WEIGHTS_n pairs. */
  getInfluences() { return this.get('influences'); }
  setInfluences(influences) { return this.set('influences', influences); }
  getPath() { return this.get('path'); }
  setPath(path) { return this.set('path', path); }
  /** Crowd variety (vbusd format 1.3): the optional part this primitive is (bit j of _VB_PARTS), or null. */
  getPart() { return this.get('part'); }
  setPart(part) { return this.set('part', part); }
}

/** Accessor usage of the time samples' values (written like instance attributes, grouped by node). */
const SAMPLE_VALUES = 'VBUSD_SAMPLE_VALUES';

/**
 * Time samples of a crowd node's crossfade and layer instance attributes (nodes[n].extensions,
 * spec/runtime-package.md 5.1): per attribute name, stage times in seconds and an accessor of
 * S x N floats. A reference, not an accessor index, so transforms renumber accessors freely.
 */
export class VirtualBonesSamples extends ExtensionProperty {
  init() {
    this.extensionName = VBUSD_VIRTUAL_BONES;
    this.propertyType = 'VirtualBonesSamples';
    this.parentTypes = [PropertyType.NODE];
  }

  getDefaults() {
    return Object.assign(super.getDefaults(), { times: {}, values: new RefMap() });
  }

  /** The sampled attribute names (`_VB_FADE_WEIGHT`, `_VB_LAYER_WEIGHT_0`, ...). */
  listNames() { return this.listRefMapKeys('values'); }
  /** The stage times (seconds) of attribute `name`'s samples, or null. */
  getTimes(name) { return this.get('times')[name] ?? null; }
  /** The accessor of attribute `name`'s S x N sample values, or null. */
  getValues(name) { return this.getRefMap('values', name); }
  /** Sets (or, with a null accessor, removes) attribute `name`'s samples. */
  setSamples(name, times, accessor) {
    const all = { ...this.get('times') };
    if (accessor) all[name] = Array.from(times); else delete all[name];
    this.set('times', all);
    return this.setRefMap('values', name, accessor, { usage: SAMPLE_VALUES });
  }
}

function where(mesh, primIndex) {
  return `mesh "${mesh.getName() || '(unnamed)'}" primitive ${primIndex}`;
}

/** The extension: `io.registerExtensions([VBUSDVirtualBones])`. */
export class VBUSDVirtualBones extends Extension {
  static EXTENSION_NAME = VBUSD_VIRTUAL_BONES;
  extensionName = VBUSD_VIRTUAL_BONES;
  prewriteTypes = [PropertyType.ACCESSOR, PropertyType.BUFFER];

  /** A new animation (root object entry), in the order animations are written. */
  createAnimation(name = '') {
    return new VirtualBonesAnimation(this.document.getGraph(), name);
  }

  /** A new primitive binding; attach with `prim.setExtension(VBUSD_VIRTUAL_BONES, binding)`. */
  createBinding() {
    return new VirtualBonesBinding(this.document.getGraph());
  }

  /** A new node object of time samples; attach with `node.setExtension(VBUSD_VIRTUAL_BONES, samples)`. */
  createSamples() {
    return new VirtualBonesSamples(this.document.getGraph());
  }

  /** The animations, in the order they are written. */
  listAnimations() {
    return Array.from(this.properties).filter((p) => p instanceof VirtualBonesAnimation && !p.isDisposed());
  }

  read(context) {
    const json = context.jsonDoc.json;
    const root = json.extensions?.[VBUSD_VIRTUAL_BONES];
    if (!root) return this;
    if (root === null || typeof root !== 'object' || !Array.isArray(root.animations)) {
      throw new VirtualBonesError('the root object is not an object with an "animations" array');
    }
    if (root.version !== EXTENSION_VERSION) {
      throw new VirtualBonesError(`version ${JSON.stringify(root.version)} is not ${EXTENSION_VERSION}, the version this reader knows`);
    }
    const animations = root.animations.map((def, index) => {
      const place = `animations[${index}]`;
      const view = def?.texture?.bufferView;
      const viewDef = json.bufferViews?.[view];
      if (!Number.isInteger(view) || !viewDef) throw new VirtualBonesError(`${place}.texture.bufferView ${JSON.stringify(view)} is not a buffer view`);
      // A copy: the property owns its bytes, independent of how the input buffer is cut.
      const bytes = context.bufferViews[view].slice();
      if (!KTX2_SIGNATURE.every((b, i) => bytes[i] === b)) throw new VirtualBonesError(`${place}: buffer view ${view} does not start with the KTX2 signature`);
      const animation = this.createAnimation(def.name ?? '')
        .setPath(def.path ?? null)
        .setTexture(bytes)
        .setLayout(def.layout ?? null)
        .setClipExtents(def.clipExtents ?? null)
        .setBuffer(context.buffers[viewDef.buffer] ?? null);
      if (def.extras !== undefined) animation.setExtras(def.extras);
      return animation;
    });
    this._rootExtras = root.extras;

    (json.meshes ?? []).forEach((meshDef, meshIndex) => {
      (meshDef.primitives ?? []).forEach((primDef, primIndex) => {
        const def = primDef.extensions?.[VBUSD_VIRTUAL_BONES];
        if (!def) return;
        const animation = animations[def.animation];
        if (!animation) throw new VirtualBonesError(`meshes[${meshIndex}].primitives[${primIndex}]: animation ${JSON.stringify(def.animation)} is not in the root object`);
        const binding = this.createBinding().setAnimation(animation).setInfluences(def.influences).setPath(def.path ?? null)
          .setPart(Number.isInteger(def.part) ? def.part : null);
        if (def.extras !== undefined) binding.setExtras(def.extras);
        context.meshes[meshIndex].listPrimitives()[primIndex].setExtension(VBUSD_VIRTUAL_BONES, binding);
      });
    });

    // Crowd nodes' time samples (spec/runtime-package.md 5.1).
    (json.nodes ?? []).forEach((nodeDef, nodeIndex) => {
      const def = nodeDef.extensions?.[VBUSD_VIRTUAL_BONES];
      if (!def) return;
      const samples = this.createSamples();
      for (const [name, entry] of Object.entries(def.samples ?? {})) {
        const accessor = context.accessors[entry?.values];
        if (!accessor || !Array.isArray(entry.times)) throw new VirtualBonesError(`nodes[${nodeIndex}]: the samples of ${name} name no accessor ${JSON.stringify(entry?.values)} with times`);
        samples.setSamples(name, entry.times, accessor);
      }
      if (def.extras !== undefined) samples.setExtras(def.extras);
      context.nodes[nodeIndex].setExtension(VBUSD_VIRTUAL_BONES, samples);
    });
    return this;
  }

  prewrite(context, propertyType) {
    if (propertyType === PropertyType.ACCESSOR) {
      // The samples' values are written like instance attributes: tightly packed, grouped by node.
      context.accessorUsageGroupedByParent.add(SAMPLE_VALUES);
      for (const property of this.properties) {
        if (!(property instanceof VirtualBonesSamples) || property.isDisposed()) continue;
        for (const name of property.listNames()) context.addAccessorToUsageGroup(property.getValues(name), SAMPLE_VALUES);
      }
      return this;
    }
    if (propertyType !== PropertyType.BUFFER) return this;
    this._check();
    const buffers = this.document.getRoot().listBuffers();
    this._views = new Map();
    for (const animation of this.listAnimations()) {
      const bytes = animation.getTexture();
      if (!(bytes instanceof Uint8Array)) throw new VirtualBonesError(`animation "${animation.getName()}" has no texture`);
      const buffer = animation.getBuffer() ?? buffers[0];
      // A fresh view object per animation: the writer maps views by identity.
      const data = new Uint8Array(bytes);
      const views = context.otherBufferViews.get(buffer) ?? [];
      views.push(data);
      context.otherBufferViews.set(buffer, views);
      this._views.set(animation, data);
    }
    return this;
  }

  write(context) {
    const json = context.jsonDoc.json;
    const animations = this.listAnimations();
    if (!animations.length) return this;
    const indexOf = new Map(animations.map((a, i) => [a, i]));
    const viewIndex = new Map();
    json.extensions ??= {};
    json.extensions[VBUSD_VIRTUAL_BONES] = {
      version: EXTENSION_VERSION,
      animations: animations.map((animation) => {
        const view = context.otherBufferViewsIndexMap.get(this._views.get(animation));
        viewIndex.set(animation, view);
        const def = { name: animation.getName(), texture: { bufferView: view, mimeType: 'image/ktx2' }, layout: animation.getLayout() };
        if (animation.getPath() !== null) def.path = animation.getPath();
        if (animation.getClipExtents() !== null) def.clipExtents = animation.getClipExtents();
        if (Object.keys(animation.getExtras()).length) def.extras = animation.getExtras();
        // Key order of the spec's example: name, path, texture, layout, clipExtents.
        return Object.fromEntries(['name', 'path', 'texture', 'layout', 'clipExtents', 'extras'].filter((k) => k in def).map((k) => [k, def[k]]));
      }),
    };
    if (this._rootExtras !== undefined) json.extensions[VBUSD_VIRTUAL_BONES].extras = this._rootExtras;

    for (const mesh of this.document.getRoot().listMeshes()) {
      const meshDef = json.meshes?.[context.meshIndexMap.get(mesh)];
      if (!meshDef) continue;
      mesh.listPrimitives().forEach((prim, primIndex) => {
        const binding = prim.getExtension(VBUSD_VIRTUAL_BONES);
        if (!binding) return;
        const def = { animation: indexOf.get(binding.getAnimation()), influences: binding.getInfluences() };
        if (binding.getPath() !== null) def.path = binding.getPath();
        if (binding.getPart() !== null) def.part = binding.getPart();
        if (Object.keys(binding.getExtras()).length) def.extras = binding.getExtras();
        const primDef = meshDef.primitives[primIndex];
        primDef.extensions ??= {};
        primDef.extensions[VBUSD_VIRTUAL_BONES] = def;
      });
    }
    for (const node of this.document.getRoot().listNodes()) {
      const samples = node.getExtension(VBUSD_VIRTUAL_BONES);
      if (!samples || !samples.listNames().length) continue;
      const nodeDef = json.nodes[context.nodeIndexMap.get(node)];
      const def = { samples: Object.fromEntries(samples.listNames().map((name) => [name,
        { times: samples.getTimes(name), values: context.accessorIndexMap.get(samples.getValues(name)) }])) };
      if (Object.keys(samples.getExtras()).length) def.extras = samples.getExtras();
      nodeDef.extensions ??= {};
      nodeDef.extensions[VBUSD_VIRTUAL_BONES] = def;
    }
    this._align(context, [...viewIndex.values()]);
    return this;
  }

  /**
   * Moves each texture's buffer view to a multiple of TEXTURE_ALIGNMENT bytes of its buffer, so
   * the KTX2 level data can be viewed as typed arrays in place. The writer places extension
   * buffer views last and unpadded; this shifts them (and pads later views to 4 bytes).
   */
  _align(context, textureViews) {
    const json = context.jsonDoc.json;
    const ours = new Set(textureViews);
    (json.buffers ?? []).forEach((bufferDef, bufferIndex) => {
      const uri = context.options.format === Format.GLB && bufferIndex === 0 ? '@glb.bin' : bufferDef.uri;
      const bytes = context.jsonDoc.resources[uri];
      if (!bytes) return;
      // Byte ranges of this buffer: its buffer views, and the compressed ranges that
      // EXT_meshopt_compression records in a view's extension (the view itself then points into
      // a fallback buffer), whichever extension wrote first.
      const views = [];
      json.bufferViews.forEach((def, index) => {
        if (def.buffer === bufferIndex) views.push({ def, index });
        const meshopt = def.extensions?.EXT_meshopt_compression;
        if (meshopt && meshopt.buffer === bufferIndex) views.push({ def: meshopt, index: -1 });
      });
      views.sort((a, b) => (a.def.byteOffset ?? 0) - (b.def.byteOffset ?? 0));
      if (!views.some(({ def, index }) => ours.has(index) && (def.byteOffset ?? 0) % TEXTURE_ALIGNMENT)) return;
      const moved = [];
      let end = 0;
      for (const { def, index } of views) {
        const offset = def.byteOffset ?? 0;
        const align = ours.has(index) ? TEXTURE_ALIGNMENT : 4;
        let target = Math.max(offset, end);
        // Accessor views are already aligned; only move what comes after a shift.
        if (target !== offset || ours.has(index)) target = Math.ceil(target / align) * align;
        moved.push({ def, from: offset, to: target });
        end = target + def.byteLength;
      }
      const length = Math.ceil(end / 4) * 4;
      const out = new Uint8Array(length);
      for (const { def, from, to } of moved) {
        out.set(bytes.subarray(from, from + def.byteLength), to);
        def.byteOffset = to;
      }
      context.jsonDoc.resources[uri] = out;
      bufferDef.byteLength = length;
    });
  }

  /** Refuses, with one clear line, a document whose Virtual Bones skinning a transform broke. */
  _check() {
    const root = this.document.getRoot();
    const animations = new Set(this.listAnimations());
    for (const mesh of root.listMeshes()) {
      mesh.listPrimitives().forEach((prim, primIndex) => {
        const binding = prim.getExtension(VBUSD_VIRTUAL_BONES);
        if (!binding) return;
        const place = where(mesh, primIndex);
        if (!animations.has(binding.getAnimation())) throw new VirtualBonesError(`${place} is bound to an animation the document no longer has`);
        const position = prim.getAttribute('POSITION');
        if (!position) throw new VirtualBonesError(`${place} has no POSITION`);
        if (position.getComponentType() !== Accessor.ComponentType.FLOAT || position.getNormalized()) {
          throw new VirtualBonesError(`${place}: POSITION is quantized; Virtual Bones skin the rest positions in mesh space, and quantize() / meshopt() put the dequantization in the node or instance transform, applied after skinning. Quantize with vbusdQuantize() or pattern ${VBUSD_QUANTIZE_PATTERN}, compress with vbusdMeshopt() or Draco (CLI: optimize --compress draco or false, or vbusd-meshopt, with web/gltf-transform/gltf-transform.config.mjs)`);
        }
        const k = binding.getInfluences();
        if (!Number.isInteger(k) || k < 1) throw new VirtualBonesError(`${place}: influences ${JSON.stringify(k)} is not a positive integer`);
        for (let set = 0; set < Math.ceil(k / 4); ++set) {
          const joints = prim.getAttribute(`_VB_JOINTS_${set}`);
          const weights = prim.getAttribute(`_VB_WEIGHTS_${set}`);
          if (!joints || !weights) throw new VirtualBonesError(`${place} lost _VB_JOINTS_${set} / _VB_WEIGHTS_${set}; the skin must travel with the vertices`);
          for (const [name, accessor] of [[`_VB_JOINTS_${set}`, joints], [`_VB_WEIGHTS_${set}`, weights]]) {
            if (accessor.getCount() !== position.getCount()) throw new VirtualBonesError(`${place}: ${name} has ${accessor.getCount()} elements, POSITION ${position.getCount()}`);
          }
          const jointType = joints.getComponentType();
          if (joints.getType() !== 'VEC4' || joints.getNormalized() || jointType !== Accessor.ComponentType.SHORT) {
            throw new VirtualBonesError(`${place}: _VB_JOINTS_${set} is no longer VEC4 SHORT bone indices (a transform converted it)`);
          }
          const bones = binding.getAnimation().getLayout()?.boneCount;
          const indices = joints.getArray();
          if (Number.isInteger(bones) && indices) {
            for (let i = 0; i < indices.length; ++i) {
              if (indices[i] < 0 || indices[i] >= bones) throw new VirtualBonesError(`${place}: _VB_JOINTS_${set} holds bone ${indices[i]}, but animation "${binding.getAnimation().getName()}" has ${bones} bones (primitives of different animations joined?)`);
            }
          }
          if (weights.getType() !== 'VEC4' || weights.getComponentType() !== Accessor.ComponentType.FLOAT || weights.getNormalized()) {
            throw new VirtualBonesError(`${place}: _VB_WEIGHTS_${set} is quantized; the weights are binary32, read bit for bit (spec 7.1). Quantize with vbusdQuantize() or pattern ${VBUSD_QUANTIZE_PATTERN}`);
          }
        }
      });
    }
    for (const mesh of root.listMeshes()) {
      mesh.listPrimitives().forEach((prim, primIndex) => {
        if (!prim.getExtension(VBUSD_VIRTUAL_BONES) && prim.listSemantics().some((s) => s.startsWith('_VB_JOINTS_'))) {
          throw new VirtualBonesError(`${where(mesh, primIndex)} has _VB_JOINTS_n but no ${VBUSD_VIRTUAL_BONES} binding: join() across nodes makes new primitives without it (and moves rest vertices between node spaces); use vbusdJoin()`);
        }
      });
    }
    for (const node of root.listNodes()) {
      const mesh = node.getMesh();
      const batch = node.getExtension('EXT_mesh_gpu_instancing');
      if (!mesh || !batch || !mesh.listPrimitives().some((p) => p.getExtension(VBUSD_VIRTUAL_BONES))) continue;
      const missing = Object.keys(INSTANCE_DEFAULTS).filter((name) => !batch.getAttribute(name));
      if (missing.length) {
        throw new VirtualBonesError(`node "${node.getName() || '(unnamed)'}" draws Virtual Bones mesh "${mesh.getName()}" with EXT_mesh_gpu_instancing but has no ${missing.join(', ')} (instance() made it?); run vbusdInstanceDefaults() after instance()`);
      }
    }
  }
}

/**
 * Transform: gives every EXT_mesh_gpu_instancing batch drawing a Virtual Bones mesh the
 * per-instance attributes it lacks, with the values a character node plays (clip 0, time offset
 * 0, rate 1): instance() turns repeated character nodes into such batches.
 */
export function vbusdInstanceDefaults() {
  return (document) => {
    for (const node of document.getRoot().listNodes()) {
      const mesh = node.getMesh();
      const batch = node.getExtension('EXT_mesh_gpu_instancing');
      if (!mesh || !batch || !mesh.listPrimitives().some((p) => p.getExtension(VBUSD_VIRTUAL_BONES))) continue;
      const template = batch.listAttributes()[0];
      if (!template) continue;
      const buffer = template.getBuffer();
      for (const [name, [type, value]] of Object.entries(INSTANCE_DEFAULTS)) {
        if (batch.getAttribute(name)) continue;
        const array = new Float32Array(template.getCount() * value.length).map((_, i) => value[i % value.length]);
        batch.setAttribute(name, document.createAccessor(name).setType(type).setArray(array).setBuffer(buffer));
      }
    }
  };
}

/**
 * quantize() that leaves POSITION and the _VB_ attributes exact (see VBUSD_QUANTIZE_PATTERN),
 * quantizing the others (normals, texture coordinates, colors) as quantize() does.
 */
export function vbusdQuantize(options = {}) {
  return quantizeExcept(options, VBUSD_QUANTIZE_PATTERN);
}

function quantizeExcept(options, pattern) {
  const inner = quantize({ ...options, pattern, patternTargets: pattern });
  return async (document) => {
    await document.transform(inner);
    // quantize() (4.5.1) decides whether KHR_mesh_quantization is needed from POSITION alone;
    // with POSITION left as FLOAT, a quantized NORMAL would otherwise be written without it
    // (glTF-Validator: MESH_PRIMITIVE_ATTRIBUTES_ACCESSOR_INVALID_FORMAT).
    const quantized = document.getRoot().listMeshes().flatMap((m) => m.listPrimitives()).some((prim) => ['NORMAL', 'TANGENT']
      .some((semantic) => prim.getAttribute(semantic) && prim.getAttribute(semantic).getComponentType() !== 5126)
      || prim.listSemantics().some((semantic) => semantic.startsWith('TEXCOORD_') && [5120, 5122].includes(prim.getAttribute(semantic).getComponentType())));
    if (quantized) document.createExtension(KHRMeshQuantization).setRequired(true);
  };
}

/**
 * meshopt compression that keeps Virtual Bones skinning exact: reorder() for locality, the
 * VB-safe quantize() for the other attributes, then EXT_meshopt_compression's lossless codecs
 * (its filters need quantized data, so POSITION and the skin compress losslessly).
 * `extension` is the EXTMeshoptCompression class (from @gltf-transform/extensions).
 */
export function vbusdMeshopt({ encoder, extension, level = 'high' } = {}) {
  if (!encoder || !extension) throw new Error('vbusdMeshopt: pass {encoder: MeshoptEncoder, extension: EXTMeshoptCompression}');
  return async (document) => {
    // As meshopt() does: in 'high' mode (filters) normals and tangents stay float for the
    // octahedral filter, and only what no filter takes is quantized; POSITION and _VB_ never.
    const pattern = level === 'medium' ? VBUSD_QUANTIZE_PATTERN : /^(TEXCOORD|COLOR|JOINTS|WEIGHTS)(_\d+)?$/;
    await document.transform(reorder({ encoder, target: 'size' }), quantizeExcept({ quantizeNormal: 8 }, pattern));
    // The octahedral filter writes normals and tangents as normalized bytes, which only
    // KHR_mesh_quantization allows (meshopt() gets it from quantizing POSITION).
    const filtered = document.getRoot().listMeshes().flatMap((m) => m.listPrimitives()).some((p) => p.getAttribute('NORMAL') || p.getAttribute('TANGENT'));
    if (level !== 'medium' && filtered) document.createExtension(KHRMeshQuantization).setRequired(true);
    document.createExtension(extension).setRequired(true)
      .setEncoderOptions({ method: level === 'medium' ? extension.EncoderMethod.QUANTIZE : extension.EncoderMethod.FILTER });
  };
}

/** The node draws a mesh with a primitive bound to a Virtual Bones animation. */
function drawsVirtualBones(node) {
  return !!node.getMesh()?.listPrimitives().some((p) => p.getExtension(VBUSD_VIRTUAL_BONES));
}

/**
 * join() that never breaks a skin. glTF-Transform's join() groups primitives by material, mode and
 * attribute types only: across nodes (`keepMeshes: false`) it would merge primitives of different
 * animations under one binding, and it moves vertices into the joined node's space, which for a
 * skinned rest mesh is not the same as moving the skinned result. Here nodes drawing Virtual
 * Bones meshes join only their own primitives of one animation and one influence count (as
 * `keepMeshes: true` does), and every other node joins as `options` say.
 */
export function vbusdJoin(options = {}) {
  const filter = options.filter ?? (() => true);
  const uniform = (node) => {
    const bindings = node.getMesh().listPrimitives().map((p) => p.getExtension(VBUSD_VIRTUAL_BONES));
    return bindings.every((b) => b && b.getAnimation() === bindings[0].getAnimation() && b.getInfluences() === bindings[0].getInfluences());
  };
  return async (document) => {
    await document.transform(
      join({ ...options, keepMeshes: true, filter: (node) => filter(node) && drawsVirtualBones(node) && uniform(node) }),
      join({ ...options, filter: (node) => filter(node) && !drawsVirtualBones(node) }),
    );
  };
}

