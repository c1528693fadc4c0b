// Types of @vbusd/core: the engine-neutral core of vbusd's web runtimes.

export type Matrix16 = ArrayLike<number>;

export interface Clip { name: string; firstRow: number; rowCount: number; rowsPerSecond: number; loop: boolean }
export interface Layout {
  encoding: string; texelFormat: string; width: number; height: number; boneCount: number; clips: Clip[];
  unormRanges?: number[][][]; compactRanges?: number[][][]; bindTransforms?: number[][]; boneParents?: number[];
  masks?: { name: string; weights: number[] }[]; [key: string]: unknown;
}
export interface DecoderSource { name?: string; layout: Layout; texels: ArrayLike<number> }
export interface TexelData<T> { width: number; height: number; data: T }
export interface Samples { [field: string]: { times: ArrayLike<number>; values: ArrayLike<number> } }
export interface FeedbackInput {
  attribute(name: string, data: ArrayBufferView, size: number, options?: { integer?: boolean; divisor?: number; offset?: number; columns?: number }): boolean;
  constant(name: string, values: ArrayLike<number>): boolean;
  uniform(name: string): WebGLUniformLocation | null;
}

export declare class VirtualBonesError extends Error { constructor(message: string) }

export const BASE_MAX_BONES: number;
export function shaderModule(encoding: string, texelFormat: string, maxInfluences?: number, maxClips?: number, skin?: 'attributes' | 'pulled', layers?: boolean, maxBones?: number): string;
export function replaceOnce(text: string, search: string, replacement: string): string;
export function definedTestModule(text: string): string;
/** GLSL statements at the top of main() skinning `position` / `normal` into vbPosition / vbNormal (every engine's body). */
export function skinningStatements(options: {
  skin?: 'attributes' | 'pulled';
  layers?: boolean;
  position?: string;
  normal?: string;
  playback: { clip: string; tau: string; fadeClip: string; fadeTau: string; fadeWeight: string;
    layerClip?: string; layerMask?: string; layerTau?: string; layerWeight?: string };
}): string;
/** Declarations of the previous-frame inputs: vb_instancePreviousFade (fadeTime, fadeWeight, reset, 0) and vb_previousTime. */
export function previousDeclarations(keyword?: string): string;
/** GLSL statements after skinningStatements (same playback): the previous-frame pose into `target` (default vbPreviousPosition). */
export function previousSkinningStatements(options: {
  layers?: boolean;
  position?: string;
  normal?: string;
  target?: string;
  declare?: boolean;
  playback: { clip: string; tau: string; fadeClip: string; fadeTau: string; fadeWeight: string;
    layerClip?: string; layerMask?: string; layerTau?: string; layerWeight?: string };
}): string;

export const SKIN_BINDINGS: string[];
export const SKIN_TEXTURE_WIDTH: number;
export function checkSkinBinding(skin: string, name?: string): void;
export function skinRecordWords(maxInfluences: number): number;
export function skinRecordTexels(maxInfluences: number): number;
export function packSkin(indexSets: unknown[], weightSets: unknown[], maxInfluences: number, name?: string): Uint32Array;
export function skinTextureData(records: Uint32Array): TexelData<Uint32Array>;

export const TEXEL_FORMATS: Record<string, { array: Function; channels: number }>;
export const ENCODINGS: Record<string, number>;
export function checkLayout(layout: Layout, texels: ArrayLike<number>, name?: string): { encoding: string; texelFormat: string; texelsPerBone: number; maxClips: number; maxBones: number; masks: string[] };
export function widenWords(layout: Layout, texels: Uint32Array): Uint32Array;
export function clipTable(clips: Clip[], maxClips: number): Float32Array;
export function unormRanges(layout: Layout): { min: Float32Array; max: Float32Array };
export function compactRanges(layout: Layout, maxBones: number): Float32Array;
export function affineInverseRows(rows: number[][]): number[][];
export function rigTexels(layout: Layout): TexelData<Float32Array> | null;

export function fromHalf(bits: number): number;
export function rowPosition(clip: Clip, tau: number): { i0: number; i1: number; f: number };
export function boneRows(source: DecoderSource, clipIndex: number, tau: number, bone: number): number[][];
export function elementsFromRows(rows: number[][]): number[];
export function multiply(a: Matrix16, b: Matrix16): number[];
export function jointElements(source: DecoderSource, bone: number, clipIndex: number, tau: number, fade?: { clip: number; tau: number; weight: number } | null): number[];
/** A layer of a socket's pose (spec virtual-bones.md 8.6, 23.4): mask an index into the layout's masks, a name, or weights. */
export interface JointLayer { clip: number; tau: number; weight: number; mask: number | string | ArrayLike<number>; mode?: 'override' | 'additive'; reference?: { clip: number; tau: number } }
export function decomposeTRS(e: ArrayLike<number>): { t: number[]; q: number[]; s: number[] };
export function composeTRS(t: ArrayLike<number>, q: ArrayLike<number>, s: ArrayLike<number>): number[];
export function slerp(q0: ArrayLike<number>, q1: ArrayLike<number>, alpha: number): number[];
export function mixLocal(x: number[], y: number[], alpha: number): number[];
export function addLocal(x: number[], layer: number[], reference: number[], alpha: number): number[];
export function maskWeights(source: DecoderSource, mask: number | string | ArrayLike<number>): ArrayLike<number>;
export function layeredJoint(source: DecoderSource, bone: number, clipIndex: number, tau: number, layers: JointLayer[]): number[];
export function layeredJointElements(source: DecoderSource, bone: number, clipIndex: number, tau: number, fade?: { clip: number; tau: number; weight: number } | null, layers?: JointLayer[] | null): number[];
export function rootMotionElements(source: DecoderSource, rootMotion: { upAxis: string; tracks: number[][][] } | null, clipIndex: number, t0: number, t1: number): number[];

export function clipTime(timeOffset: number, playbackRate: number, time: number): number;
export function evaluateSamples<T extends Record<string, { length: number; [i: number]: number }>>(samples: Samples | null | undefined, time: number, target: T): T;
export function placementMatrices(positions: ArrayLike<number>, orientations: ArrayLike<number>, scales?: ArrayLike<number> | null): Float32Array;
export function singleInstance(clip?: number): { count: number; matrices: Float32Array; clip: Int32Array; timeOffset: Float32Array; playbackRate: Float32Array };

/** The frame interval assumed when none is given (1/60 s; spec virtual-bones.md 21). */
export const DEFAULT_FRAME_INTERVAL: number;
export function checkFrameInterval(dt: number, where?: string): number;
/** timeOffset + playbackRate * (time - dt): an instance's clip-local time of the previous frame. */
export function previousClipTime(timeOffset: number, playbackRate: number, time: number, dt?: number): number;
/** Per-instance previous-frame inputs (vb_instancePreviousFade: fadeTime, fadeWeight, reset, 0) and vb_previousTime. */
export class PreviousFrame {
  constructor(count: number);
  readonly count: number;
  readonly values: Float32Array;
  time: number;
  dt: number;
  previousTime: number;
  reset(i: number): void;
  update(time: number, dt: number, fade: (i: number) => ArrayLike<number>, samples?: Samples | null): Float32Array;
}

export function screenSize(radius: number, distance: number, tanHalfFov: number, aspect?: number): number;
export function selectLevel(size: number, thresholds: number[], previous?: number, hysteresis?: number): number;
export function checkScreenSizes(thresholds: number[], levels: number, name?: string): void;

export function parsePlainScene(scene: object, buffer: ArrayBuffer): { upAxis: string; animations: object[]; crowds: object[] };
export function fetchPlainScene(url: string): Promise<{ upAxis: string; animations: object[]; crowds: object[] }>;

/** Layers per instance the runtimes play. */
export const RUNTIME_LAYERS: number;
/** A runtime package crowd node's playback arrays (spec/runtime-package.md 5.1): clip, time, crossfade (and its samples), layers (additive ones too), blends as layers. */
export function packagePlayback(options: {
  attributes: Record<string, number>;
  samples?: Record<string, { times: number[]; values: number }>;
  count: number;
  read: (accessor: number) => Promise<ArrayLike<number>>;
  what?: string;
  /** The animation's layout metadata: its blendSpaces, markers, clips and masks play _VB_BLEND_* as layers. */
  layout?: object | null;
}): Promise<{ clip: Int32Array; timeOffset: Float32Array; playbackRate: Float32Array; [field: string]: unknown }>;

export const PROBE_VARYINGS: string[];
export function probeProgram(gl: WebGL2RenderingContext, key: string, vertexSource: string, options?: { previous?: boolean }): WebGLProgram;
export function probeOutputs(world: string, options?: { previous?: boolean }): string;
export function runFeedback(gl: WebGL2RenderingContext, program: WebGLProgram, vertexCount: number, setup: (input: FeedbackInput) => void): Float32Array[];
export function assetOrder(results: Float32Array[], info: { pointIndex?: ArrayLike<number> | null; hasNormals?: boolean; pointCount?: number }): [Float32Array, Float32Array, Float32Array];
export function concatenate(arrays: ArrayLike<number>[]): Float32Array;

/** A blend space as the layout metadata's `blendSpaces` holds it (format 1.3, spec 23.6). */
export interface BlendSpace { name: string; dimensions: 1 | 2; points: { clip: string; x: number; y?: number }[]; syncMarker?: string }
/** A clip marker as the layout metadata's `markers` holds it (format 1.3, spec 23.5). */
export interface ClipMarker { clip: string; name: string; time: number }
export function triangulate(points: [number, number][]): [number, number, number][];
export function blendWeights(space: BlendSpace, x: number, y?: number): [number, number][];
export function phaseTimes(space: BlendSpace, durations: Record<string, number>, markers: ClipMarker[] | undefined, phase: number): number[];
export function layerWeights(weights: [number, number][]): [number, number][];
export function crossedMarkers(markers: ClipMarker[] | undefined, clip: string, duration: number, loop: boolean, t0: number, t1: number): { name: string; time: number }[];
export function crowdEvents(markers: ClipMarker[] | undefined, clips: { name: string; rowCount: number; rowsPerSecond: number; loop: boolean }[], clip: ArrayLike<number>, timeOffset: ArrayLike<number>, playbackRate: ArrayLike<number>, t0: number, t1: number): { instance: number; name: string; time: number }[];
export function blendLayers(space: BlendSpace, x: number, y: number, phase: number, playbackRate: number, clips: { name: string; rowCount: number; rowsPerSecond: number; loop: boolean }[], markers: ClipMarker[] | undefined): { clip: number; timeOffset: number; playbackRate: number; layers: { clip: number; timeOffset: number; playbackRate: number; weight: number }[] };

/** Additive layers in the runtimes (format 1.3, spec 23.4): the packed mask code of a layer slot. */
export const LAYER_MASK_SPAN: number;
export const ADDITIVE_LAYERS_DEFINE: string;
export function layerModeOf(mode: 'override' | 'additive' | 0 | 1 | undefined | null, what?: string): 0 | 1;
export function packLayerMask(mask: number, mode: 'override' | 'additive' | 0 | 1, referenceClip: number, clipCount: number, what?: string): number;
export function maskOfCode(code: number): number;
/** Instance `index`'s two layers at scene time `sceneTime` decoded from the runtimes' per-instance layer streams (4 values per instance each). */
export function layersOfStreams(clipMask: ArrayLike<number>, time: ArrayLike<number>, weight: ArrayLike<number>, index: number, sceneTime: number): {
  clip: number; tau: number; weight: number; mask: number; mode: 'override' | 'additive'; reference: { clip: number; tau: number } | null }[];
/** The KTX2 container of a file (header, level index, key/value data), every region checked. */
export function readKTX2Container(data: Uint8Array, name?: string): {
  vkFormat: number; typeSize: number; pixelWidth: number; pixelHeight: number; pixelDepth: number;
  layerCount: number; faceCount: number; levelCount: number; supercompressionScheme: number;
  keyValue: Record<string, Uint8Array>; levels: { levelData: Uint8Array; uncompressedByteLength: number }[];
};
/** A Virtual Bones KTX2 file's layout metadata and texels (Zstandard levels inflated with `inflate`, default zstddec). */
export function parseVirtualBonesKTX2(bytes: Uint8Array | ArrayBuffer, name?: string,
  options?: { inflate?: (data: Uint8Array, size: number) => Promise<Uint8Array> }): Promise<{ layout: object; texels: Uint16Array | Float32Array | Uint32Array }>;
/** Crowd variety (format 1.3): per-instance tint, material variant and parts mask. */
export interface VarietyInstances {
  count: number;
  tint?: Float32Array | null;
  variant?: Int32Array | null;
  parts?: Int32Array | null;
  variantNames?: string[];
  variantColors?: number[][];
  partNames?: string[];
}
export function isVaried(instances: VarietyInstances): boolean;
export function instanceColors(instances: VarietyInstances): Float32Array | null;
export function partBit(meshName: string, partNames?: string[]): number;
export function partMatrices(matrices: Float32Array, parts: Int32Array | null, bit: number): Float32Array;
/** Instance i's matrix of a part into slot `at` of a level's list, collapsed where `mask` hides part `bit` (spec 22.3). */
export function partMatrixAt(out: Float32Array, at: number, matrices: Float32Array, i: number, mask: number, bit: number): Float32Array;
/** Placement i becomes P * delta (root motion in the instance's own space, spec 8.5); in place. */
export function moveInstance(matrices: Float32Array, i: number, delta: ArrayLike<number>): Float32Array;
export function varietyOf(instances: VarietyInstances, i: number): { tint: number[]; variant: number; variantName: string | null; parts: number; partNames: string[] };
export function packageVariety(json: object, meshIndex: number, arrays?: { tint?: ArrayLike<number> | null; variant?: ArrayLike<number> | null; parts?: ArrayLike<number> | null }, count?: number): Partial<VarietyInstances>;
