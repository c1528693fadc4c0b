"""glTF 2.0 animation sampling: STEP, LINEAR (slerp for rotations) and CUBICSPLINE, and TRS math.

The rules are the glTF 2.0 specification's (section 3.11 and Appendix C, "Animation Sampler
Interpolation Modes"):

* before the first key the first value is held, after the last key the last value is held;
* LINEAR interpolates translations and scales linearly and rotations by spherical linear
  interpolation along the shortest path (the second quaternion is negated when the dot product of
  the two keys is negative);
* STEP holds each key's value until the next key;
* CUBICSPLINE is a cubic Hermite spline whose output holds (in-tangent, value, out-tangent) per key;
  tangents are multiplied by the key interval ``t_{k+1} - t_k``; rotations are normalized after
  interpolation.

Everything is vectorized over sample times with numpy; nothing here knows about files. The
quaternion-to-matrix step is :func:`vbusd.format.quaternion.quat_to_matrix`, the one the encodings use.
"""

from __future__ import annotations

import numpy as np

from vbusd.format.quaternion import quat_to_matrix

__all__ = ["KEY_TIME_TOLERANCE", "compose_trs", "sample_channel"]


KEY_TIME_TOLERANCE = 2.0 ** -23
"""A sample time this close to a key (relative to max(|t|, 1 s)) is at the key: one float32 step
(key times are float32; rounding a time to float32 moves it by at most half a step)."""


def compose_trs(t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``T * R * S`` as ``(..., 4, 4)`` column-vector matrices (glTF 2.0, 3.5.3).

    Args:
        t: (..., 3) translations.
        r: (..., 4) unit quaternions (x, y, z, w).
        s: (..., 3) scales.
    """
    shape = np.broadcast_shapes(t.shape[:-1], r.shape[:-1], s.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = quat_to_matrix(np.broadcast_to(r, shape + (4,))) * \
        np.broadcast_to(s, shape + (3,))[..., None, :]
    m[..., :3, 3] = np.broadcast_to(t, shape + (3,))
    m[..., 3, 3] = 1.0
    return m


def _slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions, row-wise."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where((dot < 0)[..., None], -q1, q1)
    dot = np.abs(dot)
    # Nearly parallel keys: fall back to linear interpolation (then normalize) to avoid 0/0.
    near = dot > 1.0 - 1e-10
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.where(near, 1.0, np.sin(theta))
    a = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / sin_theta)
    b = np.where(near, u, np.sin(u * theta) / sin_theta)
    q = a[..., None] * q0 + b[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def sample_channel(times: np.ndarray, keys: np.ndarray, values: np.ndarray, interpolation: str,
                   rotation: bool) -> np.ndarray:
    """Evaluate one animation sampler at ``times``.

    Args:
        times: (n,) seconds.
        keys: (k,) strictly increasing key times.
        values: (k, c) for STEP and LINEAR; (k, 3, c) for CUBICSPLINE (in-tangent, value,
            out-tangent).
        interpolation: ``STEP``, ``LINEAR`` or ``CUBICSPLINE``.
        rotation: True for quaternion outputs (slerp for LINEAR, normalization afterwards).

    Returns:
        (n, c) float64 values.
    """
    times = np.asarray(times, dtype=np.float64)
    k = len(keys)
    cubic = interpolation == "CUBICSPLINE"
    points = values[:, 1] if cubic else values
    if k == 1:
        out = np.broadcast_to(points[0], (len(times),) + points.shape[1:]).copy()
        return out
    # Key times are float32 in glTF: a sample time meant to fall on key k (a row at k/24 s, say)
    # can be a rounding error below float32(k/24). Times within KEY_TIME_TOLERANCE (relative) of a
    # key count as at that key; without it STEP would give the previous key's value on such rows.
    at_or_after = times + KEY_TIME_TOLERANCE * np.maximum(np.abs(times), 1.0)
    # i: index of the key at or before each time, clamped so that [i, i+1] is a valid span.
    i = np.clip(np.searchsorted(keys, at_or_after, side="right") - 1, 0, k - 2)
    t0, t1 = keys[i], keys[i + 1]
    span = t1 - t0
    u = np.clip((times - t0) / span, 0.0, 1.0)
    before = at_or_after < keys[0]
    after = at_or_after >= keys[-1]
    if interpolation == "STEP":
        out = np.where((at_or_after >= t1)[:, None], points[i + 1], points[i])
    elif interpolation == "LINEAR":
        if rotation:
            out = _slerp(points[i], points[i + 1], u)
        else:
            out = (1.0 - u)[:, None] * points[i] + u[:, None] * points[i + 1]
    else:
        u2, u3 = u * u, u * u * u
        h00 = 2 * u3 - 3 * u2 + 1
        h10 = u3 - 2 * u2 + u
        h01 = -2 * u3 + 3 * u2
        h11 = u3 - u2
        p0, p1 = values[i, 1], values[i + 1, 1]
        m0 = span[:, None] * values[i, 2]       # out-tangent of key i
        m1 = span[:, None] * values[i + 1, 0]   # in-tangent of key i+1
        out = h00[:, None] * p0 + h10[:, None] * m0 + h01[:, None] * p1 + h11[:, None] * m1
    # Hold the first and last key values outside the keyed range.
    out = np.where(before[:, None], points[0], out)
    out = np.where(after[:, None], points[-1], out)
    if rotation:
        out = out / np.linalg.norm(out, axis=-1, keepdims=True)
    return out
