// Types of @vbusd/gltf-transform (src/index.mjs): the VBUSD_virtual_bones extension for
// glTF-Transform. Hand-written, minimal: tests/test_npm_packages.py checks that every export of the
// module is declared here.
import type { Accessor, Buffer, Extension, ExtensionProperty, IProperty, ReaderContext, RefMap, Transform, WriterContext } from '@gltf-transform/core';

export const VBUSD_VIRTUAL_BONES: 'VBUSD_virtual_bones';
/** The extension's own version (spec/extensions/VBUSD_virtual_bones). */
export const EXTENSION_VERSION: number;
/** Byte alignment of a texture's buffer view. */
export const TEXTURE_ALIGNMENT: number;
/** The instance attributes a crowd node must have: name -> [accessor type, default value]. */
export const INSTANCE_DEFAULTS: Readonly<Record<string, [string, number[]]>>;
/** quantize() pattern that leaves the attributes Virtual Bones skinning reads exact. */
export const VBUSD_QUANTIZE_PATTERN: RegExp;

/** Raised for a document this extension cannot read or write as a working package. */
export class VirtualBonesError extends Error {
  constructor(message: string);
}

interface IVirtualBonesAnimation extends IProperty {
  path: string | null;
  texture: Uint8Array | null;
  layout: Record<string, any> | null;
  clipExtents: number[][][] | null;
  buffer: Buffer;
}

/** One Virtual Bones animation: its KTX2 texture (bytes), layout metadata and clip extents. */
export class VirtualBonesAnimation extends ExtensionProperty<IVirtualBonesAnimation> {
  readonly extensionName: 'VBUSD_virtual_bones';
  readonly propertyType: 'VirtualBonesAnimation';
  readonly parentTypes: string[];
  protected init(): void;
  getPath(): string | null;
  setPath(path: string | null): this;
  getTexture(): Uint8Array | null;
  setTexture(bytes: Uint8Array | null): this;
  getLayout(): Record<string, any> | null;
  setLayout(layout: Record<string, any> | null): this;
  listClips(): Array<{ name: string; firstRow: number; rowCount: number; rowsPerSecond: number; loop: boolean; startTime?: number }>;
  getClipExtents(): number[][][] | null;
  setClipExtents(extents: number[][][] | null): this;
  getBuffer(): Buffer | null;
  setBuffer(buffer: Buffer | null): this;
}

interface IVirtualBonesBinding extends IProperty {
  animation: VirtualBonesAnimation;
  influences: number;
  path: string | null;
  part: number | null;
}

/** The binding of one mesh primitive to an animation. */
export class VirtualBonesBinding extends ExtensionProperty<IVirtualBonesBinding> {
  readonly extensionName: 'VBUSD_virtual_bones';
  readonly propertyType: 'VirtualBonesBinding';
  readonly parentTypes: string[];
  protected init(): void;
  getAnimation(): VirtualBonesAnimation | null;
  setAnimation(animation: VirtualBonesAnimation | null): this;
  getInfluences(): number;
  setInfluences(influences: number): this;
  getPath(): string | null;
  setPath(path: string | null): this;
  /** Crowd variety (vbusd format 1.3): the optional part this primitive is (bit j of _VB_PARTS), or null. */
  getPart(): number | null;
  setPart(part: number | null): this;
}

interface IVirtualBonesSamples extends IProperty {
  times: Record<string, number[]>;
  values: RefMap<Accessor>;
}

/** Time samples of a crowd node's fade and layer instance attributes (spec/runtime-package.md 5.1). */
export class VirtualBonesSamples extends ExtensionProperty<IVirtualBonesSamples> {
  readonly extensionName: 'VBUSD_virtual_bones';
  readonly propertyType: 'VirtualBonesSamples';
  readonly parentTypes: string[];
  protected init(): void;
  listNames(): string[];
  getTimes(name: string): number[] | null;
  getValues(name: string): Accessor | null;
  setSamples(name: string, times: number[], accessor: Accessor | null): this;
}

/** The extension: `io.registerExtensions([VBUSDVirtualBones])`. */
export class VBUSDVirtualBones extends Extension {
  static readonly EXTENSION_NAME: 'VBUSD_virtual_bones';
  readonly extensionName: 'VBUSD_virtual_bones';
  createAnimation(name?: string): VirtualBonesAnimation;
  createBinding(): VirtualBonesBinding;
  createSamples(): VirtualBonesSamples;
  listAnimations(): VirtualBonesAnimation[];
  read(context: ReaderContext): this;
  write(context: WriterContext): this;
}

/** After instance(): gives new crowd batches TRANSLATION, ROTATION and the _VB_ attributes. */
export function vbusdInstanceDefaults(): Transform;
/** quantize() that leaves POSITION and the _VB_ attributes exact. */
export function vbusdQuantize(options?: Record<string, unknown>): Transform;
/** reorder() + that quantize + EXT_meshopt_compression (lossless for positions and the skin). */
export function vbusdMeshopt(options: { encoder: unknown; extension: unknown; level?: 'medium' | 'high' }): Transform;
/** join() in which nodes drawing Virtual Bones meshes join only their own primitives. */
export function vbusdJoin(options?: Record<string, unknown>): Transform;
