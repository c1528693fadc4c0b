// Crowd variety (format 1.3, spec/virtual-bones.md 22): per-instance tint, material variant and
// parts mask. Engine-neutral: every runtime colours, selects and hides with these, so the three.js
// (WebGL and WebGPU) and Babylon.js crowds show the same crowd.
//
// instances (parsePlainScene, or a runtime's glTF loader): `tint` Float32Array(3 N) linear RGB,
// `variant` Int32Array(N) (-1: none), `parts` Int32Array(N) (bit j shows part j), and per crowd
// `variantNames`, `variantColors` ([[r, g, b], ...] linear base colours) and `partNames`.

import { VirtualBonesError } from './errors.js';

/** Whether `instances` carry any variety (a 1.3 crowd). */
export function isVaried(instances) {
  return Boolean(instances.tint || instances.variant || instances.parts);
}

/**
 * Per-instance colour multipliers, 3 per instance (linear RGB): the variant's base colour (the
 * material the variant selects; 1 without a variant) times the tint (1 without one). A runtime
 * multiplies its material's colour by it, the material's own colour set to white when the crowd
 * has variants (the variant then gives the base colour). Null for a crowd without tint or variant.
 */
export function instanceColors(instances) {
  const { count, tint = null, variant = null, variantColors = [] } = instances;
  if (!tint && !variant) return null;
  const out = new Float32Array(3 * count).fill(1);
  for (let i = 0; i < count; ++i) {
    const v = variant ? variant[i] : -1;
    if (v >= variantColors.length) throw new VirtualBonesError(`instance ${i} has variant ${v}; the crowd has ${variantColors.length}`);
    for (let c = 0; c < 3; ++c) {
      out[3 * i + c] = (v >= 0 ? variantColors[v][c] : 1) * (tint ? tint[3 * i + c] : 1);
    }
  }
  return out;
}

/**
 * The part bit of a mesh (spec 22.3: part j is the prototype's child named partNames[j], which is
 * the bound mesh's prim name), or -1 for a mesh every instance draws.
 */
export function partBit(meshName, partNames = []) {
  const name = String(meshName ?? '').split('/').pop();
  return partNames.indexOf(name);
}

/**
 * Instance matrices (16 per instance, column-major) of a part's mesh: the crowd's, with the linear
 * part (scale, rotation) zero for the instances whose mask leaves part `bit` out, which collapses
 * the part to the instance's position (degenerate triangles: nothing drawn) in the part's one
 * instanced draw. The translation and the last row stay, so bounds stay finite (w = 1). A mesh of
 * no part (bit -1), or a crowd without masks, keeps every matrix.
 */
export function partMatrices(matrices, parts, bit) {
  if (bit < 0 || !parts) return matrices;
  const out = Float32Array.from(matrices);
  for (let i = 0; i < parts.length; ++i) if (!((parts[i] >> bit) & 1)) out.fill(0, 16 * i, 16 * i + 12);
  return out;
}

/**
 * One instance's matrix of a part's mesh into slot `at` of `out` (a level's compact instance list,
 * spec 22.3 "Parts and levels of detail"): instance `i` of `matrices`, its linear part zero when
 * mask `mask` leaves part `bit` out (as partMatrices). Levels choose where an instance is drawn,
 * the mask whether its part is: both apply.
 */
export function partMatrixAt(out, at, matrices, i, mask, bit) {
  out.set(matrices.subarray(16 * i, 16 * i + 16), 16 * at);
  if (bit >= 0 && !((mask >> bit) & 1)) out.fill(0, 16 * at, 16 * at + 12);
  return out;
}

/** What instance `i` shows: `{tint: [r, g, b], variant (-1: none), variantName, parts (mask), partNames}`. */
export function varietyOf(instances, i) {
  const { tint = null, variant = null, parts = null, variantNames = [], partNames = [] } = instances;
  const v = variant ? variant[i] : -1;
  return {
    tint: tint ? [tint[3 * i], tint[3 * i + 1], tint[3 * i + 2]] : [1, 1, 1],
    variant: v,
    variantName: v >= 0 ? (variantNames[v] ?? null) : null,
    parts: parts ? parts[i] : (1 << partNames.length) - 1,
    partNames: [...partNames],
  };
}

/**
 * The variety of a crowd node of a runtime package (spec/runtime-package.md 13) as instance fields:
 * `tint`, `variant`, `parts` from its `_VB_TINT`, `_VB_VARIANT`, `_VB_PARTS` accessors (already read,
 * or null), the variants' names from the root `KHR_materials_variants` and their base colours from
 * the materials the mesh's first primitive maps them to (`baseColorFactor`, as stored: linear), and
 * the part names from the primitives' `VBUSD_virtual_bones.part` bits (the mesh's prim name, the
 * last element of `path`). `{}` for a node without variety.
 */
export function packageVariety(json, meshIndex, { tint = null, variant = null, parts = null } = {}, count = 0) {
  if (!tint && !variant && !parts) return {};
  const out = {};
  const check = (array, width, name) => {
    if (array && array.length !== width * count) throw new VirtualBonesError(`${name} has ${array.length / width} values for ${count} instances`);
  };
  check(tint, 3, '_VB_TINT');
  check(variant, 1, '_VB_VARIANT');
  check(parts, 1, '_VB_PARTS');
  const primitives = json.meshes?.[meshIndex]?.primitives ?? [];
  if (tint) out.tint = Float32Array.from(tint);
  if (variant) {
    const variants = json.extensions?.KHR_materials_variants?.variants ?? [];
    out.variantNames = variants.map((v) => v.name);
    const mappings = primitives[0]?.extensions?.KHR_materials_variants?.mappings ?? [];
    out.variantColors = out.variantNames.map((_, k) => {
      const mapping = mappings.find((m) => (m.variants ?? []).includes(k));
      const factor = mapping ? json.materials?.[mapping.material]?.pbrMetallicRoughness?.baseColorFactor : null;
      return factor ? factor.slice(0, 3) : [1, 1, 1];
    });
    out.variant = Int32Array.from(variant, (v) => Math.floor(v + 0.5));
    for (const v of out.variant) if (!(v >= 0 && v < out.variantNames.length)) throw new VirtualBonesError(`_VB_VARIANT ${v} is not a variant of KHR_materials_variants (${out.variantNames.length})`);
  }
  if (parts) {
    const names = [];
    for (const primitive of primitives) {
      const binding = primitive.extensions?.VBUSD_virtual_bones ?? {};
      if (Number.isInteger(binding.part)) names[binding.part] = String(binding.path ?? `part${binding.part}`).split('/').pop();
    }
    out.partNames = Array.from(names, (name, j) => name ?? `part${j}`);
    out.parts = Int32Array.from(parts, (m) => Math.floor(m + 0.5));
  }
  return out;
}
