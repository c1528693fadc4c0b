// A Virtual Bones crowd in Babylon.js: one Mesh per rest mesh of the animation, its instances as
// thin instances (one draw call per mesh), each with its own clip, time offset, rate, crossfade
// and layers in thin-instance streams read by the material plugin.

import {
  Mesh, VertexData, Matrix, StandardMaterial, Color3, RawTexture, Constants, Vector3, Frustum, BoundingSphere, Camera,
} from '@babylonjs/core';
import {
  VirtualBonesError, checkSkinBinding, evaluateSamples, packSkin, skinTextureData, layeredJointElements, rootMotionElements,
  screenSize, selectLevel, checkScreenSizes, crowdEvents, instanceColors, partBit, partMatrices, partMatrixAt, varietyOf, moveInstance,
  DEFAULT_FRAME_INTERVAL, PreviousFrame, blendLayers, packLayerMask, layerModeOf, layersOfStreams,
} from '@vbusd/core';

import { skinMaterial } from './plugin.js';

/**
 * @param {Scene} scene
 * @param {object} options
 * @param {VirtualBonesAnimation} options.animation
 * @param {Array<object>} options.meshes per mesh: {name, positions: Float32Array (3 per vertex),
 *   normals (or null: Babylon computes them), triangles (or indices): Uint32Array, boneIndices /
 *   boneWeights: 4 or 8 per vertex (any numeric arrays), maxInfluences, pointIndex (or null),
 *   pointCount} (@vbusd/core's parsePlainScene gives them)
 * @param {object} options.instances {count, matrices: Float32Array(16 N) (column-major: glTF's and
 *   three's, which is Babylon's memory layout), clip, timeOffset, playbackRate; optionally
 *   fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight, fadeSamples (a fade over stage time,
 *   evaluated by updateSamples), and the layers of format 1.2 (two per instance: layerClip,
 *   layerMask, layerTimeOffset, layerPlaybackRate, layerWeight, 2 N each), and crowd variety
 *   (format 1.3: tint, variant, parts, variantNames, variantColors, partNames; @vbusd/core's
 *   variety.js): a thin-instance colour of variant colour x tint (the material's colour white when
 *   the crowd has variants), and per part mesh its own matrices, zero where the mask hides it}
 * @param {function(string): Material} [options.material] a new material per mesh (default a
 *   StandardMaterial); the plugin is added to it.
 * @param {string} [options.skin] the skin binding (spec/shaders.md, "Skin bindings"): `attributes`
 *   (default: bone indices and weights as vertex streams) or `pulled` (the skin records in an
 *   RGBA32UI texture read by gl_VertexID; the bone streams are not made). Layers run in the
 *   attributes binding.
 * @param {Array<Array<object>>} [options.levels] levels of detail 1, 2, ... (format 1.2, spec
 *   virtual-bones.md 20), each its meshes as `meshes` gives LOD 0's. With levels, call
 *   `updateLevels(camera)` before each render: every instance gets the level its screen size
 *   selects (@vbusd/core's screenSize and selectLevel, as the three.js runtime) and is culled
 *   when outside the view; each level's meshes draw their instances from thin-instance buffers of
 *   their own (one draw per level and mesh, never one per instance).
 * @param {Array<number>} [options.screenSizes] the levels' thresholds, one per level after LOD 0.
 * @param {number} [options.hysteresis] a finer level only once the screen size passes its
 *   threshold by this fraction (default 0.1, spec 20.2).
 */
export class VirtualBonesCrowd {
  constructor(scene, { animation, meshes = [], instances, material = null, name = 'crowd', adopt = null, skin = null, rootMotion = null,
    levels = null, screenSizes = null, hysteresis = 0.1 }) {
    this.scene = scene;
    this.animation = animation;
    this.name = name;
    this.capacity = instances.count;
    this.instances = instances;
    this.layered = Boolean(instances.layerWeight);
    this.skin = skin ?? 'attributes';
    checkSkinBinding(this.skin, name);
    if (this.layered && this.skin !== 'attributes') throw new VirtualBonesError(`${name}: layers (format 1.2) need the attributes skin binding`);
    if (this.layered && !animation.rigTexture) throw new VirtualBonesError(`${name}: the crowd plays layers but its animation stores no bone masks`);
    this.rootMotion = rootMotion ?? animation.layout.rootMotion ?? null;
    for (let i = 0; i < this.capacity; ++i) {
      if (!(instances.clip[i] >= 0 && instances.clip[i] < animation.clips.length)) {
        throw new VirtualBonesError(`${name}: instance ${i} plays clip ${instances.clip[i]}, the animation has ${animation.clips.length}`);
      }
    }
    this.instanceA = new Float32Array(4 * this.capacity);
    this.instanceB = new Float32Array(4 * this.capacity);
    for (let i = 0; i < this.capacity; ++i) {
      this.instanceA.set([instances.clip[i], instances.timeOffset[i], instances.playbackRate[i], instances.fadeClip?.[i] ?? 0], 4 * i);
      this.instanceB.set([instances.fadeTimeOffset?.[i] ?? 0, instances.fadePlaybackRate?.[i] ?? 1,
        Math.min(Math.max(instances.fadeWeight?.[i] ?? 0, 0), 1), 0], 4 * i);
    }
    if (this.layered) {  // two layers per instance: (clip, mask), (offset, rate), (weight, weight)
      this.instanceC = new Float32Array(4 * this.capacity);
      this.instanceD = new Float32Array(4 * this.capacity);
      this.instanceE = new Float32Array(4 * this.capacity);
      for (let i = 0; i < this.capacity; ++i) {
        for (let j = 0; j < 2; ++j) {
          const k = 2 * i + j;
          this._writeLayer(i, j, { clip: instances.layerClip[k], mask: instances.layerMask[k], timeOffset: instances.layerTimeOffset[k],
            playbackRate: instances.layerPlaybackRate[k], weight: Math.min(Math.max(instances.layerWeight[k], 0), 1),
            mode: instances.layerMode?.[k] ?? 0,
            reference: { clip: instances.layerReferenceClip?.[k] ?? instances.layerClip[k], time: instances.layerReferenceTime?.[k] ?? 0 } });
        }
      }
    }
    this.fadeSamples = instances.fadeSamples ?? null;
    if (this.fadeSamples) {
      const n = this.capacity;
      this.sampled = { fadeClip: new Int32Array(n), fadeTimeOffset: new Float32Array(n), fadePlaybackRate: new Float32Array(n), fadeWeight: new Float32Array(n) };
    }
    // The previous frame (spec 21): @vbusd/core's PreviousFrame, its values the thin-instance stream
    // vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) read by the velocity pre-pass and the probe.
    this.previous = new PreviousFrame(this.capacity);
    this.matrices = instances.matrices ? Float32Array.from(instances.matrices) : null;
    // Spec 21.1 "Instance transform": each instance's previous matrix, the placement it had at the
    // last updatePrevious (Babylon's 'previousMatrix' thin-instance buffer: previousWorld0..3 of
    // its velocity pre-pass; unset, Babylon binds none on the first frame -- a zero matrix, the
    // previous pose at the origin -- and copies the current slots after each draw, which is wrong
    // once levels of detail compact the instances anew each frame).
    this.previousMatrices = this.matrices ? Float32Array.from(this.matrices) : null;
    // Crowd variety (format 1.3): Babylon's thin-instance colour (RGBA) multiplies the material's.
    const colors = instanceColors(instances);
    this.instanceColors = null;
    if (colors) {
      this.instanceColors = new Float32Array(4 * this.capacity).fill(1);
      for (let i = 0; i < this.capacity; ++i) this.instanceColors.set(colors.subarray(3 * i, 3 * i + 3), 4 * i);
    }
    // `adopt`: meshes something else built (the glTF loader: VirtualBonesGLTFLoaderExtension), each
    // {mesh, maxInfluences, boneIndices, boneWeights}; their thin-instance matrices are kept.
    this.levels = null;
    this.adopted = Boolean(adopt);
    if (levels && levels.length) {
      // Adopted meshes (the glTF loader's, MSFT_lod): each level's entries are adopted too, and
      // the crowd's `instances.matrices` are the instance placements the levels compact.
      if (adopt && !this.matrices) throw new VirtualBonesError(`${name}: adopted levels of detail need the instance matrices`);
      const thresholds = Array.from(screenSizes ?? []);
      checkScreenSizes(thresholds, levels.length, name);
      this.screenSizes = thresholds;
      this.hysteresis = hysteresis;
      this.levelOfInstance = new Int32Array(this.capacity);
      this.levelCounts = new Array(levels.length + 1).fill(0);
      this.drawn = this.capacity;
      const n = this.capacity;
      // Each level's compacted copies of the playback streams (and of the layer streams, with layers).
      this.levelBuffers = [meshes, ...levels].map(() => ({
        matrix: new Float32Array(16 * n), previousMatrix: new Float32Array(16 * n), a: new Float32Array(4 * n), b: new Float32Array(4 * n), p: new Float32Array(4 * n),
        ...(this.layered ? { c: new Float32Array(4 * n), d: new Float32Array(4 * n), e: new Float32Array(4 * n) } : {}) }));
      this.levels = [adopt ?? meshes, ...levels].map((entries, level) => entries.map((entry) => {
        const mesh = adopt ? this._skin(entry.mesh, entry, material, this.levelBuffers[level]) : this._mesh(entry, material, this.levelBuffers[level]);
        mesh.thinInstanceCount = 0;
        mesh.metadata.virtualBones.level = level;
        return mesh;
      }));
      this.meshes = this.levels[0];
    }
    if (!this.levels) {
      this.meshes = adopt ? adopt.map((entry) => this._skin(entry.mesh, entry, material))
        : meshes.map((entry) => this._mesh(entry, material));
    }
    this.applyParts();
    this.updateSamples(animation.time ?? 0);
    this.updatePrevious(animation.time ?? 0);
  }

  _mesh(entry, material, buffers = null) {
    const vertexCount = entry.positions.length / 3;
    const slots = entry.boneIndices.length / vertexCount;
    if (slots !== 4 && slots !== 8) throw new VirtualBonesError(`${entry.name}: bone indices must be 4 or 8 per vertex, got ${slots}`);
    const mesh = new Mesh(entry.name, this.scene);
    // vbusd's triangles are counter-clockwise seen from the front (right-handed, as USD's default
    // orientation and glTF): the side Babylon culls is set as its glTF loader sets it. With its
    // default (clockwise) a right-handed scene culled the front faces and drew each figure's far side.
    mesh.sideOrientation = this.scene.useRightHandedSystem
      ? Constants.MATERIAL_CounterClockWiseSideOrientation : Constants.MATERIAL_ClockWiseSideOrientation;
    const data = new VertexData();
    data.positions = Float32Array.from(entry.positions);
    data.indices = Uint32Array.from(entry.triangles ?? entry.indices);
    if (entry.normals) data.normals = Float32Array.from(entry.normals);
    else {
      data.normals = new Float32Array(data.positions.length);
      VertexData.ComputeNormals(data.positions, data.indices, data.normals, { useRightHandedSystem: this.scene.useRightHandedSystem });
    }
    data.applyToMesh(mesh, false);
    mesh.metadata = { virtualBones: { pointIndex: entry.pointIndex ?? null, hasNormals: Boolean(entry.normals),
      pointCount: entry.pointCount ?? vertexCount } };
    return this._skin(mesh, entry, material, buffers);
  }

  // `buffers` ({matrix, a, b}): a level's own thin-instance arrays (levels of detail), else the crowd's.
  _skin(mesh, entry, material, buffers = null) {
    const vertexCount = mesh.getTotalVertices();
    const slots = entry.boneIndices.length / vertexCount;
    if (slots !== 4 && slots !== 8) throw new VirtualBonesError(`${mesh.name}: bone indices must be 4 or 8 per vertex, got ${slots}`);
    const maxInfluences = entry.maxInfluences ?? slots;
    const sets = [];
    for (let set = 0; set < slots / 4; ++set) {
      const indices = new Float32Array(4 * vertexCount);
      const weights = new Float32Array(4 * vertexCount);
      for (let v = 0; v < vertexCount; ++v) {
        for (let i = 0; i < 4; ++i) {
          indices[4 * v + i] = entry.boneIndices[v * slots + 4 * set + i];
          weights[4 * v + i] = entry.boneWeights[v * slots + 4 * set + i];
        }
      }
      sets.push([indices, weights]);
    }
    let skinTexture = null;
    if (this.skin === 'pulled') {
      // The skin records (spec/shaders.md, "Skin records") in an RGBA32UI texture read by gl_VertexID.
      const records = packSkin(sets.map(([indices]) => indices), sets.map(([, weights]) => weights), maxInfluences, mesh.name);
      const { width, height, data } = skinTextureData(records);
      skinTexture = new RawTexture(data, width, height, Constants.TEXTUREFORMAT_RGBA_INTEGER, this.scene, false, false,
        Constants.TEXTURE_NEAREST_SAMPLINGMODE, Constants.TEXTURETYPE_UNSIGNED_INTEGER);
      skinTexture.name = `${mesh.name} (skin records)`;
    } else {
      sets.forEach(([indices, weights], set) => {
        mesh.setVerticesData(`vb_boneIndices${set}`, indices, false, 4);
        mesh.setVerticesData(`vb_boneWeights${set}`, weights, false, 4);
      });
    }
    // The given material, else the mesh's own (a glTF's PBRMaterial), else a grey StandardMaterial;
    // a material some other skinned mesh already uses is cloned (the plugin holds one animation).
    let mat = material ? material(mesh.name) : mesh.material;
    if (!mat) mat = Object.assign(new StandardMaterial(`${mesh.name} material`, this.scene), { diffuseColor: new Color3(0.72, 0.74, 0.78) });
    else if (mat.metadata?.virtualBones) mat = mat.clone(`${mat.name} (${mesh.name})`);
    skinMaterial(mat, this.animation, maxInfluences, { skin: this.skin, skinTexture, layers: this.layered });
    mesh.material = mat;
    const part = partBit(entry.name ?? mesh.name, this.instances.partNames);  // applyParts() and updateLevels use it
    let partMatrix = null;
    let partPreviousMatrix = null;
    if (buffers && part >= 0 && this.instances.parts) {
      // A part at a level of detail (spec 22.3): its own compact matrices, the mask applied by updateLevels.
      partMatrix = new Float32Array(buffers.matrix.length);
      partPreviousMatrix = new Float32Array(buffers.matrix.length);
      mesh.thinInstanceSetBuffer('matrix', partMatrix, 16, false);
    } else if (buffers) mesh.thinInstanceSetBuffer('matrix', buffers.matrix, 16, false);
    if (buffers) mesh.thinInstanceSetBuffer('previousMatrix', partPreviousMatrix ?? buffers.previousMatrix, 16, false);
    if (buffers) {
      mesh.thinInstanceSetBuffer('vb_instanceA', buffers.a, 4, false);
      mesh.thinInstanceSetBuffer('vb_instanceB', buffers.b, 4, false);
      mesh.thinInstanceSetBuffer('vb_instancePreviousFade', buffers.p, 4, false);
    } else {
      if (this.matrices) mesh.thinInstanceSetBuffer('matrix', this.matrices, 16, false);
      mesh.thinInstanceSetBuffer('vb_instanceA', this.instanceA, 4, false);
      mesh.thinInstanceSetBuffer('vb_instanceB', this.instanceB, 4, false);
      mesh.thinInstanceSetBuffer('vb_instancePreviousFade', this.previous.values, 4, false);
    }
    if (this.instanceColors) {
      mesh.thinInstanceSetBuffer('color', this.instanceColors, 4, true);
      if (this.instances.variant) {  // the variant's colour is in the instance colour
        if (mat.diffuseColor) mat.diffuseColor = new Color3(1, 1, 1);
        if (mat.albedoColor) mat.albedoColor = new Color3(1, 1, 1);
      }
    }
    if (this.layered) {
      mesh.thinInstanceSetBuffer('vb_instanceC', buffers?.c ?? this.instanceC, 4, !buffers);
      mesh.thinInstanceSetBuffer('vb_instanceD', buffers?.d ?? this.instanceD, 4, !buffers);
      mesh.thinInstanceSetBuffer('vb_instanceE', buffers?.e ?? this.instanceE, 4, !buffers);
    }
    // Skinned vertices leave the rest bounds: the crowd is never culled by them.
    mesh.alwaysSelectAsActiveMesh = true;
    const hasNormals = mesh.isVerticesDataPresent('normal');
    mesh.metadata = { ...(mesh.metadata ?? {}), virtualBones: { pointIndex: null, hasNormals, pointCount: vertexCount,
      ...(mesh.metadata?.virtualBones ?? {}), crowd: this, maxInfluences, skinTexture, sets, part, partMatrix, partPreviousMatrix } };
    return mesh;
  }

  /**
   * Parts (format 1.3, spec 22.3): each part's mesh gets its own thin-instance matrices, collapsed
   * (linear part zero) for the instances whose mask hides it, from the crowd's matrices (an adopted
   * glTF crowd: the thin-instance matrices of its first mesh of no part, as Babylon's
   * EXT_mesh_gpu_instancing set them). The constructor calls it; the glTF extension calls it again
   * before the first render, once Babylon's loader has set every thin-instance buffer.
   */
  applyParts() {
    const parts = this.instances.parts;
    if (!parts || this.levels) return;
    let source = this.matrices;
    if (!source) {
      const base = this.meshes.find((mesh) => mesh.metadata.virtualBones.part < 0);
      if (!base) return;
      source = new Float32Array(16 * this.capacity);
      base.thinInstanceGetWorldMatrices().forEach((m, i) => m.copyToArray(source, 16 * i));
    }
    for (const mesh of this.meshes) {
      const bit = mesh.metadata.virtualBones.part;
      if (bit >= 0) mesh.thinInstanceSetBuffer('matrix', partMatrices(source, parts, bit), 16, false);
    }
  }

  /**
   * Move every instance by its root motion between scene times `t0` and `t1` (spec 8.5:
   * rootMotionMatrix, applied in the instance's own space), as the three.js crowd's: the placements
   * change, and with them every mesh's thin-instance matrices, the part meshes' included (spec
   * 22.3: a part moves with its instance), and the levels' at the next updateLevels.
   */
  applyRootMotion(t0, t1) {
    if (!this.rootMotion) return;
    if (!this.matrices) {
      // An adopted glTF crowd keeps its placements in its meshes' thin instances: hold them here, once.
      const base = this.meshes.find((mesh) => mesh.metadata.virtualBones.part < 0) ?? this.meshes[0];
      this.matrices = new Float32Array(16 * this.capacity);
      base.thinInstanceGetWorldMatrices().forEach((m, i) => m.copyToArray(this.matrices, 16 * i));
      if (!this.levels) {
        for (const mesh of this.meshes) if (!(mesh.metadata.virtualBones.part >= 0 && this.instances.parts)) mesh.thinInstanceSetBuffer('matrix', this.matrices, 16, false);
      }
    }
    for (let i = 0; i < this.capacity; ++i) moveInstance(this.matrices, i, this.rootMotionMatrix(i, t0, t1).m);
    this._updated('matrix');
    this.applyParts();
  }

  /** What instance `index` shows (format 1.3 crowd variety): `{tint, variant, variantName, parts, partNames}`. */
  varietyOf(index) { return varietyOf(this.instances, index); }

  /** Instances drawn (the first `count` of the capacity). */
  get count() { return this.levels ? this.drawn : (this.meshes[0]?.thinInstanceCount ?? 0); }

  set count(n) {
    const count = Math.max(0, Math.min(n, this.capacity));
    if (this.levels) this.drawn = count;
    else for (const mesh of this.meshes) mesh.thinInstanceCount = count;
  }

  _updated(...streams) {
    if (this.levels) return;  // the levels' buffers are written by updateLevels
    for (const mesh of this.meshes) for (const stream of streams) mesh.thinInstanceBufferUpdated(stream);
  }

  /** The meshes of level `level` (LOD 0's without levels). */
  meshesOfLevel(level) { return this.levels ? this.levels[level] : this.meshes; }

  /** The level instance `index` drew at the last updateLevels (-1: culled); 0 without levels. */
  levelOf(index) { return this.levels ? this.levelOfInstance[index] : 0; }

  /** The sphere around the box of every clip's extents (the rest bounds without extents), in mesh space. */
  _extentSphere() {
    const extents = this.animation.clipExtents;
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    if (extents && extents.every(Boolean)) {
      for (const [a, b] of extents) for (let c = 0; c < 3; ++c) { lo[c] = Math.min(lo[c], a[c]); hi[c] = Math.max(hi[c], b[c]); }
    } else {
      const box = this.meshes[0].getBoundingInfo().boundingBox;  // the rest bounds without extents
      [box.minimum.x, box.minimum.y, box.minimum.z].forEach((v, c) => { lo[c] = v; });
      [box.maximum.x, box.maximum.y, box.maximum.z].forEach((v, c) => { hi[c] = v; });
    }
    return {
      centre: new Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2),
      radius: 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]),
    };
  }

  /** World-space {min, max} of the instances' spheres (`_extentSphere` placed at each). */
  boundsOfInstances() {
    const { centre, radius } = this._extentSphere();
    const parent = this.meshes[0].computeWorldMatrix(true);
    const min = new Vector3(Infinity, Infinity, Infinity);
    const max = new Vector3(-Infinity, -Infinity, -Infinity);
    for (let i = 0; i < this.count; ++i) {
      const world = this.instanceMatrix(i).multiply(parent);
      const scale = Math.max(...[0, 1, 2].map((r) => Math.hypot(world.m[4 * r], world.m[4 * r + 1], world.m[4 * r + 2])));
      const point = Vector3.TransformCoordinates(centre, world);
      min.minimizeInPlace(point.subtractFromFloats(radius * scale, radius * scale, radius * scale));
      max.maximizeInPlace(point.add(new Vector3(radius * scale, radius * scale, radius * scale)));
    }
    return { min, max };
  }

  /**
   * Levels of detail (spec virtual-bones.md 20.2), as the three.js runtime's updateLevels: each
   * drawn instance's level from its screen size seen by `camera` (UsdLod's projectedSphere size of
   * the box of every clip's extents), culled (-1) when that box lies outside the view; then each
   * level's meshes get the instances choosing it in their own thin-instance buffers. Without
   * levels it does nothing.
   */
  updateLevels(camera) {
    if (!this.levels) return;
    if (this.adopted && !this._levelMatrices) {
      // The glTF loader's EXT_mesh_gpu_instancing gave the adopted meshes every instance's matrix
      // once the load completed: each level draws its compacted copy instead.
      // A part mesh keeps its own matrices (spec 22.3: the slots its mask hides collapsed).
      this.levels.forEach((meshes, level) => {
        for (const mesh of meshes) mesh.thinInstanceSetBuffer('matrix', mesh.metadata.virtualBones.partMatrix ?? this.levelBuffers[level].matrix, 16, false);
      });
      this._levelMatrices = true;
    }
    const { centre, radius } = this._extentSphere();
    const planes = Frustum.GetPlanes(camera.getTransformationMatrix(true));
    const eye = camera.globalPosition;
    const perspective = camera.mode === Camera.PERSPECTIVE_CAMERA;
    const aspect = this.scene.getEngine().getAspectRatio(camera);
    // Babylon's fov is vertical unless the camera fixes the horizontal one.
    const tangent = camera.fovMode === Camera.FOVMODE_HORIZONTAL_FIXED ? Math.tan(camera.fov / 2) / aspect : Math.tan(camera.fov / 2);
    const parent = this.meshes[0].computeWorldMatrix(true);
    const counts = this.levelCounts.fill(0);
    const point = new Vector3();
    for (let i = 0; i < this.drawn; ++i) {
      const world = this.instanceMatrix(i).multiply(parent);
      const scale = Math.max(...[0, 1, 2].map((r) => Math.hypot(world.m[4 * r], world.m[4 * r + 1], world.m[4 * r + 2])));
      Vector3.TransformCoordinatesToRef(centre, world, point);
      const sphere = new BoundingSphere(point.subtractFromFloats(radius * scale, 0, 0), point.add(new Vector3(radius * scale, 0, 0)));
      if (!sphere.isInFrustum(planes)) { this.levelOfInstance[i] = -1; continue; }
      let level = 0;
      if (perspective) level = selectLevel(screenSize(radius * scale, Vector3.Distance(point, eye), tangent, aspect), this.screenSizes, this.levelOfInstance[i], this.hysteresis);
      this.levelOfInstance[i] = level;
      const at = counts[level]++;
      const target = this.levelBuffers[level];
      target.matrix.set(this.matrices ? this.matrices.subarray(16 * i, 16 * i + 16) : this.instanceMatrix(i).m, 16 * at);
      // The instance's own previous matrix in its slot of this frame (spec 21.1), not the slot's last occupant's.
      target.previousMatrix.set(this.previousMatrices ? this.previousMatrices.subarray(16 * i, 16 * i + 16) : target.matrix.subarray(16 * at, 16 * at + 16), 16 * at);
      target.a.set(this.instanceA.subarray(4 * i, 4 * i + 4), 4 * at);
      target.b.set(this.instanceB.subarray(4 * i, 4 * i + 4), 4 * at);
      target.p.set(this.previous.values.subarray(4 * i, 4 * i + 4), 4 * at);
      // Parts (spec 22.3): the level's part meshes draw the slot collapsed where the mask hides them.
      for (const mesh of this.levels[level]) {
        const { part, partMatrix, partPreviousMatrix } = mesh.metadata.virtualBones;
        if (partMatrix) partMatrixAt(partMatrix, at, target.matrix, at, this.instances.parts[i], part);
        if (partPreviousMatrix) partMatrixAt(partPreviousMatrix, at, target.previousMatrix, at, this.instances.parts[i], part);
      }
      if (this.layered) {
        target.c.set(this.instanceC.subarray(4 * i, 4 * i + 4), 4 * at);
        target.d.set(this.instanceD.subarray(4 * i, 4 * i + 4), 4 * at);
        target.e.set(this.instanceE.subarray(4 * i, 4 * i + 4), 4 * at);
      }
    }
    const streams = ['matrix', 'previousMatrix', 'vb_instanceA', 'vb_instanceB', 'vb_instancePreviousFade', ...(this.layered ? ['vb_instanceC', 'vb_instanceD', 'vb_instanceE'] : [])];
    this.levels.forEach((meshes, level) => {
      for (const mesh of meshes) {
        for (const stream of streams) mesh.thinInstanceBufferUpdated(stream);
        mesh.thinInstanceCount = counts[level];
      }
    });
  }

  /** Triangles drawn with the levels chosen at the last updateLevels (all at LOD 0 without levels). */
  get trianglesDrawn() {
    const triangles = (mesh) => mesh.getTotalIndices() / 3;
    if (!this.levels) return this.meshes.reduce((n, mesh) => n + triangles(mesh) * mesh.thinInstanceCount, 0);
    return this.levels.reduce((n, meshes, level) => n + meshes.reduce((m, mesh) => m + triangles(mesh), 0) * this.levelCounts[level], 0);
  }

  /**
   * The clip markers (format 1.3, spec 23.5) every instance crosses between scene times t0 and t1
   * (CPU, from the clock): [{instance, name, time}], as the three.js runtime's `events`.
   */
  events(t0, t1) {
    const n = this.capacity;
    const [clip, offset, rate] = [new Int32Array(n), new Float64Array(n), new Float64Array(n)];
    for (let i = 0; i < n; ++i) [clip[i], offset[i], rate[i]] = this.instanceA.subarray(4 * i, 4 * i + 3);
    return crowdEvents(this.animation.layout.markers, this.animation.layout.clips, clip, offset, rate, t0, t1);
  }

  /** Change instance `i`'s crossfade (spec 8.3): fade clip, its time offset and rate, weight. */
  setFade(i, { fadeClip, fadeTimeOffset = 0, fadePlaybackRate = 1, fadeWeight }) {
    if (!(fadeClip >= 0 && fadeClip < this.animation.clips.length)) {
      throw new VirtualBonesError(`${this.name}: instance ${i} fades into clip ${fadeClip}, the animation has ${this.animation.clips.length}`);
    }
    this.instanceA[4 * i + 3] = fadeClip;
    this.instanceB.set([fadeTimeOffset, fadePlaybackRate, Math.min(Math.max(fadeWeight, 0), 1)], 4 * i);
    this._updated('vb_instanceA', 'vb_instanceB');
  }

  /**
   * A fade over stage time (time-sampled fade primvars, `vbusd crowd --fade-window`): every
   * instance's fade at scene time `time`, as USD resolves the samples (@vbusd/core's
   * evaluateSamples). The viewer calls it with the animation's time each frame; without samples it
   * does nothing.
   */
  updateSamples(time) {
    if (!this.fadeSamples) return;
    const { fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight } = evaluateSamples(this.fadeSamples, time, this.sampled);
    const s = this.fadeSamples;
    for (let i = 0; i < this.capacity; ++i) {
      if (s.fadeClip) this.instanceA[4 * i + 3] = fadeClip[i];
      if (s.fadeTimeOffset) this.instanceB[4 * i] = fadeTimeOffset[i];
      if (s.fadePlaybackRate) this.instanceB[4 * i + 1] = fadePlaybackRate[i];
      if (s.fadeWeight) this.instanceB[4 * i + 2] = Math.min(Math.max(fadeWeight[i], 0), 1);
    }
    if (this.meshes) this._updated('vb_instanceA', 'vb_instanceB');
  }

  /**
   * Layer `slot` (0 or 1) of instance `index` (spec 8.6, format 1.2): clip `clip` at `timeOffset +
   * playbackRate * time` over the bones of mask `mask` (index or name) with weight `weight`; with
   * `mode: 'additive'` (format 1.3, spec 23.4) the clip's difference from `reference` = {clip, time}
   * (default the layer's clip at 0) is added instead, as the three.js runtime's setLayer.
   */
  setLayer(index, slot, { clip = 0, mask = 0, timeOffset = 0, playbackRate = 1, weight = 0, mode = 'override', reference = null } = {}) {
    if (!this.layered) throw new VirtualBonesError(`${this.name}: the crowd was made without layers`);
    const maskIndex = typeof mask === 'string' ? this.animation.maskIndex(mask) : mask;
    if (!(slot === 0 || slot === 1)) throw new VirtualBonesError(`${this.name}: layer slot must be 0 or 1, got ${slot}`);
    if (!(weight >= 0 && weight <= 1)) throw new VirtualBonesError(`${this.name}: instance ${index}: layer weight must be in 0..1, got ${weight}`);
    // Format 1.3: with blend spaces, mask index masks.length is the rig's every-bone mask (blends as layers).
    const maskCount = this.animation.masks.length + (this.animation.layout?.blendSpaces ? 1 : 0);
    if (weight > 0 && !(maskIndex >= 0 && maskIndex < maskCount)) {
      throw new VirtualBonesError(`${this.name}: instance ${index}: no bone mask ${JSON.stringify(mask)} (masks: ${this.animation.masks.join(', ')})`);
    }
    this._writeLayer(index, slot, { clip, mask: maskIndex, timeOffset, playbackRate, weight, mode, reference });
    this._updated('vb_instanceC', 'vb_instanceD', 'vb_instanceE');
  }

  /** Layer `slot` of instance `index` into the streams vb_instanceC/D/E (checked by the caller). */
  _writeLayer(index, slot, { clip, mask, timeOffset, playbackRate, weight, mode = 0, reference = null }) {
    const what = `${this.name}: instance ${index} layer ${slot}`;
    const additive = layerModeOf(mode, what);
    const code = weight > 0 ? packLayerMask(mask, additive, reference?.clip ?? clip, this.animation.clips.length, what) : 0;
    this.instanceC.set([weight > 0 ? clip : 0, code], 4 * index + 2 * slot);
    this.instanceD.set([timeOffset, playbackRate], 4 * index + 2 * slot);
    this.instanceE[4 * index + slot] = weight;
    this.instanceE[4 * index + 2 + slot] = additive ? (reference?.time ?? 0) : 0;
  }

  /**
   * Instance `index` plays blend space `space` (format 1.3, spec 23.7) at parameter (x, y), phase
   * `phase` at scene time 0, advancing at `playbackRate / sum w D`: written as its clip and time plus
   * layer slots 0 and 1 under the rig's every-bone mask (spec 23.1, "Decoding a blend as layers";
   * @vbusd/core's blendLayers), the same signature and behaviour as the three.js runtime's setBlend.
   * Returns the plan ({clip, timeOffset, playbackRate, layers}).
   */
  setBlend(index, { space, x = 0, y = 0, phase = 0, playbackRate = 1 } = {}) {
    if (!this.layered) throw new VirtualBonesError(`${this.name}: the crowd was made without layers (blends play as layers)`);
    const spaces = this.animation.layout.blendSpaces ?? [];
    const found = spaces.find((s) => s.name === space);
    if (!found) throw new VirtualBonesError(`${this.name}: no blend space ${JSON.stringify(space)} (spaces: ${spaces.map((s) => s.name).join(', ')})`);
    const plan = blendLayers(found, x, y, phase, playbackRate, this.animation.layout.clips, this.animation.layout.markers);
    if (plan.layers.length > 2) throw new VirtualBonesError(`${this.name}: instance ${index}: the blend weighs ${plan.layers.length + 1} points; the runtime layers 3 at most`);
    this.instanceA.set([plan.clip, plan.timeOffset, plan.playbackRate], 4 * index);
    this.instanceB[4 * index + 2] = 0;  // a blending instance does not crossfade (spec 23.7)
    const every = this.animation.masks.length;  // the rig texture's every-bone mask (rigTexels)
    for (let slot = 0; slot < 2; ++slot) {
      const layer = plan.layers[slot];
      this._writeLayer(index, slot, layer ? { clip: layer.clip, mask: every, timeOffset: layer.timeOffset, playbackRate: layer.playbackRate, weight: layer.weight }
        : { clip: 0, mask: 0, timeOffset: 0, playbackRate: 1, weight: 0 });
    }
    this._updated('vb_instanceA', 'vb_instanceB', 'vb_instanceC', 'vb_instanceD', 'vb_instanceE');
    return plan;
  }

  /**
   * Set every instance's clip (one clip index for all, or per instance). An instance whose clip
   * changes is reset for the next frame (spec 21: no motion vector across a clip switch).
   */
  setClips(clips) {
    for (let i = 0; i < this.capacity; ++i) {
      const clip = typeof clips === 'number' ? clips : clips[i];
      if (this.instanceA[4 * i] !== clip) this.previous.reset(i);
      this.instanceA[4 * i] = clip;
    }
    this._updated('vb_instanceA');
  }

  /**
   * The previous frame (spec virtual-bones.md 21) for the frame at scene time `time` drawn `dt`
   * seconds after the last one (default 1/60): each instance's previous fade time and weight (a
   * time-sampled fade at time - dt) and the animation's previousTime, which the velocity pre-pass
   * (PrePassRenderer: MotionBlurPostProcess) and the probe read. Call each frame after the
   * animation's time and updateSamples(time); the viewer does.
   */
  updatePrevious(time = this.animation.time, dt = DEFAULT_FRAME_INTERVAL) {
    const b = this.instanceB;
    this.previous.update(time, dt, (i) => b.subarray(4 * i, 4 * i + 3), this.fadeSamples);
    this.animation.previousTime = this.previous.previousTime;
    if (this.meshes) this._updated('vb_instancePreviousFade');
    this._keepPreviousMatrices();
  }

  /**
   * Spec 21.1 "Instance transform": the placements now become the previous ones (each instance's
   * 'previousMatrix' thin-instance slot), so that a move after updatePrevious (applyRootMotion, a
   * new matrix) is motion in the next frame's velocity; a reset instance is placed by its
   * current matrix instead (the plugin).
   */
  _keepPreviousMatrices() {
    const copy = (to, from) => to.set(from.subarray(0, to.length));
    if (this.previousMatrices && this.matrices) copy(this.previousMatrices, this.matrices);
    if (!this.meshes || this.levels) return;  // the levels' slots are written by updateLevels
    for (const mesh of this.meshes) {
      // The mesh's own 'matrix' data (a part's collapsed copy, an adopted glTF mesh's loader-set buffer).
      const current = mesh._thinInstanceDataStorage?.matrixData;
      if (!current) continue;
      const meta = mesh.metadata.virtualBones;
      if (!meta.previousMatrix || meta.previousMatrix.length !== current.length) {
        meta.previousMatrix = Float32Array.from(current);
        mesh.thinInstanceSetBuffer('previousMatrix', meta.previousMatrix, 16, false);
      } else {
        copy(meta.previousMatrix, current);
        mesh.thinInstanceBufferUpdated('previousMatrix');
      }
    }
  }

  /**
   * Instance `index` switched clips or was teleported: its next frame has no motion (spec 21's
   * reset): its previous pose is its current one, and the plugin places it by its current matrix.
   */
  resetPrevious(index) { this.previous.reset(index); }

  /**
   * Socket (spec 8.4): the world transform of `bone` of instance `index` at scene time `time`
   * (clip, offset, rate, crossfade and layers of the instance, @vbusd/core's decoder on the stored texels;
   * its thin-instance matrix and the mesh's world matrix) as a Babylon Matrix: a prop follows each
   * character's hand with it.
   */
  socketMatrix(index, bone, time) {
    this.updateSamples(time);
    const [clip, offset, rate, fadeClip] = this.instanceA.subarray(4 * index, 4 * index + 4);
    const [fadeOffset, fadeRate, fadeWeight] = this.instanceB.subarray(4 * index, 4 * index + 3);
    const layers = this.layered ? layersOfStreams(this.instanceC, this.instanceD, this.instanceE, index, time) : null;
    const joint = layeredJointElements(this.animation, bone, Math.round(clip), offset + rate * time,
      { clip: Math.round(fadeClip), tau: fadeOffset + fadeRate * time, weight: fadeWeight }, layers);
    // Row vectors: the joint first, then the instance's placement, then the mesh's world.
    return Matrix.FromArray(joint).multiply(this.instanceMatrix(index)).multiply(this.meshes[0].computeWorldMatrix(true));
  }

  /**
   * Root motion (spec 8.5): how far instance `index`'s clip, baked in place, moves it between scene
   * times `t0` and `t1` (D(tau1) D(tau0)^-1 at its clip-local times), a Babylon Matrix in animation
   * space; the identity without root motion.
   */
  rootMotionMatrix(index, t0, t1) {
    const [clip, offset, rate] = this.instanceA.subarray(4 * index, 4 * index + 3);
    return Matrix.FromArray(rootMotionElements(this.animation, this.rootMotion, Math.round(clip), offset + rate * t0, offset + rate * t1));
  }

  /** Instance `i`'s placement as a Babylon Matrix. */
  instanceMatrix(i) {
    return this.matrices ? Matrix.FromArray(this.matrices, 16 * i) : this.meshes[0].thinInstanceGetWorldMatrices()[i].clone();
  }
}

/** The socket of instance `index` of `crowd` (crowd.socketMatrix). */
export function crowdSocketMatrix(crowd, index, bone, time) { return crowd.socketMatrix(index, bone, time); }
