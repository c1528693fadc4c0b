// Per-instance playback parameters (spec "Instancing", 8.3 crossfade, 8.6 layers): clip-local
// times, placement matrices, and time-sampled fade primvars evaluated at the scene time.

/** Clip-local time of an instance: timeOffset + playbackRate * time. */
export function clipTime(timeOffset, playbackRate, time) { return timeOffset + playbackRate * time; }

const INTEGER_FIELDS = new Set(['fadeClip']);

/**
 * Time-sampled fade primvars (a fade over stage time, `vbusd crowd --fade-window`) at scene time
 * `time`, as USD resolves samples (vbusd.format.model.Crowd.at): floats interpolate linearly
 * between the samples around `time`, integers hold the sample at or before it; before the first
 * and after the last sample the end sample holds. `samples` is {field: {times, values}} with
 * `values` S x N (row s: every instance's value at times[s]); each field's N values at `time` are
 * written into `target[field]` (a typed array of N). Returns `target`.
 */
export function evaluateSamples(samples, time, target) {
  for (const [field, { times, values }] of Object.entries(samples ?? {})) {
    const out = target[field];
    const n = out.length;
    const s = times.length;
    let i1 = 0;
    while (i1 < s && times[i1] <= time) ++i1;  // first sample after `time`
    if (INTEGER_FIELDS.has(field) || i1 === 0 || i1 === s) {
      const at = Math.min(Math.max(i1 - 1, 0), s - 1);
      for (let i = 0; i < n; ++i) out[i] = values[at * n + i];
      continue;
    }
    const i0 = i1 - 1;
    const f = (time - times[i0]) / (times[i1] - times[i0]);
    for (let i = 0; i < n; ++i) out[i] = values[i0 * n + i] + f * (values[i1 * n + i] - values[i0 * n + i]);
  }
  return target;
}

/**
 * Placement matrices from the point instancer's arrays: positions (3 N), orientations (4 N,
 * quaternions x y z w, normalized here), optional scales (3 N); T R S (scale, then orientation,
 * then position), 16 column-major floats per instance.
 */
export function placementMatrices(positions, orientations, scales = null) {
  const count = positions.length / 3;
  const matrices = new Float32Array(16 * count);
  for (let i = 0; i < count; ++i) {
    let [x, y, z, w] = [orientations[4 * i], orientations[4 * i + 1], orientations[4 * i + 2], orientations[4 * i + 3]];
    const length = Math.hypot(x, y, z, w) || 1;
    x /= length; y /= length; z /= length; w /= length;
    const [sx, sy, sz] = scales ? [scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]] : [1, 1, 1];
    // three's Matrix4.compose, number for number.
    const x2 = x + x; const y2 = y + y; const z2 = z + z;
    const xx = x * x2; const xy = x * y2; const xz = x * z2;
    const yy = y * y2; const yz = y * z2; const zz = z * z2;
    const wx = w * x2; const wy = w * y2; const wz = w * z2;
    matrices.set([
      (1 - (yy + zz)) * sx, (xy + wz) * sx, (xz - wy) * sx, 0,
      (xy - wz) * sy, (1 - (xx + zz)) * sy, (yz + wx) * sy, 0,
      (xz + wy) * sz, (yz - wx) * sz, (1 - (xx + yy)) * sz, 0,
      positions[3 * i], positions[3 * i + 1], positions[3 * i + 2], 1,
    ], 16 * i);
  }
  return matrices;
}

/** One instance at the origin playing clip `clip` from its start at rate 1 (a single character). */
export function singleInstance(clip = 0) {
  return {
    count: 1,
    matrices: new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
    clip: new Int32Array([clip]),
    timeOffset: new Float32Array([0]),
    playbackRate: new Float32Array([1]),
  };
}

/**
 * Move instance `i` of `matrices` (16 column-major numbers per instance) by `delta`, a displacement
 * in the instance's own animation space (root motion, spec 8.5: rootMotionElements): its placement
 * P becomes P * delta, so the character walks along its own heading. In place; returns `matrices`.
 * A runtime then re-derives what copies the placement (its part meshes' matrices, spec 22.3).
 */
export function moveInstance(matrices, i, delta) {
  const p = Array.from(matrices.subarray(16 * i, 16 * i + 16));
  for (let c = 0; c < 4; ++c) {
    for (let r = 0; r < 4; ++r) {
      let sum = 0;
      for (let k = 0; k < 4; ++k) sum += p[4 * k + r] * delta[4 * c + k];
      matrices[16 * i + 4 * c + r] = sum;
    }
  }
  return matrices;
}
