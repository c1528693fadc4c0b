// Types of @vbusd/three/webgpu (src/webgpu/index.js): the same crowds under three.js' WebGPURenderer,
// skinned by TSL node graphs. Hand-written, minimal (tests/test_npm_packages.py checks the names).
import type { VirtualBonesAnimation, VirtualBonesCrowd, SkinBinding } from './index.js';

/** The shared nodes of an animation: texture, clip table, scene time, unorm16 and compact ranges, rig texture. */
export function animationNodes(animation: VirtualBonesAnimation): Record<string, unknown>;
/** Node graph of one skinned vertex: `{position, normal}` (vec3 nodes). */
export function skinVertex(animation: VirtualBonesAnimation, input: Record<string, unknown>): { position: unknown; normal: unknown };
/** Throw one line where the renderer cannot sample the animation's texture (unorm16 without 16-bit normalized formats). */
export function checkNodeSupport(renderer: object, animation: VirtualBonesAnimation): void;
/** The K bone index and weight nodes of a vertex from its skin record; `read(texel)` gives the record texel (uvec4). */
export function pulledInfluences(read: (texel: unknown) => unknown, vertex: unknown, maxInfluences: number): { indices: unknown[]; weights: unknown[] };
/** A reader of the pulled skin's records: a storage buffer on WebGPU, the RGBA32UI texture on the WebGL 2 backend. */
export function recordReader(renderer: object, binding: { records: Uint32Array; skinTexture: object }): (texel: unknown) => unknown;
/** normalize with normalize(0) = 0, as a node. */
export function safeNormalize(v: unknown): unknown;
/** Make a node material skin from `animation` (in place; returns it). */
export function skinNodeMaterial<M extends object>(material: M, animation: VirtualBonesAnimation, maxInfluences: number,
  binding?: { skin?: SkinBinding; records?: Uint32Array; skinTexture?: object; layers?: boolean }): M;
export function vertexInputs(builder: object, animation: VirtualBonesAnimation, maxInfluences: number,
  binding?: { skin?: SkinBinding; records?: Uint32Array; skinTexture?: object; layers?: boolean }): Record<string, unknown>;
/** World-space skinned positions and normals of one instance, computed by WebGPURenderer;
 * `previous: false` leaves previousPositions null and runs (and compiles) no second compute pass. */
export function probeNodeCrowd(renderer: object, crowd: VirtualBonesCrowd, index: number, time: number,
  options?: { dt?: number; previous?: boolean }): Promise<{ positions: Float32Array; normals: Float32Array; previousPositions: Float32Array | null; lod: number }>;
/** The skinVertex playback inputs of an instance at scene time `time` (materials and probe). */
export function playbackInputs(instance: Record<string, unknown>, time: unknown): Record<string, unknown>;
/** The skinVertex playback inputs of the previous frame (spec 21): previousTime, vb_instancePreviousFade (fadeTime, fadeWeight, reset, 0). */
export function previousPlaybackInputs(instance: Record<string, unknown>, time: unknown, previousTime: unknown, previousFade: unknown): Record<string, unknown>;
