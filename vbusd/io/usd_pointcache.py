"""Write a time-sampled USD point cache: the layer ``vbusd decode`` writes (:mod:`vbusd.jobs.pointcache`).

A :class:`PointCache` is a stage built in memory: ordinary ``Mesh`` prims whose ``points``,
``extent`` and ``normals`` get one time sample per decoded row (:meth:`MeshSamples.set`), under
ancestors that carry the source asset's local transforms (:func:`source_transforms`, copied as one
matrix op each where authored), and UsdLod roots where the source has levels of detail. The job
decodes; this module authors. :meth:`PointCache.write` writes the layer as every vbusd output is
written (:func:`vbusd.io.usd.write_layer`): one :class:`vbusd.io.files.Commit` under the output's
lock, staged beside the target and renamed, so a failure or a kill never leaves a partial cache in
its place and the next run writing there removes what a killed one staged.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from vbusd.format.model import LevelsOfDetail
from vbusd.io.usd import write_layer
from vbusd.io.usd_lod import author_lod_root
from vbusd.io.usd_reader import stage_for_reading

__all__ = ["source_transforms", "MeshSamples", "PointCache"]


def source_transforms(asset_path, paths, allow_outside_paths: bool) -> tuple:
    """The asset's local transforms of ``paths`` and their ancestors, and its frames per second.

    Read once, through the one USD reader (a host's open layer is not touched, USD's diagnostics
    are captured), before the long decode.

    Returns:
        ``({path: (resets, [(time code or None, matrix)])}, frames per second)``, with an entry
        for each Xformable prim that has a transform.
    """
    table = {}
    with stage_for_reading(asset_path, allow_outside_paths=allow_outside_paths) as stage:
        wanted = {str(prefix) for path in paths for prefix in Sdf.Path(path).GetPrefixes()}
        for path in sorted(wanted):
            prim = stage.GetPrimAtPath(path)
            if not prim or not prim.IsA(UsdGeom.Xformable):
                continue
            xformable = UsdGeom.Xformable(prim)
            if not xformable.GetOrderedXformOps() and not xformable.GetResetXformStack():
                continue
            times = xformable.GetTimeSamples()
            samples = [(code, xformable.GetLocalTransformation(code)) for code in times] if times \
                else [(None, xformable.GetLocalTransformation())]
            table[path] = (xformable.GetResetXformStack(), samples)
        return table, float(stage.GetFramesPerSecond())


class MeshSamples:
    """The time-sampled attributes of one mesh of a :class:`PointCache`."""

    def __init__(self, mesh, normals: bool) -> None:
        self._points = mesh.CreatePointsAttr()
        self._extent = mesh.CreateExtentAttr()
        self._normals = mesh.CreateNormalsAttr() if normals else None

    @property
    def has_normals(self) -> bool:
        """Whether the mesh has normals (samples of them are written when given)."""
        return self._normals is not None

    def set(self, code: float, points: np.ndarray, normals: Optional[np.ndarray] = None) -> None:
        """Author the sample at time code ``code``: points (N, 3), their extent, and normals if given."""
        time = Usd.TimeCode(float(code))
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        self._points.Set(Vt.Vec3fArray.FromNumpy(points), time)
        low, high = points.min(axis=0), points.max(axis=0)
        self._extent.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, low)), Gf.Vec3f(*map(float, high))]), time)
        if self._normals is not None and normals is not None:
            self._normals.Set(Vt.Vec3fArray.FromNumpy(
                np.ascontiguousarray(np.asarray(normals, dtype=np.float32).reshape(-1, 3))), time)


class PointCache:
    """A point cache being built in memory (nothing touches the disk before :meth:`write`).

    Args:
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: The stage's ``metersPerUnit``.
        time_codes_per_second: The stage's ``timeCodesPerSecond`` (the source's).
        frames_per_second: The stage's ``framesPerSecond``.
        transforms: The source's local transforms (:func:`source_transforms`), given to the prims
            of the same paths.
    """

    def __init__(self, *, up_axis: str, meters_per_unit: float, time_codes_per_second: float,
                 frames_per_second: float, transforms: Optional[dict] = None) -> None:
        self.stage = Usd.Stage.CreateInMemory()
        self._transforms = transforms or {}
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(self.stage, float(meters_per_unit))
        self.stage.SetTimeCodesPerSecond(float(time_codes_per_second))
        self.stage.SetFramesPerSecond(float(frames_per_second))

    def lod_root(self, lods: LevelsOfDetail, clip_extents=None) -> None:
        """Author a UsdLod root (spec 20.1), before the levels' meshes, so that a viewer draws one level."""
        author_lod_root(self.stage, lods, clip_extents)

    def group(self, path: str) -> None:
        """Define ``path`` and its missing ancestors as Xforms carrying the source's transforms (a crowd)."""
        self._define_ancestors(path + "/x")

    def mesh(self, path: str, face_vertex_counts, face_vertex_indices, *,
             normals_interpolation: Optional[str] = None, transformed: bool = True) -> MeshSamples:
        """Define a mesh (and its missing ancestors) with its topology; return its samples to set.

        Args:
            path: The mesh's prim path.
            face_vertex_counts: Vertices per face.
            face_vertex_indices: Vertex indices, face by face.
            normals_interpolation: ``"vertex"`` or ``"faceVarying"`` when the mesh has normals,
                None when it has none.
            transformed: Give the mesh the source's transform of its path (a crowd's meshes,
                which the source does not have, take none).
        """
        self._define_ancestors(path)
        prim = UsdGeom.Mesh.Define(self.stage, path)
        if transformed:
            self._copy_transform(path, prim.GetPrim())
        prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(face_vertex_counts, np.int32)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(face_vertex_indices, np.int32)))
        prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        samples = MeshSamples(prim, normals=normals_interpolation is not None)
        if normals_interpolation is not None:
            prim.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying if normals_interpolation == "faceVarying"
                                         else UsdGeom.Tokens.vertex)
        return samples

    def write(self, output, *, start: float, end: float, default_prim: Optional[str], documentation: str,
              replace: bool, code: str = "decode.write") -> None:
        """Set the time range, default prim and documentation, and write the cache in one commit.

        Raises:
            VbusdError: The write failed (``code``): one line; nothing was written.
        """
        stage = self.stage
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(end)
        if default_prim and stage.GetPrimAtPath(f"/{default_prim}"):
            stage.SetDefaultPrim(stage.GetPrimAtPath(f"/{default_prim}"))
        stage.GetRootLayer().documentation = documentation
        write_layer(stage.GetRootLayer(), output, replace=replace, what="point cache", code=code)

    def _define_ancestors(self, path: str) -> None:
        """Define the missing ancestors of ``path`` as Xforms carrying the source's transforms."""
        for ancestor in Sdf.Path(path).GetParentPath().GetPrefixes():
            if self.stage.GetPrimAtPath(ancestor):
                continue
            prim = UsdGeom.Xform.Define(self.stage, ancestor).GetPrim()
            self._copy_transform(str(ancestor), prim)

    def _copy_transform(self, path: str, prim) -> None:
        """Author the source's local transform of ``path`` on ``prim`` (one matrix op)."""
        source = self._transforms.get(path)
        if source is None:
            return
        resets, samples = source
        target = UsdGeom.Xformable(prim)
        target.SetResetXformStack(resets)
        op = target.AddTransformOp()
        for code, matrix in samples:
            if code is None:
                op.Set(matrix)
            else:
                op.Set(matrix, code)
