"""Bake a :class:`~vbusd.format.model.SkinnedAnimation` into a :class:`~vbusd.format.model.VirtualBones` texture.

The baker decides the rows of every clip (rate, looping, vertical power-of-two fill), samples the
source's skinning matrices at those rows, encodes, quantizes and packs them, and binds the meshes
with at most ``max_influences`` bone influences per vertex. It touches no file.
"""

from __future__ import annotations

import dataclasses

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.encoding import (Float16OverflowError, NonRigidError, affine_singular, dequantize, encode_bones,
                       make_hemispheres_continuous, quantize, unpack, all_finite)
from vbusd.format.errors import InputError, OptionsError, UnsupportedError
from vbusd.format.layout import Encoding, Layout, Padding, TexelFormat, next_power_of_two
from vbusd.format.model import AnimationClip, BoundMesh, Clip, SkinnedAnimation, SkinnedMesh, VirtualBones
from vbusd.kernels import bake as bake_kernels
from vbusd.baking.rootmotion import in_place_clip
from vbusd.format.rootmotion import RootMotion, check_mode
from vbusd.format.motion import motion_problems
from vbusd.decoders.bounds import clip_extents

__all__ = ["DEFAULT_ROWS_PER_SECOND", "BakeOptions", "bone_masks", "check_motion", "RowPlan", "decide_loop", "plan_rows",
           "reduce_influences", "bind_mesh", "bake"]

DEFAULT_ROWS_PER_SECOND = 30.0
"""Rows per second when neither the options nor the source say (a clip without native_rate)."""


@dataclass(frozen=True)
class BakeOptions:
    """How to bake; checked on construction, before any work starts.

    Attributes:
        encoding: Bone transform encoding.
        texel_format: Channel storage.
        rows_per_second: Rows per second of every clip; None keeps each clip's native rate.
        horizontal_padding: ``powerOfTwo`` (default) or ``none``.
        vertical_padding: ``none`` (default) or ``powerOfTwo``: clips are resampled so their rows
            fill the next power of two.
        max_influences: Largest number of bone influences kept per vertex (K).
        loop: Force looping (True) or clamping (False) for every clip; None decides per clip
            (the clip's own flag, else looping when its first and last poses agree).
        rigid_tolerance: How far a linear part may be from a rotation (crossMatrix, dualQuat) or a
            uniformly scaled rotation (quatTranslation) before baking refuses it.
        loop_tolerance: Largest matrix difference, relative to the pose's size, for which the first
            and last poses count as equal when deciding to loop.
    """

    encoding: Encoding = Encoding.CROSS_MATRIX
    texel_format: TexelFormat = TexelFormat.FLOAT16
    rows_per_second: Optional[float] = None
    horizontal_padding: Padding = Padding.POWER_OF_TWO
    vertical_padding: Padding = Padding.NONE
    max_influences: int = 4
    loop: Optional[bool] = None
    rigid_tolerance: float = 1e-3
    loop_tolerance: float = 1e-5
    root_motion: str = "keep"
    up_axis: str = "Y"
    masks: tuple = ()
    """Format 1.2: ``(name, bone)`` pairs, each a bone mask of ``bone`` and every bone below it
    (spec "Layers and bone masks"; ``vbusd convert --mask NAME=BONE``)."""
    blend_spaces: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.BlendSpace` objects (spec 23; ``vbusd convert --blend-space``)."""
    markers: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.Marker` objects (spec 23.4; ``vbusd convert --marker``)."""

    def __post_init__(self) -> None:
        for name, kind in (("encoding", Encoding), ("texel_format", TexelFormat),
                           ("horizontal_padding", Padding), ("vertical_padding", Padding)):
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, kind(value))
            except ValueError:
                allowed = ", ".join(e.value for e in kind)
                raise OptionsError(f"{name} must be one of {allowed}, got {value!r}", file="bake") from None
        rate = self.rows_per_second
        if rate is not None and (isinstance(rate, bool) or not math.isfinite(float(rate)) or float(rate) <= 0):
            raise OptionsError(f"rows_per_second must be a positive number, got {rate!r}", file="bake")
        k = self.max_influences
        if isinstance(k, bool) or int(k) != k or not 1 <= int(k) <= 64:
            raise OptionsError(f"max_influences must be an integer in 1..64, got {k!r}", file="bake")
        for name in ("rigid_tolerance", "loop_tolerance"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise OptionsError(f"{name} must be a non-negative number, got {value!r}", file="bake")


@dataclass(frozen=True)
class RowPlan:
    """Rows chosen for one clip: count, rate and looping."""

    row_count: int
    rows_per_second: float
    loop: bool


def _poses_agree(first: np.ndarray, last: np.ndarray, tolerance: float) -> bool:
    scale = max(1.0, float(np.abs(first).max(initial=0.0)))
    return float(np.abs(first - last).max(initial=0.0)) <= tolerance * scale


def decide_loop(clip: AnimationClip, options: BakeOptions) -> bool:
    """Whether ``clip`` loops: the options' flag, else the clip's, else first pose == last pose."""
    if options.loop is not None:
        return bool(options.loop) and clip.duration > 0
    if clip.loop is not None:
        return bool(clip.loop) and clip.duration > 0
    if clip.duration <= 0:
        return False
    ends = clip.sample(np.array([clip.start_time, clip.end_time], dtype=np.float64))
    return _poses_agree(ends[0], ends[1], options.loop_tolerance)


def plan_rows(clips: tuple, loops: list, options: BakeOptions) -> list:
    """Choose each clip's row count and rate (spec: "Clips" and "Vertical padding").

    A looping clip of duration D at rate r gets N = round(D r) rows spanning D exactly (rate N/D);
    a clamped clip gets round(D r) + 1 rows from its first to its last pose (rate (N-1)/D). With
    vertical powerOfTwo padding, the spans are scaled so that all rows together fill the next power
    of two, distributed by duration with largest remainders.
    """
    rates = [float(options.rows_per_second or clip.native_rate or DEFAULT_ROWS_PER_SECOND) for clip in clips]
    durations = [max(0.0, clip.duration) for clip in clips]
    spans = [max(1, round(d * r)) if d > 0 else 0 for d, r in zip(durations, rates)]
    fixed = sum(0 if loop else 1 for loop in loops)  # a clamped clip has one row more than spans
    total = sum(spans) + fixed
    if options.vertical_padding is Padding.POWER_OF_TWO:
        target_spans = next_power_of_two(total) - fixed
        moving = [i for i, d in enumerate(durations) if d > 0]
        if moving and target_spans > sum(spans):
            weight = sum(durations[i] for i in moving)
            exact = {i: target_spans * durations[i] / weight for i in moving}
            new = {i: max(1, math.floor(exact[i])) for i in moving}
            # Raising tiny clips to one span can overshoot the target: take the rows back from the
            # clips that got the most above their exact share.
            while sum(new.values()) > target_spans:
                donors = [i for i in moving if new[i] > 1]
                if not donors:
                    break
                new[max(donors, key=lambda i: new[i] - exact[i])] -= 1
            leftover = target_spans - sum(new.values())
            for i in sorted(moving, key=lambda i: exact[i] - math.floor(exact[i]), reverse=True):
                if leftover <= 0:
                    break
                new[i] += 1
                leftover -= 1
            for i in moving:
                spans[i] = new[i]
    plans = []
    for span, duration, loop, rate in zip(spans, durations, loops, rates):
        if duration <= 0:
            plans.append(RowPlan(1, rate, False))
        elif loop:
            plans.append(RowPlan(span, span / duration, True))
        else:
            plans.append(RowPlan(span + 1, span / duration, False))
    return plans


def reduce_influences(indices: np.ndarray, weights: np.ndarray, max_influences: int,
                      *, mesh: str = "mesh") -> tuple[np.ndarray, np.ndarray, float]:
    """Keep the largest ``max_influences`` weights per vertex and renormalize.

    Args:
        indices: (V, K) bone indices.
        weights: (V, K) weights.
        max_influences: K' to keep.
        mesh: Mesh path, for messages.

    Returns:
        (indices (V, K''), weights (V, K''), largest weight fraction dropped from one vertex) where
        K'' = min(K, K'). Ties keep the lower influence slot. Unused slots get bone 0, weight 0.

    Raises:
        InputError: Weights are negative, not finite, or all zero for a vertex.
    """
    idx = np.asarray(indices, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)
    if idx.shape != w.shape or idx.ndim != 2:
        raise InputError(f"bone indices {idx.shape} and weights {w.shape} must be (V, K) alike", location=mesh,
                         code="binding.count")
    if not np.all(np.isfinite(w)):
        vertex = int(np.argwhere(~np.isfinite(w))[0][0])
        raise InputError(f"vertex {vertex} has a NaN or infinite weight", location=mesh, code="binding.weights.negative")
    if np.any(w < 0):
        vertex = int(np.argwhere(w < 0)[0][0])
        raise InputError(f"vertex {vertex} has a negative weight {w[vertex].min():g}", location=mesh,
                         code="binding.weights.negative")
    totals = w.sum(axis=1)
    if np.any(totals <= 0):
        raise InputError(f"vertex {int(np.argmax(totals <= 0))} has only zero weights", location=mesh,
                         code="binding.weights.sum")
    w = w / totals[:, None]
    keep = min(idx.shape[1], max_influences)
    order = np.argsort(-w, axis=1, kind="stable")[:, :keep]
    kept_w = np.take_along_axis(w, order, axis=1)
    kept_i = np.take_along_axis(idx, order, axis=1)
    kept_total = kept_w.sum(axis=1)
    dropped = float((1.0 - kept_total).max(initial=0.0))
    kept_w = kept_w / kept_total[:, None]
    kept_i = np.where(kept_w > 0, kept_i, 0)
    return kept_i.astype(np.int32), kept_w.astype(np.float32), max(dropped, 0.0)


def bind_mesh(mesh: SkinnedMesh, bone_count: int, max_influences: int) -> BoundMesh:
    """Turn a source mesh into a :class:`BoundMesh` with at most ``max_influences`` influences.

    Raises:
        InputError: Bone indices out of range, mismatched counts, non-finite points.
    """
    points = np.asarray(mesh.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must be (V, 3), got {points.shape}", location=mesh.path, code="binding.mesh")
    if not np.all(np.isfinite(points)):
        raise InputError("points contain NaN or infinity", location=mesh.path, code="binding.points.nonFinite")
    idx = np.asarray(mesh.bone_indices)
    if idx.shape[0] != points.shape[0]:
        raise InputError(f"{idx.shape[0]} influence rows for {points.shape[0]} points", location=mesh.path,
                         code="binding.count")
    if idx.size and (idx.min() < 0 or idx.max() >= bone_count):
        bad = int(idx.max() if idx.max() >= bone_count else idx.min())
        raise InputError(f"bone index {bad} out of range 0..{bone_count - 1}", location=mesh.path,
                         code="binding.indices.range")
    indices, weights, _ = reduce_influences(idx, mesh.bone_weights, max_influences, mesh=mesh.path)
    normals = None if mesh.normals is None else np.asarray(mesh.normals, dtype=np.float32)
    return BoundMesh(
        path=mesh.path, points=points.astype(np.float32),
        face_vertex_counts=np.asarray(mesh.face_vertex_counts, dtype=np.int32),
        face_vertex_indices=np.asarray(mesh.face_vertex_indices, dtype=np.int32),
        bone_indices=indices, bone_weights=weights, normals=normals,
        normals_interpolation=mesh.normals_interpolation, lod=int(getattr(mesh, "lod", 0)))


def _locate_non_rigid(error: NonRigidError, animation: SkinnedAnimation, clip: AnimationClip,
                      times: np.ndarray) -> UnsupportedError:
    row, bone = error.index[0], error.index[1]
    name = animation.bones[bone]
    message = (f"bone '{name}' at time {times[row]:.6g} s of clip '{clip.name}': {error.message}")
    return UnsupportedError(message, file=animation.source, location=animation.path,
                            code="encoding.nonRigid")


def _locate_float16_overflow(error, animation: SkinnedAnimation, clips: list) -> UnsupportedError:
    row, bone = error.index[0], error.index[1]
    clip = next(c for c in clips if c.first_row <= row < c.first_row + c.row_count)
    time = clip.row_time(row - clip.first_row)
    return UnsupportedError(f"bone '{animation.bones[bone]}' at time {time:.6g} s of clip '{clip.name}': "
                            f"{error.message}", file=animation.source, location=animation.path,
                            code="encoding.float16Overflow")


def _refuse_singular_after_rounding(stored, ranges, texel_format, animation: SkinnedAnimation,
                                    clips: list) -> None:
    """Refuse affine bones that rounding to the texel format made singular (e.g. a tiny scale in float16).

    encode_bones checked the exact matrices; a decoder and the validator see the stored ones.
    """
    linear = dequantize(stored, texel_format, ranges)[..., :3]  # (rows, B, 3 texels = rows of A, 3)
    singular = affine_singular(linear)
    if not np.any(singular):
        return
    row, bone = (int(i) for i in np.argwhere(singular)[0])
    clip = next(c for c in clips if c.first_row <= row < c.first_row + c.row_count)
    raise UnsupportedError(
        f"bone '{animation.bones[bone]}' at time {clip.row_time(row - clip.first_row):.6g} s of clip "
        f"'{clip.name}': affineMatrix cannot hold a singular (zero-scaled) matrix once rounded to "
        f"{texel_format.value}", file=animation.source, location=animation.path, code="encoding.nonRigid")


def bake(animation: SkinnedAnimation, options: BakeOptions = BakeOptions()) -> VirtualBones:
    """Bake one skinned animation into a Virtual Bones texture with its bound meshes.

    Args:
        animation: The converter's output for one skeleton.
        options: How to bake.

    Returns:
        The baked animation: layout, packed texels, clips, bound meshes and per-clip extents.

    Raises:
        UnsupportedError: The encoding or texel format cannot hold the animation (names the bone,
            time and clip).
        InputError: Bad mesh bindings.
    """
    if not animation.clips:
        raise InputError("the animation has no clip to bake", file=animation.source, location=animation.path,
                         code="animation.noClip")
    bone_count = animation.bone_count
    # Masks are resolved before any pose is sampled: a misspelt bone fails at once.
    parents, masks = bone_masks(animation, options.masks) if options.masks else (None, ())
    if options.blend_spaces and parents is None:
        # Blend spaces blend in local space (spec 23.1): they need the hierarchy as masks do.
        if animation.bone_parents is None or animation.bind_transforms is None:
            raise OptionsError("--blend-space needs the bones' hierarchy and bind transforms, which this "
                               "source's converter does not give", file=animation.source, location=animation.path,
                               code="convert.blendSpace")
        parents = tuple(int(p) for p in animation.bone_parents)
    trackers = None

    mode = check_mode(options.root_motion)
    if mode != "keep":
        # Root motion (spec "Root motion"): bake every clip in place, keep the root track apart.
        bind_root = np.eye(4) if animation.bind_transforms is None else np.asarray(animation.bind_transforms[0])
        wrapped = [in_place_clip(clip, 0, bind_root, options.up_axis, mode == "extractYaw")
                   for clip in animation.clips]
        animation = dataclasses.replace(animation, clips=tuple(w[0] for w in wrapped))
        trackers = [w[1] for w in wrapped]
    loops = [decide_loop(clip, options) for clip in animation.clips]
    plans = plan_rows(animation.clips, loops, options)
    # The layout checks the texture size before anything is sampled: an absurd rate must not
    # allocate first.
    try:
        layout = Layout(options.encoding, options.texel_format, bone_count, sum(p.row_count for p in plans),
                        options.horizontal_padding, options.vertical_padding)
    except OptionsError as error:
        rows = ", ".join(f"'{c.name}' {p.row_count} rows at {p.rows_per_second:g}/s"
                         for c, p in zip(animation.clips, plans))
        raise UnsupportedError(f"{error.message} ({rows})", file=animation.source, location=animation.path,
                               code="layout.size") from None
    try:
        meshes = tuple(bind_mesh(m, bone_count, options.max_influences) for m in animation.meshes)
    except InputError as error:
        raise error.at(file=animation.source)

    values, clips, extents, first_row = [], [], [], 0
    for clip, plan in zip(animation.clips, plans):
        times = clip.start_time + np.arange(plan.row_count, dtype=np.float64) / plan.rows_per_second
        matrices = np.asarray(clip.sample(times), dtype=np.float64)
        if matrices.shape != (plan.row_count, bone_count, 4, 4):
            raise InputError(f"clip '{clip.name}' sampled {matrices.shape}, expected "
                             f"{(plan.row_count, bone_count, 4, 4)}", file=animation.source,
                             location=animation.path, code="animation.sampleShape")
        if not all_finite(matrices):
            row, bone = (int(i) for i in np.argwhere(~np.isfinite(matrices))[0][:2])
            raise InputError(f"bone '{animation.bones[bone]}' has a NaN or infinite transform at "
                             f"{times[row]:.6g} s of clip '{clip.name}'", file=animation.source,
                             location=animation.path, code="animation.nonFinite")
        try:
            encoded = encode_bones(matrices, options.encoding, tolerance=options.rigid_tolerance, compiled=bake_kernels)
        except NonRigidError as error:
            raise _locate_non_rigid(error, animation, clip, times) from None
        values.append(make_hemispheres_continuous(encoded, options.encoding))
        # Zero boxes without meshes; with meshes they come from the decoded texels below.
        extents.append(np.zeros((2, 3), np.float32))
        clips.append(Clip(name=clip.name, first_row=first_row, row_count=plan.row_count,
                          rows_per_second=plan.rows_per_second, loop=plan.loop,
                          start_time=float(clip.start_time)))
        first_row += plan.row_count

    # Quantized straight into the zero-padded texture (no separate array of stored values to pack).
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    try:
        stored, ranges = quantize(values[0] if len(values) == 1 else np.concatenate(values, axis=0),
                                  options.texel_format, out=unpack(texels, layout))
    except Float16OverflowError as error:
        raise _locate_float16_overflow(error, animation, clips) from None
    except UnsupportedError as error:
        raise error.at(file=animation.source, location=animation.path)
    if options.encoding is Encoding.AFFINE_MATRIX:
        _refuse_singular_after_rounding(stored, ranges, options.texel_format, animation, clips)
    texels.setflags(write=False)
    bind = None if animation.bind_transforms is None else np.asarray(animation.bind_transforms, np.float64)
    motion = None
    if trackers is not None:
        tracks = []
        for clip, plan, track in zip(animation.clips, plans, trackers):
            entries = plan.row_count + (1 if plan.loop else 0)
            tracks.append(track(clip.start_time + np.arange(entries, dtype=np.float64) / plan.rows_per_second))
        motion = RootMotion(options.up_axis, tuple(tracks))
    check_motion(options.blend_spaces, options.markers, clips, animation)
    baked = VirtualBones(layout=layout, texels=texels, bones=tuple(animation.bones), clips=tuple(clips),
                         unorm_ranges=ranges, meshes=meshes, path=animation.path,
                         clip_extents=np.stack(extents), bind_transforms=bind, root_motion=motion,
                         bone_parents=parents, masks=masks, blend_spaces=tuple(options.blend_spaces),
                         markers=tuple(options.markers))
    if meshes:
        # vb:clipExtents from the decoded texels, at rows and between rows (spec 13): they bound
        # what every decoder computes, quantization included.

        baked = dataclasses.replace(baked, clip_extents=clip_extents(baked).astype(np.float32))
    return baked


def check_motion(spaces, markers, clips, animation: SkinnedAnimation) -> None:
    """Refuse blend spaces and markers that do not fit the baked clips (spec 23.6), in one line.

    Raises:
        OptionsError: The first problem (code ``convert.marker`` for a marker, ``convert.blendSpace``
            for a blend space).
    """
    durations = {c.name: c.duration for c in clips}
    for parts, message in motion_problems(tuple(spaces), tuple(markers), durations):
        code = "convert.marker" if parts[0] == "markers" else "convert.blendSpace"
        raise OptionsError(message, file=animation.source, location=animation.path, code=code)


def bone_masks(animation: SkinnedAnimation, requests) -> tuple:
    """The bone parents and named masks of ``--mask NAME=BONE`` requests (spec "Layers and bone masks").

    Each mask weighs 1 the bone named and every bone below it (its descendants under the
    animation's bone parents), 0 every other bone.

    Args:
        animation: The converter's animation; it must know its bones' parents and bind transforms.
        requests: ``(name, bone)`` pairs; a bone is a full bone name or its last path element.

    Returns:
        ``(parents tuple, ((name, weights), ...))``.

    Raises:
        OptionsError: A bone no bone of the animation is named, an ambiguous short name, a repeated
            mask name, or an animation without parents or bind transforms (code ``convert.mask``).
    """
    where = dict(file=animation.source, location=animation.path, code="convert.mask")
    if animation.bone_parents is None or animation.bind_transforms is None:
        raise OptionsError("--mask needs the bones' hierarchy and bind transforms, which this source's "
                           "converter does not give", **where)
    parents = tuple(int(p) for p in animation.bone_parents)
    names = [str(b) for b in animation.bones]
    children: dict = {}
    for b, p in enumerate(parents):
        children.setdefault(p, []).append(b)
    masks, seen = [], set()
    for name, bone in requests:
        if name in seen:
            raise OptionsError(f"--mask {name}={bone}: the mask name {name!r} is given twice", **where)
        seen.add(name)
        found = [i for i, n in enumerate(names) if n == bone] or \
            [i for i, n in enumerate(names) if n.rsplit("/", 1)[-1] == bone]
        if len(found) != 1:
            shown = ", ".join(n.rsplit("/", 1)[-1] for n in names[:12]) + (", ..." if len(names) > 12 else "")
            why = "is ambiguous" if found else "is not a bone of the animation"
            raise OptionsError(f"--mask {name}={bone}: {bone!r} {why} (bones: {shown})", **where)
        weights = np.zeros(len(names))
        stack = [found[0]]
        while stack:
            b = stack.pop()
            weights[b] = 1.0
            stack.extend(children.get(b, ()))
        weights.setflags(write=False)
        masks.append((str(name), weights))
    return parents, tuple(masks)
