"""Root motion (spec virtual-bones.md "Root motion", format 1.1): clips that play in place plus a root track.

A walk baked as it is carries the character away from its instance's position and snaps it back
at every loop. Extracting root motion removes the root joint's horizontal translation (and,
optionally, its rotation about the up axis) from every bone of every row, so the clip plays in
place, and keeps the removed part per clip as a **root track** ``D(t)``: the skinned source pose
is ``D(t)`` applied to the in-place pose. A runtime moves each instance by the displacement
between two times, :func:`displacement` (``vbusd.root_motion``).

``D(t) = T(d) R_up(phi)``: a rotation ``phi`` about the up axis through the origin, then a
horizontal translation ``d``. The root joint is bone 0 (the first joint: UsdSkel and glTF list
parents first). Stored per row as ``(d_x, d_y, d_z, phi)``; looping
clips store one entry more, the displacement over one whole loop (at ``t = N / rowsPerSecond``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.errors import OptionsError

__all__ = ["MODES", "RootMotion", "rotation_about_up", "track_entries", "matrices", "at",
           "displacement", "check_mode"]

MODES = ("keep", "extract", "extractYaw")
"""``keep``: bake as the source moves; ``extract``: remove the root's horizontal translation;
``extractYaw``: also its rotation about the up axis."""


@dataclass(frozen=True)
class RootMotion:
    """Root tracks of an animation's clips (spec "Root motion").

    Attributes:
        up_axis: ``"Y"`` or ``"Z"``: the axis the yaw turns about and the translation leaves alone.
        tracks: Per clip, ``(entries, 4)`` float64 ``(d_x, d_y, d_z, phi)``: one entry per row, plus
            one for a looping clip (its displacement over one loop).
    """

    up_axis: str
    tracks: tuple


def _up_index(up_axis: str) -> int:
    if up_axis not in ("Y", "Z"):
        raise OptionsError(f"up axis must be Y or Z, got {up_axis!r}", file="root motion")
    return 1 if up_axis == "Y" else 2


def rotation_about_up(angle, up_axis: str) -> np.ndarray:
    """(..., 4, 4) rotations by ``angle`` (radians, right-handed) about the up axis."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(angle.shape + (4, 4))
    out[..., 3, 3] = 1.0
    if up_axis == "Y":
        out[..., 0, 0], out[..., 0, 2], out[..., 1, 1], out[..., 2, 0], out[..., 2, 2] = c, s, 1.0, -s, c
    else:
        out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def _yaw(linear: np.ndarray, up_axis: str) -> np.ndarray:
    """Rotation about the up axis of (..., 3, 3) matrices: the heading of their forward axis."""
    if up_axis == "Y":  # heading of the Z axis in the XZ plane
        return np.arctan2(linear[..., 0, 2], linear[..., 2, 2])
    return np.arctan2(linear[..., 1, 0], linear[..., 0, 0])  # heading of the X axis in the XY plane


def track_entries(root_world: np.ndarray, first: np.ndarray, up_axis: str, yaw: bool) -> np.ndarray:
    """``(d_x, d_y, d_z, phi)`` of ``D = T(h) R(theta) (T(h0) R(theta0))^-1`` for root transforms.

    Args:
        root_world: (n, 4, 4) the root joint's transforms ``J = M B`` at the times.
        first: (4, 4) its transform at the clip's start (where ``D`` is the identity).
        up_axis: ``"Y"`` or ``"Z"``.
        yaw: Also take out the rotation about the up axis.
    """
    up = _up_index(up_axis)
    h = root_world[:, :3, 3].copy()
    h[:, up] = 0.0
    h0 = first[:3, 3].copy()
    h0[up] = 0.0
    if not yaw:
        return np.concatenate([h - h0, np.zeros((len(h), 1))], axis=1)
    phi = _yaw(root_world[:, :3, :3], up_axis) - _yaw(first[:3, :3], up_axis)
    phi = np.unwrap(phi)
    turned = np.einsum("nij,j->ni", rotation_about_up(phi, up_axis)[:, :3, :3], h0)
    return np.concatenate([h - turned, phi[:, None]], axis=1)


def matrices(entries: np.ndarray, up_axis: str) -> np.ndarray:
    """(n, 4, 4) ``D = T(d) R_up(phi)`` of (n, 4) track entries."""
    entries = np.atleast_2d(np.asarray(entries, dtype=np.float64))
    out = rotation_about_up(entries[:, 3], up_axis)
    out[:, :3, 3] = entries[:, :3]
    return out


def at(track: np.ndarray, clip, tau: float, up_axis: str) -> np.ndarray:
    """``D(tau)`` (4, 4) of one clip: entries blended linearly between rows; loops accumulate.

    A looping clip of period ``P`` (``N`` rows) is ``L^k D(tau - k P)`` with ``k = floor(tau / P)``
    and ``L = D(P)`` (the extra entry); a clamped clip holds its first and last entries.
    """
    track = np.asarray(track, dtype=np.float64)
    n = clip.row_count
    x = float(tau) * clip.rows_per_second
    loops = 0
    if clip.loop:
        loops = math.floor(x / n)
        x -= loops * n
        i0 = min(int(math.floor(x)), n - 1)
        i1 = i0 + 1  # entry n is the loop's end
    else:
        x = min(max(x, 0.0), n - 1)
        i0 = int(math.floor(x))
        i1 = min(i0 + 1, n - 1)
    f = x - i0
    entry = (1.0 - f) * track[i0] + f * track[i1]
    result = matrices(entry, up_axis)[0]
    if loops:
        period = matrices(track[n], up_axis)[0]
        result = np.linalg.matrix_power(period if loops > 0 else np.linalg.inv(period), abs(loops)) @ result
    return result


def displacement(motion: RootMotion, clip_index: int, clip, t0: float, t1: float) -> np.ndarray:
    """The root displacement ``D(t1) D(t0)^-1`` (4, 4) between two clip-local times."""
    track = motion.tracks[clip_index]
    return at(track, clip, t1, motion.up_axis) @ np.linalg.inv(at(track, clip, t0, motion.up_axis))


def check_mode(mode: Optional[str]) -> str:
    """The root-motion mode, checked."""
    mode = "keep" if mode is None else str(mode)
    if mode not in MODES:
        raise OptionsError(f"root motion must be one of {', '.join(MODES)}, got {mode!r}", file="root motion")
    return mode
