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
