"""The talk's stadium crowd, generated: an 18-bone rig, 202 vertices, 352 triangles, a 10 s cheer.

This reproduces the reference case of Virtual Bones (V. Lopatin, SIGGRAPH 2017): a low-poly
spectator whose looping cheer bakes into a 64x512 float16 crossMatrix texture (262,144 bytes of
texels, 512 rows over 10 s), instanced 1,200 times on one point instancer.

Everything is procedural and deterministic (fixed seeds, no I/O until a writer is called):

* the rig: 18 joints in a T-pose bind pose (Y up, metres, facing +Z);
* the mesh: 13 closed low-poly parts (tubes, capsules and boxes) merged into one mesh of exactly
  202 vertices and 352 triangles (each closed genus-0 part has 2V - 4 triangles), with
  area-weighted vertex normals and smooth skin weights of up to 4 influences;
* the cheer: 10 s of arms raised and waving, a knee bounce, chest twist and head bob. Every motion
  is a sum of sines with an integer number of periods in 10 s (on time wrapped into [0, 10)), so the
  pose at 10 s equals the pose at 0 s exactly. Joints only rotate (and the hips translate): rigid.

Outputs (``python samples/stadium_crowd.py --out samples/stadium_crowd`` or
``python -m samples.stadium_crowd``):

* ``stadium_crowd.usda``: the UsdSkel asset (SkelRoot, Skeleton, SkelAnimation sampled at 30 fps,
  time codes 0..300, and the skinned Mesh): the input of ``vbusd convert``;
* ``stadium_crowd_vb.usda`` (+ its texture and sidecar JSON): the Virtual Bones asset baked from
  the generator's own float64 matrices, with a crowd of 1,200 instances.

The exact skinning matrices at any time are :func:`skinning_matrices`; benchmarks/accuracy.py and
the tests use them as ground truth.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

# Import vbusd before any pxr use: importing it registers the Virtual Bones USD schema plugin, and
# OpenUSD's schema registry does not pick up plugins registered after its first use in a process.
import vbusd  # noqa: F401
from vbusd.format.quaternion import quat_multiply, quat_to_matrix

# ------------------------------------------------------------------------------------------------
# Constants of the reference case
# ------------------------------------------------------------------------------------------------

DURATION = 10.0
"""Seconds of the looping cheer."""

FPS = 30.0
"""Time codes per second of the UsdSkel asset; frames 0..300 cover the loop (300 == 0)."""

FRAME_COUNT = 300
"""Frames in one loop; the UsdSkel asset stores FRAME_COUNT + 1 samples (0..300)."""

CROWD_SIZE = 1200
"""Instances on the point instancer, as in the talk."""

CROWD_SEED = 2017
"""Seed of the crowd's random clip offsets, rates and jitter (the talk's year)."""

BONE_COUNT = 18
VERTEX_COUNT = 202
TRIANGLE_COUNT = 352

USDSKEL_NAME = "stadium_crowd.usda"
VB_NAME = "stadium_crowd_vb.usda"

# Joint table: name, parent index (-1 for the root), bind position in world space (metres), and
# the point the bone segment runs to (for skin weights by distance).
_JOINTS = (
    ("hips", -1, (0.0, 1.00, 0.0), (0.0, 1.15, 0.0)),
    ("spine", 0, (0.0, 1.15, 0.0), (0.0, 1.35, 0.0)),
    ("chest", 1, (0.0, 1.35, 0.0), (0.0, 1.58, 0.0)),
    ("head", 2, (0.0, 1.58, 0.0), (0.0, 1.84, 0.0)),
    ("L_shoulder", 2, (0.05, 1.50, 0.0), (0.18, 1.48, 0.0)),
    ("L_upperArm", 4, (0.18, 1.48, 0.0), (0.46, 1.48, 0.0)),
    ("L_forearm", 5, (0.46, 1.48, 0.0), (0.71, 1.48, 0.0)),
    ("L_hand", 6, (0.71, 1.48, 0.0), (0.82, 1.48, 0.0)),
    ("R_shoulder", 2, (-0.05, 1.50, 0.0), (-0.18, 1.48, 0.0)),
    ("R_upperArm", 8, (-0.18, 1.48, 0.0), (-0.46, 1.48, 0.0)),
    ("R_forearm", 9, (-0.46, 1.48, 0.0), (-0.71, 1.48, 0.0)),
    ("R_hand", 10, (-0.71, 1.48, 0.0), (-0.82, 1.48, 0.0)),
    ("L_thigh", 0, (0.10, 0.95, 0.0), (0.10, 0.52, 0.0)),
    ("L_shin", 12, (0.10, 0.52, 0.0), (0.10, 0.08, 0.0)),
    ("L_foot", 13, (0.10, 0.08, 0.0), (0.10, 0.02, 0.16)),
    ("R_thigh", 0, (-0.10, 0.95, 0.0), (-0.10, 0.52, 0.0)),
    ("R_shin", 15, (-0.10, 0.52, 0.0), (-0.10, 0.08, 0.0)),
    ("R_foot", 16, (-0.10, 0.08, 0.0), (-0.10, 0.02, 0.16)),
)

JOINT_NAMES = tuple(j[0] for j in _JOINTS)
PARENTS = np.array([j[1] for j in _JOINTS], dtype=np.int64)
_BIND_POSITIONS = np.array([j[2] for j in _JOINTS], dtype=np.float64)
_BONE_ENDS = np.array([j[3] for j in _JOINTS], dtype=np.float64)


def _joint_paths() -> tuple:
    paths = []
    for name, parent, _, _ in _JOINTS:
        paths.append(name if parent < 0 else f"{paths[parent]}/{name}")
    return tuple(paths)


JOINT_PATHS = _joint_paths()
"""UsdSkel joint paths (parent-first order): ``hips``, ``hips/spine``, ..."""

_J = {name: i for i, name in enumerate(JOINT_NAMES)}

# ------------------------------------------------------------------------------------------------
# Small rotation helpers (float64, quaternions (x, y, z, w), column vectors)
#
# vbusd.format.encoding has the same Hamilton product and quaternion-to-matrix formulas (quat_multiply,
# quat_to_matrix). They are written again here on purpose: this generator is the ground truth that
# benchmarks/accuracy.py and the tests compare vbusd's encodings and decoders against, so its exact
# matrices must not come from the code under test (a sign slip there would otherwise shift the
# oracle along with the decoder and go unseen).
# ------------------------------------------------------------------------------------------------


def _quat_axis_angle(axis: Sequence[float], angle: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions rotating ``angle`` radians (array) about a unit ``axis``."""
    angle = np.asarray(angle, dtype=np.float64)
    half = 0.5 * angle
    s = np.sin(half)
    out = np.empty(angle.shape + (4,), dtype=np.float64)
    out[..., 0] = axis[0] * s
    out[..., 1] = axis[1] * s
    out[..., 2] = axis[2] * s
    out[..., 3] = np.cos(half)
    return out


_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)

# ------------------------------------------------------------------------------------------------
# The cheer
# ------------------------------------------------------------------------------------------------


def local_pose(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint-local translations and rotations of the cheer at ``times`` (seconds).

    Times wrap into [0, DURATION) first, so t = 10 s gives bit for bit the pose of t = 0 s.

    Args:
        times: (n,) seconds.

    Returns:
        ``(translations, rotations)``: (n, 18, 3) float64 and (n, 18, 4) float64 unit quaternions
        (x, y, z, w), relative to the parent joint (UsdSkel's joint-local space).
    """
    t = np.mod(np.asarray(times, dtype=np.float64).reshape(-1), DURATION)
    n = t.shape[0]
    w = 2.0 * math.pi / DURATION  # one period per loop; every motion uses integer multiples

    translations = np.empty((n, BONE_COUNT, 3), dtype=np.float64)
    for j in range(BONE_COUNT):
        parent = PARENTS[j]
        offset = _BIND_POSITIONS[j] - (_BIND_POSITIONS[parent] if parent >= 0 else 0.0)
        translations[:, j] = offset
    rotations = np.zeros((n, BONE_COUNT, 4), dtype=np.float64)
    rotations[..., 3] = 1.0

    def rot(joint: str, *parts) -> None:
        q = np.zeros((n, 4))
        q[:, 3] = 1.0
        for axis, angle in parts:  # applied in order: the first part is outermost
            q = quat_multiply(q, _quat_axis_angle(axis, angle))
        rotations[:, _J[joint]] = q

    # Knee bounce: crouch depth in [0, 1], five bounces per loop (0.5 Hz).
    crouch = 0.5 + 0.5 * np.cos(5 * w * t)
    translations[:, _J["hips"], 1] -= 0.07 * crouch
    translations[:, _J["hips"], 0] += 0.02 * np.sin(w * t)
    rot("hips", (_Y, 0.12 * np.sin(w * t)), (_X, 0.06 * crouch))
    rot("spine", (_X, -0.05 * crouch + 0.04 * np.sin(5 * w * t + 0.5)))
    rot("chest", (_Y, 0.18 * np.sin(2 * w * t)), (_Z, 0.05 * np.sin(3 * w * t)))
    # Head bob at 1 Hz, looking around slowly.
    rot("head", (_Y, 0.30 * np.sin(3 * w * t)), (_X, -0.15 + 0.18 * np.sin(10 * w * t)))

    # Arms raised (T-pose arm along +X; +Z rotation lifts the left arm, -Z the right one) and waving.
    for side, sign, phase in (("L", 1.0, 0.0), ("R", -1.0, 0.5 * math.pi)):
        rot(f"{side}_shoulder", (_Z, sign * (0.25 + 0.10 * np.sin(5 * w * t + phase))))
        rot(f"{side}_upperArm",
            (_Y, sign * -0.35 * np.sin(3 * w * t + phase)),
            (_Z, sign * (1.05 + 0.30 * np.sin(4 * w * t + phase))))
        rot(f"{side}_forearm",
            (_Z, sign * (0.45 + 0.40 * np.sin(10 * w * t + phase))),
            (_X, 0.25 * np.sin(7 * w * t + phase)))
        rot(f"{side}_hand",
            (_X, 0.60 * np.sin(10 * w * t + 1.0 + phase)),
            (_Z, sign * 0.25 * np.sin(6 * w * t + phase)))
        # Legs follow the crouch: hip flexes forward, knee back, ankle compensates.
        rot(f"{side}_thigh", (_X, -0.38 * crouch), (_Z, sign * 0.04 * np.sin(w * t)))
        rot(f"{side}_shin", (_X, 0.72 * crouch))
        rot(f"{side}_foot", (_X, -0.34 * crouch))
    return translations, rotations


def _compose(translations: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(n, J, 4, 4) matrices T(t) R(q) from local translations and rotations."""
    n, j = translations.shape[:2]
    out = np.zeros((n, j, 4, 4), dtype=np.float64)
    out[..., :3, :3] = quat_to_matrix(rotations)
    out[..., :3, 3] = translations
    out[..., 3, 3] = 1.0
    return out


def world_matrices(times: np.ndarray) -> np.ndarray:
    """(n, 18, 4, 4) float64 joint world transforms (column vectors) of the cheer at ``times``."""
    local = _compose(*local_pose(times))
    world = np.empty_like(local)
    for j in range(BONE_COUNT):  # parent-first order
        parent = PARENTS[j]
        world[:, j] = local[:, j] if parent < 0 else world[:, parent] @ local[:, j]
    return world


def bind_matrices() -> np.ndarray:
    """(18, 4, 4) float64 joint world transforms at bind (the T-pose: translation only)."""
    bind = np.tile(np.eye(4), (BONE_COUNT, 1, 1))
    bind[:, :3, 3] = _BIND_POSITIONS
    return bind


def rest_local_matrices() -> np.ndarray:
    """(18, 4, 4) float64 joint-local rest transforms (the bind pose, relative to the parent)."""
    bind = bind_matrices()
    rest = bind.copy()
    for j in range(BONE_COUNT):
        if PARENTS[j] >= 0:
            rest[j, :3, 3] = _BIND_POSITIONS[j] - _BIND_POSITIONS[PARENTS[j]]
    return rest


def skinning_matrices(times: np.ndarray) -> np.ndarray:
    """Exact skinning matrices: joint world transform x inverse bind transform.

    Args:
        times: (n,) seconds (any real value; the cheer loops every 10 s).

    Returns:
        (n, 18, 4, 4) float64, column vectors: ``deformed = sum_i w_i M_i p_rest``.
    """
    inverse_bind = np.linalg.inv(bind_matrices())
    return world_matrices(times) @ inverse_bind


# ------------------------------------------------------------------------------------------------
# The mesh
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rig:
    """The generated spectator: rest mesh, skin and skeleton, all float64/int64.

    Attributes:
        points: (202, 3) rest positions (bind pose, world space).
        normals: (202, 3) unit area-weighted vertex normals.
        triangles: (352, 3) vertex indices, counter-clockwise seen from outside.
        bone_indices: (202, 4) joint indices (unused slots: 0 with weight 0).
        bone_weights: (202, 4) weights, each row summing to one.
        parts: Names of the 13 closed parts, with their (first vertex, vertex count).
    """

    points: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    bone_indices: np.ndarray
    bone_weights: np.ndarray
    parts: tuple

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Rest bounding box (min, max)."""
        return self.points.min(axis=0), self.points.max(axis=0)


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors u, v with (u, v, axis) right-handed."""
    axis = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, axis)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def _tube(start, end, radii, ring: int, stations, *, poles: bool = False, phase: float = 0.0,
          squash: tuple = (1.0, 1.0)):
    """A closed tube: ``len(stations)`` rings of ``ring`` vertices along start->end.

    Without poles the ends are flat caps fanned from the ring's first vertex (V = n m, 2 n m - 4
    triangles); with poles each end gets one apex vertex (V = n m + 2, 2 n m triangles). Either way
    the part is closed and genus 0: triangles = 2 V - 4.

    Args:
        start, end: Axis end points.
        radii: Radius at each station (sequence, same length as ``stations``).
        ring: Vertices per ring.
        stations: Fractions in [0, 1] along the axis.
        poles: Add an apex beyond each end instead of flat caps.
        phase: Ring rotation (radians), e.g. pi/4 to make a 4-ring a box.
        squash: Scale of the (u, v) cross-section axes, for elliptic sections.
    """
    start, end = np.asarray(start, float), np.asarray(end, float)
    axis = end - start
    u, v = _frame(axis)
    angles = phase + 2 * math.pi * np.arange(ring) / ring
    points = []
    for s, r in zip(stations, radii):
        centre = start + s * axis
        for a in angles:
            points.append(centre + r * (squash[0] * math.cos(a) * u + squash[1] * math.sin(a) * v))
    n = len(stations)
    tris = []
    for i in range(n - 1):
        for j in range(ring):
            a, b = i * ring + j, i * ring + (j + 1) % ring
            c, d = (i + 1) * ring + (j + 1) % ring, (i + 1) * ring + j
            tris += [(a, b, c), (a, c, d)]
    if poles:
        length = np.linalg.norm(axis)
        bottom, top = len(points), len(points) + 1
        points.append(start - 0.6 * radii[0] / length * axis)
        points.append(end + 0.6 * radii[-1] / length * axis)
        last = (n - 1) * ring
        for j in range(ring):
            tris.append((bottom, (j + 1) % ring, j))
            tris.append((top, last + j, last + (j + 1) % ring))
    else:
        last = (n - 1) * ring
        for j in range(1, ring - 1):
            tris.append((0, j + 1, j))
            tris.append((last, last + j, last + j + 1))
    return np.array(points), np.array(tris, dtype=np.int64)


def _box(lo, hi):
    """An axis-aligned box as a 4-vertex-ring tube along X: 8 vertices, 12 triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    y0, y1, z0, z1 = lo[1], hi[1], lo[2], hi[2]
    ring = [(y0, z0), (y1, z0), (y1, z1), (y0, z1)]
    points = np.array([(x, y, z) for x in (lo[0], hi[0]) for (y, z) in ring])
    tris = []
    for j in range(4):
        a, b = j, (j + 1) % 4
        tris += [(a, b, 4 + b), (a, 4 + b, 4 + a)]
    tris += [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7)]
    return points, np.array(tris, dtype=np.int64)


# Each part: its geometry and the joints whose bones may influence it (nearest wins, smoothly).
def _parts():
    parts = [
        ("torso", _tube((0, 0.88, 0), (0, 1.56, 0), (0.15, 0.14, 0.15, 0.17, 0.16), 8,
                        (0.0, 0.25, 0.5, 0.78, 1.0), squash=(1.0, 0.68)),
         ("hips", "spine", "chest", "L_shoulder", "R_shoulder")),
        ("neck", _tube((0, 1.52, -0.005), (0, 1.66, -0.005), (0.05, 0.045), 4, (0.0, 1.0),
                       phase=math.pi / 4), ("chest", "head")),
        ("head", _tube((0, 1.64, 0.01), (0, 1.82, 0.01), (0.09, 0.11, 0.085), 8, (0.0, 0.45, 1.0),
                       poles=True), ("head",)),
    ]
    for side, sx in (("L", 1.0), ("R", -1.0)):
        parts += [
            (f"{side}_arm", _tube((sx * 0.13, 1.48, 0), (sx * 0.71, 1.48, 0), (0.06, 0.05, 0.045, 0.035),
                                  6, (0.0, 0.4, 0.62, 1.0)),
             (f"{side}_shoulder", f"{side}_upperArm", f"{side}_forearm", f"{side}_hand")),
            (f"{side}_hand", _box((min(sx * 0.70, sx * 0.83), 1.445, -0.025),
                                  (max(sx * 0.70, sx * 0.83), 1.515, 0.025)),
             (f"{side}_forearm", f"{side}_hand")),
            (f"{side}_thigh", _tube((sx * 0.10, 0.99, 0), (sx * 0.10, 0.50, 0), (0.085, 0.065), 6,
                                    (0.0, 1.0)),
             ("hips", f"{side}_thigh", f"{side}_shin")),
            (f"{side}_shin", _tube((sx * 0.10, 0.54, 0), (sx * 0.10, 0.07, 0), (0.06, 0.045), 6,
                                   (0.0, 1.0)),
             (f"{side}_thigh", f"{side}_shin", f"{side}_foot")),
            (f"{side}_foot", _box((sx * 0.10 - 0.05, 0.0, -0.05), (sx * 0.10 + 0.05, 0.09, 0.18)),
             (f"{side}_shin", f"{side}_foot")),
        ]
    return parts


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    s = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * ab), axis=1)


def build_rig() -> Rig:
    """Build the spectator mesh and its skin (deterministic; no randomness involved).

    Returns:
        The :class:`Rig` with exactly 202 vertices and 352 triangles.
    """
    all_points, all_tris, indices, weights, spans = [], [], [], [], []
    base = 0
    for name, (points, tris), joints in _parts():
        # Outward winding: a closed part's signed volume must be positive.
        p0, p1, p2 = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
        if np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() < 0:
            tris = tris[:, ::-1]
        # Smooth weights: inverse fourth power of the distance to each candidate bone segment,
        # the largest four kept and renormalized, tiny ones dropped so weights stay meaningful.
        ids = np.array([_J[j] for j in joints])
        dist = np.stack([_segment_distance(points, _BIND_POSITIONS[i], _BONE_ENDS[i]) for i in ids], 1)
        raw = 1.0 / (dist + 0.03) ** 4
        order = np.argsort(-raw, axis=1, kind="stable")[:, :4]
        top = np.take_along_axis(raw, order, axis=1)
        top = top / top.sum(axis=1, keepdims=True)
        top[top < 0.02] = 0.0
        top = top / top.sum(axis=1, keepdims=True)
        k_ids = ids[order]
        pad = 4 - k_ids.shape[1]
        if pad:
            k_ids = np.pad(k_ids, ((0, 0), (0, pad)))
            top = np.pad(top, ((0, 0), (0, pad)))
        k_ids[top == 0.0] = 0
        all_points.append(points)
        all_tris.append(tris + base)
        indices.append(k_ids)
        weights.append(top)
        spans.append((name, base, len(points)))
        base += len(points)
    points = np.concatenate(all_points)
    triangles = np.concatenate(all_tris)
    assert points.shape == (VERTEX_COUNT, 3), points.shape
    assert triangles.shape == (TRIANGLE_COUNT, 3), triangles.shape
    # Area-weighted vertex normals (the cross product's length is twice the area).
    face_normals = np.cross(points[triangles[:, 1]] - points[triangles[:, 0]],
                            points[triangles[:, 2]] - points[triangles[:, 0]])
    normals = np.zeros_like(points)
    for corner in range(3):
        np.add.at(normals, triangles[:, corner], face_normals)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return Rig(points=points, normals=normals, triangles=triangles,
               bone_indices=np.concatenate(indices).astype(np.int64),
               bone_weights=np.concatenate(weights), parts=tuple(spans))


def skin(rig: Rig, matrices: np.ndarray) -> np.ndarray:
    """Exact linear blend skinning in float64: ``sum_i w_i M_i p`` for each pose.

    Args:
        rig: The rig.
        matrices: (n, 18, 4, 4) skinning matrices (see :func:`skinning_matrices`).

    Returns:
        (n, 202, 3) float64 deformed points.
    """
    p = rig.points
    out = np.zeros((matrices.shape[0],) + p.shape)
    for k in range(rig.bone_indices.shape[1]):
        m = matrices[:, rig.bone_indices[:, k]]  # (n, V, 4, 4)
        moved = np.einsum("nvij,vj->nvi", m[..., :3, :3], p) + m[..., :3, 3]
        out += rig.bone_weights[None, :, k, None] * moved
    return out


# ------------------------------------------------------------------------------------------------
# The crowd
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CrowdPlacement:
    """Per-instance data of the stadium stand, float64.

    Attributes:
        positions: (1200, 3).
        orientations: (1200, 4) unit quaternions (x, y, z, w): yaw about +Y facing the pitch.
        time_offset: (1200,) clip time offsets in [0, 10) s.
        playback_rate: (1200,) rates in [0.9, 1.1].
    """

    positions: np.ndarray
    orientations: np.ndarray
    time_offset: np.ndarray
    playback_rate: np.ndarray


def crowd_placement(count: int = CROWD_SIZE, seed: int = CROWD_SEED) -> CrowdPlacement:
    """Seat ``count`` spectators on a stepped stand along one side of the pitch.

    The stand has 12 tiers of 100 seats (0.6 m apart, tiers 0.85 m deep and 0.45 m high) on the
    +Z side of a pitch centred at the origin; each spectator yaws to face the pitch's centre line
    plus a little seeded jitter. Clip offsets and playback rates are seeded uniform draws.
    """
    rng = np.random.default_rng(seed)
    seats_per_tier = 100
    tiers = -(-count // seats_per_tier)
    seat = np.arange(count)
    tier, column = seat // seats_per_tier, seat % seats_per_tier
    x = (column - (seats_per_tier - 1) / 2) * 0.6 + rng.uniform(-0.08, 0.08, count)
    y = tier * 0.45
    z = 40.0 + tier * 0.85 + rng.uniform(-0.05, 0.05, count)
    positions = np.stack([x, y, z], axis=1)
    # Face the point of the pitch's halfway line level with the spectator's seat (x / 3 gives a
    # slight turn toward the middle); forward is +Z at rest, yaw theta maps it to (sin, 0, cos).
    target = np.stack([x / 3.0, np.zeros(count), np.zeros(count)], axis=1)
    d = target - positions
    yaw = np.arctan2(d[:, 0], d[:, 2]) + rng.uniform(-0.1, 0.1, count)
    orientations = _quat_axis_angle(_Y, yaw)
    time_offset = rng.uniform(0.0, DURATION, count)
    playback_rate = rng.uniform(0.9, 1.1, count)
    del tiers
    return CrowdPlacement(positions, orientations, time_offset, playback_rate)


# ------------------------------------------------------------------------------------------------
# Writers
# ------------------------------------------------------------------------------------------------


def _atomic_export(layer, path: Path) -> None:
    """Export an Sdf layer to ``path`` through a temporary file beside it, then rename (vbusd.io.files)."""
    from vbusd.io.files import atomic_write_many

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write_many() as transaction:
        if not layer.Export(str(transaction.temp_path(path))):
            raise OSError(f"{path}: USD could not export the layer")


def _to_usd_matrix(m: np.ndarray):
    from pxr import Gf

    # vbusd matrices act on column vectors; USD's on row vectors: transpose.
    return Gf.Matrix4d(*np.asarray(m, dtype=np.float64).T.reshape(-1).tolist())


def write_usdskel(path: os.PathLike, rig: Optional[Rig] = None) -> Path:
    """Write the UsdSkel asset (the input of ``vbusd convert``).

    Layout: ``/StadiumCrowd`` (SkelRoot, default prim) holding ``Skeleton`` (joints, bind and rest
    transforms), ``Skeleton/Cheer`` (SkelAnimation: translations, rotations and scales at time
    codes 0..300, 30 per second) and ``Body`` (Mesh with SkelBindingAPI, 4 influences per vertex).

    Args:
        path: Output .usda path.
        rig: The rig (built when None).

    Returns:
        The path written.
    """
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    rig = rig or build_rig()
    path = Path(path)
    stage = Usd.Stage.CreateInMemory()
    stage.SetMetadata("upAxis", UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(FRAME_COUNT)
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetFramesPerSecond(FPS)
    stage.GetRootLayer().documentation = (
        "The Virtual Bones stadium-crowd spectator (18 joints, 202 points, 352 triangles, 10 s "
        "looping cheer), generated by samples/stadium_crowd.py; do not edit by hand.")

    root = UsdSkel.Root.Define(stage, "/StadiumCrowd")
    stage.SetDefaultPrim(root.GetPrim())

    skeleton = UsdSkel.Skeleton.Define(stage, "/StadiumCrowd/Skeleton")
    skeleton.CreateJointsAttr(Vt.TokenArray(list(JOINT_PATHS)))
    skeleton.CreateJointNamesAttr(Vt.TokenArray(list(JOINT_NAMES)))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([_to_usd_matrix(m) for m in bind_matrices()]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([_to_usd_matrix(m) for m in rest_local_matrices()]))

    anim = UsdSkel.Animation.Define(stage, "/StadiumCrowd/Skeleton/Cheer")
    anim.CreateJointsAttr(Vt.TokenArray(list(JOINT_PATHS)))
    frames = np.arange(FRAME_COUNT + 1)
    translations, rotations = local_pose(frames / FPS)
    t_attr = anim.CreateTranslationsAttr()
    r_attr = anim.CreateRotationsAttr()
    s_attr = anim.CreateScalesAttr()
    ones = Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * BONE_COUNT)
    for f in frames:
        code = Usd.TimeCode(float(f))
        t_attr.Set(Vt.Vec3fArray.FromNumpy(translations[f].astype(np.float32)), code)
        # Gf.Quatf is (real, imaginary); ours are (x, y, z, w).
        r_attr.Set(Vt.QuatfArray([Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2]))
                                  for q in rotations[f]]), code)
        s_attr.Set(ones, code)
    binding = UsdSkel.BindingAPI.Apply(skeleton.GetPrim())
    binding.CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    mesh = UsdGeom.Mesh.Define(stage, "/StadiumCrowd/Body")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rig.points.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * TRIANGLE_COUNT))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(rig.triangles.reshape(-1).tolist()))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(rig.normals.astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = rig.bounds
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))
    mesh_binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    mesh_binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    mesh_binding.CreateJointIndicesPrimvar(False, 4).Set(
        Vt.IntArray(rig.bone_indices.reshape(-1).tolist()))
    mesh_binding.CreateJointWeightsPrimvar(False, 4).Set(
        Vt.FloatArray(rig.bone_weights.astype(np.float32).reshape(-1).tolist()))
    mesh_binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    # An animated extent for the whole loop so viewers frame the motion.
    moving = skin(rig, skinning_matrices(frames / FPS)).reshape(-1, 3)
    UsdGeom.Boundable(root.GetPrim()).CreateExtentAttr(
        Vt.Vec3fArray([Gf.Vec3f(*moving.min(0).tolist()), Gf.Vec3f(*moving.max(0).tolist())]))

    _atomic_export(stage.GetRootLayer(), path)
    return path


def make_skinned_animation(rig: Optional[Rig] = None):
    """The cheer as a :class:`vbusd.format.model.SkinnedAnimation`, sampling the exact float64 matrices.

    The clip's sampler is :func:`skinning_matrices` itself (not the USD file), so the baked texture
    carries only the format's own quantization and resampling error.
    """
    from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh

    rig = rig or build_rig()
    clip = AnimationClip(name="cheer", start_time=0.0, end_time=DURATION, sample=skinning_matrices,
                         native_rate=FPS, loop=True,
                         key_times=np.arange(FRAME_COUNT + 1, dtype=np.float64) / FPS)
    mesh = SkinnedMesh(path="/StadiumCrowd/Body", points=rig.points,
                       face_vertex_counts=np.full(TRIANGLE_COUNT, 3, dtype=np.int32),
                       face_vertex_indices=rig.triangles.reshape(-1).astype(np.int32),
                       bone_indices=rig.bone_indices.astype(np.int32), bone_weights=rig.bone_weights,
                       normals=rig.normals, normals_interpolation="vertex",
                       source_path="samples/stadium_crowd.py")
    return SkinnedAnimation(name="Cheer", path="/StadiumCrowd/Cheer", bones=JOINT_PATHS,
                            clips=(clip,), meshes=(mesh,), source="samples/stadium_crowd.py")


def reference_bake_options(**overrides):
    """The talk's bake: crossMatrix, float16, power-of-two width and height, looping.

    Keyword arguments override fields of :class:`vbusd.baking.baker.BakeOptions` (the accuracy benchmark
    sweeps encodings and texel formats this way).
    """
    from vbusd.baking.baker import BakeOptions

    options = dict(encoding="crossMatrix", texel_format="float16", horizontal_padding="powerOfTwo",
                   vertical_padding="powerOfTwo", loop=True)
    options.update(overrides)
    return BakeOptions(**options)


def bake_reference(rig: Optional[Rig] = None, **overrides):
    """Bake the cheer (:func:`reference_bake_options`); returns a :class:`vbusd.format.model.VirtualBones`."""
    from vbusd.baking.baker import bake

    return bake(make_skinned_animation(rig), reference_bake_options(**overrides))


def make_asset(rig: Optional[Rig] = None):
    """The Virtual Bones asset: the baked cheer and a crowd of 1,200 spectators on one instancer."""
    from vbusd.format.model import Crowd, VirtualBonesAsset

    baked = bake_reference(rig)
    seats = crowd_placement()
    crowd = Crowd(path="/StadiumCrowd/Crowd",
                  positions=seats.positions.astype(np.float32),
                  orientations=seats.orientations.astype(np.float32),
                  clip=np.zeros(CROWD_SIZE, dtype=np.int32),
                  time_offset=seats.time_offset.astype(np.float32),
                  playback_rate=seats.playback_rate.astype(np.float32))
    return VirtualBonesAsset(animations=(baked,), crowds=(crowd,), crowd_animation=(0,),
                             up_axis="Y", meters_per_unit=1.0, time_codes_per_second=FPS,
                             default_prim="StadiumCrowd")


def hat_mesh(path: str = "/StadiumCrowd/Hat"):
    """An optional hat part (spec "Crowd variety", modular characters): a flat box on top of the head,
    bound rigidly to the ``head`` joint, in bind space like the body (8 vertices, 12 triangles)."""
    from vbusd.format.model import SkinnedMesh

    top = _BONE_ENDS[_J["head"]]
    points, triangles = _box((top[0] - 0.13, top[1] - 0.03, top[2] - 0.13), (top[0] + 0.13, top[1] + 0.07, top[2] + 0.13))
    centre = points.mean(axis=0)
    normals = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    count = len(points)
    return SkinnedMesh(path=path, points=points, face_vertex_counts=np.full(len(triangles), 3, dtype=np.int32),
                       face_vertex_indices=triangles.reshape(-1).astype(np.int32),
                       bone_indices=np.full((count, 1), _J["head"], dtype=np.int32), bone_weights=np.ones((count, 1)),
                       normals=normals, normals_interpolation="vertex", source_path="samples/stadium_crowd.py")


FLAG_BONE = "R_hand"
"""The joint whose socket holds the flag prop (spec 22.3, "Props at sockets")."""


def flag_local():
    """The flag prop in the joint space of :data:`FLAG_BONE` (metres): a pole along the joint's +Y from
    just past the hand, and a cloth plate at its top reaching outwards (-X, away from the body), thin
    along Z. Returns (points (16, 3), triangles (24, 3), normals (16, 3)), float64 / int64."""
    pole, pole_tris = _box((-0.095, -0.05, -0.015), (-0.065, 0.75, 0.015))
    cloth, cloth_tris = _box((-0.45, 0.45, -0.01), (-0.095, 0.75, 0.01))
    points = np.concatenate([pole, cloth])
    triangles = np.concatenate([pole_tris, cloth_tris + len(pole)])
    normals = np.concatenate([(box - box.mean(axis=0)) / np.linalg.norm(box - box.mean(axis=0), axis=1, keepdims=True)
                              for box in (pole, cloth)])
    return points, triangles, normals


def flag_mesh(path: str = "/StadiumCrowd/Flag"):
    """An optional flag prop held in the right hand (spec "Crowd variety", props at sockets): the points
    of :func:`flag_local` placed at the bind pose of :data:`FLAG_BONE` with
    ``vbusd.format.variety.socket_prop`` and bound rigidly to that joint, so that it draws at the socket
    ``J p`` at every time (16 vertices, 24 triangles)."""
    from vbusd.format.model import SkinnedMesh
    from vbusd.format.variety import socket_prop

    local, triangles, local_normals = flag_local()
    points, normals = socket_prop(bind_matrices()[_J[FLAG_BONE]], local, local_normals)
    count = len(points)
    return SkinnedMesh(path=path, points=points, face_vertex_counts=np.full(len(triangles), 3, dtype=np.int32),
                       face_vertex_indices=triangles.reshape(-1).astype(np.int32),
                       bone_indices=np.full((count, 1), _J[FLAG_BONE], dtype=np.int32), bone_weights=np.ones((count, 1)),
                       normals=normals, normals_interpolation="vertex", source_path="samples/stadium_crowd.py")


def write_modular(path: os.PathLike, rig: Optional[Rig] = None) -> Path:
    """The spectator as a modular character (format 1.3 crowd variety): the body, an optional ``Hat`` part and
    an optional ``Flag`` prop at the right hand's socket, sharing its skeleton and texture, with the joints'
    bind transforms (sockets), no crowd of its own (``vbusd crowd --parts Hat=P,Flag=Q`` places it)."""
    import dataclasses

    from vbusd.baking.baker import bake
    from vbusd.format.model import VirtualBonesAsset
    from vbusd.io import usd as usd_io

    animation = make_skinned_animation(rig)
    animation = dataclasses.replace(animation, meshes=animation.meshes + (hat_mesh(), flag_mesh()),
                                    bind_transforms=bind_matrices())
    baked = bake(animation, reference_bake_options())
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    usd_io.write_asset(VirtualBonesAsset(animations=(baked,), up_axis="Y", meters_per_unit=1.0,
                                         time_codes_per_second=FPS, default_prim="StadiumCrowd"), path)
    return path


def write_virtual_bones(path: os.PathLike, rig: Optional[Rig] = None) -> Path:
    """Write the Virtual Bones asset (USD + texture + sidecar JSON) with ``vbusd.io.usd``."""
    from vbusd.io import usd as usd_io

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    usd_io.write_asset(make_asset(rig), path)
    return path


def generate(out_dir: os.PathLike, *, virtual_bones: bool = True) -> list:
    """Write every output of the sample into ``out_dir``; returns the USD paths written."""
    out_dir = Path(out_dir)
    rig = build_rig()
    written = [write_usdskel(out_dir / USDSKEL_NAME, rig)]
    if virtual_bones:
        written.append(write_virtual_bones(out_dir / VB_NAME, rig))
    return written


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command line: ``python samples/stadium_crowd.py [--out DIR] [--usdskel-only]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "stadium_crowd"),
                        help="output folder (default: samples/stadium_crowd beside this script)")
    parser.add_argument("--usdskel-only", action="store_true",
                        help="write only the UsdSkel asset (no vbusd bake)")
    args = parser.parse_args(argv)
    from vbusd.format.errors import VbusdError

    if Path(args.out).exists() and not Path(args.out).is_dir():
        print(f"stadium_crowd: {args.out}: --out must be a folder", file=sys.stderr)
        return 2
    try:
        written = generate(args.out, virtual_bones=not args.usdskel_only)
    except OSError as error:  # one line, no traceback: an unwritable or non-folder --out
        print(f"stadium_crowd: {error.filename or args.out}: {error.strerror or error}", file=sys.stderr)
        return 2
    except VbusdError as error:
        print(f"stadium_crowd: {error}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
