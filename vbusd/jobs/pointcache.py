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
``.usdc`` and only when needed. Before it decodes anything, :func:`decode` adds up what the cache
will hold (:func:`cache_bytes`) and refuses, naming the bytes, when that exceeds ``max_memory``
(``vbusd decode --max-memory``; by default the memory available,
:func:`vbusd.process.memory.available_memory`), and refuses a crowd mesh of more points than USD's
32-bit face-vertex indices address.

Transforms: the meshes' ancestors (and the meshes) keep the local transforms they have in the
asset (copied as one matrix op where authored), so world positions match the asset's.

Decoding uses the numpy reference decoder (:mod:`vbusd.decoders.reference`), or the warp decoder
(:mod:`vbusd.decoders.warp`) when a device is named and warp can be imported. Rows are decoded in
chunks so the temporary arrays stay small; the samples themselves live in the USD layer until it is
written. This module decodes; the layer is authored by :class:`vbusd.io.usd_pointcache.PointCache`
and written through :class:`vbusd.io.files.Commit`: under the output's lock, staged beside the
target and renamed; a failure or a kill never leaves a partial cache in its place, and the next run
writing there removes what a killed one staged.
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
from vbusd.io.usd import read_asset
from vbusd.io.usd_pointcache import PointCache, source_transforms
from vbusd.decoders import reference
from vbusd.process.memory import available_memory, human_bytes

__all__ = ["DEVICES", "DecodeReport", "row_times", "cache_bytes", "decode"]

DEVICES = ("cpu", "cuda")

MAX_MESH_POINTS = 2**31 - 1
"""The most points one cache mesh may have: USD's ``faceVertexIndices`` are 32-bit integers."""

_SAMPLE_BYTES_PER_POINT = 12
"""A time sample of ``points`` (or of ``normals``) holds three float32 per point."""

_TOPOLOGY_BYTES = 4
"""``faceVertexCounts`` and ``faceVertexIndices`` hold one int32 per face and per face-vertex."""


_ALLOCATOR_OVERHEAD = 1.3
"""What the process's heap grows by per byte of samples kept: the samples are freed temporaries'
neighbours, and glibc's allocator measured 1.26 (400 stadium spectators: 949 MiB of samples, the
process 1,191 MiB larger)."""


def _working_bytes_per_point(mesh) -> int:
    """An upper bound of what skinning one sample takes per point, beyond its result: the numpy
    reference's temporaries measure about 260 bytes per point with 4 influences (float64 positions,
    normals and a weighted sum per influence)."""
    return 64 * (int(mesh.max_influences) + 1)


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


def cache_bytes(asset: VirtualBonesAsset, clip=None, crowds: bool = False) -> int:
    """The memory a point cache of ``asset`` takes while it is built: every time sample of every
    mesh's points and normals (float32) and every mesh's topology (int32), which the USD layer holds
    until it is written (with the allocator's overhead), plus the largest one sample's skinning takes
    (see :func:`_working_bytes_per_point`). With ``crowds``: one mesh of all instances per crowd and mesh,
    ``instances x points x samples x 24`` bytes with normals."""

    def mesh_bytes(mesh, copies: int, samples: int) -> tuple[int, int]:
        points = int(mesh.points.shape[0]) * copies
        per_sample = _SAMPLE_BYTES_PER_POINT * (2 if mesh.normals is not None else 1)
        topology = _TOPOLOGY_BYTES * (len(mesh.face_vertex_counts) + len(mesh.face_vertex_indices)) * copies
        # Building the topology takes its int32 arrays twice (the pattern repeated, then the copy
        # USD keeps); skinning one sample takes the working bytes per point.
        transient = max(topology, _working_bytes_per_point(mesh) * points)
        return points * per_sample * samples + topology, transient

    held, transient = 0, 0
    for vb in asset.animations:
        samples = row_times(vb, _clip_index(vb, clip))[0].size
        for mesh in vb.meshes:
            kept, extra = mesh_bytes(mesh, 1, samples)
            held, transient = held + kept, max(transient, extra)
    if crowds:
        for crowd, index in zip(asset.crowds, asset.crowd_animation):
            vb = asset.animations[index]
            samples = row_times(vb, 0)[0].size
            for mesh in vb.meshes:
                kept, extra = mesh_bytes(mesh, int(crowd.instance_count), samples)
                held, transient = held + kept, max(transient, extra)
    return int(held * _ALLOCATOR_OVERHEAD) + transient


def _check_size(asset: VirtualBonesAsset, asset_path: Path, clip, crowds: bool,
                max_memory: Optional[int]) -> None:
    """Refuse, before decoding, a cache that would not fit ``max_memory`` (default: the memory
    available) or a crowd mesh with more points than USD indexes."""
    if crowds:
        for crowd, index in zip(asset.crowds, asset.crowd_animation):
            for mesh in asset.animations[index].meshes:
                points = int(crowd.instance_count) * int(mesh.points.shape[0])
                if points > MAX_MESH_POINTS:
                    raise OptionsError(
                        f"--crowd: {crowd.path} would decode into one mesh of {points:,} points "
                        f"({crowd.instance_count:,} instances x {mesh.points.shape[0]:,}), more than USD's 32-bit "
                        f"face-vertex indices address ({MAX_MESH_POINTS:,})", file=str(asset_path),
                        code="decode.memory")
    need = cache_bytes(asset, clip, crowds)
    bound = max_memory if max_memory is not None else available_memory()
    if bound is not None and need > bound:
        if max_memory is not None:
            limit = f"--max-memory {human_bytes(bound)} ({bound:,} bytes)"
            hint = "decode fewer instances or samples, or raise --max-memory where the memory is there"
        else:
            limit = f"the {human_bytes(bound)} ({bound:,} bytes) available"
            hint = "decode fewer instances or samples, or on a machine with more memory"
        raise OptionsError(f"the point cache{' with --crowd' if crowds else ''} needs {human_bytes(need)} "
                           f"({need:,} bytes) in memory, more than {limit}; {hint}", file=str(asset_path),
                           code="decode.memory")


def decode(asset_path, output, *, device: Optional[str] = None, clip=None, force: bool = False,
           allow_outside_paths: bool = False, crowds: bool = False, max_memory: Optional[int] = None,
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
        max_memory: The most bytes the cache may take while it is built (:func:`cache_bytes`);
            None: the memory available (:func:`vbusd.process.memory.available_memory`).
        progress: Optional ``progress(step, done, total)`` callback.

    Returns:
        A :class:`DecodeReport`.

    Raises:
        OptionsError: Bad options or output (before any work); a cache that would not fit
            ``max_memory`` (code ``decode.memory``, before any decoding).
        InputError: The asset cannot be read; it has no bound mesh (``decode.noMeshes``: nothing to
            decode, though the asset may be valid).
    """
    started = time.perf_counter()
    asset_path, output = Path(asset_path), Path(output)
    check_output_path(asset_path, output, force=force, what="cache", source_what="asset")
    if asset_path.is_dir():
        raise InputError("is a folder, not a Virtual Bones USD asset", file=str(asset_path), code="file.kind")
    warnings: list = []
    skin, skin_crowd, decoder_name = _skinner(device, warnings)

    if max_memory is not None and (isinstance(max_memory, bool) or not isinstance(max_memory, int)
                                   or max_memory <= 0):
        raise OptionsError(f"max_memory must be a positive number of bytes, got {max_memory!r}", file="decode")
    asset: VirtualBonesAsset = read_asset(asset_path, allow_outside_paths=allow_outside_paths)
    for vb in asset.animations:
        _clip_index(vb, clip)  # a clip no animation has: one line before the size is reckoned
    _check_size(asset, asset_path, clip, crowds, max_memory)
    placed = [m.path for vb in asset.animations for m in vb.meshes] + [c.path + "/x" for c in asset.crowds]
    transforms, source_fps = source_transforms(asset_path, placed, allow_outside_paths)
    tcps = float(asset.time_codes_per_second)
    cache = PointCache(up_axis=asset.up_axis, meters_per_unit=asset.meters_per_unit, time_codes_per_second=tcps,
                       frames_per_second=asset.extra.get("frames_per_second", source_fps), transforms=transforms)

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
            cache.lod_root(vb.lods, vb.clip_extents)  # the cache keeps the UsdLod root: a viewer draws one level
        for mesh in vb.meshes:
            samples = cache.mesh(mesh.path, mesh.face_vertex_counts, mesh.face_vertex_indices,
                                 normals_interpolation=None if mesh.normals is None else mesh.normals_interpolation)
            chunk = max(1, int(4_000_000 // max(1, mesh.points.shape[0] * mesh.max_influences)))
            for start in range(0, tau.size, chunk):
                part = slice(start, min(tau.size, start + chunk))
                points, normals = skin(vb, mesh, clip_index, tau[part])
                points = np.asarray(points, dtype=np.float32)
                for j, code in enumerate(codes[part]):
                    samples.set(code, points[j], None if normals is None else normals[j])
            report.meshes.append({"path": mesh.path, "points": int(mesh.points.shape[0]), "samples": int(tau.size),
                                  "clip": vb.clips[clip_index].name, "animation": vb.path,
                                  "normals": samples.has_normals})
            done += 1
            if progress:
                progress("decode", done, total)
    if crowds:
        for crowd, animation_index in zip(asset.crowds, asset.crowd_animation):
            vb = asset.animations[animation_index]
            codes = _snap(row_times(vb, 0)[1] * tcps)
            first_code, last_code = min(first_code, float(codes[0])), max(last_code, float(codes[-1]))
            report.meshes.extend(_decode_crowd(cache, vb, crowd, codes, tcps, skin_crowd))
    if not report.meshes:
        # Not a verdict on the asset (an animation needs no bound mesh: validate calls it valid); the
        # job has nothing to write (usd-conversion.md 10), as export has nothing to export.
        raise InputError("the asset has no mesh bound to an animation: there is nothing to decode",
                         file=str(asset_path), location="file", code="decode.noMeshes")
    # One commit (spec, "File names and the write guarantee"): under the output's lock, the cache
    # is staged beside the target and one rename makes it current; a run killed half way leaves a
    # staged file that the next run writing there removes.
    cache.write(output, start=first_code, end=last_code, default_prim=asset.default_prim,
                documentation=f"Point cache decoded by vbusd from {asset_path.name} ({decoder_name})",
                replace=force, code="decode.write")
    report.start_time_code, report.end_time_code = first_code, last_code
    report.bytes = output.stat().st_size
    report.seconds = round(time.perf_counter() - started, 4)
    return report


def _decode_crowd(cache: PointCache, vb: VirtualBones, crowd, codes: np.ndarray, tcps: float,
                  skin_crowd: Callable) -> list:
    """Write one mesh per bound mesh holding every instance of ``crowd``, time-sampled at ``codes``.

    Points are in the instancer's space (scale, orientation, position applied per instance, as the
    spec's "Instancing" places them); the crowd prim keeps the instancer's path and transform.
    """
    cache.group(crowd.path)  # the crowd prim and its ancestors, with the asset's transforms
    count = crowd.instance_count
    written = []
    for mesh in vb.meshes:
        path = f"{crowd.path}/{mesh.path.rsplit('/', 1)[-1]}"
        vertices = mesh.points.shape[0]
        counts = np.tile(np.asarray(mesh.face_vertex_counts, np.int32), count)
        # int32 throughout (count x vertices fits: _check_size), instance i's indices offset by i x vertices
        indices = (np.asarray(mesh.face_vertex_indices, np.int32)[None, :]
                   + (np.arange(count, dtype=np.int32) * np.int32(vertices))[:, None]).ravel()
        samples = cache.mesh(path, counts, indices, transformed=False,
                             normals_interpolation=None if mesh.normals is None else mesh.normals_interpolation)
        for code in codes:
            points, normals = skin_crowd(vb, mesh, crowd, float(code) / tcps)
            samples.set(code, points, normals)
        written.append({"path": path, "points": int(vertices * count), "samples": int(len(codes)),
                        "clip": "per instance", "animation": vb.path, "normals": samples.has_normals,
                        "instances": int(count)})
    return written
