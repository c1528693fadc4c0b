"""The levels of detail of an animation's meshes on a USD stage (format 1.2, spec/virtual-bones.md 20.1).

One function, :func:`levels_of`, shared by the strict reader (:mod:`vbusd.io.usd_reader`) and
``vbusd validate`` (:mod:`vbusd.validators.api`), so both apply the same rules and codes:
``lod.structure`` (one LOD root for all of an animation's meshes, 2 to 8 levels, none empty, an
authored ``lod:default:index`` naming one of them) and ``lod.heuristic`` (``lod:heuristics``
targets exactly one prim, a LODScreenSizeHeuristic, with thresholds one per level after the first,
in (0, 1], strictly decreasing).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from vbusd.format.diagnostics import UsdSite, finding
from vbusd.format.model import LevelsOfDetail
from pxr import Sdf
from pxr import Usd, UsdGeom
from vbusd.format import names
from pxr import UsdLod, Vt

__all__ = ["LOD_ROOT_API", "levels_of", "levels_of_animation", "check_animation_levels", "author_lod_root"]

LOD_ROOT_API = "LODRootAPI"
"""UsdLod's API schema of a level-of-detail root, as it appears in apiSchemas."""

DEFAULT_INDEX = "lod:default:index"
"""LODRootAPI's default level; authored, it must name a level (vbusd writes 0)."""


def _root_of(stage, Sdf, mesh_path: str):
    """The innermost LODRootAPI ancestor of a mesh (a nested root's levels belong to it), or None."""
    found = None
    path = Sdf.Path(mesh_path)
    for ancestor in path.GetAncestorsRange():
        prim = stage.GetPrimAtPath(ancestor)
        if ancestor != path and prim and LOD_ROOT_API in prim.GetAppliedSchemas():
            found = prim
    return found


def levels_of(stage, animation_path: str, mesh_paths: list) -> tuple:
    """The level of each of an animation's bound meshes and its :class:`LevelsOfDetail`.

    Args:
        stage: The open ``Usd.Stage``.
        animation_path: The VirtualBonesAnimation the meshes are bound to.
        mesh_paths: Their prim paths.

    Returns:
        ``(findings, levels, lods)``: ``levels`` (one int per mesh) and ``lods`` are None when no
        mesh lies under a LOD root, or when a finding makes the levels unusable.
    """

    roots = [_root_of(stage, Sdf, p) for p in mesh_paths]
    if not mesh_paths or all(root is None for root in roots):
        return [], None, None
    paths = {str(root.GetPath()) if root else None for root in roots}
    if len(paths) != 1:
        listed = ", ".join(sorted(p or "(no LOD root)" for p in paths))
        return [finding("lod.structure", f"the meshes bound to {animation_path} lie under different LOD roots or "
                        f"partly outside one: {listed}; all must lie under one LODRootAPI prim",
                        UsdSite(animation_path))], None, None
    root = roots[0]
    root_site = UsdSite(str(root.GetPath()))
    items = list(root.GetChildren())
    if not 2 <= len(items) <= 8:
        return [finding("lod.structure", f"the LOD root has {len(items)} children (levels); 2 to 8",
                        root_site)], None, None
    level_of = {item.GetPath(): level for level, item in enumerate(items)}
    levels = [next(level_of[a] for a in Sdf.Path(p).GetAncestorsRange() if a in level_of) for p in mesh_paths]
    empty = [str(item.GetPath()) for level, item in enumerate(items) if level not in levels]
    if empty:
        return [finding("lod.structure", f"level(s) {', '.join(empty)} hold no mesh bound to {animation_path}",
                        root_site)], None, None
    default = root.GetAttribute(DEFAULT_INDEX)
    if default and default.HasAuthoredValue():
        index = default.Get()
        if not (isinstance(index, int) and 0 <= index < len(items)):
            return [finding("lod.structure", f"{DEFAULT_INDEX} is {index!r}; it names a level, 0..{len(items) - 1} "
                            "(vbusd writes 0)", UsdSite(str(root.GetPath()), DEFAULT_INDEX))], None, None
    relationship = root.GetRelationship("lod:heuristics")
    targets = list(relationship.GetTargets()) if relationship else []
    screen = [stage.GetPrimAtPath(t) for t in targets]
    screen = [h for h in screen if h and h.GetTypeName() == "LODScreenSizeHeuristic"]
    if len(targets) != 1 or len(screen) != 1:
        listed = ", ".join(str(t) for t in targets[:4]) + (", ..." if len(targets) > 4 else "")
        return [finding("lod.heuristic", f"lod:heuristics targets {len(targets)} prim(s) ({listed or 'none'}), "
                        f"{len(screen)} of them LODScreenSizeHeuristic; exactly one target, a "
                        "LODScreenSizeHeuristic", UsdSite(str(root.GetPath()), "lod:heuristics"))], None, None
    attribute = screen[0].GetAttribute("thresholds")
    value: Optional[object] = attribute.Get() if attribute and attribute.HasAuthoredValue() else None
    thresholds = np.asarray(value if value is not None else [], np.float64).reshape(-1)
    site = UsdSite(str(screen[0].GetPath()), "thresholds")
    if len(thresholds) != len(items) - 1:
        return [finding("lod.heuristic", f"{len(thresholds)} thresholds for {len(items)} levels; "
                        f"{len(items) - 1} are needed", site)], None, None
    if not np.all(np.isfinite(thresholds)) or np.any((thresholds <= 0) | (thresholds > 1)) or \
            np.any(np.diff(thresholds) >= 0):
        return [finding("lod.heuristic", f"thresholds {thresholds.tolist()} must lie in (0, 1] and decrease "
                        "strictly", site)], None, None
    lods = LevelsOfDetail(root=str(root.GetPath()), screen_sizes=tuple(float(t) for t in thresholds),
                          item_names=tuple(item.GetName() for item in items))
    return [], levels, lods


def check_animation_levels(prim) -> list:
    """``lod.*`` findings of one VirtualBonesAnimation prim: :func:`levels_of` over the meshes bound to it."""
    return levels_of_animation(prim)[0]


def levels_of_animation(prim) -> tuple:
    """:func:`levels_of` over the meshes bound to one VirtualBonesAnimation prim: ``(findings, levels, lods)``.

    Meshes below a point instancer are prototypes referencing the bound meshes (readers skip them),
    so they are not counted twice.
    """

    target = prim.GetPath()
    meshes = []
    iterator = iter(Usd.PrimRange(prim.GetStage().GetPseudoRoot()))
    for other in iterator:
        if other.IsA(UsdGeom.PointInstancer):
            iterator.PruneChildren()
            continue
        if names.BINDING_API not in other.GetAppliedSchemas():
            continue
        relationship = other.GetRelationship(names.ANIMATION_REL)
        if relationship and list(relationship.GetTargets())[:1] == [target]:
            meshes.append(str(other.GetPath()))
    return levels_of(prim.GetStage(), str(target), meshes)


HEURISTIC_SUFFIX = "_screenSize"
"""The LODScreenSizeHeuristic of a LOD root is its sibling ``<root name>_screenSize`` (spec 20.1)."""


def author_lod_root(stage, lods: LevelsOfDetail, clip_extents=None, root: Optional[str] = None):
    """Author a UsdLod root (spec 20.1) on ``stage``: the ``LODRootAPI`` prim, its children in level order
    and a ``LODScreenSizeHeuristic`` beside it. Call it before defining the levels' meshes, so that the
    children are the levels in order.

    Shared by the asset writer, the point cache and the UsdSkel fallback, so that each keeps the levels.

    Args:
        stage: The stage being written.
        lods: The levels (root path, thresholds, child names).
        clip_extents: (clips, 2, 3) extents; their union is the heuristic's ``extent``. None: not authored.
        root: Where to author the root instead of ``lods.root`` (the UsdSkel fallback nests it).

    Returns:
        The root's ``Sdf.Path``.
    """

    root_path = Sdf.Path(root or lods.root)
    for ancestor in root_path.GetParentPath().GetPrefixes():
        if not stage.GetPrimAtPath(ancestor):
            UsdGeom.Xform.Define(stage, ancestor)
    prim = stage.GetPrimAtPath(root_path) or UsdGeom.Xform.Define(stage, root_path).GetPrim()
    for level in range(lods.level_count):
        item = root_path.AppendChild(lods.item_name(level))
        if not stage.GetPrimAtPath(item):
            UsdGeom.Xform.Define(stage, item)
    api = UsdLod.RootAPI.Apply(prim)
    api.CreateLodDefaultIndexAttr(0)
    heuristic = UsdLod.ScreenSizeHeuristic.Define(stage, root_path.GetParentPath().AppendChild(
        root_path.name + HEURISTIC_SUFFIX))
    heuristic.CreateLodDomainAttr(UsdLod.Tokens.imaging)
    heuristic.CreateProjectionMethodAttr(UsdLod.Tokens.projectedSphere)
    heuristic.CreateThresholdsAttr(Vt.FloatArray([float(t) for t in lods.screen_sizes]))
    if clip_extents is not None and len(clip_extents):
        # Every pose of every clip: the choice must not depend on the pose (spec 20.1).
        extents = np.asarray(clip_extents, dtype=np.float32)
        box = np.stack([extents[:, 0].min(axis=0), extents[:, 1].max(axis=0)])
        heuristic.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(box)))
    api.CreateLodHeuristicsRel().SetTargets([heuristic.GetPath()])
    return root_path
