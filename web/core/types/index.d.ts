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
export function rootMotionElements(source: DecoderSource, rootMotion: { upAxis: string; tracks: number[][][] } | null, clipIndex: number, t0: number, t1: number): number[];

export function clipTime(timeOffset: number, playbackRate: number, time: number): number;
export function evaluateSamples<T extends Record<string, { length: number; [i: number]: number }>>(samples: Samples | null | undefined, time: number, target: T): T;
export function placementMatrices(positions: ArrayLike<number>, orientations: ArrayLike<number>, scales?: ArrayLike<number> | null): Float32Array;
export function singleInstance(clip?: number): { count: number; matrices: Float32Array; clip: Int32Array; timeOffset: Float32Array; playbackRate: Float32Array };

export function screenSize(radius: number, distance: number, tanHalfFov: number, aspect?: number): number;
export function selectLevel(size: number, thresholds: number[], previous?: number, hysteresis?: number): number;
export function checkScreenSizes(thresholds: number[], levels: number, name?: string): void;

export function parsePlainScene(scene: object, buffer: ArrayBuffer): { upAxis: string; animations: object[]; crowds: object[] };
export function fetchPlainScene(url: string): Promise<{ upAxis: string; animations: object[]; crowds: object[] }>;

export function probeProgram(gl: WebGL2RenderingContext, key: string, vertexSource: string): WebGLProgram;
export function probeOutputs(world: string): string;
export function runFeedback(gl: WebGL2RenderingContext, program: WebGLProgram, vertexCount: number, setup: (input: FeedbackInput) => void): [Float32Array, Float32Array];
export function assetOrder(results: [Float32Array, Float32Array], info: { pointIndex?: ArrayLike<number> | null; hasNormals?: boolean; pointCount?: number }): [Float32Array, Float32Array];
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
