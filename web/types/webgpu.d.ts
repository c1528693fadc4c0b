// Types of @vbusd/three/webgpu (src/webgpu/index.js): the same crowds under three.js' WebGPURenderer,
// skinned by TSL node graphs. Hand-written, minimal (tests/test_npm_packages.py checks the names).
import type { VirtualBonesAnimation, VirtualBonesCrowd, SkinBinding } from './index.js';

/** The shared nodes of an animation: texture, clip table and scene time. */
export function animationNodes(animation: VirtualBonesAnimation): Record<string, unknown>;
/** Node graph of one skinned vertex: `{position, normal}` (vec3 nodes). */
export function skinVertex(animation: VirtualBonesAnimation, input: Record<string, unknown>): { position: unknown; normal: unknown };
/** normalize with normalize(0) = 0, as a node. */
export function safeNormalize(v: unknown): unknown;
/** Make a node material skin from `animation` (in place; returns it). */
export function skinNodeMaterial<M extends object>(material: M, animation: VirtualBonesAnimation, maxInfluences: number,
  options?: { skin?: SkinBinding }): M;
export function vertexInputs(builder: object, animation: VirtualBonesAnimation, maxInfluences: number): Record<string, unknown>;
/** World-space skinned positions and normals of one instance, computed by WebGPURenderer. */
export function probeNodeCrowd(renderer: object, crowd: VirtualBonesCrowd, index: number, time: number): Promise<{ positions: Float32Array; normals: Float32Array }>;
