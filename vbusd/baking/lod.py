"""Levels of detail that share one Virtual Bones texture (format 1.2, spec/virtual-bones.md section 20).

Three things live here, all numpy (meshoptimizer only for :func:`add_levels`):

* :func:`add_levels` makes LOD 1..n of every bound mesh of a baked animation by simplifying LOD 0
  to triangle ratios (``vbusd convert --lod-ratios 0.5,0.2``), with fewer influences per level;
* :func:`screen_size` is UsdLod's ``projectedSphere`` screen size of instances (what
  ``UsdLodScreenSizeHeuristic.ComputeScreenSize`` returns), vectorized over a crowd;
* :func:`select_levels` turns screen sizes into levels (``ComputeLOD``), with optional hysteresis.

The simplifier is meshoptimizer's Python binding (the ``lod`` extra); it is imported only when
levels are generated, so reading or drawing levels needs nothing beyond numpy.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Optional, Sequence

import numpy as np

from vbusd.format.errors import OptionsError, UnsupportedError
from vbusd.format.model import BoundMesh, LevelsOfDetail, VirtualBones
from vbusd.format.names import unique_names
from vbusd.baking.baker import reduce_influences

__all__ = ["MAX_LEVELS", "default_screen_sizes", "parse_ratios", "check_screen_sizes", "weld_points", "simplify_mesh",
           "poorly_simplified",
           "add_levels", "adopt_levels", "levels_from_names", "screen_size", "select_levels", "level_meshes"]

MAX_LEVELS = 8
"""Most levels an animation may have (spec 20.1)."""

HYSTERESIS = 0.1
"""What the runtimes use (spec 20.2): a finer level only once the size passes its threshold by 10 %."""


def default_screen_sizes(count: int) -> tuple:
    """Thresholds for ``count`` levels: 0.01 for LOD 1, then a tenth of the one before (spec 20.3).

    LOD 1 once the character's bounding sphere covers 1 % of the view or less (about a sixth of the
    screen's height across), LOD 2 below 0.1 %: a level per factor 10 of screen area, about 3.2 of
    distance, as crowd tools step their levels.
    """
    return tuple(0.01 * 0.1 ** i for i in range(count - 1))


def parse_ratios(text: str, *, option: str = "--lod-ratios") -> tuple:
    """Parse ``0.5,0.2`` into strictly descending ratios in (0, 1).

    Raises:
        OptionsError: Not numbers, out of (0, 1), not strictly descending, or too many levels
            (code ``options.invalid``).
    """
    try:
        values = tuple(float(part) for part in str(text).split(","))
    except ValueError:
        raise OptionsError(f"{option} takes numbers separated by commas, e.g. 0.5,0.2; got {text!r}",
                           location=option, code="options.invalid") from None
    if not values or any(not (0.0 < v < 1.0) or not math.isfinite(v) for v in values):
        raise OptionsError(f"{option}: every ratio must be above 0 and below 1, got {text}", location=option,
                           code="options.invalid")
    if any(b >= a for a, b in zip(values, values[1:])):
        raise OptionsError(f"{option}: ratios must decrease strictly (LOD 1 keeps the most), got {text}",
                           location=option, code="options.invalid")
    if len(values) + 1 > MAX_LEVELS:
        raise OptionsError(f"{option}: at most {MAX_LEVELS - 1} ratios ({MAX_LEVELS} levels), got {len(values)}",
                           location=option, code="options.invalid")
    return values


def check_screen_sizes(sizes: Sequence[float], count: int, *, option: str = "--lod-screen-sizes") -> tuple:
    """Check ``count - 1`` thresholds strictly descending in (0, 1] (spec 20.1) and return them.

    Raises:
        OptionsError: Wrong count or values (code ``options.invalid``).
    """
    sizes = tuple(float(s) for s in sizes)
    if len(sizes) != count - 1:
        raise OptionsError(f"{option}: {count} levels need {count - 1} screen sizes, got {len(sizes)}",
                           location=option, code="options.invalid")
    if any(not (0.0 < s <= 1.0) for s in sizes) or any(b >= a for a, b in zip(sizes, sizes[1:])):
        raise OptionsError(f"{option}: screen sizes must lie in (0, 1] and decrease strictly, got "
                           f"{','.join(f'{s:g}' for s in sizes)}", location=option, code="options.invalid")
    return sizes


def _meshoptimizer():
    try:
        import meshoptimizer
    except ImportError:
        raise UnsupportedError("generating levels of detail needs meshoptimizer: pip install 'vbusd[lod]' "
                               "(it builds from source: needs a C++ compiler and Python's headers, Debian: "
                               "apt install g++ python3-dev)", location="--lod-ratios",
                               code="convert.lodSimplifier") from None
    return meshoptimizer


def _triangles(mesh: BoundMesh) -> tuple:
    """(triangles (T, 3) point indices, corner of each triangle vertex (T, 3)) as fans of the faces."""
    counts = np.asarray(mesh.face_vertex_counts, dtype=np.int64)
    corners_of = np.asarray(mesh.face_vertex_indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    fans = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(counts.size), fans)
    step = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans)
    first = starts[face]
    corners = np.stack([first, first + step + 1, first + step + 2], axis=1)
    return corners_of[corners], corners


def _vertex_normals(mesh: BoundMesh) -> Optional[np.ndarray]:
    """Per-point normals: the mesh's own, or for faceVarying ones the normalized mean of each point's corners.

    A simplified mesh has fewer, moved corners, so faceVarying normals cannot be kept as they are;
    a point's mean normal is what a smooth LOD shows (hard edges soften at distance, where it does
    not show).
    """
    if mesh.normals is None:
        return None
    normals = np.asarray(mesh.normals, dtype=np.float64)
    if mesh.normals_interpolation != "faceVarying":
        return normals
    total = np.zeros((len(mesh.points), 3))
    np.add.at(total, np.asarray(mesh.face_vertex_indices, dtype=np.int64), normals)
    length = np.linalg.norm(total, axis=1, keepdims=True)
    return np.where(length > 0, total / np.where(length > 0, length, 1.0), np.array([0.0, 1.0, 0.0]))


def weld_points(points, bone_indices, bone_weights, normals=None) -> np.ndarray:
    """For each point, the first point equal to it in rest position, influences (indices and
    weights, slot by slot) and normal (when given): (V,) indices, ``weld[weld] == weld``. Exact
    equality: welding changes no vertex a level keeps, only which triangles share it."""
    columns = [np.asarray(points, dtype=np.float64).reshape(len(points), -1),
               np.asarray(bone_indices, dtype=np.float64).reshape(len(points), -1),
               np.asarray(bone_weights, dtype=np.float64).reshape(len(points), -1)]
    if normals is not None:
        columns.append(np.asarray(normals, dtype=np.float64).reshape(len(points), -1))
    _, first, inverse = np.unique(np.concatenate(columns, axis=1), axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


def simplify_mesh(mesh: BoundMesh, ratio: float, max_influences: int, path: str, level: int) -> BoundMesh:
    """One mesh simplified to about ``ratio`` of its triangles, with at most ``max_influences`` influences.

    Surviving points keep their rest position and influences (the largest ``max_influences``,
    renormalized as the bake does); unused points are dropped.

    Args:
        mesh: LOD 0 mesh.
        ratio: Triangle ratio in (0, 1).
        max_influences: Influences kept per vertex (>= 1).
        path: Prim path of the new mesh.
        level: Its level.

    Returns:
        The simplified mesh (triangles only, vertex normals when the source had normals).
    """

    meshopt = _meshoptimizer()
    triangles, _ = _triangles(mesh)
    normals = _vertex_normals(mesh)
    # Weld first (spec 20.3): points equal in position, influences and normal are one vertex, so
    # an unindexed mesh (glTF's Fox: three points per triangle) is connected and can collapse.
    weld = weld_points(mesh.points, mesh.bone_indices, mesh.bone_weights, normals)
    # Only the welded points the triangles use go to the simplifier: an unused duplicate at a used
    # point's position would make meshoptimizer take that point for a seam it must keep.
    welded, compact = np.unique(weld[triangles].reshape(-1), return_inverse=True)
    all_points = np.asarray(mesh.points, dtype=np.float32)
    points = np.ascontiguousarray(all_points[welded])
    indices = np.ascontiguousarray(compact.reshape(-1), dtype=np.uint32)
    target = max(3, 3 * math.ceil(ratio * len(triangles)))
    destination = np.zeros(indices.size, dtype=np.uint32)
    # target_error 1 (the whole mesh extent): the triangle count decides, not an error bound;
    # meshoptimizer still removes the least visible edges first.
    count = meshopt.simplify(destination, indices, points, index_count=indices.size, vertex_count=len(points),
                             target_index_count=target, target_error=1.0)
    kept = welded[destination[:count].astype(np.int64)].reshape(-1, 3)
    used, remapped = np.unique(kept.reshape(-1), return_inverse=True)
    bone_indices, bone_weights, _ = reduce_influences(np.asarray(mesh.bone_indices)[used],
                                                      np.asarray(mesh.bone_weights)[used], max_influences, mesh=path)
    return BoundMesh(path=path, points=all_points[used].copy(),
                     face_vertex_counts=np.full(len(kept), 3, dtype=np.int32),
                     face_vertex_indices=remapped.astype(np.int32).reshape(-1),
                     bone_indices=bone_indices, bone_weights=bone_weights,
                     normals=None if normals is None else normals[used].astype(np.float32),
                     normals_interpolation="vertex", lod=level)


def poorly_simplified(source_triangles: int, kept_triangles: int, ratio: float) -> Optional[str]:
    """Why a generated level is not the simpler level asked for, or None: the simplifier removed
    less than half of the triangles ratio ``ratio`` asks it to remove (spec 20.3)."""
    target = math.ceil(ratio * source_triangles)
    if source_triangles - kept_triangles >= 0.5 * (source_triangles - target):
        return None
    return (f"keeps {kept_triangles} of {source_triangles} triangles, not about {target} (ratio {ratio:g}): "
            "the simplifier cannot collapse this mesh further without flipping faces or tearing seams")


def add_levels(vb: VirtualBones, ratios: Sequence[float], *, screen_sizes: Optional[Sequence[float]] = None,
               root: Optional[str] = None, warnings: Optional[list] = None) -> VirtualBones:
    """Give a baked animation generated levels of detail (spec 20.3).

    LOD 0 is the animation's meshes, moved under ``<root>/lod0``; LOD ``i`` simplifies each of them
    to ``ratios[i-1]`` of its triangles with ``max(1, K >> i)`` influences, under ``<root>/lod<i>``.
    The texture, clips and clip extents are unchanged (every level's points are LOD 0 points).

    Args:
        vb: A baked animation without levels, with meshes.
        ratios: Triangle ratios of LOD 1, 2, ... (see :func:`parse_ratios`).
        screen_sizes: Thresholds (one per generated level), default :func:`default_screen_sizes`.
        root: Prim path of the LOD root, default ``<parent of the first mesh>/<animation name>_lods``.
        warnings: Where to append one line per level mesh that the simplifier could not reduce
            meaningfully (:func:`poorly_simplified`): it is written all the same.

    Returns:
        The animation with ``lods`` set and every level's meshes.

    Raises:
        OptionsError: The animation already has levels or has no mesh; bad ratios or sizes.
        UnsupportedError: meshoptimizer is not installed (code ``convert.lodSimplifier``).
    """
    if vb.lods is not None:
        raise OptionsError(f"{vb.path} already has levels of detail from its source; --lod-ratios would add "
                           "a second set", location="--lod-ratios", code="options.invalid")
    if not vb.meshes:
        raise OptionsError(f"{vb.path} has no mesh to make levels of", location="--lod-ratios", code="options.invalid")
    ratios = tuple(float(r) for r in ratios)
    count = len(ratios) + 1
    sizes = check_screen_sizes(default_screen_sizes(count) if screen_sizes is None else screen_sizes, count)
    if root is None:
        parent = vb.meshes[0].path.rsplit("/", 1)[0] or ""
        root = f"{parent}/{vb.path.rstrip('/').rsplit('/', 1)[-1]}_lods"
    lods = LevelsOfDetail(root=root, screen_sizes=sizes)
    names = unique_names([m.path.rstrip("/").rsplit("/", 1)[-1] for m in vb.meshes])
    meshes = [dataclasses.replace(m, path=f"{lods.item_path(0)}/{name}", lod=0) for m, name in zip(vb.meshes, names)]
    for level, ratio in enumerate(ratios, start=1):
        for mesh, name in zip(vb.meshes, names):
            influences = max(1, mesh.max_influences >> level)
            simplified = simplify_mesh(mesh, ratio, influences, f"{lods.item_path(level)}/{name}", level)
            note = poorly_simplified(len(_triangles(mesh)[0]), len(simplified.face_vertex_counts), ratio)
            if note and warnings is not None:
                warnings.append(f"{simplified.path}: LOD {level} of {mesh.path} {note}")
            meshes.append(simplified)
    return dataclasses.replace(vb, meshes=tuple(meshes), lods=lods)


def adopt_levels(vb: VirtualBones, screen_sizes: Optional[Sequence[float]] = None, *,
                 root: Optional[str] = None) -> VirtualBones:
    """Give a baked animation the levels its source gave its meshes (``BoundMesh.lod``; glTF ``MSFT_lod``).

    The meshes keep their order (the accuracy check pairs them with the source's) and move under
    ``<root>/lod<i>``; the root defaults as in :func:`add_levels`. Levels the source leaves empty
    are an error, as are thresholds that break spec 20.1.

    Args:
        vb: A baked animation whose meshes carry their level.
        screen_sizes: The source's thresholds (one per level after the first), default
            :func:`default_screen_sizes`.
        root: Prim path of the LOD root.

    Returns:
        The animation with ``lods`` set, or ``vb`` itself when every mesh is at level 0.
    """
    count = max((m.lod for m in vb.meshes), default=0) + 1
    if count == 1:
        return vb
    if count > MAX_LEVELS:
        raise OptionsError(f"{vb.path}: the source has {count} levels of detail; at most {MAX_LEVELS}",
                           location=vb.path, code="options.invalid")
    missing = [level for level in range(count) if not any(m.lod == level for m in vb.meshes)]
    if missing:
        raise OptionsError(f"{vb.path}: level(s) {missing} of detail have no mesh bound to this animation",
                           location=vb.path, code="options.invalid")
    sizes = tuple(screen_sizes)[:count - 1] if screen_sizes is not None else ()
    if len(sizes) != count - 1:
        sizes = default_screen_sizes(count)
    sizes = check_screen_sizes(sizes, count, option="MSFT_screencoverage")
    if root is None:
        first = next(m for m in vb.meshes if m.lod == 0)
        parent = first.path.rsplit("/", 1)[0] or ""
        root = f"{parent}/{vb.path.rstrip('/').rsplit('/', 1)[-1]}_lods"
    lods = LevelsOfDetail(root=root, screen_sizes=sizes)
    names = unique_names([m.path.rstrip("/").rsplit("/", 1)[-1] for m in vb.meshes])
    meshes = tuple(dataclasses.replace(m, path=f"{lods.item_path(m.lod)}/{name}") for m, name in zip(vb.meshes, names))
    return dataclasses.replace(vb, meshes=meshes, lods=lods)


LOD_NAME = re.compile(r"^(?P<base>.*?)[_-]?LOD(?P<level>[0-9])$", re.IGNORECASE)
"""A mesh named for its level, as DCCs and engines name them (Unity's and Unreal's ``Body_LOD1``)."""


def levels_from_names(vb: VirtualBones) -> Optional[VirtualBones]:
    """The meshes' levels from their names (spec 20.3): every mesh named ``<name>_LOD<i>`` (or
    ``LOD<i>``, any case) with levels 0 .. n-1 all present, n >= 2; None when the names do not say.
    """
    levels = []
    for mesh in vb.meshes:
        match = LOD_NAME.match(mesh.path.rstrip("/").rsplit("/", 1)[-1])
        if match is None:
            return None
        levels.append(int(match.group("level")))
    if len(set(levels)) < 2 or set(levels) != set(range(max(levels) + 1)):
        return None
    return dataclasses.replace(vb, meshes=tuple(dataclasses.replace(m, lod=level)
                                                for m, level in zip(vb.meshes, levels)))


def level_meshes(vb: VirtualBones, level: int) -> tuple:
    """The meshes of one level (all meshes when the animation has no levels and ``level`` is 0)."""
    return tuple(m for m in vb.meshes if m.lod == level)


def screen_size(extent, world, eye, fov_y_degrees: float, aspect: float) -> np.ndarray:
    """UsdLod's ``projectedSphere`` screen size of instances (spec 20.2).

    ``s = pi * (r / (d * tan(fovY / 2)))^2 / (4 * aspect)``: the fraction of the view plane that the
    bounding sphere of ``extent`` covers, with ``r`` half the extent's diagonal times the largest
    scale of ``world`` and ``d`` the distance from ``eye`` to the sphere's centre.

    Args:
        extent: (2, 3) box in the instances' local space (the animation's clip extents' union).
        world: (N, 4, 4) or (4, 4) column-vector world matrices.
        eye: (3,) camera position in world space.
        fov_y_degrees: Vertical field of view.
        aspect: Width / height.

    Returns:
        (N,) float64 screen sizes (infinite for an instance whose centre is at the eye).
    """
    extent = np.asarray(extent, dtype=np.float64).reshape(2, 3)
    world = np.asarray(world, dtype=np.float64).reshape(-1, 4, 4)
    centre = extent.mean(axis=0)
    radius = 0.5 * np.linalg.norm(extent[1] - extent[0])
    centres = world[:, :3, :3] @ centre + world[:, :3, 3]
    scale = np.linalg.norm(world[:, :3, :3], axis=1).max(axis=1)  # column lengths: the axis scales
    distance = np.linalg.norm(centres - np.asarray(eye, dtype=np.float64), axis=1)
    tangent = math.tan(math.radians(fov_y_degrees) / 2.0)
    with np.errstate(divide="ignore"):
        projected = (radius * scale) / (distance * tangent)
    return math.pi * projected ** 2 / (4.0 * float(aspect))


def select_levels(sizes, thresholds: Sequence[float], previous=None, hysteresis: float = 0.0) -> np.ndarray:
    """Levels from screen sizes: the number of thresholds ``t`` with ``s <= t`` (UsdLod's ComputeLOD).

    Args:
        sizes: (N,) screen sizes.
        thresholds: Descending thresholds (n - 1 of them).
        previous: (N,) levels of the frame before, for hysteresis, or None.
        hysteresis: An instance moves to a finer level than ``previous`` only when its size passes
            the crossed threshold by this fraction (spec 20.2; the runtimes use :data:`HYSTERESIS`).

    Returns:
        (N,) int32 levels in [0, n - 1].
    """
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1)
    t = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    levels = (sizes[:, None] <= t[None, :]).sum(axis=1)
    if previous is not None and hysteresis > 0:
        previous = np.asarray(previous, dtype=np.int64).reshape(-1)
        raised = (sizes[:, None] <= t[None, :] * (1.0 + hysteresis)).sum(axis=1)
        # Going finer (a lower level) needs the raised thresholds; coarser goes at once.
        levels = np.where(levels < previous, np.minimum(previous, raised), levels)
    return levels.astype(np.int32)
