"""Blend spaces, phase synchronization and clip markers (format 1.3, spec section 23), as rules.

Pure data and functions of numbers (numpy only), shared by the metadata, the USD reader and writer,
the validators, the decoders and ``vbusd.events``:

* :class:`BlendSpace` (a named 1D or 2D space of clips) and :class:`Marker` (a named time of a clip);
* :func:`parse_blend_space` / :func:`parse_marker`: ``vbusd convert --blend-space`` and ``--marker``;
* :func:`motion_problems`: what is wrong with a document's spaces and markers (one place for the
  metadata checks, the USD reader and the validator);
* :func:`triangulate` (spec 23.2: the Delaunay triangulation with its tie rule), :func:`blend_weights`
  (spec 23.1, 23.2), :func:`phase_times` (spec 23.3) and :func:`crossed_markers` (spec 23.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence


from vbusd.format.errors import OptionsError

__all__ = ["BlendSpace", "Marker", "parse_blend_space", "parse_marker", "motion_problems", "spaces_from_dict",
           "markers_from_dict", "spaces_to_dict", "markers_to_dict", "triangulate", "blend_weights",
           "phase_times", "crossed_markers", "MAX_POINTS", "as_layer_weights", "instance_blend"]

MAX_POINTS = 64
"""The most points a blend space may hold (the 2D triangulation is found by an O(n^4) search)."""


@dataclass(frozen=True)
class BlendSpace:
    """A named space of clips (spec 23.1, 23.2).

    Attributes:
        name: Unique among the animation's spaces.
        dimensions: 1 or 2.
        clips: The clip name of each point (a clip may sit at several points).
        points: Each point's position, ``(x,)`` or ``(x, y)``.
        sync_marker: A marker name every clip of the space has: phase 0 of each clip is that
            marker's first time (spec 23.3), or None (phase 0 is each clip's time 0).
    """

    name: str
    dimensions: int
    clips: tuple
    points: tuple
    sync_marker: Optional[str] = None


@dataclass(frozen=True)
class Marker:
    """A named time of a clip (spec 23.4): ``time`` in clip-local seconds, in ``[0, duration]``."""

    clip: str
    name: str
    time: float


def _number(text: str, what: str, where: str, code: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value):
        raise OptionsError(f"{what}: {text!r} is not a finite number", file=where, code=code)
    return value


def parse_blend_space(text: str) -> BlendSpace:
    """``NAME=CLIP@X,CLIP@X,...`` (1D) or ``NAME=CLIP@X:Y,...`` (2D), as ``--blend-space`` takes it.

    Raises:
        OptionsError: Not of that form (code ``convert.blendSpace``).
    """
    where, code = "convert", "convert.blendSpace"
    form = "--blend-space takes NAME=CLIP@X,CLIP@X,... (1D) or NAME=CLIP@X:Y,... (2D)"
    name, sep, body = str(text).partition("=")
    if not sep or not name or not body:
        raise OptionsError(f"{form}, got {text!r}", file=where, code=code)
    clips, points = [], []
    for item in body.split(","):
        clip, at, position = item.rpartition("@")
        if not at or not clip or not position:
            raise OptionsError(f"{form}: {item!r} is not CLIP@X or CLIP@X:Y", file=where, code=code)
        coordinates = tuple(_number(v, f"blend space {name!r} point {item!r}", where, code)
                            for v in position.split(":"))
        if len(coordinates) > 2:
            raise OptionsError(f"{form}: {item!r} has {len(coordinates)} coordinates", file=where, code=code)
        clips.append(clip)
        points.append(coordinates)
    dimensions = {len(p) for p in points}
    if len(dimensions) != 1:
        raise OptionsError(f"blend space {name!r} mixes 1D (CLIP@X) and 2D (CLIP@X:Y) points", file=where, code=code)
    return BlendSpace(name, dimensions.pop(), tuple(clips), tuple(points))


def parse_marker(text: str) -> Marker:
    """``CLIP:NAME@SECONDS``, as ``--marker`` takes it.

    Raises:
        OptionsError: Not of that form (code ``convert.marker``).
    """
    where, code = "convert", "convert.marker"
    head, at, seconds = str(text).rpartition("@")
    clip, colon, name = head.rpartition(":")
    if not at or not colon or not clip or not name or not seconds:
        raise OptionsError(f"--marker takes CLIP:NAME@SECONDS, got {text!r}", file=where, code=code)
    return Marker(clip, name, _number(seconds, f"marker {text!r}", where, code))


# --------------------------------------------------------------------------------------------
# The metadata form (spec 23.6) and the checks
# --------------------------------------------------------------------------------------------


def spaces_to_dict(spaces) -> list:
    """``blendSpaces`` as the metadata holds it."""
    out = []
    for space in spaces:
        points = [{"clip": str(c), "x": float(p[0]), **({"y": float(p[1])} if space.dimensions == 2 else {})}
                  for c, p in zip(space.clips, space.points)]
        out.append({"name": str(space.name), "dimensions": int(space.dimensions), "points": points,
                    **({"syncMarker": str(space.sync_marker)} if space.sync_marker else {})})
    return out


def markers_to_dict(markers) -> list:
    """``markers`` as the metadata holds it."""
    return [{"clip": str(m.clip), "name": str(m.name), "time": float(m.time)} for m in markers]


def spaces_from_dict(items) -> tuple:
    """:class:`BlendSpace` objects of a checked ``blendSpaces`` list."""
    return tuple(BlendSpace(s["name"], int(s["dimensions"]), tuple(p["clip"] for p in s["points"]),
                            tuple((float(p["x"]),) if int(s["dimensions"]) == 1 else (float(p["x"]), float(p.get("y", 0.0)))
                                  for p in s["points"]), s.get("syncMarker") or None)
                 for s in items or ())


def markers_from_dict(items) -> tuple:
    """:class:`Marker` objects of a checked ``markers`` list."""
    return tuple(Marker(m["clip"], m["name"], float(m["time"])) for m in items or ())


def motion_problems(spaces, markers, clip_durations: dict) -> list:
    """What is wrong with a document's blend spaces and markers (spec 23.6), as ``(path, message)``.

    ``path`` is a list of JSON pointer parts into the metadata (``["blendSpaces", 0, "points", 1]``).

    Args:
        spaces: :class:`BlendSpace` objects.
        markers: :class:`Marker` objects.
        clip_durations: Clip name -> duration in seconds (spec 7).
    """
    problems = []
    seen: dict = {}
    for j, m in enumerate(markers):
        if m.clip not in clip_durations:
            problems.append((["markers", j, "clip"], f"marker {m.name!r} names clip {m.clip!r}, which the animation "
                             f"does not have (clips: {', '.join(clip_durations)})"))
            continue
        if not m.name:
            problems.append((["markers", j, "name"], "a marker name must not be empty"))
        duration = clip_durations[m.clip]
        if not (math.isfinite(m.time) and 0.0 <= m.time <= duration):
            problems.append((["markers", j, "time"], f"marker {m.name!r} of clip {m.clip!r} is at {m.time:g} s, "
                             f"outside the clip's [0, {duration:g}] s"))
        if (m.clip, m.name, m.time) in seen:
            problems.append((["markers", j], f"marker {m.name!r} of clip {m.clip!r} at {m.time:g} s repeats marker "
                             f"{seen[(m.clip, m.name, m.time)]}"))
        seen.setdefault((m.clip, m.name, m.time), j)
    names: dict = {}
    for j, space in enumerate(spaces):
        at = ["blendSpaces", j]
        if not space.name:
            problems.append((at + ["name"], "a blend space name must not be empty"))
        if space.name in names:
            problems.append((at + ["name"], f"blend space name {space.name!r} is already used by blend space "
                             f"{names[space.name]}"))
        names.setdefault(space.name, j)
        if space.dimensions not in (1, 2):
            problems.append((at + ["dimensions"], f"blend space {space.name!r} has {space.dimensions} dimensions; "
                             "it must have 1 or 2"))
            continue
        if not 1 <= len(space.points) <= MAX_POINTS:
            problems.append((at + ["points"], f"blend space {space.name!r} holds {len(space.points)} points; it "
                             f"must hold 1 to {MAX_POINTS}"))
            continue
        bad = False
        for k, (clip, point) in enumerate(zip(space.clips, space.points)):
            if clip not in clip_durations:
                problems.append((at + ["points", k, "clip"], f"blend space {space.name!r} names clip {clip!r}, which "
                                 f"the animation does not have (clips: {', '.join(clip_durations)})"))
                bad = True
            if len(point) != space.dimensions or not all(math.isfinite(v) for v in point):
                problems.append((at + ["points", k], f"blend space {space.name!r} point {k} must be "
                                 f"{space.dimensions} finite numbers"))
                bad = True
        if bad:
            continue
        positions = [tuple(p) for p in space.points]
        if len(set(positions)) != len(positions):
            k = next(k for k, p in enumerate(positions) if positions.index(p) != k)
            problems.append((at + ["points", k], f"blend space {space.name!r} point {k} repeats the position of "
                             f"point {positions.index(positions[k])}"))
            continue
        if space.dimensions == 2 and len(positions) >= 1 and not triangulate(positions):
            problems.append((at + ["points"], f"2D blend space {space.name!r} needs at least three points not on "
                             "one line"))
        if space.sync_marker is not None:
            lacking = [c for c in dict.fromkeys(space.clips)
                       if not any(m.clip == c and m.name == space.sync_marker for m in markers)]
            if lacking:
                problems.append((at + ["syncMarker"], f"blend space {space.name!r} syncs on marker "
                                 f"{space.sync_marker!r}, which clip {lacking[0]!r} does not have"))
    return problems


# --------------------------------------------------------------------------------------------
# Weights (spec 23.1, 23.2)
# --------------------------------------------------------------------------------------------


def _in_circle(a, b, c, d) -> float:
    """Positive when ``d`` lies inside the circle through the counter-clockwise ``a, b, c``."""
    rows = [(p[0] - d[0], p[1] - d[1]) for p in (a, b, c)]
    m = [(x, y, x * x + y * y) for x, y in rows]
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def _orient(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def triangulate(points: Sequence) -> tuple:
    """The triangles of a 2D blend space (spec 23.2), as sorted index triples in ascending order.

    The Delaunay triangulation of the points, made unique where it is not: every triple of points
    not on one line whose circumcircle holds no other point strictly inside is a candidate; a
    candidate whose circle has exactly its three points on it is a triangle; the points on a
    circle with four or more (a convex polygon, its Delaunay cell) are fanned from the one that comes
    first in (x, y) order. "On the circle" and "on one line" are decided with a tolerance of
    ``1e-9`` times the scale of the points (its fourth and second power).
    """
    p = [tuple(map(float, q)) for q in points]
    n = len(p)
    if n < 3:
        return ()
    span = max(max(abs(a - b) for a, b in zip(q, r)) for q in p for r in p) or 1.0
    line_tol, circle_tol = 1e-9 * span * span, 1e-9 * span ** 4
    triangles = set()
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(j + 1, n):
                a, b, c = p[i], p[j], p[k]
                o = _orient(a, b, c)
                if abs(o) <= line_tol:
                    continue
                ccw = (i, j, k) if o > 0 else (i, k, j)
                on, inside = [i, j, k], False
                for m in range(n):
                    if m in (i, j, k):
                        continue
                    s = _in_circle(p[ccw[0]], p[ccw[1]], p[ccw[2]], p[m])
                    if s > circle_tol:
                        inside = True
                        break
                    if s >= -circle_tol:
                        on.append(m)
                if inside:
                    continue
                if len(on) == 3:
                    triangles.add(tuple(sorted(on)))
                    continue
                # A cell of four or more cocircular points: fan from its first point in (x, y) order.
                cx = sum(p[m][0] for m in on) / len(on)
                cy = sum(p[m][1] for m in on) / len(on)
                ring = sorted(on, key=lambda m: math.atan2(p[m][1] - cy, p[m][0] - cx))
                start = ring.index(min(on, key=lambda m: (p[m][0], p[m][1])))
                ring = ring[start:] + ring[:start]
                for q in range(1, len(ring) - 1):
                    triangles.add(tuple(sorted((ring[0], ring[q], ring[q + 1]))))
    return tuple(sorted(triangles))


def _barycentric(a, b, c, x, y):
    d = _orient(a, b, c)
    wa = _orient((x, y), b, c) / d
    wb = _orient(a, (x, y), c) / d
    return wa, wb, 1.0 - wa - wb


def _closest_on_segment(a, b, x, y):
    ax, ay = b[0] - a[0], b[1] - a[1]
    length = ax * ax + ay * ay
    t = 0.0 if length == 0 else min(1.0, max(0.0, ((x - a[0]) * ax + (y - a[1]) * ay) / length))
    return t, (a[0] + t * ax - x) ** 2 + (a[1] + t * ay - y) ** 2


def blend_weights(space: BlendSpace, x: float, y: float = 0.0) -> list:
    """The weight of each point of ``space`` at ``(x, y)`` (spec 23.1, 23.2): ``[(point, weight)]``
    for the points of non-zero weight, in point order, summing to 1.

    1D: the points sorted by x; outside ``[x_min, x_max]`` the nearest end alone; else the two
    neighbours ``x_i <= x <= x_{i+1}`` with ``(x_{i+1} - x) / (x_{i+1} - x_i)`` and the rest.
    2D: the barycentric weights in the first triangle (in :func:`triangulate`'s order) that holds
    ``(x, y)`` (every weight >= -1e-12); outside every triangle, ``(x, y)`` is first moved to the
    nearest point of the triangles' boundary edges (ties: the first edge in (triangle, edge) order).
    """
    points = [tuple(map(float, q)) for q in space.points]
    if len(points) == 1:
        return [(0, 1.0)]
    if space.dimensions == 1:
        order = sorted(range(len(points)), key=lambda k: points[k][0])
        xs = [points[k][0] for k in order]
        if x <= xs[0]:
            return [(order[0], 1.0)]
        if x >= xs[-1]:
            return [(order[-1], 1.0)]
        i = max(i for i in range(len(xs) - 1) if xs[i] <= x)
        f = (x - xs[i]) / (xs[i + 1] - xs[i])
        pairs = {order[i]: 1.0 - f, order[i + 1]: f}
        return [(k, w) for k, w in sorted(pairs.items()) if w > 0.0]
    triangles = triangulate(points)
    for tri in triangles:
        weights = _barycentric(*(points[k] for k in tri), x, y)
        if min(weights) >= -1e-12:
            return _clean(tri, weights)
    # Outside: the nearest point on an edge that belongs to one triangle only (the hull).
    count: dict = {}
    for tri in triangles:
        for edge in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[0], tri[2])):
            count[edge] = count.get(edge, 0) + 1
    best = None
    for tri in triangles:
        for edge in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[0], tri[2])):
            if count[edge] != 1:
                continue
            t, distance = _closest_on_segment(points[edge[0]], points[edge[1]], x, y)
            if best is None or distance < best[0]:
                best = (distance, edge, t)
    _, (a, b), t = best
    return _clean((a, b), (1.0 - t, t))


def as_layer_weights(weights) -> list:
    """A blend's ``[(point, weight)]`` (in the space's order) as a base and override layers (spec 23.1,
    "Decoding a blend as layers"): ``[(point, w_k / (w_1 + ... + w_k))]``, the first entry's 1 being the base.
    A decoder that layers with a mask of every bone decodes the blend with these weights."""
    out, total = [], 0.0
    for k, w in weights:
        total += float(w)
        out.append((k, float(w) / total if total > 0 else 0.0))
    return out


def instance_blend(space: BlendSpace, x: float, y: float, phase: float, rate: float, durations: dict,
                   markers) -> list:
    """An instance's blend (spec 23.7) as clip times linear in the scene time ``t``: per weighted point in
    the space's order, ``(point, weight, layer weight, offset, rate)`` with the point's clip-local time
    ``offset + rate t``. The phase is ``phase + rate t / D`` with ``D = sum w_k D_k``, so point ``k`` plays
    ``s_k + phase D_k + (rate D_k / D) t`` (23.3); the layer weights are :func:`as_layer_weights`'s."""
    weights = blend_weights(space, x, y)
    cycle = sum(w * durations[space.clips[k]] for k, w in weights)
    starts = phase_times(space, durations, markers, 0.0)
    layered = as_layer_weights(weights)
    out = []
    for (k, w), (_, relative) in zip(weights, layered):
        duration = durations[space.clips[k]]
        out.append((k, w, relative, starts[k] + float(phase) * duration,
                    float(rate) * duration / cycle if cycle > 0 else 0.0))
    return out


def _clean(indices, weights) -> list:
    pairs: dict = {}
    for k, w in zip(indices, weights):
        w = min(1.0, max(0.0, float(w)))
        if w > 0.0:
            pairs[k] = pairs.get(k, 0.0) + w
    total = sum(pairs.values())
    return [(k, w / total) for k, w in sorted(pairs.items())]


# --------------------------------------------------------------------------------------------
# Phase (spec 23.3) and markers (spec 23.5)
# --------------------------------------------------------------------------------------------


def phase_times(space: BlendSpace, durations: dict, markers, phase: float) -> list:
    """Each point's clip-local time at normalized phase ``phase`` (spec 23.3): ``phase x duration``
    of its clip, plus the clip's first ``sync_marker`` time when the space syncs on a marker."""
    out = []
    for clip in space.clips:
        offset = 0.0
        if space.sync_marker is not None:
            times = [m.time for m in markers if m.clip == clip and m.name == space.sync_marker]
            offset = min(times) if times else 0.0
        out.append(offset + float(phase) * durations[clip])
    return out


def crossed_markers(markers, clip: str, duration: float, loop: bool, t0: float, t1: float) -> list:
    """The markers of ``clip`` crossed when its clip-local time goes from ``t0`` to ``t1`` (spec 23.5).

    Forward (``t1 >= t0``): every time ``m + k x duration`` (``k`` any integer for a looping clip, 0
    for a clamped one) in ``(t0, t1]``, in increasing time (equal times: marker order). Backward
    (``t1 < t0``): those in ``[t1, t0)``, in decreasing time. Each as ``{"name", "time"}`` with the
    unwrapped time.
    """
    own = [m for m in markers if m.clip == clip]
    found = []
    low, high = (t0, t1) if t1 >= t0 else (t1, t0)
    for order, m in enumerate(own):
        if loop and duration > 0:
            k = math.floor((low - m.time) / duration)
            time = m.time + k * duration
            while time <= high:
                if (low < time <= high) if t1 >= t0 else (low <= time < high):
                    found.append((time, order, m.name))
                k += 1
                time = m.time + k * duration
        else:
            inside = (low < m.time <= high) if t1 >= t0 else (low <= m.time < high)
            if inside:
                found.append((m.time, order, m.name))
    found.sort(key=lambda e: (e[0], e[1]), reverse=t1 < t0)
    return [{"name": name, "time": float(time)} for time, _, name in found]
