"""Draw-time cost of Virtual Bones against the alternatives, in a real OpenGL pipeline (issue 18).

N instances of a character are drawn into a 1920 x 1080 colour + depth framebuffer (depth test,
back-face culling, one Lambert light) by six methods:

1. ``static``: the rest mesh placed per instance, no animation (the floor), from a vertex buffer of
   position and normal only (24 bytes a vertex), as a static mesh is stored;
2. ``vb``: Virtual Bones, the reference GLSL module exactly as ``vbusd shader`` prints it (with
   ``main`` off, so the draw's own vertex function calls ``vbSkin`` and then places and projects),
   one instanced draw, per encoding and texel format; the skin binding ``attributes``: bone indices
   and weights as vertex attributes (a 56-byte vertex);
2b. ``vb_pulled``: the same with the module of ``vbusd shader --skin pulled`` (issue 25): the mesh
   keeps position and normal (the static mesh's vertex buffer), and the module's
   ``vbSkinInfluences`` reads each vertex's skin record (``vbusd.decoders.shaders.pack_skin``) by
   ``gl_VertexID`` from its storage buffer ``VbSkin``;
3. ``vat``: a vertex animation texture, the talk's "previous work": positions and normals of every
   vertex at every row of the same clip (same 51.2 rows/s, looping, linear interpolation between
   rows), RGBA float16, fetched by ``gl_VertexID``;
4. ``palette``: classic palette skinning: every frame the CPU evaluates every instance's 18 bone
   matrices from the animation's keys (the sample's joint-local translations and rotations at its
   30 fps time codes: lerp / nlerp, hierarchy, inverse bind, vectorized numpy, float32), uploads
   them into a shader storage buffer, and the vertex shader skins with them;
5b. ``vb_lod`` (issue 29): Virtual Bones with three levels of detail sharing the texture (LOD 1 and 2
   made by ``vbusd.baking.lod`` at 0.5 and 0.2 of the triangles, 2 and 1 influences); per frame a compute
   shader picks every instance's level (UsdLod's projectedSphere screen size, thresholds 0.01 and
   0.001, culled by the view), writes per-level instance lists and the instance counts of three
   indirect draws, which read their lists by ``gl_InstanceID`` (no draw call per instance);
5c. ``vb_variety`` (issue 37, ``run --variety on|both``): ``vb`` with crowd variety (format 1.3): per
   instance a tint (3 floats), a material variant (an int selecting one of 8 base colours, a uniform
   array) and a parts mask (an int) in a 20-byte instance stream; the fragment colour is the
   variant's colour times the tint; the spectator's hat part (samples/stadium_crowd.py ``hat_mesh``,
   8 vertices, 12 triangles, on about half the instances) is a second instanced draw whose vertex
   shader collapses the instances whose mask hides it (what the web runtimes do with zero matrices);
5. ``warp``: vbusd's warp decoder (``vbusd.Decoder.skin_crowd``) writes world-space positions and
   normals into GL buffers (CUDA-GL interop when CUDA is there, else a copy through the host,
   reported as such), then a draw pulls them by ``gl_InstanceID`` and ``gl_VertexID``.

Characters: ``stadium``, the talk's spectator (samples/stadium_crowd.py, 202 vertices, 352
triangles, 18 bones, 4 influences) and ``dense``, the same body with every triangle split 17 x 17
(50,890 vertices, 101,728 triangles; positions, normals and skin weights interpolated, top 4
influences), skinned to the same skeleton. Instances stand on a square grid (0.6 m x 0.85 m seats)
with seeded yaw, clip offsets in [0, 10) s and rates in [0.9, 1.1]; the camera frames the grid.

Per configuration the script first reads back, through transform feedback of the very vertex
shader it times, the world-space positions and normals of the first and last instances and
compares them with an independent numpy computation (``vbusd.decoders.reference.skin_crowd`` for
Virtual Bones and warp; float64 interpolation of the stored float16 texels for the VAT; float64
linear blend skinning with the uploaded matrices for palette skinning; the placed rest mesh for
static). It also reports each method's distance from the exact animation (the generator's float64
skinning matrices at the same clip times). Then it times frames: GL timer queries (GL_TIME_ELAPSED)
around the draw (and around the palette upload), CUDA events around the warp decoder's launches,
``time.perf_counter`` around the CPU's work per frame, and the wall time of a whole frame ended by
``glFinish``. Medians over the runs are reported. Bytes of animation data on the GPU are counted
per method (textures, per-instance animation inputs, bone palettes, decoder buffers).

Usage::

    python benchmarks/draw_cost.py run --json OUT.json [--budget 420] [--sizes 1200,10000]
    python benchmarks/draw_cost.py run --plan issue25 --json OUT.json   # issue 25's set, one device call
    python benchmarks/draw_cost.py run --plan issue37 --json OUT.json   # variety off vs on, 100,000 spectators
    python benchmarks/draw_cost.py run --variety both --sizes 100000 --characters stadium --methods vb --json OUT.json
    python benchmarks/draw_cost.py factors --json OUT.json [--sizes 100000,10000]
    python benchmarks/draw_cost.py report --json benchmarks/results/draw_cost_h200.json \\
        --markdown --plot benchmarks/results/draw_cost_h200.png

``--plan issue25`` runs exactly issue 25's configurations (:data:`PLANS`): static, ``vb``,
``vb_pulled`` and the VAT, crossMatrix float16, stadium character at 100,000, 1,000,000 and 10,000
instances and the dense one at 1,200 and 10,000, within a 400 s budget and at least 10 timed frames
each; ``report`` then adds a table of each method's GPU draw time as a factor of static, with every
row's error against numpy (:func:`bindings_markdown`).

``--plan issue29`` compares ``vb`` (one level) with ``vb_lod`` (three) for the stadium at 1,000,000,
100,000 and 10,000 instances seen from the grid's edge (:func:`stand_camera`, the same view for
both); ``report`` adds frame and GPU time and triangles drawn per level (:func:`lod_markdown`).
``lod-meshes --out FILE`` writes the generated levels for a machine without meshoptimizer
(``$VBUSD_LOD_MESHES``).

``--previous on|both`` (issue 36) also draws the Virtual Bones methods (``vb``, ``vb_pulled``,
``vb_pulled_texture``) with the module of ``vbusd shader --previous``: the draw's main skins each
vertex a second time at the previous frame's time (``vb_previousTime = t - 1/60``), projects both
positions and writes the screen-space velocity into a second colour target (``RG16F``, as a TAA or
motion-blur pass reads it); the read-back checks the previous positions against
``reference.skin_crowd_previous`` too. ``both`` times each such configuration without and with it,
``report`` then adds the cost table (:func:`previous_markdown`); ``--plan issue36`` is that set.

``factors`` is the one-factor study around Virtual Bones' vertex cost (:func:`run_factors`): skin
attributes fetched or not, packed or not, read from storage buffers, K influences; its variants keep
the 56-byte vertex of the attribute binding, static included, so that one factor changes at a time.
benchmarks/draw_run.sh runs ``run``, ``run --plan issue25`` and ``factors`` on the device tool's GPU
machine; ``report`` runs anywhere (the plot needs matplotlib).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import vbusd  # noqa: E402
from vbusd.decoders import reference  # noqa: E402
from vbusd.decoders.shaders import pack_skin  # noqa: E402
from vbusd.format.quaternion import quat_to_matrix  # noqa: E402

ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
FORMATS = ("float16", "float32", "unorm16")
SIZES = (1_200, 10_000, 100_000, 1_000_000)
RESOLUTION = (1920, 1080)
DENSE_SPLITS = 17  # each triangle of the body split 17 x 17: 50,890 vertices
GLSL_VERSION = "#version 430 core\n"
SEAT = (0.6, 0.85)  # metres between neighbours across and along the grid
FRAME_STEP = 1.0 / 60.0  # scene time advances one 60 Hz frame per timed frame
PREVIOUS_DT = FRAME_STEP  # --previous: the frame interval of the previous pose (spec 21's default)
PREVIOUS_METHODS = ("vb", "vb_pulled", "vb_pulled_texture")  # the methods --previous draws both ways
CHECK_TIME = 1.2345  # scene time of the read-back checks
MAX_OUTPUT_GIB = 40.0  # warp: largest decoded vertex buffers (positions + normals) we allocate
SKIN_BINDING = 3  # vb_pulled: storage binding of the skin records (palette: 0, warp: 0 and 1, factor study: 1 and 2)


def _load_sample():
    path = ROOT / "samples" / "stadium_crowd.py"
    spec = importlib.util.spec_from_file_location("draw_cost_stadium_crowd", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


SAMPLE = _load_sample()

# ------------------------------------------------------------------------------------------ data


@dataclass
class Character:
    """A bound mesh and its triangles."""

    name: str
    mesh: "vbusd.BoundMesh"
    triangles: np.ndarray  # (F, 3) uint32

    @property
    def vertex_count(self) -> int:
        return int(self.mesh.points.shape[0])


def stadium_character(vb) -> Character:
    mesh = vb.meshes[0]
    triangles = np.asarray(mesh.face_vertex_indices, dtype=np.uint32).reshape(-1, 3)
    return Character("stadium", mesh, triangles)


def _top_influences(dense: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest weights of each row of a dense (V, B) weight matrix, renormalized."""
    order = np.argsort(-dense, axis=1, kind="stable")[:, :k]
    weights = np.take_along_axis(dense, order, axis=1)
    weights = weights / weights.sum(axis=1, keepdims=True)
    return order.astype(np.int32), weights.astype(np.float32)


def subdivide(character: Character, splits: int, bone_count: int) -> Character:
    """Split every triangle into ``splits`` x ``splits`` (shared edges split once).

    New vertices interpolate the corners barycentrically: positions (flat, so the surface keeps its
    shape), normals (renormalized) and skin weights (the largest K of the blend, renormalized).
    Vertex count: V + E (s - 1) + F (s - 1)(s - 2) / 2.
    """
    mesh, tris, n = character.mesh, character.triangles.astype(np.int64), splits
    v_count, f_count = mesh.points.shape[0], tris.shape[0]
    sides = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1)  # (F, 3, 2)
    edges, inverse = np.unique(np.sort(sides.reshape(-1, 2), axis=1), axis=0, return_inverse=True)
    edge_of = inverse.reshape(f_count, 3)
    interior = (n - 1) * (n - 2) // 2
    first_interior = v_count + len(edges) * (n - 1)

    lattice = [(i, j) for j in range(n + 1) for i in range(n + 1 - j)]
    slot = {ij: s for s, ij in enumerate(lattice)}
    ids = np.empty((f_count, len(lattice)), dtype=np.int64)
    bary = np.empty((len(lattice), 3))
    interior_index = 0
    for s, (i, j) in enumerate(lattice):
        bary[s] = ((n - i - j) / n, i / n, j / n)
        if (i, j) == (0, 0):
            ids[:, s] = tris[:, 0]
        elif (i, j) == (n, 0):
            ids[:, s] = tris[:, 1]
        elif (i, j) == (0, n):
            ids[:, s] = tris[:, 2]
        elif j == 0 or i + j == n or i == 0:
            side, step = (0, i) if j == 0 else (1, j) if i + j == n else (2, n - j)
            start = sides[:, side, 0]
            end = sides[:, side, 1]
            k = np.where(start < end, step, n - step)  # steps from the edge's smaller vertex
            ids[:, s] = v_count + edge_of[:, side] * (n - 1) + (k - 1)
        else:
            ids[:, s] = first_interior + np.arange(f_count) * interior + interior_index
            interior_index += 1
    total = first_interior + f_count * interior
    flat_ids = ids.reshape(-1)
    unique_ids, first = np.unique(flat_ids, return_index=True)
    assert unique_ids.shape[0] == total and unique_ids[-1] == total - 1
    face = first // len(lattice)
    weights3 = bary[first % len(lattice)]  # (total, 3)
    corners = tris[face]  # (total, 3)

    points = np.einsum("vc,vcd->vd", weights3, np.asarray(mesh.points, np.float64)[corners])
    normals = np.einsum("vc,vcd->vd", weights3, np.asarray(mesh.normals, np.float64)[corners])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    dense = np.zeros((v_count, bone_count))
    np.add.at(dense, (np.repeat(np.arange(v_count), mesh.bone_indices.shape[1]), mesh.bone_indices.reshape(-1)),
              np.asarray(mesh.bone_weights, np.float64).reshape(-1))
    blended = np.einsum("vc,vcb->vb", weights3, dense[corners])
    bone_indices, bone_weights = _top_influences(blended, mesh.bone_indices.shape[1])

    triangles = []
    for j in range(n):
        for i in range(n - j):
            triangles.append(ids[:, [slot[(i, j)], slot[(i + 1, j)], slot[(i, j + 1)]]])
            if i + j <= n - 2:
                triangles.append(ids[:, [slot[(i + 1, j)], slot[(i + 1, j + 1)], slot[(i, j + 1)]]])
    triangles = np.concatenate(triangles, axis=0).astype(np.uint32)
    dense_mesh = vbusd.BoundMesh(path="/DrawCost/Dense", points=points.astype(np.float32),
                                 face_vertex_counts=np.full(len(triangles), 3, np.int32),
                                 face_vertex_indices=triangles.reshape(-1).astype(np.int32),
                                 bone_indices=bone_indices, bone_weights=bone_weights,
                                 normals=normals.astype(np.float32))
    return Character("dense", dense_mesh, triangles)


def crowd_grid(count: int, seed: int = 18) -> "vbusd.Crowd":
    """``count`` instances on a square grid centred at the origin, seeded yaw, offsets and rates."""
    rng = np.random.default_rng(seed)
    side = int(math.ceil(math.sqrt(count)))
    rows = -(-count // side)
    index = np.arange(count)
    x = (index % side - (side - 1) / 2) * SEAT[0]
    z = (index // side - (rows - 1) / 2) * SEAT[1]
    positions = np.stack([x, np.zeros(count), z], axis=1)
    yaw = rng.uniform(-math.pi, math.pi, count)
    orientations = np.stack([np.zeros(count), np.sin(yaw / 2), np.zeros(count), np.cos(yaw / 2)], axis=1)
    return vbusd.Crowd(path="/DrawCost/Crowd", positions=positions.astype(np.float32),
                       orientations=orientations.astype(np.float32), clip=np.zeros(count, np.int32),
                       time_offset=rng.uniform(0.0, SAMPLE.DURATION, count).astype(np.float32),
                       playback_rate=rng.uniform(0.9, 1.1, count).astype(np.float32))


def crowd_rows(crowd, rows: np.ndarray) -> "vbusd.Crowd":
    """The instances ``rows`` of a crowd, as a crowd."""
    return vbusd.Crowd(path=crowd.path, positions=crowd.positions[rows], orientations=crowd.orientations[rows],
                       clip=crowd.clip[rows], time_offset=crowd.time_offset[rows],
                       playback_rate=crowd.playback_rate[rows])


def view_projection(count: int) -> np.ndarray:
    """A 60 degree perspective camera looking down at 40 degrees onto the whole grid (column vectors)."""
    side = math.ceil(math.sqrt(count))
    rows = -(-count // side)
    radius = 0.5 * math.hypot(side * SEAT[0], rows * SEAT[1]) + 2.0
    fov = math.radians(60.0)
    distance = radius / math.sin(fov / 2)
    pitch = math.radians(40.0)
    eye = np.array([0.0, distance * math.sin(pitch), distance * math.cos(pitch)])
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    near, far = max(distance - radius, 0.1) * 0.5, distance + radius
    aspect = RESOLUTION[0] / RESOLUTION[1]
    f = 1.0 / math.tan(fov / 2)
    projection = np.zeros((4, 4))
    projection[0, 0], projection[1, 1] = f / aspect, f
    projection[2, 2], projection[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    projection[3, 2] = -1.0
    return projection @ view


@dataclass
class Camera:
    """A perspective camera (issue 29's levels of detail need its eye, field of view and aspect)."""

    eye: np.ndarray
    fov_y_degrees: float
    aspect: float
    view_projection: np.ndarray
    planes: np.ndarray  # (6, 4) frustum planes a x + b y + c z + d >= 0 inside, normalized


def _look(eye, target, fov_y_degrees: float, near: float, far: float) -> Camera:
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    aspect = RESOLUTION[0] / RESOLUTION[1]
    f = 1.0 / math.tan(math.radians(fov_y_degrees) / 2)
    projection = np.zeros((4, 4))
    projection[0, 0], projection[1, 1] = f / aspect, f
    projection[2, 2], projection[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    projection[3, 2] = -1.0
    m = projection @ view
    planes = np.array([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    return Camera(eye, fov_y_degrees, aspect, m, planes)


def stand_camera(count: int) -> Camera:
    """Issue 29's view of the stadium: from 6 m up, 3 m before the grid's near edge, looking across it 6
    degrees down, so that near spectators are large and far ones a few pixels (60 degree field of view)."""
    side = math.ceil(math.sqrt(count))
    rows = -(-count // side)
    depth = rows * SEAT[1]
    eye = np.array([0.0, 6.0, depth / 2 + 3.0])
    target = eye + np.array([0.0, -math.tan(math.radians(6.0)), -1.0])
    return _look(eye, target, 60.0, 0.5, depth + 50.0)


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (x, y, z, w), normalized first."""
    return quat_to_matrix(q / np.linalg.norm(q, axis=-1, keepdims=True))


def place(crowd, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object-space (S, V, 3) points and normals placed by the crowd's orientation and position."""
    rotation = quat_matrices(np.asarray(crowd.orientations, np.float64))
    world = np.einsum("sij,svj->svi", rotation, points) + np.asarray(crowd.positions, np.float64)[:, None, :]
    return world, np.einsum("sij,svj->svi", rotation, normals)


def linear_blend(matrices: np.ndarray, mesh) -> tuple[np.ndarray, np.ndarray]:
    """Float64 linear blend skinning of ``mesh`` with (S, B, 3 or 4, 4) matrices: (S, V, 3) each."""
    m = np.asarray(matrices, np.float64)[:, :, :3, :]
    idx, w = mesh.bone_indices, np.asarray(mesh.bone_weights, np.float64)
    p = np.asarray(mesh.points, np.float64)
    nrm = np.asarray(mesh.normals, np.float64)
    points = np.zeros((m.shape[0],) + p.shape)
    normals = np.zeros_like(points)
    for k in range(idx.shape[1]):
        bone = m[:, idx[:, k]]  # (S, V, 3, 4)
        points += w[None, :, k, None] * (np.einsum("svij,vj->svi", bone[..., :3], p) + bone[..., 3])
        normals += w[None, :, k, None] * np.einsum("svij,vj->svi", bone[..., :3], nrm)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return points, np.where(length > 0, normals / np.where(length > 0, length, 1), normals)


def exact_pose(crowd, mesh, t: float) -> tuple[np.ndarray, np.ndarray]:
    """World-space points and normals from the generator's exact float64 matrices at each clip time."""
    taus = reference.instance_time(crowd, t)
    return place(crowd, *linear_blend(SAMPLE.skinning_matrices(taus), mesh))


# ------------------------------------------------------------------------------------------ VAT


@dataclass
class VertexAnimation:
    """Positions and normals of every vertex at every row, RGBA float16, ``per_row`` texels wide."""

    positions: np.ndarray  # (rows * rows_per_frame, width, 4) float16
    normals: np.ndarray
    frames: int
    rows_per_second: float
    width: int
    rows_per_frame: int

    @property
    def nbytes(self) -> int:
        return int(self.positions.nbytes + self.normals.nbytes)

    def lookup(self, values: np.ndarray, frame: np.ndarray, vertex: np.ndarray) -> np.ndarray:
        return values[frame * self.rows_per_frame + vertex // self.width, vertex % self.width]


def bake_vat(mesh, clip, chunk: int = 16) -> VertexAnimation:
    """Sample the exact animation at every row time of ``clip`` and store it per vertex, float16."""
    v = mesh.points.shape[0]
    rows_per_frame = -(-v // 4096)
    width = -(-v // rows_per_frame)
    frames = clip.row_count
    shape = (frames * rows_per_frame, width, 4)
    positions = np.zeros(shape, np.float16)
    normals = np.zeros(shape, np.float16)
    for start in range(0, frames, chunk):
        rows = np.arange(start, min(start + chunk, frames))
        points, nrm = linear_blend(SAMPLE.skinning_matrices(clip.start_time + rows / clip.rows_per_second), mesh)
        for k, row in enumerate(rows):
            block = np.zeros((rows_per_frame * width, 4))
            block[:v, :3], block[:v, 3] = points[k], 1.0
            positions[row * rows_per_frame:(row + 1) * rows_per_frame] = block.reshape(rows_per_frame, width, 4)
            block[:v, :3], block[:v, 3] = nrm[k], 0.0
            normals[row * rows_per_frame:(row + 1) * rows_per_frame] = block.reshape(rows_per_frame, width, 4)
    return VertexAnimation(positions, normals, frames, clip.rows_per_second, width, rows_per_frame)


def vat_pose(vat: VertexAnimation, crowd, vertex_count: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Float64 reading of the stored texels: the spec's looping row rule, then linear interpolation."""
    taus = reference.instance_time(crowd, t)
    n = float(vat.frames)
    x = taus * vat.rows_per_second
    x = x - n * np.floor(x / n)
    i0 = np.minimum(np.floor(x), n - 1)
    i1 = np.where(i0 + 1 >= n, 0, i0 + 1)
    blend = (x - i0)[:, None, None]
    vertex = np.arange(vertex_count)[None, :]
    i0, i1 = i0.astype(np.int64)[:, None], i1.astype(np.int64)[:, None]
    p0 = vat.lookup(vat.positions, i0, vertex)[..., :3].astype(np.float64)
    p1 = vat.lookup(vat.positions, i1, vertex)[..., :3].astype(np.float64)
    n0 = vat.lookup(vat.normals, i0, vertex)[..., :3].astype(np.float64)
    n1 = vat.lookup(vat.normals, i1, vertex)[..., :3].astype(np.float64)
    normals = n0 + (n1 - n0) * blend
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return place(crowd, p0 + (p1 - p0) * blend, normals)


# ------------------------------------------------------------------------------------------ palette


class KeyedAnimation:
    """The cheer as an engine holds it: joint-local keys at the asset's 30 fps time codes.

    :meth:`evaluate` is what a CPU animation system does per instance and frame: find the two keys,
    lerp translations, nlerp rotations, compose the hierarchy, apply the inverse bind, in float32.
    """

    def __init__(self) -> None:
        key_times = np.arange(SAMPLE.FRAME_COUNT + 1) / SAMPLE.FPS
        translations, rotations = SAMPLE.local_pose(key_times)
        self.translations = translations.astype(np.float32)
        self.rotations = rotations.astype(np.float32)
        self.bone_translations = np.ascontiguousarray(self.translations.transpose(1, 0, 2))
        self.bone_rotations = np.ascontiguousarray(self.rotations.transpose(1, 0, 2))
        self.parents = np.asarray(SAMPLE.PARENTS)
        self.bind_positions = SAMPLE.bind_matrices()[:, :3, 3].astype(np.float32)
        self.bone_count = len(self.parents)

    def evaluate(self, taus: np.ndarray, out: Optional[np.ndarray] = None, chunk: int = 65_536) -> np.ndarray:
        """(N, B, 3, 4) float32 skinning matrices (rows of [R | t]) at clip times ``taus``."""
        n = taus.shape[0]
        out = np.empty((n, self.bone_count, 3, 4), np.float32) if out is None else out
        for start in range(0, n, chunk):
            self._evaluate(np.asarray(taus[start:start + chunk]), out[start:start + chunk])
        return out

    def _evaluate(self, taus: np.ndarray, out: np.ndarray) -> None:
        # Bone-major (B, n, ...) arrays keep each joint's slice contiguous for the batched products.
        u = np.mod(taus, SAMPLE.DURATION) * SAMPLE.FPS
        k0 = np.minimum(np.floor(u).astype(np.int64), SAMPLE.FRAME_COUNT - 1)
        f = (u - k0).astype(np.float32)[None, :, None]
        t0, t1 = self.bone_translations[:, k0], self.bone_translations[:, k0 + 1]
        t = t0 + (t1 - t0) * f
        q0, q1 = self.bone_rotations[:, k0], self.bone_rotations[:, k0 + 1]
        sign = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0, np.float32(-1), np.float32(1))
        q = q0 * (1 - f) + q1 * (f * sign)
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
        r = np.empty(q.shape[:2] + (3, 3), np.float32)
        r[..., 0, 0], r[..., 0, 1], r[..., 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
        r[..., 1, 0], r[..., 1, 1], r[..., 1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
        r[..., 2, 0], r[..., 2, 1], r[..., 2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
        world = np.empty(q.shape[:2] + (3, 4), np.float32)  # [R | t] per joint
        for j, parent in enumerate(self.parents):  # parent-first order
            if parent < 0:
                world[j, :, :, :3], world[j, :, :, 3] = r[j], t[j]
            else:
                world[j, :, :, :3] = world[parent, :, :, :3] @ r[j]
                world[j, :, :, 3] = (world[parent, :, :, :3] @ t[j][..., None])[..., 0] + world[parent, :, :, 3]
        # Inverse bind is a translation by -bind position: M = W T(-b), so t' = t_W - R_W b.
        world[..., 3] -= (world[..., :3] @ self.bind_positions[:, None, :, None])[..., 0]
        out[...] = world.transpose(1, 0, 2, 3)


# ------------------------------------------------------------------------------------------ shaders

_PLACE = """
uniform mat4 view_projection;
in vec3 instance_position;
in vec4 instance_orientation;
out vec3 world_position;
out vec3 world_normal;
vec3 placeRotate(vec4 q, vec3 v) { return v + 2.0 * cross(q.xyz, cross(q.xyz, v) + q.w * v); }
void emit(vec3 p, vec3 n)
{
    world_position = placeRotate(instance_orientation, p) + instance_position;
    world_normal = placeRotate(instance_orientation, n);
    gl_Position = view_projection * vec4(world_position, 1.0);
}
"""

_MESH_INPUTS = """
in vec3 rest_position;
in vec3 rest_normal;
in ivec4 bone_indices;
in vec4 bone_weights;
"""

STATIC_VS = GLSL_VERSION + _PLACE + _MESH_INPUTS + """
void main() { emit(rest_position, rest_normal); }
"""

VB_MAIN = _PLACE + _MESH_INPUTS + """
in int instance_clip;
in vec2 instance_time;  // (timeOffset, playbackRate)
#ifdef VB_VARIETY
in vec3 instance_tint;
in int instance_variant;
in int instance_parts;
uniform vec3 variant_colors[8];
uniform int part_bit;   // -1: the body, drawn on every instance
out vec3 vb_color;
#endif
void main()
{
#ifdef VB_VARIETY
    vb_color = variant_colors[instance_variant] * instance_tint;
    if (part_bit >= 0 && ((instance_parts >> part_bit) & 1) == 0)
    {
        world_position = instance_position;
        world_normal = vec3(0.0, 1.0, 0.0);
        gl_Position = vec4(0.0, 0.0, 0.0, 1.0);  // every vertex at one point: degenerate triangles
        return;
    }
#endif
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        boneIndex[i] = bone_indices[i];
        boneWeight[i] = bone_weights[i];
    }
    vec3 position;
    vec3 normal;
    vbSkin(VB_ARGS instance_clip, instance_time.x + instance_time.y * vb_time, rest_position, rest_normal,
           boneIndex, boneWeight, position, normal);
    emit(position, normal);
}
"""

# Factor study: the rest mesh, but the skinned vertex's bone attributes are fetched too (4 attributes,
# as VB and palette skinning read, instead of static's 2). The 1e-30 term keeps them alive.
STATIC_SKIN_ATTRIBUTES_VS = GLSL_VERSION + _PLACE + _MESH_INPUTS + """
void main()
{
    float keep = 1e-30 * (float(bone_indices.x + bone_indices.y + bone_indices.z + bone_indices.w)
                          + bone_weights.x + bone_weights.y + bone_weights.z + bone_weights.w);
    emit(rest_position + vec3(keep), rest_normal);
}
"""

# Factor study: Virtual Bones with the bone indices and weights read from storage buffers by
# gl_VertexID instead of vertex attributes (same module, same math, 2 vertex attributes like static).
VB_MAIN_SKIN_BUFFERS = _PLACE + """
in vec3 rest_position;
in vec3 rest_normal;
layout(std430, binding = 1) readonly buffer SkinIndices { ivec4 skin_index[]; };
layout(std430, binding = 2) readonly buffer SkinWeights { vec4 skin_weight[]; };
in int instance_clip;
in vec2 instance_time;  // (timeOffset, playbackRate)
void main()
{
    ivec4 bi = skin_index[gl_VertexID];
    vec4 bw = skin_weight[gl_VertexID];
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        boneIndex[i] = bi[i];
        boneWeight[i] = bw[i];
    }
    vec3 position;
    vec3 normal;
    vbSkin(VB_ARGS instance_clip, instance_time.x + instance_time.y * vb_time, rest_position, rest_normal,
           boneIndex, boneWeight, position, normal);
    emit(position, normal);
}
"""

# Virtual Bones with the pulled skin binding (issue 25): the module ``vbusd shader --skin pulled``
# prints, its skin records (vbusd.decoders.shaders.pack_skin) in its storage buffer ``VbSkin``, read by
# the module's own vbSkinInfluences at gl_VertexID; the mesh has 2 vertex attributes, like static.
VB_MAIN_PULLED = _PLACE + """
in vec3 rest_position;
in vec3 rest_normal;
in int instance_clip;
in vec2 instance_time;  // (timeOffset, playbackRate)
void main()
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    vbSkinInfluences(VB_ARGS gl_VertexID, boneIndex, boneWeight);
    vec3 position;
    vec3 normal;
    vbSkin(VB_ARGS instance_clip, instance_time.x + instance_time.y * vb_time, rest_position, rest_normal,
           boneIndex, boneWeight, position, normal);
    emit(position, normal);
}
"""

# --previous (issue 36): the same mains, skinning a second time at the previous frame's time
# (vbusd shader --previous declares vb_previousTime) and projecting both positions for the velocity
# target. The crowd stands still, so each instance's previous transform is its current one.
_PREVIOUS_EMIT = """
out vec4 clip_now;
out vec4 clip_previous;
out vec3 previous_world_position;
void emitPrevious(vec3 previousPosition)
{
    previous_world_position = placeRotate(instance_orientation, previousPosition) + instance_position;
    clip_now = gl_Position;
    clip_previous = view_projection * vec4(previous_world_position, 1.0);
}
"""

_PREVIOUS_CALL = """    emit(position, normal);
    vec3 previousPosition;
    vbSkin(VB_ARGS instance_clip, instance_time.x + instance_time.y * vb_previousTime, rest_position, rest_normal,
           boneIndex, boneWeight, previousPosition, normal);
    emitPrevious(previousPosition);
}"""


def _with_previous(main: str) -> str:
    """A draw main that also writes the previous skinned position and both clip-space positions."""
    assert main.count("    emit(position, normal);\n}") == 1
    return main.replace(_PLACE, _PLACE + _PREVIOUS_EMIT, 1).replace("    emit(position, normal);\n}", _PREVIOUS_CALL)


VB_MAIN_PREVIOUS = _with_previous(VB_MAIN)
VB_MAIN_PULLED_PREVIOUS = _with_previous(VB_MAIN_PULLED)

# Crowd variety (issue 37, format 1.3): the draw's main of ``vb`` with its VB_VARIETY switch on: a
# per-instance tint, variant and parts mask; the colour (variant colour x tint) goes to the fragment
# shader. part_bit >= 0 makes it a part's draw: instances whose mask lacks the bit collapse to a point
# (no triangle is drawn). VB_MAIN itself leaves VB_VARIETY undefined: the plain vb draw.
VB_MAIN_VARIETY = "#define VB_VARIETY\n" + VB_MAIN

VAT_VS = GLSL_VERSION + _PLACE + """
uniform highp sampler2D vat_positions;
uniform highp sampler2D vat_normals;
uniform vec4 vat_clip;   // (frames, rows per second, texels per texture row, texture rows per frame)
uniform float scene_time;
in vec2 instance_time;   // (timeOffset, playbackRate)
ivec2 vatTexel(int frame, int vertex)
{
    int width = int(vat_clip.z);
    return ivec2(vertex % width, frame * int(vat_clip.w) + vertex / width);
}
void main()
{
    float n = vat_clip.x;
    float x = (instance_time.x + instance_time.y * scene_time) * vat_clip.y;
    x = x - n * floor(x / n);
    float i0 = min(floor(x), n - 1.0);
    float i1 = (i0 + 1.0 >= n) ? 0.0 : i0 + 1.0;
    float blend = x - i0;
    ivec2 a = vatTexel(int(i0), gl_VertexID);
    ivec2 b = vatTexel(int(i1), gl_VertexID);
    vec3 position = mix(texelFetch(vat_positions, a, 0).xyz, texelFetch(vat_positions, b, 0).xyz, blend);
    vec3 normal = normalize(mix(texelFetch(vat_normals, a, 0).xyz, texelFetch(vat_normals, b, 0).xyz, blend));
    emit(position, normal);
}
"""

PALETTE_VS = GLSL_VERSION + _PLACE + _MESH_INPUTS + """
layout(std430, binding = 0) readonly buffer Palette { vec4 palette[]; };
uniform int bone_count;
uniform int instance_base;
void main()
{
    int base = (gl_InstanceID + instance_base) * bone_count * 3;
    vec4 p = vec4(rest_position, 1.0);
    vec3 position = vec3(0.0);
    vec3 normal = vec3(0.0);
    for (int i = 0; i < 4; ++i)
    {
        float w = bone_weights[i];
        if (w == 0.0) continue;
        int o = base + bone_indices[i] * 3;
        vec4 r0 = palette[o];
        vec4 r1 = palette[o + 1];
        vec4 r2 = palette[o + 2];
        position += w * vec3(dot(r0, p), dot(r1, p), dot(r2, p));
        normal += w * vec3(dot(r0.xyz, rest_normal), dot(r1.xyz, rest_normal), dot(r2.xyz, rest_normal));
    }
    float length_ = length(normal);
    emit(position, length_ > 0.0 ? normal / length_ : normal);
}
"""

WARP_VS = GLSL_VERSION + """
uniform mat4 view_projection;
uniform int vertex_count;
uniform int instance_base;
layout(std430, binding = 0) readonly buffer Positions { float positions[]; };
layout(std430, binding = 1) readonly buffer Normals { float normals[]; };
out vec3 world_position;
out vec3 world_normal;
void main()
{
    int i = ((gl_InstanceID + instance_base) * vertex_count + gl_VertexID) * 3;
    world_position = vec3(positions[i], positions[i + 1], positions[i + 2]);
    world_normal = vec3(normals[i], normals[i + 1], normals[i + 2]);
    gl_Position = view_projection * vec4(world_position, 1.0);
}
"""

FRAGMENT = GLSL_VERSION + """
in vec3 world_position;
in vec3 world_normal;
out vec4 color;
void main()
{
    float light = max(dot(normalize(world_normal), vec3(0.3, 0.8, 0.52)), 0.0);
    color = vec4(vec3(0.15 + 0.85 * light), 1.0);
}
"""

FRAGMENT_VARIETY = GLSL_VERSION + """
in vec3 world_position;
in vec3 world_normal;
in vec3 vb_color;
out vec4 color;
void main()
{
    float light = max(dot(normalize(world_normal), vec3(0.3, 0.8, 0.52)), 0.0);
    color = vec4(vb_color * (0.15 + 0.85 * light), 1.0);
}
"""

VARYINGS = ["world_position", "world_normal"]

FRAGMENT_VELOCITY = GLSL_VERSION + """
in vec3 world_position;
in vec3 world_normal;
in vec4 clip_now;
in vec4 clip_previous;
layout(location = 0) out vec4 color;
layout(location = 1) out vec2 velocity;   // the RG16F velocity target of a TAA / motion-blur pass
void main()
{
    float light = max(dot(normalize(world_normal), vec3(0.3, 0.8, 0.52)), 0.0);
    color = vec4(vec3(0.15 + 0.85 * light), 1.0);
    velocity = clip_now.xy / clip_now.w - clip_previous.xy / clip_previous.w;
}
"""

VARYINGS_PREVIOUS = VARYINGS + ["previous_world_position"]


def vb_vertex_shader(encoding: str, texel_format: str, max_influences: int, main: str = VB_MAIN,
                     skin: str = "attributes", skin_storage: bool = True, previous: bool = False) -> str:
    """The draw's vertex shader: the module ``vbusd shader --skin SKIN`` prints (main off), then the draw's main.

    Args:
        encoding: Bone encoding token.
        texel_format: ``float16``, ``float32`` or ``unorm16``.
        max_influences: The module's K.
        main: The draw's entry point (it calls the module's functions, then places and projects).
        skin: The module's skin binding, ``attributes`` or ``pulled``.
        skin_storage: Pulled only: False defines ``VB_SKIN_STORAGE 0`` before the module (its own
            switch, spec/shaders.md), so it reads the records from the ``RGBA32UI`` texture, as WebGL 2
            and the three.js runtime must.
        previous: The module of ``vbusd shader --previous`` (``vb_previousTime``; issue 36).

    Returns:
        GLSL 4.30 source: the version line, the shipped module unchanged, the draw's ``main``.
    """
    module = vbusd.shader("glsl", encoding, texel_format, max_influences=max_influences, main=False, skin=skin,
                          previous=previous)
    switch = "#define VB_SKIN_STORAGE 0\n" if skin == "pulled" and not skin_storage else ""
    return GLSL_VERSION + switch + module + main


# ------------------------------------------------------------------------------------------ GL scene


def create_context():
    """A standalone EGL OpenGL 4.3 context with a 1920 x 1080 colour + depth framebuffer bound."""
    import moderngl

    ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    framebuffer = ctx.framebuffer(color_attachments=[ctx.renderbuffer(RESOLUTION)],
                                  depth_attachment=ctx.depth_renderbuffer(RESOLUTION))
    framebuffer.use()
    return ctx, framebuffer


@dataclass
class Frame:
    """One timed frame's figures (milliseconds)."""

    gpu_draw: float
    gpu_other: float
    cpu: float
    wall: float


@dataclass
class Method:
    """A method set up for one character and crowd: its GL objects and per-frame work."""

    name: str
    config: str
    draw_vao: object
    tf_vao: Optional[object]
    program: object
    tf_program: object
    anim_bytes: int
    before_draw: object = None  # callable(t) -> (cpu-side work done, gpu_other ms or None)
    set_time: object = None  # callable(program, t)
    draws: list = field(default_factory=lambda: [(0, None)])  # (instance base, instance count) per draw
    notes: str = ""
    release: list = field(default_factory=list)


class Scene:
    """GL resources shared by every method for one character and one crowd size."""

    def __init__(self, ctx, framebuffer, character: Character, crowd, check_rows: np.ndarray,
                 packed_skin: bool = False, view: str = "grid"):
        """``packed_skin``: bone indices as 4 x uint8 and weights as 4 x unorm8 (a 32-byte vertex, as
        engines pack skins) instead of 4 x int32 + 4 x float32 (56 bytes); the weights must then be
        multiples of 1/255 (:func:`packed_weights`)."""
        import moderngl

        self.moderngl = moderngl
        self.ctx, self.framebuffer, self.character, self.crowd = ctx, framebuffer, character, crowd
        self.count = crowd.instance_count
        self.check_rows = check_rows
        self.check_crowd = crowd_rows(crowd, check_rows)
        # "grid" frames the whole grid from above; "stand" (issue 29) looks across it from its edge.
        self.view = view
        self.camera = stand_camera(self.count) if view == "stand" else None
        self.view_projection = view_projection(self.count) if view == "grid" else self.camera.view_projection
        mesh = character.mesh
        k = mesh.bone_indices.shape[1]
        assert k <= 4, "the draw shaders read one ivec4/vec4 pair"
        idx = np.zeros((len(mesh.points), 4), np.int32)
        w = np.zeros((len(mesh.points), 4), np.float32)
        idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
        if packed_skin:
            w8 = np.floor(w.astype(np.float64) * 255 + 0.5)
            assert np.array_equal(w8 / 255, w.astype(np.float64)) or np.abs(w8 / 255 - w).max() < 1e-7, \
                "packed weights must be multiples of 1/255"
            vertex = np.zeros((len(mesh.points), 32), np.uint8)
            vertex[:, :24] = np.concatenate([np.asarray(mesh.points, np.float32),
                                             np.asarray(mesh.normals, np.float32)], axis=1).view(np.uint8)
            vertex[:, 24:28], vertex[:, 28:32] = idx.astype(np.uint8), w8.astype(np.uint8)
            self.mesh_format = ("3f 3f 4u1 4f1",) + self.MESH_FORMAT[1:]
        else:
            vertex = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(mesh.normals, np.float32),
                                     idx.view(np.float32), w], axis=1)
            self.mesh_format = self.MESH_FORMAT
        self.vertices = ctx.buffer(np.ascontiguousarray(vertex).tobytes())
        self.skin_stride = int(np.ascontiguousarray(vertex).nbytes // len(mesh.points))
        # The mesh without its skin (static, vb_pulled): position and normal, 24 bytes a vertex.
        rest = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(mesh.normals, np.float32)], axis=1)
        self.rest_vertices = ctx.buffer(np.ascontiguousarray(rest).tobytes())
        self.rest_stride = int(rest.shape[1] * 4)
        self.indices = ctx.buffer(np.ascontiguousarray(character.triangles, dtype=np.uint32).tobytes())
        self.placement = ctx.buffer(self._placement_bytes(crowd))
        self.animation = ctx.buffer(self._animation_bytes(crowd))
        # The read-back check draws the checked instances from buffers of their own (first and last).
        self.check_placement = ctx.buffer(self._placement_bytes(self.check_crowd))
        self.check_animation = ctx.buffer(self._animation_bytes(self.check_crowd))

    @staticmethod
    def _placement_bytes(crowd) -> bytes:
        return np.ascontiguousarray(np.concatenate([crowd.positions, crowd.orientations], axis=1),
                                    dtype=np.float32).tobytes()

    @staticmethod
    def _animation_bytes(crowd) -> bytes:
        rec = np.rec.fromarrays([crowd.clip.astype("<i4"), crowd.time_offset.astype("<f4"),
                                 crowd.playback_rate.astype("<f4")])
        return rec.tobytes()

    MESH_FORMAT = ("3f 3f 4i 4f", "rest_position", "rest_normal", "bone_indices", "bone_weights")
    REST_FORMAT = ("3f 3f", "rest_position", "rest_normal")

    def vertex_arrays(self, program, tf_program, instance_formats, mesh_attributes):
        """(draw VAO with the index buffer, read-back VAO without it over the checked instances).

        ``mesh_attributes``: True reads the mesh from the vertex buffer with the skin (position,
        normal, bone indices, bone weights), ``"rest"`` from the one without it (position, normal),
        False reads no mesh attributes.
        """
        if mesh_attributes == "rest":
            mesh = [(self.rest_vertices, *self.REST_FORMAT)]
        else:
            mesh = [(self.vertices, *self.mesh_format)] if mesh_attributes else []
        draw = mesh + [(self.placement if b == "placement" else self.animation, *f) for b, f in instance_formats]
        check = mesh + [(self.check_placement if b == "placement" else self.check_animation, *f)
                        for b, f in instance_formats]
        draw_vao = self.ctx.vertex_array(program, draw, index_buffer=self.indices, index_element_size=4,
                                         skip_errors=True)
        tf_vao = self.ctx.vertex_array(tf_program, check, skip_errors=True)
        return draw_vao, tf_vao

    def programs(self, vertex_shader: str, fragment_shader: str = FRAGMENT, varyings=VARYINGS):
        program = self.ctx.program(vertex_shader=vertex_shader, fragment_shader=fragment_shader)
        tf_program = self.ctx.program(vertex_shader=vertex_shader, varyings=varyings)
        for p in (program, tf_program):
            if "view_projection" in p:
                p["view_projection"].write(self.view_projection.T.astype("f4").tobytes())
        return program, tf_program

    def release(self) -> None:
        for buffer in (self.vertices, self.rest_vertices, self.indices, self.placement, self.animation,
                       self.check_placement, self.check_animation):
            buffer.release()


PLACEMENT = ("placement", ("3f 4f/i", "instance_position", "instance_orientation"))
ANIMATION_TIME = ("animation", ("4x 2f/i", "instance_time"))
ANIMATION_CLIP_TIME = ("animation", ("1i 2f/i", "instance_clip", "instance_time"))


def setup_static(scene: Scene, vertex_shader: str = STATIC_VS, config: str = "rest mesh",
                 skinned_vertex: Optional[bool] = None) -> Method:
    """The rest mesh placed per instance: the floor.

    ``skinned_vertex``: read it from the vertex buffer that also holds the skin (the factor study's
    variants, one factor at a time; the default for a vertex shader other than ``STATIC_VS``, which
    may read the skin attributes); otherwise from the mesh as a static mesh is stored, position and
    normal only (24 bytes a vertex), the vertex buffer ``vb_pulled`` draws too.
    """
    if skinned_vertex is None:
        skinned_vertex = vertex_shader != STATIC_VS
    program, tf = scene.programs(vertex_shader)
    draw, check = scene.vertex_arrays(program, tf, [PLACEMENT], True if skinned_vertex else "rest")
    stride = scene.skin_stride if skinned_vertex else scene.rest_stride
    return Method("static", config, draw, check, program, tf, 0, notes=f"vertex {stride} bytes")


def _texture_dtype(texel_format: str) -> str:
    return {"float16": "f2", "float32": "f4", "unorm16": "nu2"}[texel_format]


def setup_vb(scene: Scene, vb, encoding: str, texel_format: str, skin_buffers: bool = False,
             skin: str = "attributes", previous: bool = False) -> Method:
    """Virtual Bones, the shipped module in one of its skin bindings.

    Args:
        scene: The character, crowd and shared GL objects.
        vb: The baked Virtual Bones texture and clips.
        encoding: Bone encoding token.
        texel_format: Texel format token.
        skin_buffers: Factor study only (attribute module): bone indices and weights from two storage
            buffers of the study's own layout, by ``gl_VertexID``.
        skin: ``attributes`` (method ``vb``: indices and weights as vertex attributes) or ``pulled``
            (method ``vb_pulled``: the module of ``vbusd shader --skin pulled``, the mesh's skin records
            from ``pack_skin`` in its storage buffer; the mesh keeps position and normal only).
            ``pulled_texture`` (method ``vb_pulled_texture``): the same module with ``VB_SKIN_STORAGE
            0``, the records in an ``RGBA32UI`` texture ``min(texels, 4096)`` wide read by
            ``texelFetch``, as in WebGL 2 and the three.js runtime (``skinTexture``).
        previous: Issue 36: the module of ``vbusd shader --previous``; the draw also skins at
            ``vb_previousTime`` and writes the screen-space velocity into a second colour target
            (``RG16F``) of a framebuffer of its own; the read-back adds the previous positions.

    Returns:
        The method, ready to check and time.
    """
    ctx, moderngl = scene.ctx, scene.moderngl
    in_texture = skin == "pulled_texture"
    pulled = skin in ("pulled", "pulled_texture")
    if pulled and skin_buffers:
        raise ValueError("skin_buffers is the factor study's variant of the attribute module")
    k = scene.character.mesh.bone_indices.shape[1]
    if previous and skin_buffers:
        raise ValueError("previous is not a factor of the factor study")
    main = VB_MAIN_PULLED if pulled else VB_MAIN_SKIN_BUFFERS if skin_buffers else VB_MAIN
    if previous:
        main = VB_MAIN_PULLED_PREVIOUS if pulled else VB_MAIN_PREVIOUS
    shader = vb_vertex_shader(encoding, texel_format, k, main, skin="pulled" if pulled else skin,
                              skin_storage=not in_texture, previous=previous)
    if previous:
        program, tf = scene.programs(shader, FRAGMENT_VELOCITY, VARYINGS_PREVIOUS)
    else:
        program, tf = scene.programs(shader)
    texture = ctx.texture((vb.layout.width, vb.layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype=_texture_dtype(texel_format))
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips]
    clips += [(0.0, 1.0, 1.0, 0.0)] * (16 - len(clips))
    for p in (program, tf):
        p["vb_texture"].value = 0
        p["vb_clips"].value = clips
        if vb.unorm_ranges is not None:
            p["vb_rangeMin"].value = [tuple(r) for r in vb.unorm_ranges[..., 0]]
            p["vb_rangeMax"].value = [tuple(r) for r in vb.unorm_ranges[..., 1]]
    draw, check = scene.vertex_arrays(program, tf, [PLACEMENT, ANIMATION_CLIP_TIME], "rest" if pulled else True)

    mesh = scene.character.mesh
    skin_objects = []  # (storage binding, buffer)
    if skin_buffers:
        idx = np.zeros((len(mesh.points), 4), np.int32)
        w = np.zeros((len(mesh.points), 4), np.float32)
        idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
        skin_objects = [(1, ctx.buffer(idx.tobytes())), (2, ctx.buffer(w.tobytes()))]
    records_bytes = 0
    if pulled:
        records = pack_skin(mesh.bone_indices, mesh.bone_weights, k)
        records_bytes = int(records.nbytes)
        if in_texture:
            skin_records = _skin_texture(ctx, moderngl, records)
            for p in (program, tf):
                p["vb_skinTexture"].value = 1
        else:
            skin_objects = [(SKIN_BINDING, ctx.buffer(np.ascontiguousarray(records).tobytes()))]
            skin_records = skin_objects[0][1]
            for p in (program, tf):
                p["VbSkin"].binding = SKIN_BINDING

    def set_time(p, t):
        texture.use(location=0)
        if in_texture:
            skin_records.use(location=1)
        for binding, buffer in skin_objects:
            buffer.bind_to_storage_buffer(binding)
        p["vb_time"].value = t
        if previous:
            p["vb_previousTime"].value = t - PREVIOUS_DT

    texel_bytes = int(np.asarray(vb.texels).nbytes)
    notes = f"texture {vb.layout.width}x{vb.layout.height} {texel_format}: {texel_bytes} bytes"
    if pulled:
        where = "RGBA32UI texture" if in_texture else "storage buffer"
        config = f"{encoding} {texel_format}, skin pulled ({where})"
        notes += (f"; skin records {records_bytes // len(mesh.points)} bytes a vertex ({records_bytes} bytes) in a "
                  f"{where}; vertex {scene.rest_stride} bytes (position, normal)")
    else:
        config = f"{encoding} {texel_format}" + (", skin from storage buffers" if skin_buffers else "")
        notes += f"; vertex {scene.skin_stride} bytes (position, normal, bone indices, bone weights)"
    name = "vb_pulled_texture" if in_texture else "vb_pulled" if pulled else "vb"
    targets = []
    if previous:
        config += ", previous pose"
        notes += "; previous pose: a second skin at vb_previousTime, velocity into an RG16F target"
        targets = [ctx.renderbuffer(RESOLUTION), ctx.renderbuffer(RESOLUTION, components=2, dtype="f2"),
                   ctx.depth_renderbuffer(RESOLUTION)]
    method = Method(name, config,
                    draw, check, program, tf, texel_bytes + 12 * scene.count, set_time=set_time,
                    release=[texture] + [buffer for _, buffer in skin_objects] + ([skin_records] if in_texture else []),
                    notes=notes)
    if previous:
        method.previous = True
        method.framebuffer = ctx.framebuffer(color_attachments=targets[:2], depth_attachment=targets[2])
        method.release += [method.framebuffer] + targets
    if pulled:
        method.skin_records = skin_records  # the storage buffer the module reads (tests look into it)
    return method


VARIETY_TINTS = ((1.0, 1.0, 1.0), (1.0, 0.2158605, 0.0), (0.0144438, 0.1169707, 1.0))
"""The variety run's palette: #ffffff, #ff8000, #2060ff in linear RGB (vbusd crowd --tints)."""
VARIETY_HAT_PROBABILITY = 0.5


def variety_arrays(count: int, seed: int = 37) -> tuple:
    """Per instance (tint (N, 3) float32, variant (N,) int32 of 2, parts mask (N,) int32 with the hat on
    about half), seeded: what ``vbusd crowd --tints ... --variants home=1,away=1 --parts Hat=0.5`` authors."""
    rng = np.random.default_rng(seed)
    tint = np.asarray(VARIETY_TINTS, np.float32)[rng.integers(len(VARIETY_TINTS), size=count)]
    variant = rng.integers(2, size=count).astype(np.int32)
    parts = (rng.random(count) < VARIETY_HAT_PROBABILITY).astype(np.int32)
    return tint, variant, parts


def _variety_bytes(count: int) -> bytes:
    tint, variant, parts = variety_arrays(count)
    rec = np.rec.fromarrays([tint[:, 0], tint[:, 1], tint[:, 2], variant.astype("<i4"), parts.astype("<i4")],
                            formats=["<f4", "<f4", "<f4", "<i4", "<i4"])
    return rec.tobytes()


def setup_vb_variety(scene: Scene, vb, encoding: str, texel_format: str, hat) -> Method:
    """``vb`` with crowd variety (issue 37): the body's draw reads a 20-byte instance stream (tint,
    variant, parts mask) and colours by variant colour x tint; the hat (``hat``: a SkinnedMesh bound to
    the same bones) is a second instanced draw of the same shader with ``part_bit`` 0, whose vertex
    shader collapses the instances that do not wear it. The read-back checks the body, whose positions
    variety must not change."""
    from vbusd.format.variety import VARIANT_COLORS

    ctx, moderngl = scene.ctx, scene.moderngl
    k = scene.character.mesh.bone_indices.shape[1]
    vertex_shader = vb_vertex_shader(encoding, texel_format, k, VB_MAIN_VARIETY)
    program = ctx.program(vertex_shader=vertex_shader, fragment_shader=FRAGMENT_VARIETY)
    tf = ctx.program(vertex_shader=vertex_shader, varyings=VARYINGS)
    texture = ctx.texture((vb.layout.width, vb.layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype=_texture_dtype(texel_format))
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips]
    clips += [(0.0, 1.0, 1.0, 0.0)] * (16 - len(clips))
    for p in (program, tf):
        p["view_projection"].write(scene.view_projection.T.astype("f4").tobytes())
        p["vb_texture"].value = 0
        p["vb_clips"].value = clips
        if "variant_colors" in p:
            p["variant_colors"].value = [tuple(c) for c in VARIANT_COLORS]
        if "part_bit" in p:
            p["part_bit"].value = -1
        if vb.unorm_ranges is not None:
            p["vb_rangeMin"].value = [tuple(r) for r in vb.unorm_ranges[..., 0]]
            p["vb_rangeMax"].value = [tuple(r) for r in vb.unorm_ranges[..., 1]]
    variety = ctx.buffer(_variety_bytes(scene.count))
    variety_format = (variety, "3f 1i 1i/i", "instance_tint", "instance_variant", "instance_parts")
    instances = [(scene.placement, *PLACEMENT[1]), (scene.animation, *ANIMATION_CLIP_TIME[1]), variety_format]
    draw = ctx.vertex_array(program, [(scene.vertices, *scene.mesh_format)] + instances,
                            index_buffer=scene.indices, index_element_size=4, skip_errors=True)
    _, check_vao = scene.vertex_arrays(program, tf, [PLACEMENT, ANIMATION_CLIP_TIME], True)
    # The hat: its own vertex and index buffers, the same instance streams, part_bit 0 in its own program.
    hat_program = ctx.program(vertex_shader=vertex_shader, fragment_shader=FRAGMENT_VARIETY)
    hat_program["view_projection"].write(scene.view_projection.T.astype("f4").tobytes())
    hat_program["vb_texture"].value = 0
    hat_program["vb_clips"].value = clips
    hat_program["variant_colors"].value = [tuple(c) for c in VARIANT_COLORS]
    hat_program["part_bit"].value = 0
    hk = np.asarray(hat.bone_indices).shape[1]
    idx = np.zeros((len(hat.points), 4), np.int32)
    w = np.zeros((len(hat.points), 4), np.float32)
    idx[:, :hk], w[:, :hk] = hat.bone_indices, hat.bone_weights
    hat_vertices = ctx.buffer(np.ascontiguousarray(np.concatenate(
        [np.asarray(hat.points, np.float32), np.asarray(hat.normals, np.float32), idx.view(np.float32), w],
        axis=1)).tobytes())
    hat_indices = ctx.buffer(np.ascontiguousarray(hat.face_vertex_indices, dtype=np.uint32).tobytes())
    hat_vao = ctx.vertex_array(hat_program, [(hat_vertices, *Scene.MESH_FORMAT)] + instances,
                               index_buffer=hat_indices, index_element_size=4, skip_errors=True)

    def set_time(p, t):
        texture.use(location=0)
        p["vb_time"].value = t
        if p is program:
            hat_program["vb_time"].value = t

    texel_bytes = int(np.asarray(vb.texels).nbytes)
    shown = int(variety_arrays(scene.count)[2].sum())
    method = Method("vb_variety", f"{encoding} {texel_format}, variety (tint, 2 variants, hat on {shown})",
                    draw, check_vao, program, tf, texel_bytes + 12 * scene.count + 20 * scene.count,
                    set_time=set_time, release=[texture, variety, hat_vertices, hat_indices, hat_vao, hat_program],
                    notes=f"texture {vb.layout.width}x{vb.layout.height} {texel_format}: {texel_bytes} bytes; variety "
                          f"20 bytes an instance (tint, variant, parts mask); hat part ({len(hat.points)} vertices, "
                          f"{len(hat.face_vertex_indices) // 3} triangles) a second instanced draw over every "
                          f"instance, {shown} of {scene.count} shown")
    method.part_vaos = [hat_vao]
    method.variety_buffer, method.hat_vertices, method.vertex_shader = variety, hat_vertices, vertex_shader
    method.hat_shown = shown
    method.hat_triangles = len(hat.face_vertex_indices) // 3
    return method


def _skin_texture(ctx, moderngl, records: np.ndarray):
    """The skin records as the three.js runtime uploads them: RGBA32UI, ``min(texels, 4096)`` wide, NEAREST."""
    texels = np.ascontiguousarray(records, dtype=np.uint32).reshape(-1, 4)
    width = min(len(texels), 4096)
    height = -(-len(texels) // width)
    padded = np.zeros((width * height, 4), np.uint32)
    padded[:len(texels)] = texels
    texture = ctx.texture((width, height), 4, padded.tobytes(), dtype="u4")
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return texture


# Issue 29: levels of detail. Per frame a compute shader picks every instance's level (UsdLod's
# projectedSphere screen size, spec/virtual-bones.md 20.2; culled when the bounding sphere of its
# clips' extents is outside the view) and appends the instance to that level's list with an atomic
# counter that is the instanceCount of the level's indirect draw command; then one indirect draw per
# level reads its list by gl_InstanceID. No draw call per instance, no CPU pass over the instances.
LOD_BINDINGS = {"placement": 4, "animation": 5, "lists": 6, "commands": 7}
LOD_RATIOS = (0.5, 0.2)  # vbusd convert --lod-ratios 0.5,0.2: LOD 1 and 2
LOD_SCREEN_SIZES = (0.01, 0.001)  # vbusd's default thresholds for 3 levels (vbusd.baking.lod.default_screen_sizes)

LOD_SELECT_CS = GLSL_VERSION + """
layout(local_size_x = 256) in;
layout(std430, binding = 4) readonly buffer Placement { float placement[]; };
layout(std430, binding = 6) writeonly buffer Lists { uint lists[]; };
layout(std430, binding = 7) buffer Commands { uint commands[]; };  // 5 per level: DrawElementsIndirectCommand
uniform uint instance_count;
uniform vec3 eye;
uniform vec3 centre_local;
uniform float radius;
uniform float inverse_tangent;  // 1 / tan(fovY / 2)
uniform float aspect;
uniform vec4 planes[6];
uniform float thresholds[7];
uniform int threshold_count;
vec3 placeRotate(vec4 q, vec3 v) { return v + 2.0 * cross(q.xyz, cross(q.xyz, v) + q.w * v); }
void main()
{
    uint i = gl_GlobalInvocationID.x;
    if (i >= instance_count) return;
    vec3 p = vec3(placement[7u * i], placement[7u * i + 1u], placement[7u * i + 2u]);
    vec4 q = vec4(placement[7u * i + 3u], placement[7u * i + 4u], placement[7u * i + 5u], placement[7u * i + 6u]);
    vec3 c = placeRotate(q, centre_local) + p;
    for (int k = 0; k < 6; ++k)
        if (dot(planes[k].xyz, c) + planes[k].w < -radius) return;  // outside the view: culled
    float projected = radius * inverse_tangent / distance(c, eye);
    float size = 3.14159265358979 * projected * projected / (4.0 * aspect);
    int level = 0;
    for (int k = 0; k < threshold_count; ++k)
        if (size <= thresholds[k]) ++level;
    uint slot = atomicAdd(commands[5 * level + 1], 1u);
    lists[uint(level) * instance_count + slot] = i;
}
"""

VB_MAIN_LOD = """
uniform mat4 view_projection;
uniform uint level_base;
layout(std430, binding = 4) readonly buffer Placement { float placement[]; };
struct VbInstance { int clip; float offset; float rate; };
layout(std430, binding = 5) readonly buffer Animation { VbInstance animation[]; };
layout(std430, binding = 6) readonly buffer Lists { uint lists[]; };
in vec3 rest_position;
in vec3 rest_normal;
in ivec4 bone_indices;
in vec4 bone_weights;
out vec3 world_position;
out vec3 world_normal;
vec3 placeRotate(vec4 q, vec3 v) { return v + 2.0 * cross(q.xyz, cross(q.xyz, v) + q.w * v); }
void main()
{
    uint i = lists[level_base + uint(gl_InstanceID)];
    vec3 p = vec3(placement[7u * i], placement[7u * i + 1u], placement[7u * i + 2u]);
    vec4 q = vec4(placement[7u * i + 3u], placement[7u * i + 4u], placement[7u * i + 5u], placement[7u * i + 6u]);
    VbInstance a = animation[i];
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int k = 0; k < VB_MAX_INFLUENCES; ++k)
    {
        boneIndex[k] = bone_indices[k];
        boneWeight[k] = bone_weights[k];
    }
    vec3 position;
    vec3 normal;
    vbSkin(VB_ARGS a.clip, a.offset + a.rate * vb_time, rest_position, rest_normal, boneIndex, boneWeight,
           position, normal);
    world_position = placeRotate(q, position) + p;
    world_normal = placeRotate(q, normal);
    gl_Position = view_projection * vec4(world_position, 1.0);
}
"""


LOD_FIELDS = ("points", "face_vertex_counts", "face_vertex_indices", "bone_indices", "bone_weights", "normals")


def lod_meshes(mesh) -> list:
    """LOD 0 (the mesh) and the levels ``vbusd convert --lod-ratios 0.5,0.2`` makes of it (vbusd.baking.lod).

    The GPU machine has no meshoptimizer (no wheel for its Python, no compiler needed there): with
    ``$VBUSD_LOD_MESHES`` set, the levels come from the file ``draw_cost.py lod-meshes`` wrote here
    (benchmarks/draw_run.sh pack-lod), made by the same call.
    """
    saved = os.environ.get("VBUSD_LOD_MESHES")
    if saved:
        data = np.load(saved)
        if not np.array_equal(data["lod0_points"], np.asarray(mesh.points, np.float32)):
            raise ValueError(f"{saved} was made from another LOD 0 mesh; run draw_cost.py lod-meshes again")
        return [mesh] + [vbusd.BoundMesh(path=f"/lod{level}", lod=level, normals_interpolation="vertex",
                                         **{name: data[f"lod{level}_{name}"] for name in LOD_FIELDS})
                         for level in range(1, len(LOD_RATIOS) + 1)]
    from vbusd.baking.lod import simplify_mesh

    levels = [mesh]
    for level, ratio in enumerate(LOD_RATIOS, start=1):
        levels.append(simplify_mesh(mesh, ratio, max(1, mesh.max_influences >> level), f"/lod{level}", level))
    return levels


def save_lod_meshes(args) -> int:
    """``lod-meshes --out FILE``: the stadium character's levels (see :func:`lod_meshes`) as one .npz."""
    mesh = stadium_character(SAMPLE.bake_reference()).mesh
    arrays = {"lod0_points": np.asarray(mesh.points, np.float32)}
    for level, lod in enumerate(lod_meshes(mesh)[1:], start=1):
        arrays.update({f"lod{level}_{name}": np.asarray(getattr(lod, name)) for name in LOD_FIELDS})
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **arrays)
    print(f"wrote {args.out}: " + ", ".join(f"LOD {i} {len(arrays[f'lod{i}_face_vertex_counts'])} triangles"
                                           for i in range(1, len(LOD_RATIOS) + 1)))
    return 0


def lod_extent(vb) -> np.ndarray:
    """The UsdLod heuristic's extent (spec 20.1): the union of the animation's clip extents."""
    extents = np.asarray(vb.clip_extents, np.float64)
    return np.stack([extents[:, 0].min(axis=0), extents[:, 1].max(axis=0)])


def expected_levels(scene: Scene, extent: np.ndarray, chunk: int = 100_000) -> np.ndarray:
    """Each instance's level by vbusd.baking.lod (UsdLod's rule, tested against UsdLod itself), -1 when culled."""
    from vbusd.baking.lod import screen_size, select_levels

    camera = scene.camera
    centre_local = extent.mean(axis=0)
    radius = 0.5 * float(np.linalg.norm(extent[1] - extent[0]))
    out = np.empty(scene.count, np.int32)
    for start in range(0, scene.count, chunk):
        crowd = crowd_rows(scene.crowd, np.arange(start, min(start + chunk, scene.count)))
        world = np.zeros((crowd.instance_count, 4, 4))
        world[:, :3, :3] = quat_matrices(np.asarray(crowd.orientations, np.float64))
        world[:, :3, 3] = crowd.positions
        world[:, 3, 3] = 1.0
        sizes = screen_size(extent, world, camera.eye, camera.fov_y_degrees, camera.aspect)
        levels = select_levels(sizes, LOD_SCREEN_SIZES)
        centres = world[:, :3, :3] @ centre_local + world[:, :3, 3]
        inside = np.all(centres @ camera.planes[:, :3].T + camera.planes[:, 3] >= -radius, axis=1)
        out[start:start + crowd.instance_count] = np.where(inside, levels, -1)
    return out


def setup_vb_lod(scene: Scene, vb, encoding: str, texel_format: str) -> Method:
    """Virtual Bones with 3 levels of detail sharing one texture (issue 29), selected per instance on the GPU.

    Needs the scene's ``stand`` camera (its eye, field of view and aspect feed the selection).
    """
    ctx, moderngl = scene.ctx, scene.moderngl
    if scene.camera is None:
        raise ValueError("vb_lod needs a Scene with view='stand'")
    camera = scene.camera
    meshes = lod_meshes(scene.character.mesh)
    extent = lod_extent(vb)
    n = scene.count
    texture = ctx.texture((vb.layout.width, vb.layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype=_texture_dtype(texel_format))
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips]
    clips += [(0.0, 1.0, 1.0, 0.0)] * (16 - len(clips))
    lists = ctx.buffer(reserve=4 * n * len(meshes))
    check_lists = ctx.buffer(np.arange(len(scene.check_rows), dtype=np.uint32).tobytes())
    levels, release = [], [texture, lists, check_lists]
    for level, mesh in enumerate(meshes):
        k = mesh.max_influences
        program = ctx.program(vertex_shader=vb_vertex_shader(encoding, texel_format, k, VB_MAIN_LOD),
                              fragment_shader=FRAGMENT)
        tf_program = ctx.program(vertex_shader=vb_vertex_shader(encoding, texel_format, k, VB_MAIN_LOD),
                                 varyings=VARYINGS)
        for p in (program, tf_program):
            p["view_projection"].write(camera.view_projection.T.astype("f4").tobytes())
            p["vb_texture"].value = 0
            p["vb_clips"].value = clips
            if vb.unorm_ranges is not None:
                p["vb_rangeMin"].value = [tuple(r) for r in vb.unorm_ranges[..., 0]]
                p["vb_rangeMax"].value = [tuple(r) for r in vb.unorm_ranges[..., 1]]
        idx = np.zeros((len(mesh.points), 4), np.int32)
        w = np.zeros((len(mesh.points), 4), np.float32)
        idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
        vertex = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(mesh.normals, np.float32),
                                 idx.view(np.float32), w], axis=1)
        vertices = ctx.buffer(np.ascontiguousarray(vertex).tobytes())
        triangles = np.asarray(mesh.face_vertex_indices, np.uint32).reshape(-1, 3)
        indices = ctx.buffer(np.ascontiguousarray(triangles).tobytes())
        layout = [(vertices, *Scene.MESH_FORMAT)]
        draw = ctx.vertex_array(program, layout, index_buffer=indices, index_element_size=4, skip_errors=True)
        tf = ctx.vertex_array(tf_program, layout, skip_errors=True)
        levels.append({"mesh": mesh, "program": program, "tf_program": tf_program, "draw": draw, "tf": tf,
                       "triangles": int(len(triangles)), "vertices": int(len(mesh.points))})
        # LOD 0's VAOs and programs are the method's own (run() releases them).
        release += [vertices, indices] + ([draw, tf, program, tf_program] if level else [])
    commands = ctx.buffer(reserve=20 * len(levels))
    reset = np.zeros((len(levels), 5), np.uint32)
    reset[:, 0] = [3 * lv["triangles"] for lv in levels]
    select = ctx.compute_shader(LOD_SELECT_CS)
    select["instance_count"].value = n
    select["eye"].value = tuple(float(v) for v in camera.eye)
    select["centre_local"].value = tuple(float(v) for v in extent.mean(axis=0))
    select["radius"].value = 0.5 * float(np.linalg.norm(extent[1] - extent[0]))
    select["inverse_tangent"].value = 1.0 / math.tan(math.radians(camera.fov_y_degrees) / 2)
    select["aspect"].value = float(camera.aspect)
    select["planes"].value = [tuple(float(v) for v in plane) for plane in camera.planes]
    select["thresholds"].value = list(LOD_SCREEN_SIZES) + [0.0] * (7 - len(LOD_SCREEN_SIZES))
    select["threshold_count"].value = len(LOD_SCREEN_SIZES)
    release += [commands, select]
    state = {"t": 0.0}

    def set_time(p, t):
        state["t"] = t

    def select_levels():
        commands.write(reset.tobytes())
        scene.placement.bind_to_storage_buffer(LOD_BINDINGS["placement"])
        lists.bind_to_storage_buffer(LOD_BINDINGS["lists"])
        commands.bind_to_storage_buffer(LOD_BINDINGS["commands"])
        select.run(group_x=-(-n // 256))
        ctx.memory_barrier()

    def draw_levels():
        select_levels()
        texture.use(location=0)
        scene.animation.bind_to_storage_buffer(LOD_BINDINGS["animation"])
        for level, entry in enumerate(levels):
            entry["program"]["vb_time"].value = state["t"]
            entry["program"]["level_base"].value = level * n
            entry["draw"].render_indirect(commands, moderngl.TRIANGLES, count=1, first=level)

    def counts() -> np.ndarray:
        return np.frombuffer(commands.read(), dtype=np.uint32).reshape(-1, 5)[:, 1].copy()

    def custom_check() -> dict:
        """Each level's skinned vertices against numpy, and the GPU's choice against vbusd.baking.lod."""
        s = len(scene.check_rows)
        check_placement = scene.check_placement
        point_error = normal_error = exact_error = 0.0
        limit = 0.0
        for level, entry in enumerate(levels):
            p = entry["tf_program"]
            p["vb_time"].value = CHECK_TIME
            p["level_base"].value = 0
            texture.use(location=0)
            check_placement.bind_to_storage_buffer(LOD_BINDINGS["placement"])
            scene.check_animation.bind_to_storage_buffer(LOD_BINDINGS["animation"])
            check_lists.bind_to_storage_buffer(LOD_BINDINGS["lists"])
            v = entry["vertices"]
            out = ctx.buffer(reserve=s * v * 24)
            entry["tf"].transform(out, mode=moderngl.POINTS, vertices=v, instances=s)
            data = np.frombuffer(out.read(), dtype="<f4").reshape(s, v, 6).astype(np.float64)
            out.release()
            want_points, want_normals = reference.skin_crowd(vb, entry["mesh"], scene.check_crowd, CHECK_TIME)
            point_error = max(point_error, float(np.abs(data[..., :3] - want_points).max()))
            normal_error = max(normal_error, float(np.abs(data[..., 3:] - want_normals).max()))
            limit = max(limit, tolerance(want_points))
            if level == 0:
                exact_points, _ = exact_pose(scene.check_crowd, entry["mesh"], CHECK_TIME)
                exact_error = float(np.abs(data[..., :3] - exact_points).max())
        select_levels()
        gpu = counts()
        want = expected_levels(scene, extent)
        cpu = np.array([(want == level).sum() for level in range(len(levels))])
        # float32 on the GPU against float64: an instance within rounding of a threshold or of the
        # view's edge may fall on the other side; at most 1 in 10,000 is allowed to.
        mismatch = int(np.abs(gpu.astype(np.int64) - cpu).sum())
        agrees = point_error <= limit and normal_error <= 1e-3 and mismatch <= max(2, n // 10_000)
        return {"instances_checked": int(s), "position_error_m": point_error, "normal_error": normal_error,
                "tolerance_m": limit, "agrees": bool(agrees), "exact_position_error_m": exact_error,
                "exact_normal_error": None, "levels_gpu": gpu.tolist(), "levels_numpy": cpu.tolist(),
                "culled_numpy": int((want < 0).sum()), "level_count_mismatch": mismatch}

    texel_bytes = int(np.asarray(vb.texels).nbytes)
    notes = (f"texture {vb.layout.width}x{vb.layout.height} {texel_format}: {texel_bytes} bytes; levels "
             + ", ".join(f"LOD {i} {lv['triangles']} triangles K={lv['mesh'].max_influences}" for i, lv in enumerate(levels))
             + f"; screen sizes {LOD_SCREEN_SIZES}; selection by compute shader, {len(levels)} indirect draws")
    method = Method("vb_lod", f"{encoding} {texel_format}, 3 levels", levels[0]["draw"], levels[0]["tf"],
                    levels[0]["program"], levels[0]["tf_program"],
                    texel_bytes + 12 * n + 4 * n * len(levels) + 20 * len(levels), set_time=set_time,
                    release=release, notes=notes)
    method.draw_levels = draw_levels
    method.custom_check = custom_check
    method.level_counts = counts
    method.level_triangles = [lv["triangles"] for lv in levels]
    return method


def setup_vat(scene: Scene, vat: VertexAnimation) -> Method:
    ctx, moderngl = scene.ctx, scene.moderngl
    program, tf = scene.programs(VAT_VS)
    textures = []
    for values in (vat.positions, vat.normals):
        texture = ctx.texture((values.shape[1], values.shape[0]), 4, np.ascontiguousarray(values).tobytes(), dtype="f2")
        texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        textures.append(texture)
    for p in (program, tf):
        p["vat_positions"].value = 0
        p["vat_normals"].value = 1
        p["vat_clip"].value = (float(vat.frames), float(vat.rows_per_second), float(vat.width),
                               float(vat.rows_per_frame))
    draw, check = scene.vertex_arrays(program, tf, [PLACEMENT, ANIMATION_TIME], False)

    def set_time(p, t):
        textures[0].use(location=0)
        textures[1].use(location=1)
        p["scene_time"].value = t

    return Method("vat", "positions + normals, RGBA float16", draw, check, program, tf,
                  vat.nbytes + 8 * scene.count, set_time=set_time, release=textures,
                  notes=f"2 textures {vat.width}x{vat.positions.shape[0]} RGBA float16: {vat.nbytes} bytes")


def setup_palette(scene: Scene, keys: KeyedAnimation) -> Method:
    ctx = scene.ctx
    program, tf = scene.programs(PALETTE_VS)
    n, b = scene.count, keys.bone_count
    host = np.empty((n, b, 3, 4), np.float32)
    check_host = np.empty((len(scene.check_rows), b, 3, 4), np.float32)
    buffer = ctx.buffer(reserve=host.nbytes, dynamic=True)
    check_buffer = ctx.buffer(reserve=check_host.nbytes, dynamic=True)
    for p in (program, tf):
        p["bone_count"].value = b
        p["instance_base"].value = 0
    draw, check = scene.vertex_arrays(program, tf, [PLACEMENT], True)
    offsets = np.asarray(scene.crowd.time_offset, np.float64)
    rates = np.asarray(scene.crowd.playback_rate, np.float64)
    upload_query = ctx.query(time=True)
    state = {}

    def before_draw(t):
        keys.evaluate(offsets + rates * t, out=host)
        with upload_query:
            buffer.orphan()
            buffer.write(host)
        buffer.bind_to_storage_buffer(0)
        state["query"] = upload_query

    def gpu_other():
        return upload_query.elapsed / 1e6

    def check_bind(t):
        taus = reference.instance_time(scene.check_crowd, t)
        keys.evaluate(taus, out=check_host)
        check_buffer.write(check_host)
        check_buffer.bind_to_storage_buffer(0)
        return check_host.copy()

    method = Method("palette", "CPU keys (numpy float32) + SSBO upload", draw, check, program, tf,
                    host.nbytes, before_draw=before_draw, release=[buffer, check_buffer],
                    notes=f"{b} bones x 48 bytes per instance uploaded every frame")
    method.gpu_other = gpu_other
    method.check_bind = check_bind
    return method


def setup_warp(scene: Scene, vb, device: str) -> Method:
    """The warp decoder writing GL buffers (interop on CUDA, else through the host), then a draw."""
    import warp as wp

    from vbusd.decoders.warp import SkinResult

    ctx = scene.ctx
    program, tf = scene.programs(WARP_VS)
    n, v = scene.count, scene.character.vertex_count
    decoder = vbusd.Decoder(vb, scene.character.mesh, device=device)
    crowd = decoder.upload_crowd(scene.crowd)
    nbytes = n * v * 12
    positions = ctx.buffer(reserve=nbytes)
    normals = ctx.buffer(reserve=nbytes)
    interop = None
    if decoder.device.is_cuda:
        try:
            interop = [wp.RegisteredGLBuffer(buf.glo, decoder.device, flags=wp.RegisteredGLBuffer.WRITE_DISCARD,
                                             fallback_to_copy=False) for buf in (positions, normals)]
        except Exception as error:  # no CUDA-GL interop: the copy path below
            print(f"# warp: no CUDA-GL interop ({error}); copying through the host", flush=True)
    host_out = None if interop else decoder.allocate(n)
    limit = int(scene.ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27))
    per_draw = max(1, min(n, (min(limit, 1 << 31) - 1) // (v * 12)))
    per_draw = per_draw if per_draw == n else max(64, per_draw // 64 * 64)  # keep offsets 256-byte aligned
    draws = [(start, min(per_draw, n - start)) for start in range(0, n, per_draw)]
    events = (wp.Event(decoder.device, enable_timing=True), wp.Event(decoder.device, enable_timing=True)) \
        if decoder.device.is_cuda else None
    state = {"ms": None}
    for p in (program, tf):
        p["vertex_count"].value = v
        p["instance_base"].value = 0

    def decode(t):
        if events:
            wp.record_event(events[0])
        if interop:
            out = SkinResult(interop[0].map(dtype=wp.vec3, shape=(n, v)), interop[1].map(dtype=wp.vec3, shape=(n, v)))
            decoder.skin_crowd(crowd, t, out=out)
            if events:
                wp.record_event(events[1])
            interop[0].unmap()
            interop[1].unmap()
        else:
            out = decoder.skin_crowd(crowd, t, out=host_out)
            if events:
                wp.record_event(events[1])
            points, nrm = out.numpy()
            positions.write(points)
            normals.write(nrm)
        state["events"] = bool(events)

    def gpu_other():
        if not events:
            return None
        wp.synchronize_event(events[1])
        return wp.get_event_elapsed_time(events[0], events[1])

    def bind(start, count):
        positions.bind_to_storage_buffer(0, offset=start * v * 12, size=count * v * 12)
        normals.bind_to_storage_buffer(1, offset=start * v * 12, size=count * v * 12)

    draw_vao = ctx.vertex_array(program, [], index_buffer=scene.indices, index_element_size=4, skip_errors=True)
    tf_vao = ctx.vertex_array(tf, [], skip_errors=True)
    method = Method("warp", f"{vb.layout.encoding.value} {vb.layout.texel_format.value}, "
                            f"{'CUDA-GL interop' if interop else 'copy through host'}",
                    draw_vao, tf_vao, program, tf, 2 * nbytes,
                    before_draw=decode, draws=draws, release=[positions, normals],
                    notes=f"{len(draws)} draw(s); decoded vertex buffers {2 * nbytes} bytes")
    method.gpu_other = gpu_other
    method.bind = bind
    method.keep = (decoder, crowd, interop, host_out)

    def count_bytes():  # the decoder allocates its bone buffers on its first call (the check)
        decoder_bytes = _decoder_buffer_bytes(decoder)
        method.anim_bytes = 2 * nbytes + decoder_bytes
        method.notes += f", decoder arrays {decoder_bytes} bytes"

    method.count_bytes = count_bytes
    method.uses_interop = bool(interop)
    return method


def _decoder_buffer_bytes(decoder) -> int:
    """Bytes of the decoder's own device arrays (texture, mesh, clips, crowd, bone buffers)."""
    total = 0
    for value in list(vars(decoder).values()) + [b for bones in getattr(decoder, "_bones", {}).values()
                                                 for b in vars(bones).values()]:
        total += int(getattr(value, "capacity", 0) or 0) if type(value).__name__ == "array" else 0
    return total


# ------------------------------------------------------------------------------------------ running


def _draw(method: Method, scene: Scene) -> None:
    if getattr(method, "draw_levels", None) is not None:  # vb_lod: selection, then one draw per level
        method.draw_levels()
        return
    for start, count in method.draws:
        count = scene.count if count is None else count
        if hasattr(method, "bind"):  # warp: each draw reads its range of the decoded buffers
            method.bind(start, count)
        method.draw_vao.render(scene.moderngl.TRIANGLES, instances=count)
        for vao in getattr(method, "part_vaos", ()):  # vb_variety: one instanced draw per part
            vao.render(scene.moderngl.TRIANGLES, instances=count)


def render_frame(method: Method, scene: Scene, t: float, query) -> Frame:
    """One frame: the method's CPU work, then clear and draw; GPU times from timer queries."""
    ctx = scene.ctx
    start = time.perf_counter()
    if method.before_draw is not None:
        method.before_draw(t)
    if method.set_time is not None:
        method.set_time(method.program, t)
    target = getattr(method, "framebuffer", None) or scene.framebuffer  # --previous: colour + velocity
    target.use()
    target.clear(0.55, 0.6, 0.7, 1.0, depth=1.0)
    with query:
        _draw(method, scene)
    if target is not scene.framebuffer:
        scene.framebuffer.use()
    cpu = time.perf_counter() - start
    ctx.finish()
    wall = time.perf_counter() - start
    other = method.gpu_other() if hasattr(method, "gpu_other") else None
    return Frame(query.elapsed / 1e6, other if other is not None else 0.0, cpu * 1e3, wall * 1e3)


def read_back(method: Method, scene: Scene, t: float):
    """World-space points and normals of the checked instances, by transform feedback of ``method``'s shader."""
    ctx, moderngl = scene.ctx, scene.moderngl
    v = scene.character.vertex_count
    s = len(scene.check_rows)
    extra = None
    if method.name == "palette":
        extra = method.check_bind(t)
    if method.before_draw is not None and method.name == "warp":
        method.before_draw(t)
    if method.set_time is not None:
        method.set_time(method.tf_program, t)
    previous = getattr(method, "previous", False)
    floats = 9 if previous else 6  # --previous: the previous world position after position and normal
    out = ctx.buffer(reserve=s * v * floats * 4)
    if method.name == "warp":
        # One instance at a time from the decoded buffers: bind the draw's range holding it.
        results = []
        for row in scene.check_rows:
            start, count = next((a, c) for a, c in method.draws if a <= row < a + c)
            method.bind(start, count)
            method.tf_program["instance_base"].value = int(row - start)
            part = ctx.buffer(reserve=v * 24)
            method.tf_vao.transform(part, mode=moderngl.POINTS, vertices=v, instances=1)
            results.append(np.frombuffer(part.read(), dtype="<f4").reshape(1, v, 6))
            part.release()
        method.tf_program["instance_base"].value = 0
        data = np.concatenate(results)
    else:
        method.tf_vao.transform(out, mode=moderngl.POINTS, vertices=v, instances=s)
        data = np.frombuffer(out.read(), dtype="<f4").reshape(s, v, floats)
    out.release()
    if previous:  # the previous world positions travel as the extra
        extra = data[..., 6:9].astype(np.float64)
    return data[..., :3].astype(np.float64), data[..., 3:6].astype(np.float64), extra


def expected(method: Method, scene: Scene, t: float, vb, vat, extra):
    """The independent numpy result for the checked instances (world space)."""
    crowd, mesh = scene.check_crowd, scene.character.mesh
    if method.name == "static":
        s = crowd.instance_count
        return place(crowd, np.broadcast_to(np.asarray(mesh.points, np.float64), (s,) + mesh.points.shape),
                     np.broadcast_to(np.asarray(mesh.normals, np.float64), (s,) + mesh.normals.shape))
    if method.name in ("vb", "vb_pulled", "vb_pulled_texture", "vb_variety", "warp"):
        return reference.skin_crowd(vb, mesh, crowd, t)
    if method.name == "vat":
        return vat_pose(vat, crowd, scene.character.vertex_count, t)
    if method.name == "palette":
        return place(crowd, *linear_blend(extra, mesh))
    raise ValueError(method.name)


def tolerance(points: np.ndarray) -> float:
    """float32 arithmetic on the GPU against float64: 5e-6 of a 2.5 m body plus 4 ulps of the coordinates."""
    return 5e-6 * 2.52 + 4 * float(np.spacing(np.float32(np.abs(points).max())))


def check(method: Method, scene: Scene, vb, vat) -> dict:
    points, normals, extra = read_back(method, scene, CHECK_TIME)
    want_points, want_normals = expected(method, scene, CHECK_TIME, vb, vat, extra)
    point_error = float(np.abs(points - want_points).max())
    normal_error = float(np.abs(normals - want_normals).max())
    exact_points, exact_normals = exact_pose(scene.check_crowd, scene.character.mesh, CHECK_TIME)
    limit = tolerance(want_points)
    previous = {}
    if getattr(method, "previous", False):  # issue 36: the previous positions against the reference at t - dt
        want_previous, _ = reference.skin_crowd_previous(vb, scene.character.mesh, scene.check_crowd, CHECK_TIME,
                                                         PREVIOUS_DT)
        previous = {"previous_position_error_m": float(np.abs(extra - want_previous).max()),
                    "previous_motion_m": float(np.abs(want_previous - want_points).max())}
    return {"instances_checked": int(len(scene.check_rows)), "position_error_m": point_error,
            "normal_error": normal_error, "tolerance_m": limit, **previous,
            "agrees": bool(point_error <= limit and normal_error <= 1e-3
                           and previous.get("previous_position_error_m", 0.0) <= limit),
            "exact_position_error_m": float(np.abs(points - exact_points).max()),
            "exact_normal_error": float(np.abs(normals - exact_normals).max()) if method.name != "static" else None}


def time_method(method: Method, scene: Scene, budget_s: float, max_runs: int, min_runs: int = 3,
                warm_s: float = 0.0) -> dict:
    """Warm-up frames, then up to ``max_runs`` timed frames within ``budget_s`` (at least ``min_runs``).

    ``warm_s``: keep drawing untimed frames this long first (the run's first configuration, so that
    the GPU has left its idle clocks before anything is timed).
    """
    query = scene.ctx.query(time=True)
    t = 2.0
    first = render_frame(method, scene, t, query)
    warm = [first]
    if first.wall < 500:
        warm.append(render_frame(method, scene, t + FRAME_STEP, query))
    warm_until = time.perf_counter() + warm_s
    while time.perf_counter() < warm_until:
        warm.append(render_frame(method, scene, t + len(warm) * FRAME_STEP, query))
    per_frame = warm[-1].wall / 1e3
    runs = int(max(min_runs, min(max_runs, budget_s / max(per_frame, 1e-4))))
    frames = [render_frame(method, scene, t + (k + 2) * FRAME_STEP, query) for k in range(runs)]


    def stat(name):
        values = np.array([getattr(f, name) for f in frames])
        return {"median": float(np.median(values)), "min": float(values.min()), "max": float(values.max())}

    return {"runs": runs, "gpu_draw_ms": stat("gpu_draw"), "gpu_other_ms": stat("gpu_other"),
            "cpu_ms": stat("cpu"), "frame_ms": stat("wall"), "first_frame_ms": first.wall}


def command_line(argv=None) -> str:
    """The command as a result records it, without this machine's paths: a path under ``$OUT`` as
    ``$OUT/...``, one in the repository relative to it, any other absolute path by its name."""
    out = os.environ.get("OUT", "").rstrip("/")
    words = []
    for word in (sys.argv if argv is None else argv):
        if out and (word == out or word.startswith(out + "/")):
            word = "$OUT" + word[len(out):]
        elif os.path.isabs(word):
            path = Path(word)
            word = str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else path.name
        words.append(word)
    return " ".join(words)


def _gpu_facts(ctx) -> dict:
    facts = {"GL_RENDERER": ctx.info.get("GL_RENDERER"), "GL_VERSION": ctx.info.get("GL_VERSION"),
             "GL_VENDOR": ctx.info.get("GL_VENDOR"), "python": platform.python_version(),
             "numpy": np.__version__, "host": platform.node(), "cpu_count": os.cpu_count()}
    try:
        facts["nvidia_smi"] = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total,clocks.max.sm", "--format=csv,noheader"],
            capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        facts["nvidia_smi"] = None
    return facts


# Named plans (``run --plan NAME``): exactly these configurations, in this order (the goal's first).
# issue25: the shipped module in both skin bindings beside the static mesh and the VAT, crossMatrix
# float16; the stadium character at 100,000 and 1,000,000 instances (the goal's sizes) first.
PLANS = {
    "issue25": [(character, n, method) + (("crossMatrix", "float16") if method.startswith("vb") else (None, None))
                for character, n in (("stadium", 100_000), ("stadium", 1_000_000), ("stadium", 10_000),
                                     ("dense", 1_200), ("dense", 10_000))
                for method in ("static", "vb", "vb_pulled", "vat")],
    # issue25-texture: the pulled binding as WebGL 2 and the three.js runtime must read it (records in an
    # RGBA32UI texture, VB_SKIN_STORAGE 0) beside the storage buffer, static and attributes: what the
    # runtime's default skin binding is chosen by (docs/engines.md).
    "issue25-texture": [(character, n, method) + (("crossMatrix", "float16") if method.startswith("vb") else (None, None))
                        for character, n in (("stadium", 100_000), ("stadium", 1_000_000), ("stadium", 10_000),
                                             ("dense", 1_200), ("dense", 10_000))
                        for method in ("static", "vb", "vb_pulled", "vb_pulled_texture")],
}
# issue29: the million-spectator stadium (and 100,000 and 10,000) seen from its edge ("stand" view),
# one level of detail (vb) against three sharing the texture (vb_lod), crossMatrix float16.
PLANS["issue29"] = [("stadium", n, method, "crossMatrix", "float16")
                    for n in (1_000_000, 100_000, 10_000) for method in ("vb", "vb_lod")]
# issue36: the previous pose's cost (run with --previous both: each vb configuration without, then
# with it), attribute and texture-pulled bindings beside static, stadium 100,000 / 1,000,000 / 10,000
# and dense 10,000, crossMatrix float16.
PLANS["issue36"] = [(character, n, method) + (("crossMatrix", "float16") if method.startswith("vb") else (None, None))
                    for character, n in (("stadium", 100_000), ("stadium", 1_000_000), ("stadium", 10_000),
                                         ("dense", 10_000))
                    for method in ("static", "vb", "vb_pulled_texture")]
# issue37: crowd variety off (vb) against on (vb_variety) at 100,000 and 1,000,000 spectators (and 10,000).
PLANS["issue37"] = [("stadium", n, method, "crossMatrix", "float16")
                    for n in (100_000, 1_000_000, 10_000) for method in ("vb", "vb_variety")]
PLAN_DEFAULTS = {"issue25": {"budget": 400.0, "per_config_s": 3.0, "min_runs": 10, "warmup_s": 3.0,
                             "factors": False},
                 "issue25-texture": {"budget": 400.0, "per_config_s": 3.0, "min_runs": 10, "warmup_s": 3.0,
                                     "factors": False},
                 "issue29": {"budget": 400.0, "per_config_s": 5.0, "min_runs": 10, "warmup_s": 3.0,
                             "factors": False},
                 "issue36": {"budget": 400.0, "per_config_s": 3.0, "min_runs": 10, "warmup_s": 3.0,
                             "factors": False, "previous": "both"},
                 "issue37": {"budget": 300.0, "per_config_s": 5.0, "min_runs": 10, "warmup_s": 3.0,
                             "factors": False}}
PLAN_VIEWS = {"issue29": "stand"}
"""The camera of a plan's scenes (default ``grid``)."""


def _plan(args) -> list:
    """(character, N, method, encoding, format) in priority order: what the goal needs first."""
    if getattr(args, "plan", None):
        return list(PLANS[args.plan])
    sizes = [int(s) for s in args.sizes.split(",")]
    characters = args.characters.split(",")
    methods = args.methods.split(",")
    main_vb = ("crossMatrix", "float16")
    plan = []

    def add(character, n, method, encoding=None, texel_format=None):
        if character in characters and n in sizes and method in methods:
            item = (character, n, method, encoding, texel_format)
            if item not in plan:
                plan.append(item)

    five = [("static",), ("vb",) + main_vb, ("vb_pulled",) + main_vb, ("vat",), ("palette",), ("warp",) + main_vb]
    variety = getattr(args, "variety", "off")
    if variety != "off":  # issue 37: each vb configuration with crowd variety (and without, for "both")
        if "vb" in methods and "vb_variety" not in methods:
            methods = methods + ["vb_variety"]
        if variety == "on":
            methods = [m for m in methods if m != "vb"]
        five = [m for item in five for m in ([item, ("vb_variety",) + main_vb] if item[0] == "vb" else [item])]
    for n in sorted(sizes, key=lambda s: (s != 100_000, s)):
        for m in five:
            add("stadium", n, *m)
    for encoding in ENCODINGS:
        for texel_format in FORMATS:
            add("stadium", 100_000, "vb", encoding, texel_format)
    for n in sorted(sizes):
        for m in five:
            add("dense", n, *m)
    for n in sorted(sizes):
        for encoding in ENCODINGS:
            for texel_format in FORMATS:
                add("stadium", n, "vb", encoding, texel_format)
    for n in sorted(sizes):
        for encoding in ENCODINGS:
            add("dense", n, "vb", encoding, "float16")
    return plan


def _too_big(character: Character, n: int, method: str, block_limit: int) -> Optional[str]:
    v = character.vertex_count
    if method == "warp" and n * v * 24 / 2**30 > MAX_OUTPUT_GIB:
        return f"decoded vertex buffers would take {n * v * 24 / 2**30:.0f} GiB (limit {MAX_OUTPUT_GIB:.0f})"
    if method == "palette" and n * 18 * 48 > block_limit:
        return f"palette buffer {n * 18 * 48:,} bytes over GL_MAX_SHADER_STORAGE_BLOCK_SIZE {block_limit:,}"
    return None


def run(args) -> int:
    import moderngl

    started = time.perf_counter()
    plan = _plan(args)
    try:
        if not any(item[2] == "warp" for item in plan):
            raise ImportError("no warp method in the plan")
        import warp as wp  # started before any GL work so that its start-up is not timed

        wp.config.quiet = True
        wp.init()
        device = "cuda" if wp.is_cuda_available() else "cpu"
    except ImportError:
        device = None
    ctx, framebuffer = create_context()
    ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
    result = {"issue": {"issue25": 25, "issue29": 29, "issue36": 36, "issue37": 37}.get(args.plan, 18), "plan": args.plan,
              "budget_s": args.budget, "previous": args.previous,
              "resolution": list(RESOLUTION), "warp_device": device, "facts": _gpu_facts(ctx),
              "command": command_line(), "runs": [], "skipped": [], "factors": []}
    print(f"# {result['facts']['GL_RENDERER']} | {result['facts']['GL_VERSION']} | warp on {device}", flush=True)

    baked = {}

    def vb_for(encoding, texel_format):
        if (encoding, texel_format) not in baked:
            baked[(encoding, texel_format)] = SAMPLE.bake_reference(encoding=encoding, texel_format=texel_format)
        return baked[(encoding, texel_format)]

    base_vb = vb_for("crossMatrix", "float16")
    characters = {"stadium": stadium_character(base_vb)}
    if any(item[0] == "dense" for item in plan):
        characters["dense"] = subdivide(characters["stadium"], DENSE_SPLITS, base_vb.layout.bone_count)
    vats = {}
    keys = KeyedAnimation()
    for name, ch in characters.items():
        result.setdefault("characters", {})[name] = {"vertices": ch.vertex_count, "triangles": int(len(ch.triangles))}
    print(f"# characters: {result['characters']}", flush=True)

    block_limit = int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27))
    result["facts"]["GL_MAX_SHADER_STORAGE_BLOCK_SIZE"] = block_limit
    per_vertex_instance = {}  # (method, encoding, format) -> frame seconds per vertex-instance
    scene = None
    scene_key = None
    previous_axis = {"off": (False,), "on": (True,), "both": (False, True)}[args.previous]
    expanded = [item + (previous,) for item in plan
                for previous in (previous_axis if item[2] in PREVIOUS_METHODS else (False,))]
    for character_name, n, method_name, encoding, texel_format, previous in expanded:
        character = characters[character_name]
        label = f"{character_name} N={n} {method_name} {encoding or ''} {texel_format or ''}".strip() + \
            (" previous" if previous else "")
        elapsed = time.perf_counter() - started
        remaining = args.budget - elapsed
        too_big = _too_big(character, n, method_name, block_limit)
        if method_name == "warp" and device is None:
            too_big = "warp is not importable here"
        rate = per_vertex_instance.get((character_name, method_name, encoding, texel_format)) or \
            per_vertex_instance.get((character_name, method_name, "crossMatrix", "float16"))
        predicted = rate * n * character.vertex_count if rate else None
        reason = too_big
        if reason is None and predicted is not None and predicted * (args.min_runs + 3) + 2 > remaining:
            reason = f"predicted {predicted:.2f} s per frame; {remaining:.0f} s of the budget left"
        if reason is None and remaining < 5:
            reason = "time budget spent"
        if reason is None and predicted is not None and predicted > args.max_frame_s:
            reason = f"predicted {predicted:.1f} s per frame (over --max-frame-s {args.max_frame_s})"
        if reason:
            result["skipped"].append({"what": label, "why": reason})
            print(f"# skip {label}: {reason}", flush=True)
            continue
        try:
            if scene_key != (character_name, n):
                if scene is not None:
                    scene.release()
                crowd = crowd_grid(n)
                s = 32 if character_name == "stadium" else 4
                rows = np.unique(np.concatenate([np.arange(min(s, n)), np.arange(max(n - s, 0), n)]))
                scene = Scene(ctx, framebuffer, character, crowd, rows, view=PLAN_VIEWS.get(args.plan, "grid"))
                scene_key = (character_name, n)
            if method_name == "static":
                method = setup_static(scene)
            elif method_name in ("vb", "vb_pulled", "vb_pulled_texture"):
                method = setup_vb(scene, vb_for(encoding, texel_format), encoding, texel_format,
                                  skin={"vb": "attributes", "vb_pulled": "pulled",
                                        "vb_pulled_texture": "pulled_texture"}[method_name], previous=previous)
            elif method_name == "vb_lod":
                method = setup_vb_lod(scene, vb_for(encoding, texel_format), encoding, texel_format)
            elif method_name == "vb_variety":
                method = setup_vb_variety(scene, vb_for(encoding, texel_format), encoding, texel_format,
                                          SAMPLE.hat_mesh())
            elif method_name == "vat":
                if character_name not in vats:
                    vats[character_name] = bake_vat(character.mesh, base_vb.clips[0])
                method = setup_vat(scene, vats[character_name])
            elif method_name == "palette":
                method = setup_palette(scene, keys)
            else:
                method = setup_warp(scene, vb_for(encoding, texel_format), device)
            if hasattr(method, "custom_check"):
                correctness = method.custom_check()
            else:
                correctness = check(method, scene, vb_for(encoding or "crossMatrix", texel_format or "float16"),
                                    vats.get(character_name))
            if hasattr(method, "count_bytes"):
                method.count_bytes()
            budget = min(args.per_config_s, max(remaining / 8, 0.5))
            timing = time_method(method, scene, budget, args.max_runs, args.min_runs,
                                 warm_s=0.0 if result["runs"] else args.warmup_s)
            row = {"character": character_name, "vertices": character.vertex_count, "instances": n,
                   "method": method_name, "config": method.config, "encoding": encoding,
                   "texel_format": texel_format, "anim_bytes": int(method.anim_bytes), "notes": method.notes,
                   "correctness": correctness, "previous": bool(previous), **timing}
            if method_name == "warp":
                row["interop"] = method.uses_interop
            if method_name == "vb_lod":  # what the last timed frame drew, level by level
                drawn = method.level_counts()
                row["levels"] = {"instances": drawn.tolist(), "triangles_each": method.level_triangles,
                                 "culled": int(n - drawn.sum())}
                row["triangles_drawn"] = int(sum(int(c) * t for c, t in zip(drawn, method.level_triangles)))
            else:
                row["triangles_drawn"] = int(n * len(character.triangles))
            if method_name == "vb_variety":  # the hat's triangles on the instances that wear it
                row["triangles_drawn"] += int(method.hat_shown * method.hat_triangles)
                row["variety"] = True
            row["view"] = scene.view
            result["runs"].append(row)
            per_vertex_instance[(character_name, method_name, encoding, texel_format)] = \
                timing["frame_ms"]["median"] / 1e3 / (n * character.vertex_count)
            print(f"{label:52s} gpu {timing['gpu_draw_ms']['median']:9.3f} + {timing['gpu_other_ms']['median']:8.3f} ms"
                  f"  cpu {timing['cpu_ms']['median']:9.3f} ms  frame {timing['frame_ms']['median']:9.3f} ms"
                  f"  x{timing['runs']:<3d} err {correctness['position_error_m']:.2e} m"
                  f" {'ok' if correctness['agrees'] else 'DISAGREES'}  anim {method.anim_bytes:,} B", flush=True)
            if args.factors and character_name == "stadium" and n == args.factor_size and not previous \
                    and method_name in ("static", "vb", "vat", "palette") \
                    and (method_name != "vb" or (encoding, texel_format) == ("crossMatrix", "float16")):
                result["factors"].append(factor_study(method, scene, args))
            for item in method.release:
                item.release()
            for vao in (method.draw_vao, method.tf_vao):
                vao.release()
            method.program.release()
            method.tf_program.release()
        except Exception as error:  # record and go on: one broken configuration must not lose the rest
            import traceback

            traceback.print_exc()
            result["skipped"].append({"what": label, "why": f"error: {type(error).__name__}: {error}"})
        _write_json(Path(args.json), result)
    result["elapsed_s"] = time.perf_counter() - started
    _write_json(Path(args.json), result)
    return 0


def factor_study(method: Method, scene: Scene, args) -> dict:
    """The same draw with the rasterizer off (vertex work alone) and at a 64 x 64 viewport."""
    ctx = scene.ctx
    out = {"method": method.name, "config": method.config, "instances": scene.count}
    ctx.enable(scene.moderngl.RASTERIZER_DISCARD)
    try:
        out["rasterizer_discard"] = time_method(method, scene, 0.5, 10)
    finally:
        ctx.disable(scene.moderngl.RASTERIZER_DISCARD)
    viewport = ctx.viewport
    ctx.viewport = (0, 0, 64, 64)
    try:
        out["viewport_64"] = time_method(method, scene, 0.5, 10)
    finally:
        ctx.viewport = viewport
    return out


def fewer_influences(character: Character, k: int, bone_count: int) -> Character:
    """The character with each vertex's ``k`` largest weights kept (renormalized): the factor study's K."""
    mesh = character.mesh
    dense = np.zeros((mesh.points.shape[0], bone_count))
    np.add.at(dense, (np.repeat(np.arange(mesh.points.shape[0]), mesh.bone_indices.shape[1]),
                      mesh.bone_indices.reshape(-1)), np.asarray(mesh.bone_weights, np.float64).reshape(-1))
    bone_indices, bone_weights = _top_influences(dense, k)
    return Character(f"{character.name}-k{k}", dataclasses.replace(mesh, bone_indices=bone_indices,
                                                                   bone_weights=bone_weights),
                     character.triangles)


def packed_weights(character: Character) -> Character:
    """The character with its weights rounded to multiples of 1/255 (still summing to one): unorm8 skins."""
    w = np.asarray(character.mesh.bone_weights, np.float64)
    q = np.floor(w * 255 + 0.5)
    rows = np.arange(len(w))
    q[rows, np.argmax(w, axis=1)] += 255 - q.sum(axis=1)
    return Character(f"{character.name}-unorm8", dataclasses.replace(character.mesh,
                                                                     bone_weights=(q / 255).astype(np.float32)),
                     character.triangles)


def run_factors(args) -> int:
    """One factor at a time around Virtual Bones' vertex cost, stadium character (``factors`` command).

    Every variant is checked against numpy like the main run, then timed twice: as drawn, and with
    the rasterizer discarded (the vertex stage alone). Variants: the rest mesh (2 vertex attributes);
    the rest mesh also fetching the skin's bone indices and weights (4 attributes, what VB and palette
    skinning read); the same and Virtual Bones with the skin packed as engines do (4 x uint8 indices,
    4 x unorm8 weights: a 32-byte vertex instead of 56); Virtual Bones with K = 1..4 influences kept
    per vertex (same 56-byte vertex); Virtual Bones with the skin read from storage buffers instead
    of vertex attributes; the VAT.
    """
    import moderngl

    started = time.perf_counter()
    ctx, framebuffer = create_context()
    ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
    result = {"issue": 18, "resolution": list(RESOLUTION), "facts": _gpu_facts(ctx), "command": command_line(),
              "variants": []}
    print(f"# {result['facts']['GL_RENDERER']} | {result['facts']['GL_VERSION']}", flush=True)
    vb = SAMPLE.bake_reference(encoding="crossMatrix", texel_format="float16")
    body = stadium_character(vb)
    nonzero = np.bincount((np.asarray(body.mesh.bone_weights) > 0).sum(axis=1), minlength=5)
    result["nonzero_influences_histogram"] = [int(c) for c in nonzero]
    vat = bake_vat(body.mesh, vb.clips[0])
    for n in [int(x) for x in args.sizes.split(",")]:
        crowd = crowd_grid(n)
        rows = np.unique(np.concatenate([np.arange(min(32, n)), np.arange(max(n - 32, 0), n)]))
        variants = [
            ("attributes", "static: rest mesh (2 vertex attributes)", body,
             lambda sc: setup_static(sc, skinned_vertex=True)),
            ("attributes", "static + skin attributes fetched (4 attributes)", body,
             lambda sc: setup_static(sc, STATIC_SKIN_ATTRIBUTES_VS, "rest mesh + skin attributes", True)),
            ("attributes", "vb K=4, skin from storage buffers (2 attributes)", body,
             lambda sc: setup_vb(sc, vb, "crossMatrix", "float16", skin_buffers=True)),
        ]
        packed = packed_weights(body)
        variants += [
            ("packing", "static + skin attributes packed (4 attributes, 32-byte vertex)", packed,
             lambda sc: setup_static(sc, STATIC_SKIN_ATTRIBUTES_VS, "rest mesh + packed skin attributes", True)),
            ("packing", "vb K=4, skin attributes packed (32-byte vertex)", packed,
             lambda sc: setup_vb(sc, vb, "crossMatrix", "float16")),
        ]
        for k in (4, 3, 2, 1):
            variants.append(("influences", f"vb K={k} (4 attributes)", fewer_influences(body, k, vb.layout.bone_count),
                             lambda sc: setup_vb(sc, vb, "crossMatrix", "float16")))
        variants.append(("reference", "vat (no vertex attributes)", body, lambda sc: setup_vat(sc, vat)))
        for factor, label, character, setup in variants:
            scene = Scene(ctx, framebuffer, character, crowd, rows, packed_skin=factor == "packing")
            method = setup(scene)
            correctness = check(method, scene, vb, vat)
            drawn = time_method(method, scene, args.per_config_s, args.max_runs)
            ctx.enable(moderngl.RASTERIZER_DISCARD)
            try:
                discarded = time_method(method, scene, args.per_config_s, args.max_runs)
            finally:
                ctx.disable(moderngl.RASTERIZER_DISCARD)
            row = {"factor": factor, "variant": label, "instances": n, "config": method.config,
                   "correctness": correctness, "drawn": drawn, "rasterizer_discard": discarded}
            result["variants"].append(row)
            print(f"N={n:<8d} {label:52s} drawn {drawn['gpu_draw_ms']['median']:9.3f} ms  vertex stage alone "
                  f"{discarded['gpu_draw_ms']['median']:9.3f} ms  x{drawn['runs']}/{discarded['runs']}  "
                  f"err {correctness['position_error_m']:.1e} m {'ok' if correctness['agrees'] else 'DISAGREES'}",
                  flush=True)
            for item in method.release:
                item.release()
            for vao in (method.draw_vao, method.tf_vao):
                vao.release()
            method.program.release()
            method.tf_program.release()
            scene.release()
            _write_json(Path(args.json), result)
    result["elapsed_s"] = time.perf_counter() - started
    _write_json(Path(args.json), result)
    return 0


def factors_markdown(data: dict) -> str:
    """The factor study as a markdown table."""
    rows = ["| instances | variant | GPU draw ms (drawn) | GPU draw ms (rasterizer discard) | runs "
            "| max error vs numpy (m) |", "|--:|---|--:|--:|--:|--:|"]
    for r in data["variants"]:
        c = r["correctness"]
        rows.append(f"| {r['instances']:,} | {r['variant']} | {r['drawn']['gpu_draw_ms']['median']:.3f} "
                    f"| {r['rasterizer_discard']['gpu_draw_ms']['median']:.3f} "
                    f"| {r['drawn']['runs']}/{r['rasterizer_discard']['runs']} "
                    f"| {c['position_error_m']:.1e}{'' if c['agrees'] else ' (DISAGREES)'} |")
    return "\n".join(rows)


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


# ------------------------------------------------------------------------------------------ report


def _find(runs, character, n, method, encoding=None, texel_format=None):
    for r in runs:
        if (r["character"], r["instances"], r["method"]) == (character, n, method) and \
                (encoding is None or (r["encoding"], r["texel_format"]) == (encoding, texel_format)):
            return r
    return None


def goals(data: dict) -> list:
    """The issue's four goals, judged from the measured runs (lines of text)."""
    runs = data["runs"]
    lines = []
    static = _find(runs, "stadium", 100_000, "static")
    vb = _find(runs, "stadium", 100_000, "vb", "crossMatrix", "float16")
    vat = _find(runs, "stadium", 100_000, "vat")
    palette = _find(runs, "stadium", 100_000, "palette")
    if static and vb:
        ratio = vb["gpu_draw_ms"]["median"] / static["gpu_draw_ms"]["median"]
        lines.append(f"VB GPU time at 100,000 stadium instances = {ratio:.2f} x static "
                     f"({vb['gpu_draw_ms']['median']:.2f} vs {static['gpu_draw_ms']['median']:.2f} ms): "
                     f"goal <= 1.3x {'MET' if ratio <= 1.3 else 'MISSED by ' + format(ratio / 1.3 - 1, '.0%')}")
    for n in (100_000, 1_000_000):  # issue 25: the shipped pulled binding at most 1.05x static
        static_n = _find(runs, "stadium", n, "static")
        pulled = _find(runs, "stadium", n, "vb_pulled", "crossMatrix", "float16")
        if static_n and pulled:
            ratio = pulled["gpu_draw_ms"]["median"] / static_n["gpu_draw_ms"]["median"]
            agrees = pulled["correctness"]["agrees"] and static_n["correctness"]["agrees"]
            lines.append(f"VB pulled GPU time at {n:,} stadium instances = {ratio:.3f} x static "
                         f"({pulled['gpu_draw_ms']['median']:.3f} vs {static_n['gpu_draw_ms']['median']:.3f} ms): "
                         f"goal <= 1.05x {'MET' if ratio <= 1.05 else 'MISSED'}"
                         f"{'' if agrees else ' (a read-back DISAGREES with numpy)'}")
    if vb and vat:
        ratio = vb["gpu_draw_ms"]["median"] / vat["gpu_draw_ms"]["median"]
        lines.append(f"VB GPU time / VAT GPU time at 100,000 = {ratio:.2f}: goal < 1 {'MET' if ratio < 1 else 'MISSED'}")
    if vb and palette:
        ratio = palette["frame_ms"]["median"] / vb["frame_ms"]["median"]
        lines.append(f"palette skinning's whole frame / VB's at 100,000 = {ratio:.1f}x "
                     f"({palette['frame_ms']['median']:.1f} vs {vb['frame_ms']['median']:.2f} ms)")
    if vb and vat:
        vb_tex = vb["anim_bytes"] - 12 * vb["instances"]
        vat_tex = vat["anim_bytes"] - 8 * vat["instances"]
        lines.append(f"animation texture bytes, stadium clip: VAT {vat_tex:,} / VB {vb_tex:,} = {vat_tex / vb_tex:.2f}x: "
                     f"goal >= 6x {'MET' if vat_tex / vb_tex >= 6 else 'MISSED'}")
    return lines


BINDING_METHODS = (("vb", "VB attributes"), ("vb_pulled", "VB pulled"), ("vb_pulled_texture", "VB pulled (texture)"),
                   ("vat", "VAT"))


def bindings_markdown(data: dict) -> str:
    """Issue 25's table: per character and size, static and each method's GPU draw time as a factor of static.

    The Virtual Bones rows are crossMatrix float16 (the plan's); each method's error is its largest
    position error against numpy in the read-back (metres), marked where it is over the tolerance.
    """
    runs = data["runs"]
    head = ["character", "instances", "static GPU ms"] \
        + [f"{label} GPU ms (x static)" for _, label in BINDING_METHODS] + ["static error vs numpy (m)"] \
        + [f"{label} error (m)" for _, label in BINDING_METHODS] + ["timed frames"]
    rows = ["| " + " | ".join(head) + " |", "|---|--:|--:|" + "--:|" * (2 * len(BINDING_METHODS) + 2)]
    keys = sorted({(r["character"], r["instances"]) for r in runs if r["method"] == "static"},
                  key=lambda key: (key[0] != "stadium", key[1]))
    for character, n in keys:
        static = _find(runs, character, n, "static")
        found = [_find(runs, character, n, m, *(("crossMatrix", "float16") if m.startswith("vb") else (None, None)))
                 for m, _ in BINDING_METHODS]
        base = static["gpu_draw_ms"]["median"]

        def error(r):
            if r is None:
                return "not run"
            c = r["correctness"]
            return f"{c['position_error_m']:.1e}" + ("" if c["agrees"] else " (DISAGREES)")

        cells = [character, f"{n:,}", f"{base:.3f}"]
        for r in found:
            cells.append("not run" if r is None else
                         f"{r['gpu_draw_ms']['median']:.3f} ({r['gpu_draw_ms']['median'] / base:.2f}x)")
        cells += [error(static)] + [error(r) for r in found]
        cells.append("/".join(str(r["runs"]) if r else "-" for r in [static] + found))
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def previous_markdown(data: dict) -> str:
    """Issue 36: each Virtual Bones configuration's GPU draw and frame time without and with the
    previous pose (``--previous both``), the cost as a ratio, and the previous positions' error."""
    rows = ["| character | instances | method | GPU draw ms, off | GPU draw ms, previous on | x | frame ms, off "
            "| frame ms, on | previous pose error vs numpy (m) |", "|---|--:|---|--:|--:|--:|--:|--:|--:|"]
    on = [r for r in data["runs"] if r.get("previous")]
    for r in sorted(on, key=lambda r: (r["character"] != "stadium", r["instances"], r["method"])):
        off = next((o for o in data["runs"] if not o.get("previous") and o["character"] == r["character"]
                    and o["instances"] == r["instances"] and o["method"] == r["method"]
                    and o["encoding"] == r["encoding"] and o["texel_format"] == r["texel_format"]), None)
        off_draw = off["gpu_draw_ms"]["median"] if off else float("nan")
        draw = r["gpu_draw_ms"]["median"]
        rows.append(f"| {r['character']} | {r['instances']:,} | {r['method']} ({r['encoding']} {r['texel_format']}) "
                    f"| {off_draw:.3f} | {draw:.3f} | {draw / off_draw:.2f} "
                    f"| {off['frame_ms']['median'] if off else float('nan'):.3f} | {r['frame_ms']['median']:.3f} "
                    f"| {r['correctness'].get('previous_position_error_m', float('nan')):.2e} |")
    return "\n".join(rows)


def markdown(data: dict) -> str:
    rows = ["| character | instances | method | configuration | GPU draw ms | GPU other ms | CPU ms | frame ms "
            "| runs | animation bytes on GPU | max error vs numpy (m) | vs exact (m) |",
            "|---|--:|---|---|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for r in sorted(data["runs"], key=lambda r: (r["character"] != "stadium", r["instances"],
                                                 ["static", "vb", "vb_variety", "vb_pulled", "vb_pulled_texture", "vb_lod", "vat", "palette", "warp"].index(
                                                     r["method"]),
                                                 r["config"])):
        c = r["correctness"]
        rows.append(f"| {r['character']} | {r['instances']:,} | {r['method']} | {r['config']} "
                    f"| {r['gpu_draw_ms']['median']:.3f} | {r['gpu_other_ms']['median']:.3f} "
                    f"| {r['cpu_ms']['median']:.3f} | {r['frame_ms']['median']:.3f} | {r['runs']} "
                    f"| {r['anim_bytes']:,} | {c['position_error_m']:.1e}{'' if c['agrees'] else ' (DISAGREES)'} "
                    f"| {c['exact_position_error_m']:.1e} |")
    return "\n".join(rows)


def plot(data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    styles = {"static": "k--", "vb": "C0-o", "vb_pulled": "C4-v", "vb_pulled_texture": "C5-<", "vat": "C1-s", "palette": "C3-^", "warp": "C2-d"}
    for ax, character in zip(axes, ("stadium", "dense")):
        for method, style in styles.items():
            points = sorted((r["instances"], r["frame_ms"]["median"], r["gpu_draw_ms"]["median"] + r["gpu_other_ms"]["median"])
                            for r in data["runs"] if r["character"] == character and r["method"] == method and
                            (method not in ("vb", "vb_pulled", "vb_pulled_texture", "warp") or
                             (r["encoding"], r["texel_format"]) == ("crossMatrix", "float16")))
            if not points:
                continue
            n, frame, gpu = zip(*points)
            ax.plot(n, gpu, style, label=f"{method} GPU")
            if method == "palette":
                ax.plot(n, frame, "C3:^", label="palette whole frame (CPU + upload + GPU)")
        vertices = data.get("characters", {}).get(character, {}).get("vertices")
        ax.set(xscale="log", yscale="log", xlabel="instances", ylabel="ms per frame",
               title=f"{character} ({vertices:,} vertices)" if vertices else character)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    facts = data.get("facts", {})
    fig.suptitle(f"Draw cost per frame, {facts.get('nvidia_smi') or facts.get('GL_RENDERER')}, "
                 f"{data['resolution'][0]}x{data['resolution'][1]}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def lod_markdown(data: dict) -> str:
    """Issue 29's table: per crowd size, one level against three in the same view (frame and GPU time,
    triangles drawn, instances per level and culled), each row's error against numpy."""
    lines = ["| instances | levels | frame ms | GPU ms (selection + draws) | triangles drawn | per level (LOD 0 / 1 / 2), culled "
             "| max error vs numpy (m) |", "|---:|---|---:|---:|---:|---|---:|"]
    for n in sorted({r["instances"] for r in data["runs"]}, reverse=True):
        for method, label in (("vb", "1 (LOD 0 only)"), ("vb_lod", "3 (0.5, 0.2 of the triangles)")):
            row = _find(data["runs"], "stadium", n, method, "crossMatrix", "float16")
            if row is None:
                continue
            levels = row.get("levels")
            per = (" / ".join(f"{c:,}" for c in levels["instances"]) + f", {levels['culled']:,} culled") if levels \
                else f"{n:,} / 0 / 0, not culled"
            lines.append(f"| {n:,} | {label} | {row['frame_ms']['median']:.2f} | {row['gpu_draw_ms']['median']:.2f} "
                         f"| {row.get('triangles_drawn', 0):,} | {per} | {row['correctness']['position_error_m']:.1e} |")
    return "\n".join(lines)


def variety_markdown(data: dict) -> str:
    """Issue 37: per crowd size, vb without and with crowd variety (tint, variant, hat part), and the cost."""
    lines = ["| instances | variety off: GPU draw ms | on: GPU draw ms | on / off | frame ms off / on "
             "| triangles drawn on (hats) | max error vs numpy (m) on |", "|---:|---:|---:|---:|---|---:|---:|"]
    for n in sorted({r["instances"] for r in data["runs"]}):
        off = _find(data["runs"], "stadium", n, "vb", "crossMatrix", "float16")
        on = _find(data["runs"], "stadium", n, "vb_variety", "crossMatrix", "float16")
        if off is None or on is None:
            continue
        a, b = off["gpu_draw_ms"]["median"], on["gpu_draw_ms"]["median"]
        lines.append(f"| {n:,} | {a:.3f} | {b:.3f} | {b / a:.2f}x | {off['frame_ms']['median']:.2f} / "
                     f"{on['frame_ms']['median']:.2f} | {on.get('triangles_drawn', 0):,} "
                     f"| {on['correctness']['position_error_m']:.1e} |")
    return "\n".join(lines)


def report(args) -> int:
    data = json.loads(Path(args.json).read_text())
    facts = data.get("facts", {})
    print(f"GPU: {facts.get('nvidia_smi')} | {facts.get('GL_RENDERER')} | {facts.get('GL_VERSION')}")
    if "variants" in data:  # a factor study
        print(f"nonzero influences per vertex (0..4): {data.get('nonzero_influences_histogram')}")
        print(factors_markdown(data))
        return 0
    if args.markdown:
        print(markdown(data))
    if any(r["method"] == "vb_pulled" for r in data["runs"]):
        print()
        print(bindings_markdown(data))
        print()
    if any(r["method"] == "vb_variety" for r in data["runs"]):
        print()
        print(variety_markdown(data))
        print()
    if any(r["method"] == "vb_lod" for r in data["runs"]):
        print()
        print(lod_markdown(data))
        print()
    if any(r.get("previous") for r in data["runs"]):
        print()
        print(previous_markdown(data))
        print()
    for line in goals(data):
        print("*", line)
    for s in data.get("skipped", []):
        print(f"* not run: {s['what']}: {s['why']}")
    for f in data.get("factors", []):
        print(f"* factor {f['method']} {f['config']} N={f['instances']:,}: rasterizer discard "
              f"{f['rasterizer_discard']['gpu_draw_ms']['median']:.3f} ms, 64x64 viewport "
              f"{f['viewport_64']['gpu_draw_ms']['median']:.3f} ms")
    if args.plot:
        plot(data, Path(args.plot))
        print(f"plot: {args.plot}")
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    """The command line, with ``run``'s defaults (and a named plan's) filled in."""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        epilog="run --previous off|on|both (issue 36): also time the Virtual Bones methods with the previous-frame "
               "pose (vbusd shader --previous, a velocity target); --plan issue36 is that comparison. "
               "See 'run --help'.")
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="measure (needs moderngl with an EGL driver, numpy, warp)")
    r.add_argument("--json", required=True, help="where the results go (rewritten after every configuration)")
    r.add_argument("--plan", choices=sorted(PLANS),
                   help="run exactly this named set of configurations (--sizes, --characters and --methods are "
                        "then ignored); issue25: stadium 10,000 / 100,000 / 1,000,000 and dense 1,200 / 10,000 "
                        "instances, static, vb, vb_pulled and vat; issue25-texture: the same sizes, static, vb, "
                        "vb_pulled and vb_pulled_texture (the skin records in an RGBA32UI texture, as WebGL 2); "
                        "issue29: stadium 1,000,000 / 100,000 / 10,000 seen from the grid's edge, vb (one level) "
                        "and vb_lod (three); issue36: stadium 100,000 / 1,000,000 / 10,000 and dense 10,000, static, "
                        "vb and vb_pulled_texture, previous pose off and on; issue37: stadium 100,000 / 1,000,000 / 10,000, vb and "
                        "vb_variety")
    r.add_argument("--sizes", default=",".join(str(s) for s in SIZES))
    r.add_argument("--characters", default="stadium,dense")
    r.add_argument("--methods", default="static,vb,vb_pulled,vat,palette,warp")
    r.add_argument("--budget", type=float, help="seconds for the whole run; the rest is skipped (default 420; "
                                                "issue25: 400)")
    r.add_argument("--per-config-s", type=float, help="seconds of timed frames per configuration (default 1.5; "
                                                      "issue25: 3)")
    r.add_argument("--min-runs", type=int, help="timed frames per configuration at least (default 3; issue25: 10)")
    r.add_argument("--max-runs", type=int, default=30)
    r.add_argument("--warmup-s", type=float, help="untimed frames before the first timed configuration, seconds "
                                                  "(default 0; issue25: 3)")
    r.add_argument("--max-frame-s", type=float, default=8.0, help="skip a configuration predicted slower than this")
    r.add_argument("--previous", choices=("off", "on", "both"),
                   help="issue 36: draw the Virtual Bones methods (vb, vb_pulled, vb_pulled_texture) with the previous "
                        "pose on (vbusd shader --previous: a second skin at vb_previousTime = t - 1/60, screen-space "
                        "velocity into an RG16F target, previous positions checked against the reference), off, "
                        "or both (each configuration timed without, then with it; report adds the cost table) "
                        "(default off; issue36: both)")
    r.add_argument("--variety", choices=("off", "on", "both"), default="off",
                   help="issue 37: crowd variety (format 1.3) on the vb configurations: off (default), on (vb_variety "
                        "instead of vb) or both (each vb configuration also with variety); --plan issue37 is both at "
                        "100,000, 1,000,000 and 10,000 spectators")
    r.add_argument("--no-factors", dest="factors", action="store_false")
    r.add_argument("--factor-size", type=int, default=100_000, help="crowd size of the one-factor study")
    f = sub.add_parser("factors", help="one factor at a time around VB's vertex cost (stadium character)")
    f.add_argument("--json", required=True)
    f.add_argument("--sizes", default="100000")
    f.add_argument("--per-config-s", type=float, default=1.0)
    f.add_argument("--max-runs", type=int, default=20)
    lod = sub.add_parser("lod-meshes", help="issue 29: write the stadium character's generated levels (needs "
                                            "meshoptimizer) for a run on a machine without it ($VBUSD_LOD_MESHES)")
    lod.add_argument("--out", required=True)
    p = sub.add_parser("report", help="table, goals and plot from a results JSON")
    p.add_argument("--json", required=True)
    p.add_argument("--markdown", action="store_true")
    p.add_argument("--plot")
    args = parser.parse_args(argv)
    if args.command == "run":
        defaults = {"budget": 420.0, "per_config_s": 1.5, "min_runs": 3, "warmup_s": 0.0, "previous": "off"}
        defaults.update(PLAN_DEFAULTS.get(args.plan, {}))
        for key, value in defaults.items():
            if key == "factors":
                args.factors = args.factors and value
            elif getattr(args, key) is None:
                setattr(args, key, value)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.command == "factors":
        return run_factors(args)
    if args.command == "lod-meshes":
        return save_lod_meshes(args)
    return run(args) if args.command == "run" else report(args)


if __name__ == "__main__":
    sys.exit(main())
