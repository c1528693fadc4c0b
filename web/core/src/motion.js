// Blend spaces, phase synchronization and clip markers (format 1.3, spec/virtual-bones.md section 23)
// for the runtimes, on the CPU: a blend space's weights at a parameter (1D neighbours; 2D barycentric
// over the spec's Delaunay triangulation with its tie rule), each point's clip time at a phase, the
// weights as a base and override layers (spec 23.1, "Decoding a blend as layers"), and the markers an
// instance crosses between two scene times (events: footsteps, particles). The JavaScript twin of
// vbusd.format.motion; tests/test_web_motion.py checks the two against each other and the spec's
// examples.

/**
 * A blend space from the layout metadata's `blendSpaces` entry: {name, dimensions, points:
 * [{clip, x, y?}], syncMarker?}. Returned as is; the functions below read those keys.
 */

function orient(a, b, c) { return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]); }

function inCircle(a, b, c, d) {
  const m = [a, b, c].map((p) => { const x = p[0] - d[0]; const y = p[1] - d[1]; return [x, y, x * x + y * y]; });
  return m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
    + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
}

/** The triangles of 2D points [[x, y]...] (spec 23.2), sorted index triples in ascending order. */
export function triangulate(points) {
  const n = points.length;
  if (n < 3) return [];
  let span = 0;
  for (const p of points) for (const q of points) span = Math.max(span, Math.abs(p[0] - q[0]), Math.abs(p[1] - q[1]));
  span = span || 1;
  const lineTol = 1e-9 * span * span;
  const circleTol = 1e-9 * span ** 4;
  const found = new Map();
  const add = (t) => { const s = [...t].sort((a, b) => a - b); found.set(s.join(','), s); };
  for (let i = 0; i < n; ++i) for (let j = i + 1; j < n; ++j) for (let k = j + 1; k < n; ++k) {
    const o = orient(points[i], points[j], points[k]);
    if (Math.abs(o) <= lineTol) continue;
    const ccw = o > 0 ? [i, j, k] : [i, k, j];
    const on = [i, j, k];
    let inside = false;
    for (let m = 0; m < n && !inside; ++m) {
      if (m === i || m === j || m === k) continue;
      const s = inCircle(points[ccw[0]], points[ccw[1]], points[ccw[2]], points[m]);
      if (s > circleTol) inside = true;
      else if (s >= -circleTol) on.push(m);
    }
    if (inside) continue;
    if (on.length === 3) { add(on); continue; }
    // A cell of four or more cocircular points: a fan from its first point in (x, y) order.
    const cx = on.reduce((a, m) => a + points[m][0], 0) / on.length;
    const cy = on.reduce((a, m) => a + points[m][1], 0) / on.length;
    const ring = [...on].sort((a, b) => Math.atan2(points[a][1] - cy, points[a][0] - cx)
      - Math.atan2(points[b][1] - cy, points[b][0] - cx));
    const first = on.reduce((a, m) => (points[m][0] < points[a][0]
      || (points[m][0] === points[a][0] && points[m][1] < points[a][1]) ? m : a), on[0]);
    const start = ring.indexOf(first);
    const fan = ring.slice(start).concat(ring.slice(0, start));
    for (let q = 1; q < fan.length - 1; ++q) add([fan[0], fan[q], fan[q + 1]]);
  }
  return [...found.values()].sort((a, b) => a[0] - b[0] || a[1] - b[1] || a[2] - b[2]);
}

function clean(indices, weights) {
  const pairs = new Map();
  indices.forEach((k, i) => {
    const w = Math.min(1, Math.max(0, weights[i]));
    if (w > 0) pairs.set(k, (pairs.get(k) ?? 0) + w);
  });
  let total = 0;
  for (const w of pairs.values()) total += w;
  return [...pairs.entries()].sort((a, b) => a[0] - b[0]).map(([k, w]) => [k, w / total]);
}

/**
 * The weight of each point of a blend space at (x, y) (spec 23.1, 23.2): [[point index, weight]...]
 * for the points of non-zero weight, in point order, summing to 1.
 */
export function blendWeights(space, x, y = 0) {
  const points = space.points.map((p) => [p.x, p.y ?? 0]);
  if (points.length === 1) return [[0, 1]];
  if (space.dimensions === 1) {
    const order = points.map((_, k) => k).sort((a, b) => points[a][0] - points[b][0]);
    const xs = order.map((k) => points[k][0]);
    if (x <= xs[0]) return [[order[0], 1]];
    if (x >= xs[xs.length - 1]) return [[order[order.length - 1], 1]];
    let i = 0;
    for (let m = 0; m < xs.length - 1; ++m) if (xs[m] <= x) i = m;
    const f = (x - xs[i]) / (xs[i + 1] - xs[i]);
    return [[order[i], 1 - f], [order[i + 1], f]].filter(([, w]) => w > 0).sort((a, b) => a[0] - b[0]);
  }
  const triangles = triangulate(points);
  for (const t of triangles) {
    const [a, b, c] = t.map((k) => points[k]);
    const d = orient(a, b, c);
    const wa = orient([x, y], b, c) / d;
    const wb = orient(a, [x, y], c) / d;
    const weights = [wa, wb, 1 - wa - wb];
    if (Math.min(...weights) >= -1e-12) return clean(t, weights);
  }
  // Outside: the nearest point of an edge that belongs to one triangle only.
  const count = new Map();
  const edges = (t) => [[t[0], t[1]], [t[1], t[2]], [t[0], t[2]]];
  for (const t of triangles) for (const e of edges(t)) count.set(e.join(','), (count.get(e.join(',')) ?? 0) + 1);
  let best = null;
  for (const t of triangles) for (const e of edges(t)) {
    if (count.get(e.join(',')) !== 1) continue;
    const [a, b] = [points[e[0]], points[e[1]]];
    const ax = b[0] - a[0]; const ay = b[1] - a[1];
    const length = ax * ax + ay * ay;
    const s = length === 0 ? 0 : Math.min(1, Math.max(0, ((x - a[0]) * ax + (y - a[1]) * ay) / length));
    const distance = (a[0] + s * ax - x) ** 2 + (a[1] + s * ay - y) ** 2;
    if (best === null || distance < best[0]) best = [distance, e, s];
  }
  return clean(best[1], [1 - best[2], best[2]]);
}

/**
 * Each point's clip-local time at normalized phase `phase` (spec 23.3): phase x its clip's duration,
 * from the clip's first `syncMarker` time when the space names one. `durations` maps clip name to
 * seconds; `markers` is the metadata's `markers` list.
 */
export function phaseTimes(space, durations, markers, phase) {
  return space.points.map(({ clip }) => {
    let offset = 0;
    if (space.syncMarker) {
      const times = (markers ?? []).filter((m) => m.clip === clip && m.name === space.syncMarker).map((m) => m.time);
      if (times.length) offset = Math.min(...times);
    }
    return offset + phase * durations[clip];
  });
}

/** A blend's weights as a base and override layers (spec 23.1): [[point, w_k / (w_1 + ... + w_k)]...]. */
export function layerWeights(weights) {
  let total = 0;
  return weights.map(([k, w]) => { total += w; return [k, total > 0 ? w / total : 0]; });
}

/**
 * The markers of `clip` crossed when its clip-local time goes from t0 to t1 (spec 23.5): forward, the
 * times m + k D in (t0, t1] in increasing time; backward (t1 < t0), those in [t1, t0) in decreasing
 * time; a clamped clip's markers once (k = 0). Returns [{name, time}] with the unwrapped time.
 */
export function crossedMarkers(markers, clip, duration, loop, t0, t1) {
  const forward = t1 >= t0;
  const low = Math.min(t0, t1); const high = Math.max(t0, t1);
  const found = [];
  (markers ?? []).filter((m) => m.clip === clip).forEach((m, order) => {
    const inside = (time) => (forward ? low < time && time <= high : low <= time && time < high);
    if (loop && duration > 0) {
      let k = Math.floor((low - m.time) / duration);
      for (let time = m.time + k * duration; time <= high; time = m.time + (++k) * duration) {
        if (inside(time)) found.push([time, order, m.name]);
      }
    } else if (inside(m.time)) {
      found.push([m.time, order, m.name]);
    }
  });
  found.sort((a, b) => (a[0] - b[0]) || (a[1] - b[1]));
  if (!forward) found.reverse();
  return found.map(([time, , name]) => ({ name, time }));
}

/**
 * The events of a crowd between scene times t0 and t1 (spec 23.5): instance i plays clip clip[i] at
 * clip-local time timeOffset[i] + playbackRate[i] * t. `clips` are the metadata's clip objects
 * ({name, rowCount, rowsPerSecond, loop}). Returns [{instance, name, time}], instance by instance.
 */
export function crowdEvents(markers, clips, clip, timeOffset, playbackRate, t0, t1) {
  const out = [];
  for (let i = 0; i < clip.length; ++i) {
    const c = clips[clip[i]];
    const duration = (c.loop ? c.rowCount : c.rowCount - 1) / c.rowsPerSecond;
    const a = timeOffset[i] + playbackRate[i] * t0;
    const b = timeOffset[i] + playbackRate[i] * t1;
    for (const event of crossedMarkers(markers, c.name, duration, c.loop, a, b)) out.push({ instance: i, ...event });
  }
  return out;
}

/**
 * An instance's blend (spec 23.7) as the per-instance data of a crowd that layers (spec 23.1,
 * "Decoding a blend as layers"): {clip, timeOffset, playbackRate, layers: [{clip, timeOffset,
 * playbackRate, weight}]}, every clip time linear in the scene time t (offset + rate t): the first
 * weighted point's clip is the base, each further point an override layer of weight w_k / (w_1 + ...
 * + w_k) under a mask of every bone. `clips` are the metadata's clip objects; `markers` its markers.
 * The twin of vbusd.decoders.reference.blends_as_layers for one instance.
 */
export function blendLayers(space, x, y, phase, playbackRate, clips, markers) {
  const durations = Object.fromEntries(clips.map((c) => [c.name, (c.loop ? c.rowCount : c.rowCount - 1) / c.rowsPerSecond]));
  const index = (name) => clips.findIndex((c) => c.name === name);
  const weights = blendWeights(space, x, y);
  const cycle = weights.reduce((sum, [k, w]) => sum + w * durations[space.points[k].clip], 0);
  const starts = phaseTimes(space, durations, markers, 0);
  const entries = layerWeights(weights).map(([k, relative]) => {
    const duration = durations[space.points[k].clip];
    return {
      clip: index(space.points[k].clip), weight: relative, timeOffset: starts[k] + phase * duration,
      playbackRate: cycle > 0 ? (playbackRate * duration) / cycle : 0,
    };
  });
  const [base, ...layers] = entries;
  return { clip: base.clip, timeOffset: base.timeOffset, playbackRate: base.playbackRate, layers };
}
