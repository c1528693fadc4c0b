// Levels of detail (format 1.2, spec/virtual-bones.md 20.2): UsdLod's projected-sphere screen size
// and the level it selects, with hysteresis.

import { VirtualBonesError } from './errors.js';

/**
 * The fraction of the view plane a sphere of `radius` at `distance` from a perspective eye covers
 * (UsdLod's projectedSphere size): pi r'^2 / (4 aspect), r' = radius / (distance tan(fov / 2)).
 */
export function screenSize(radius, distance, tanHalfFov, aspect = 1) {
  const projected = radius / (distance * tanHalfFov);
  return Math.PI * projected * projected / (4 * aspect);
}

/**
 * The level a screen size `size` selects from the decreasing `thresholds` (one per level after
 * LOD 0): the number of thresholds it is at most. A finer level than `previous` (-1: none yet)
 * only once the size passes its threshold by the fraction `hysteresis`; a coarser one at once.
 */
export function selectLevel(size, thresholds, previous = -1, hysteresis = 0.1) {
  let level = 0;
  for (const t of thresholds) if (size <= t) ++level;
  if (previous >= 0 && level < previous) {
    let raised = 0;
    for (const t of thresholds) if (size <= t * (1 + hysteresis)) ++raised;
    level = Math.min(previous, raised);
  }
  return level;
}

/** Throw unless `thresholds` lie in (0, 1] and decrease, one per level after LOD 0. */
export function checkScreenSizes(thresholds, levels, name = '') {
  if (thresholds.length !== levels) throw new VirtualBonesError(`${name}: ${levels + 1} levels need ${levels} screen sizes, got ${thresholds.length}`);
  for (let t = 0; t < thresholds.length; ++t) {
    if (!(thresholds[t] > 0 && thresholds[t] <= 1) || (t > 0 && !(thresholds[t] < thresholds[t - 1]))) {
      throw new VirtualBonesError(`${name}: screen sizes must lie in (0, 1] and decrease, got ${thresholds.join(', ')}`);
    }
  }
}
