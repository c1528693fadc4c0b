"""Decode a Virtual Bones asset into a USD point cache that any USD viewer plays.

``vbusd decode ASSET.usda -o CACHE.usda`` writes every bound mesh at its own prim path (the path it
had in the source, for converted assets) as an ordinary ``Mesh`` whose ``points``, ``normals`` and
``extent`` are time-sampled, one sample per texture row, on the source's timeline:

    time code of clip row i = (clip.startTime + i / clip.rowsPerSecond) * timeCodesPerSecond

so the cache and the source can be compared frame by frame. A looping clip gets one more sample
at its end (row N = row 0, the wrap the decoder plays), so the cache spans the source's whole
range. Bound meshes play clip 0 (spec, "Mesh binding"), or the clip chosen with ``clip``.

Crowds (``crowds=True``, ``vbusd decode --crowd``): for each point instancer and each bound mesh,
one mesh holding every instance (scale, orientation, position applied; each instance at its own
clip and clip-local time) at ``<instancer path>/<mesh name>``, sampled at clip 0's row times. The
stadium sample's 1,200 instances x 202 points x 513 samples make about 3 GB: decode crowds to
``.usdc`` and only when needed.

Transforms: the meshes' ancestors (and the meshes) keep the local transforms they have in the
asset (copied as one matrix op where authored), so world positions match the asset's.

Decoding uses the numpy reference decoder (:mod:`vbusd.decoders.reference`), or the warp decoder
(:mod:`vbusd.decoders.warp`) when a device is named and warp can be imported. Rows are decoded in
chunks so the temporary arrays stay small; the samples themselves live in the USD layer until it is
written. The cache is written through :class:`vbusd.io.files.Commit`: under the output's lock,
staged beside the target and renamed; a failure or a kill never leaves a partial cache in its
place, and the next run writing there removes what a killed one staged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from vbusd.format.errors import InputError, OptionsError
from vbusd.format.jsonform import json_ready
from vbusd.format.model import VirtualBones, VirtualBonesAsset
from vbusd.io.paths import check_output_path

__all__ = ["DEVICES", "DecodeReport", "row_times", "decode"]

DEVICES = ("cpu", "cuda")


@dataclass
class DecodeReport:
    """What :func:`decode` wrote.

    Attributes:
        asset: The Virtual Bones asset read.
        output: The point cache written.
        decoder: ``numpy reference`` or ``warp (<device>)``.
        meshes: Per mesh: path, points, samples, clip.
        start_time_code: First time code written.
        end_time_code: Last time code written.
        bytes: Size of the written cache.
        seconds: Wall time.
        warnings: Warnings (for example a fallback to numpy).
    """

    asset: str
    output: str
    decoder: str
    meshes: list = field(default_factory=list)
    start_time_code: float = 0.0
    end_time_code: float = 0.0
    bytes: int = 0
    seconds: float = 0.0
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """The report as ``vbusd decode --format json`` prints it: camelCase keys, times rounded
        (:func:`vbusd.format.jsonform.json_ready`)."""
        return json_ready(self)


def _skinner(device: Optional[str], warnings: list) -> tuple[Callable, Callable, str]:
    """(skin_mesh, skin_crowd, name): warp on ``device``, else the numpy reference decoder."""
    from vbusd.decoders import reference

    if device is None:
        return reference.skin_mesh, reference.skin_crowd, "numpy reference"
    if device not in DEVICES and not str(device).startswith("cuda:"):
        raise OptionsError(f"device must be cpu or cuda (or cuda:N), got {device!r}", file="decode")
    try:
        from vbusd.decoders import warp as warp_decoder
    except ImportError as error:
        warnings.append(f"warp is not available ({error}); decoding with the numpy reference decoder")
        return reference.skin_mesh, reference.skin_crowd, "numpy reference"

    def skin(vb, mesh, clip_index, tau):
        return warp_decoder.skin_mesh(vb, mesh, clip_index, tau, device=device)

    def skin_crowd(vb, mesh, crowd, t):
        return warp_decoder.skin_crowd(vb, mesh, crowd, t, device=device)

    return skin, skin_crowd, f"warp ({device})"


def _clip_index(vb: VirtualBones, clip) -> int:
    if clip is None:
        return 0
    names = [c.name for c in vb.clips]
    if str(clip) in names:
        return names.index(str(clip))
    try:
        index = int(clip)
    except (TypeError, ValueError):
        index = -1
    if 0 <= index < len(vb.clips):
        return index
    raise OptionsError(f"animation {vb.path} has no clip {clip!r} (clips: {', '.join(names)})", file="decode")


def row_times(vb: VirtualBones, clip_index: int) -> tuple[np.ndarray, np.ndarray]:
    """Clip-local times (s) of the samples written for a clip, and their source times (s).

    Every row, plus the wrap sample (row N = row 0) at the end of a looping clip.
    """
    clip = vb.clips[clip_index]
    count = clip.row_count + (1 if clip.loop and clip.row_count > 1 else 0)
    tau = np.arange(count, dtype=np.float64) / clip.rows_per_second
    return tau, clip.start_time + tau


def _snap(codes: np.ndarray) -> np.ndarray:
    """Time codes within 1e-9 of an integer become that integer (float noise of start + i / rate)."""
    nearest = np.round(codes)
    return np.where(np.abs(codes - nearest) <= 1e-9 * np.maximum(1.0, np.abs(codes)), nearest, codes)


def _source_transforms(asset_path: Path, paths, allow_outside_paths: bool) -> tuple:
    """The asset's local transforms of ``paths`` and their ancestors, and its frames per second.

    Read once, through the one USD reader (a host's open layer is not touched, USD's diagnostics
    are captured), before the long decode: ``{path: (resets, [(time code or None, matrix)])}`` for
    each Xformable prim that has a transform.
    """
    from pxr import Sdf, UsdGeom

    from vbusd.io.usd_reader import stage_for_reading

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


def _copy_transform(source, target_prim, UsdGeom) -> None:
    """Author a prim's local transform (one matrix op) from :func:`_source_transforms`' entry."""
    if source is None:
        return
    resets, samples = source
    target = UsdGeom.Xformable(target_prim)
    target.SetResetXformStack(resets)
    op = target.AddTransformOp()
    for code, matrix in samples:
        if code is None:
            op.Set(matrix)
        else:
            op.Set(matrix, code)


def decode(asset_path, output, *, device: Optional[str] = None, clip=None, force: bool = False,
           allow_outside_paths: bool = False, crowds: bool = False,
           progress: Optional[Callable] = None) -> DecodeReport:
    """Decode a Virtual Bones asset into a time-sampled USD point cache.

    Args:
        asset_path: The Virtual Bones USD asset.
        output: The cache to write (.usda, .usdc or .usd).
        device: None for the numpy reference decoder; ``cpu`` or ``cuda`` for the warp decoder.
        clip: Clip name or index to play on every animation (default: clip 0).
        force: Replace an existing output.
        allow_outside_paths: Let the asset reference files outside its folder.
        crowds: Also decode every crowd: per bound mesh, one mesh holding all instances at
            ``<crowd path>/<mesh name>``, sampled on clip 0's row times (large: instances x points
            x samples).
        progress: Optional ``progress(step, done, total)`` callback.

    Returns:
        A :class:`DecodeReport`.

    Raises:
        OptionsError: Bad options or output (before any work).
        InputError: The asset cannot be read.
    """
    started = time.perf_counter()
    asset_path, output = Path(asset_path), Path(output)
    check_output_path(asset_path, output, force=force, what="cache", source_what="asset")
    if asset_path.is_dir():
        raise InputError("is a folder, not a Virtual Bones USD asset", file=str(asset_path), code="file.kind")
    warnings: list = []
    skin, skin_crowd, decoder_name = _skinner(device, warnings)

    from pxr import Gf, Usd, UsdGeom, Vt

    from vbusd.io.usd import read_asset

    asset: VirtualBonesAsset = read_asset(asset_path, allow_outside_paths=allow_outside_paths)
    placed = [m.path for vb in asset.animations for m in vb.meshes] + [c.path + "/x" for c in asset.crowds]
    transforms, source_fps = _source_transforms(asset_path, placed, allow_outside_paths)
    tcps = float(asset.time_codes_per_second)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if asset.up_axis == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(asset.meters_per_unit))
    stage.SetTimeCodesPerSecond(tcps)
    stage.SetFramesPerSecond(float(asset.extra.get("frames_per_second", source_fps)))

    report = DecodeReport(asset=str(asset_path), output=str(output), decoder=decoder_name, warnings=warnings)
    first_code, last_code = np.inf, -np.inf
    total = sum(len(vb.meshes) for vb in asset.animations)
    done = 0
    for vb in asset.animations:
        clip_index = _clip_index(vb, clip)
        tau, seconds = row_times(vb, clip_index)
        codes = _snap(seconds * tcps)
        first_code, last_code = min(first_code, float(codes[0])), max(last_code, float(codes[-1]))
        if vb.lods is not None:
            from vbusd.io.usd_lod import author_lod_root

            # Levels of detail: the cache keeps the UsdLod root, so a viewer draws one level.
            author_lod_root(stage, vb.lods, vb.clip_extents)
        for mesh in vb.meshes:
            _define_path(stage, transforms, mesh.path, UsdGeom)
            prim = UsdGeom.Mesh.Define(stage, mesh.path)
            _copy_transform(transforms.get(mesh.path), prim.GetPrim(), UsdGeom)
            prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_counts, np.int32)))
            prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_indices, np.int32)))
            prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            points_attr = prim.CreatePointsAttr()
            extent_attr = prim.CreateExtentAttr()
            normals_attr = None
            if mesh.normals is not None:
                normals_attr = prim.CreateNormalsAttr()
                prim.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying if mesh.normals_interpolation == "faceVarying"
                                             else UsdGeom.Tokens.vertex)
            chunk = max(1, int(4_000_000 // max(1, mesh.points.shape[0] * mesh.max_influences)))
            for start in range(0, tau.size, chunk):
                part = slice(start, min(tau.size, start + chunk))
                points, normals = skin(vb, mesh, clip_index, tau[part])
                points = np.asarray(points, dtype=np.float32)
                for j, code in enumerate(codes[part]):
                    code = Usd.TimeCode(float(code))
                    points_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points[j])), code)
                    low, high = points[j].min(axis=0), points[j].max(axis=0)
                    extent_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, low)), Gf.Vec3f(*map(float, high))]), code)
                    if normals_attr is not None and normals is not None:
                        normals_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals[j], dtype=np.float32)),
                                         code)
            report.meshes.append({"path": mesh.path, "points": int(mesh.points.shape[0]), "samples": int(tau.size),
                                  "clip": vb.clips[clip_index].name, "animation": vb.path,
                                  "normals": normals_attr is not None})
            done += 1
            if progress:
                progress("decode", done, total)
    if crowds:
        for crowd, animation_index in zip(asset.crowds, asset.crowd_animation):
            vb = asset.animations[animation_index]
            codes = _snap(row_times(vb, 0)[1] * tcps)
            first_code, last_code = min(first_code, float(codes[0])), max(last_code, float(codes[-1]))
            report.meshes.extend(_decode_crowd(stage, transforms, vb, crowd, codes, tcps, skin_crowd))
    if not report.meshes:
        raise OptionsError("the asset has no bound mesh to decode", file=str(asset_path))
    stage.SetStartTimeCode(first_code)
    stage.SetEndTimeCode(last_code)
    default = asset.default_prim
    if default and stage.GetPrimAtPath(f"/{default}"):
        stage.SetDefaultPrim(stage.GetPrimAtPath(f"/{default}"))
    stage.GetRootLayer().documentation = f"Point cache decoded by vbusd from {asset_path.name} ({decoder_name})"

    from vbusd.io.usd import write_layer

    # One commit (spec, "File names and the write guarantee"): under the output's lock, the cache
    # is staged beside the target and one rename makes it current; a run killed half way leaves a
    # staged file that the next run writing there removes.
    write_layer(stage.GetRootLayer(), output, replace=force, what="point cache", code="decode.write")
    report.start_time_code, report.end_time_code = first_code, last_code
    report.bytes = output.stat().st_size
    report.seconds = round(time.perf_counter() - started, 4)
    return report


def _decode_crowd(stage, transforms: dict, vb: VirtualBones, crowd, codes: np.ndarray, tcps: float,
                  skin_crowd: Callable) -> list:
    """Write one mesh per bound mesh holding every instance of ``crowd``, time-sampled at ``codes``.

    Points are in the instancer's space (scale, orientation, position applied per instance, as the
    spec's "Instancing" places them); the crowd prim keeps the instancer's path and transform.
    """
    from pxr import Gf, Usd, UsdGeom, Vt

    # The crowd prim and its ancestors, each with the asset's transform (copied once).
    _define_path(stage, transforms, crowd.path + "/x", UsdGeom)
    count = crowd.instance_count
    written = []
    for mesh in vb.meshes:
        path = f"{crowd.path}/{mesh.path.rsplit('/', 1)[-1]}"
        prim = UsdGeom.Mesh.Define(stage, path)
        vertices = mesh.points.shape[0]
        counts = np.tile(np.asarray(mesh.face_vertex_counts, np.int32), count)
        offsets = np.repeat(np.arange(count, dtype=np.int64) * vertices, len(mesh.face_vertex_indices))
        indices = (np.tile(np.asarray(mesh.face_vertex_indices, np.int64), count) + offsets).astype(np.int32)
        prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(counts)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(indices)))
        prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        points_attr, extent_attr = prim.CreatePointsAttr(), prim.CreateExtentAttr()
        normals_attr = None
        if mesh.normals is not None:
            normals_attr = prim.CreateNormalsAttr()
            prim.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying if mesh.normals_interpolation == "faceVarying"
                                         else UsdGeom.Tokens.vertex)
        for code in codes:
            points, normals = skin_crowd(vb, mesh, crowd, float(code) / tcps)
            flat = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
            time = Usd.TimeCode(float(code))
            points_attr.Set(Vt.Vec3fArray.FromNumpy(flat), time)
            low, high = flat.min(axis=0), flat.max(axis=0)
            extent_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, low)), Gf.Vec3f(*map(float, high))]), time)
            if normals_attr is not None and normals is not None:
                normals_attr.Set(Vt.Vec3fArray.FromNumpy(
                    np.ascontiguousarray(np.asarray(normals, dtype=np.float32).reshape(-1, 3))), time)
        written.append({"path": path, "points": int(vertices * count), "samples": int(len(codes)),
                        "clip": "per instance", "animation": vb.path, "normals": normals_attr is not None,
                        "instances": int(count)})
    return written


def _define_path(stage, transforms: dict, path: str, UsdGeom) -> None:
    """Define the ancestors of ``path`` as Xforms carrying the asset's transforms."""
    from pxr import Sdf

    for ancestor in Sdf.Path(path).GetParentPath().GetPrefixes():
        if stage.GetPrimAtPath(ancestor):
            continue
        prim = UsdGeom.Xform.Define(stage, ancestor).GetPrim()
        _copy_transform(transforms.get(str(ancestor)), prim, UsdGeom)
