// Types of @vbusd/babylon (src/index.js): Virtual Bones crowds in Babylon.js. Hand-written, minimal:
// the names and shapes of the exports; tests/test_npm_packages.py checks that every export of the
// module is declared here. The JSDoc of each function in src/ says more.
import type { Engine, Material, MaterialPluginBase, Matrix, Mesh, Scene } from '@babylonjs/core';

export type Encoding = 'crossMatrix' | 'affineMatrix' | 'quatTranslation' | 'dualQuat' | 'compactQuatTranslation';
export type TexelFormat = 'float16' | 'float32' | 'unorm16' | 'uint32';
export type SkinBinding = 'attributes' | 'pulled';
export interface Binding { skin?: SkinBinding; skinTexture?: object | null; layers?: boolean }

/** An error in the data handed to the runtime, or a browser that cannot run it. */
export class VirtualBonesError extends Error {
  constructor(message: string);
}

/** The GLSL of `vbusd shader --lang glsl --no-main` (@vbusd/core's), character for character. */
export function shaderModule(encoding: Encoding, texelFormat: TexelFormat, maxInfluences?: number, maxClips?: number, skin?: SkinBinding, layers?: boolean, maxBones?: number): string;
export function skinningDeclarations(animation: VirtualBonesAnimation, maxInfluences: number, keyword?: string, skin?: SkinBinding, layers?: boolean): string;
export function skinningCall(position: string, normal: string, maxInfluences: number, skin?: SkinBinding, layers?: boolean): string;
/** Statements after skinningCall: the previous-frame skinned position (spec 21) into `target`. */
export function previousSkinningCall(position: string, normal: string, target: string, layers?: boolean): string;

/** One Virtual Bones texture on a Babylon scene: its RawTexture, clip table and clock. */
export class VirtualBonesAnimation {
  constructor(scene: Scene, options: { layout: Record<string, any>; texels: Uint16Array | Float32Array | Uint32Array; clipExtents?: number[][][] | null; name?: string });
  readonly name: string;
  readonly layout: Record<string, any>;
  readonly clips: Array<{ name: string; firstRow: number; rowCount: number; rowsPerSecond: number; loop: boolean }>;
  /** Scene time in seconds. */
  time: number;
  /** Scene time of the previous frame (vb_previousTime): VirtualBonesCrowd.updatePrevious sets it. */
  previousTime: number;
  clipIndex(name: string): number;
  maskIndex(name: string): number;
  dispose(): void;
}

/** The material plugin that skins a StandardMaterial or PBRMaterial from a Virtual Bones texture. */
export class VirtualBonesPluginMaterial extends MaterialPluginBase {
  constructor(material: Material, animation: VirtualBonesAnimation, maxInfluences?: number, binding?: Binding);
}
/** Make `material` skin from `animation` (the plugin and a ShadowDepthWrapper); returns the plugin. */
export function skinMaterial(material: Material, animation: VirtualBonesAnimation, maxInfluences?: number, binding?: Binding): VirtualBonesPluginMaterial;
/** The vertex streams of a skinned mesh. */
export function vertexInputs(maxInfluences: number, skin?: SkinBinding, layers?: boolean): string[];

/** A crowd: one Mesh per rest mesh, its instances as thin instances. */
export class VirtualBonesCrowd {
  constructor(scene: Scene, options: {
    animation: VirtualBonesAnimation;
    meshes?: Array<Record<string, any>>;
    instances: { count: number; matrices?: Float32Array; clip: ArrayLike<number>; timeOffset: ArrayLike<number>; playbackRate: ArrayLike<number>; [key: string]: unknown };
    material?: ((name: string) => Material) | null;
    name?: string;
    adopt?: Mesh[] | null;
    skin?: SkinBinding | null;
    rootMotion?: { upAxis: string; tracks: number[][][] } | null;
    /** Levels of detail 1, 2, ...: each its meshes as `meshes` gives LOD 0's. */
    levels?: Array<Array<Record<string, any>>> | null;
    screenSizes?: number[] | null;
    hysteresis?: number;
  });
  readonly scene: Scene;
  readonly animation: VirtualBonesAnimation;
  readonly name: string;
  readonly capacity: number;
  readonly meshes: Mesh[];
  /** Instances drawn (the first `count` of the capacity). */
  count: number;
  setFade(index: number, fade: { fadeClip: number; fadeTimeOffset?: number; fadePlaybackRate?: number; fadeWeight: number }): void;
  /** Format 1.3: the clip markers every instance crosses between scene times t0 and t1 (spec 23.5). */
  events(t0: number, t1: number): { instance: number; name: string; time: number }[];
  updateSamples(time: number): void;
  setLayer(index: number, slot: number, layer?: { clip?: number; mask?: number | string; timeOffset?: number; playbackRate?: number; weight?: number; mode?: 'override' | 'additive' | 0 | 1; reference?: { clip?: number; time?: number } | null }): void;
  setBlend(index: number, blend: { space: string; x?: number; y?: number; phase?: number; playbackRate?: number }): { clip: number; timeOffset: number; playbackRate: number; layers: { clip: number; timeOffset: number; playbackRate: number; weight: number }[] };
  setClips(clips: number | ArrayLike<number>): void;
  /** The previous frame (motion vectors): previous fades and the animation's previousTime for interval dt (default 1/60). */
  updatePrevious(time?: number, dt?: number): void;
  /** Instance `index` switched clips or was teleported: zero motion at the next frame. */
  resetPrevious(index: number): void;
  /** What instance `index` shows (format 1.3 crowd variety). */
  varietyOf(index: number): { tint: number[]; variant: number; variantName: string | null; parts: number; partNames: string[] };
  rootMotionMatrix(index: number, t0: number, t1: number): Matrix;
  /** Move every instance by its root motion between scene times t0 and t1 (spec 8.5); part meshes follow (spec 22.3). */
  applyRootMotion(t0: number, t1: number): void;
  socketMatrix(index: number, bone: number, time: number): Matrix;
  instanceMatrix(index: number): Matrix;
  /** Each level's meshes (null without levels of detail). */
  readonly levels: Mesh[][] | null;
  meshesOfLevel(level: number): Mesh[];
  /** The level instance `index` drew at the last updateLevels (-1: culled). */
  levelOf(index: number): number;
  updateLevels(camera: object): void;
  readonly trianglesDrawn: number;
}

/** World-space skinned positions and normals of one instance, computed by the GPU (WebGL 2);
 * `previous: false` leaves previousPositions empty and compiles a shader that skins once. */
export function probeBabylonCrowd(engine: Engine, crowd: VirtualBonesCrowd, index: number, time: number,
  options?: { dt?: number; previous?: boolean }): { positions: Float32Array; normals: Float32Array; previousPositions: Float32Array; lod: number };

/** The VBUSD_virtual_bones glTF extension's name. */
export const EXTENSION: 'VBUSD_virtual_bones';
/** Babylon glTF loader extension for VBUSD_virtual_bones. */
export class VirtualBonesGLTFLoaderExtension {
  constructor(loader: object, options?: { material?: ((name: string) => Material) | null });
  readonly name: 'VBUSD_virtual_bones';
  enabled: boolean;
  dispose(): void;
}
/** Register the extension with Babylon's glTF loader (every later load uses it). */
export function registerVirtualBonesGLTFExtension(options?: { material?: ((name: string) => Material) | null }): void;

/** Socket (spec 8.4) of an instance: the world transform of `bone` at scene time `time`. */
export function crowdSocketMatrix(crowd: VirtualBonesCrowd, index: number, bone: number, time: number): Matrix;
