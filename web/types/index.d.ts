// Types of @vbusd/three (src/index.js): Virtual Bones crowds in three.js. Hand-written, minimal:
// the names and shapes of the exports; tests/test_npm_packages.py checks that every export of the
// module is declared here. The JSDoc of each function in src/ says more.
import type { Box3, BufferGeometry, Group, Material, Matrix4, WebGLRenderer } from 'three';

export type Encoding = 'crossMatrix' | 'affineMatrix' | 'quatTranslation' | 'dualQuat' | 'compactQuatTranslation';
export type TexelFormat = 'float16' | 'float32' | 'unorm16' | 'uint32';
export type SkinBinding = 'attributes' | 'pulled';
export type Texels = Uint16Array | Float32Array | Uint32Array;

/** The layout metadata of a Virtual Bones texture (spec "Layout metadata"). */
export interface Layout {
  formatVersion: number;
  formatMinorVersion?: number;
  encoding: Encoding;
  texelFormat: TexelFormat;
  boneCount: number;
  width: number;
  height: number;
  clips: Array<{ name: string; firstRow: number; rowCount: number; rowsPerSecond: number; loop: boolean; startTime?: number }>;
  [key: string]: unknown;
}

/** An error in the data handed to the runtime, or a browser that cannot run it. */
export class VirtualBonesError extends Error {
  constructor(message: string);
}

/** One Virtual Bones texture with its layout metadata, clip table and clock. */
export class VirtualBonesAnimation {
  constructor(options: { layout: Layout; texels: Texels; clipExtents?: number[][][] | null; name?: string });
  readonly name: string;
  readonly layout: Layout;
  readonly clips: Layout['clips'];
  /** The stored texels, as given (the CPU decoder of sockets reads them). */
  readonly texels: Texels;
  /** Scene time in seconds: an instance's clip-local time is timeOffset + playbackRate * time. */
  time: number;
  /** Scene time of the previous frame (vb_previousTime; VirtualBonesCrowd.updatePrevious sets it). */
  previousTime: number;
  clipIndex(name: string): number;
  maskIndex(name: string): number;
  boundsOfClips(clipIndices: number[]): Box3 | null;
  checkSupport(renderer: WebGLRenderer): void;
  dispose(): void;
}

/** Per-instance data of a crowd: matrices (16 per instance, T R S) and playback. */
export interface Instances {
  count: number;
  matrices: Float32Array;
  clip: Int32Array;
  timeOffset: Float32Array;
  playbackRate: Float32Array;
  fadeClip?: Int32Array;
  fadeTimeOffset?: Float32Array;
  fadePlaybackRate?: Float32Array;
  fadeWeight?: Float32Array;
  /** A fade over stage time: per fade field its stage times and S x N values (VirtualBonesCrowd.updateSamples). */
  fadeSamples?: { [field: string]: { times: ArrayLike<number>; values: ArrayLike<number> } } | null;
  layerClip?: Int32Array;
  layerTimeOffset?: Float32Array;
  layerPlaybackRate?: Float32Array;
  layerWeight?: Float32Array;
  layerMask?: Int32Array;
  [key: string]: unknown;
}

export interface CrowdMesh {
  geometry: BufferGeometry;
  maxInfluences: number;
  name?: string;
  [key: string]: unknown;
}

/** A crowd: one InstancedMesh per bound mesh, skinned on any three.js material. */
export class VirtualBonesCrowd extends Group {
  constructor(options: {
    animation: VirtualBonesAnimation;
    meshes: CrowdMesh[];
    instances: Instances;
    material?: (name: string) => Material;
    name?: string;
    skin?: SkinBinding | null;
    levels?: CrowdMesh[][] | null;
    screenSizes?: number[] | null;
    hysteresis?: number;
    rootMotion?: { upAxis: string; tracks: number[][][] } | null;
    skinMaterial?: ((material: Material, animation: VirtualBonesAnimation, maxInfluences: number, binding: SkinBinding) => Material) | null;
  });
  readonly animation: VirtualBonesAnimation;
  readonly capacity: number;
  /** Instances drawn (the first `count`). */
  count: number;
  readonly trianglesDrawn: number;
  setFade(index: number, fade?: { clip?: number; timeOffset?: number; playbackRate?: number; weight?: number }): void;
  setLayer(index: number, slot: number, layer?: { clip?: number; mask?: number | string; timeOffset?: number; playbackRate?: number; weight?: number; mode?: 'override' | 'additive' | 0 | 1; reference?: { clip?: number; time?: number } | null }): void;
  /** Format 1.3: the clip markers every instance crosses between scene times t0 and t1 (spec 23.5). */
  events(t0: number, t1: number): { instance: number; name: string; time: number }[];
  /** Format 1.3: instance `index` plays a blend space, as its clip plus layer slots 0 and 1 under the every-bone mask. */
  setBlend(index: number, blend: { space: string; x?: number; y?: number; phase?: number; playbackRate?: number }): { clip: number; timeOffset: number; playbackRate: number; layers: { clip: number; timeOffset: number; playbackRate: number; weight: number }[] };
  /** A fade over stage time: every instance's time-sampled fade at scene time `time` (no-op without samples). */
  updateSamples(time: number): void;
  /** The previous frame (motion vectors): previous fades and the animation's previousTime for interval dt (default 1/60). */
  updatePrevious(time?: number, dt?: number): void;
  /** Instance `index` switched clips or was teleported: zero motion at the next frame. */
  resetPrevious(index: number): void;
  socketMatrix(index: number, bone: number, time: number): Matrix4;
  /** Instance `index`'s layers at scene time `time` as @vbusd/core's layeredJointElements takes them (null without layers). */
  socketLayers(index: number, time: number): { clip: number; tau: number; weight: number; mask: number }[] | null;
  /** Root motion (spec 8.5) of instance `index` between scene times t0 and t1, in animation space. */
  rootMotionMatrix(index: number, t0: number, t1: number): Matrix4;
  /** Move every instance by its root motion between scene times t0 and t1 (spec 8.5); part meshes follow (spec 22.3). */
  applyRootMotion(t0: number, t1: number): void;
  /** Rewrite the part meshes' matrices from the placements, collapsed where the mask hides a part (spec 22.3). */
  applyParts(): void;
  rootMotion: { upAxis: string; tracks: number[][][] } | null;
  /** What instance `index` shows (format 1.3 crowd variety). */
  varietyOf(index: number): { tint: number[]; variant: number; variantName: string | null; parts: number; partNames: string[] };
  updateLevels(camera: object): void;
  boundsOfInstances(): Box3;
  updateBounds(): void;
}

export interface Description {
  upAxis: 'Y' | 'Z';
  animations: Array<{ animation: VirtualBonesAnimation; meshes: CrowdMesh[]; levels?: CrowdMesh[][] | null; screenSizes?: number[] | null }>;
  crowds: Array<{ animation: number; instances: Instances; name?: string; matrix?: Matrix4 | null; [key: string]: unknown }>;
  [key: string]: unknown;
}

export function shaderModule(encoding: Encoding, texelFormat: TexelFormat, maxInfluences?: number, maxClips?: number,
  skin?: SkinBinding, layers?: boolean, maxBones?: number): string;
export function patchMaterial<M extends Material>(material: M, animation: VirtualBonesAnimation, maxInfluences: number,
  options?: { skin?: SkinBinding; skinTexture?: object | null; layers?: boolean }): M;
export function patchVertexShader(vertexShader: string, animation: VirtualBonesAnimation, maxInfluences: number,
  skin?: SkinBinding, layers?: boolean): string;
export function skinningDeclarations(animation: VirtualBonesAnimation, maxInfluences: number, skin?: SkinBinding, layers?: boolean): string;
export function skinningCall(skin?: SkinBinding, layers?: boolean): string;
export const SKINNING_CALL: string;

export const SKIN_BINDINGS: SkinBinding[];
export const DEFAULT_SKIN: SkinBinding;
export function packSkin(indexSets: ArrayLike<number>[], weightSets: ArrayLike<number>[], maxInfluences: number, name?: string): Uint32Array;
export function pullSkin(geometry: BufferGeometry, maxInfluences: number): BufferGeometry;
export function skinTexture(records: Uint32Array): object;
export function skinRecordTexels(maxInfluences: number): number;
export function skinRecordWords(maxInfluences: number): number;

export function skinnedGeometry(arrays: {
  positions: Float32Array; normals?: Float32Array | null; triangles: Uint32Array; boneIndices: ArrayLike<number>;
  boneWeights: ArrayLike<number>; pointIndex?: Uint32Array | null; pointCount?: number | null; name?: string;
}): BufferGeometry;
export function instancesFromPlacement(placement: {
  positions: ArrayLike<number>; orientations: ArrayLike<number>; scales?: ArrayLike<number> | null; clip: Int32Array;
  timeOffset: Float32Array; playbackRate: Float32Array; fade?: object | null; layers?: object | null;
}): Instances;
export function singleInstance(clip?: number): Instances;

/** The plain files of `vbusd view` (scene.json and scene.bin) as a Description. */
export function parsePlainScene(scene: object, buffer: ArrayBuffer): Description;
export function loadPlainScene(url: string): Promise<Description>;
export function buildObjects(description: Description, options?: {
  material?: (name: string) => Material; skin?: SkinBinding | null;
  skinMaterial?: ((material: Material, animation: VirtualBonesAnimation, maxInfluences: number, binding: SkinBinding) => Material) | null;
}): { group: Group; crowds: VirtualBonesCrowd[]; animations: VirtualBonesAnimation[] };

/** World-space skinned positions and normals of one instance, computed by the GPU;
 * `previous: false` leaves previousPositions empty and compiles a shader that skins once. */
export function probeCrowd(renderer: WebGLRenderer, crowd: VirtualBonesCrowd, index: number, time: number,
  options?: { dt?: number; previous?: boolean }): { positions: Float32Array; normals: Float32Array; previousPositions: Float32Array; lod: number };
/** Declarations of the previous-frame inputs (vb_instancePreviousFade, vb_previousTime). */
export function previousDeclarations(): string;
/** Statements after skinningCall: the previous-frame skinned position into vbPreviousPosition. */
export function previousSkinningCall(layers?: boolean): string;
/** A crowd mesh's velocity material: ndcCurrent - ndcPrevious (packed: three's VelocityShader encoding). */
export function velocityMaterial(animation: VirtualBonesAnimation, maxInfluences: number,
  binding?: { skin?: SkinBinding; skinTexture?: object | null; layers?: boolean }, options?: { packed?: boolean }): Material;
/** The velocity material of a rigid mesh. */
export function staticVelocityMaterial(options?: { packed?: boolean }): Material;
/** Draw a scene's velocity (crowd meshes with their previous pose) into `target`. */
export function renderVelocity(renderer: WebGLRenderer, scene: object, camera: object, target: object | null, options?: { packed?: boolean }): void;

export function parseVirtualBonesKTX2(bytes: Uint8Array | ArrayBuffer, name?: string): Promise<{ layout: Layout; texels: Texels }>;

/** The VBUSD_virtual_bones glTF extension's name. */
export const EXTENSION: 'VBUSD_virtual_bones';
/** GLTFLoader plugin: `loader.register((parser) => new VirtualBonesGLTFPlugin(parser))`. */
export class VirtualBonesGLTFPlugin {
  constructor(parser: object);
  readonly name: 'VBUSD_virtual_bones';
  afterRoot(gltf: object): Promise<void>;
}
export function descriptionFromGLTF(gltf: object): Description;

export function rowPosition(clip: Layout['clips'][number], tau: number): { i0: number; i1: number; f: number };
export function boneRows(animation: VirtualBonesAnimation, clipIndex: number, tau: number, bone: number): number[][];
export function socketMatrix(animation: VirtualBonesAnimation, bone: number, clipIndex: number, tau: number,
  fade?: { clip: number; tau: number; weight: number } | null,
  layers?: { clip: number; tau: number; weight: number; mask: number | string | ArrayLike<number>; mode?: 'override' | 'additive'; reference?: { clip: number; tau: number } }[] | null): Matrix4;
export function rootMotionMatrix(animation: VirtualBonesAnimation, rootMotion: { upAxis: string; tracks: number[][][] } | null,
  clipIndex: number, t0: number, t1: number): Matrix4;
