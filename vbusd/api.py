"""The public jobs of vbusd that have no other natural home: validate, skin and shader.

They are thin: each checks its arguments, then calls the module that does the work
(:mod:`vbusd.validators.api`, :mod:`vbusd.decoders.reference`, :mod:`vbusd.decoders.shaders`), so that
``import vbusd`` gives a host application the main jobs under one name (see docs/api.md).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np

from vbusd.format.errors import OptionsError
from vbusd.format.model import VirtualBones, VirtualBonesAsset
from vbusd.validators.api import validate as _validate
from vbusd.io.usd import read_asset
from vbusd.decoders.reference import skin_mesh, skin_mesh_crossfade, skin_mesh_layered
from vbusd.decoders.reference import Additive, mask_weights, check_frame_interval
from vbusd.format.motion import blend_weights, crossed_markers, phase_times
from vbusd.decoders.reference import crowd_joint_transforms, joint_transforms, layered_skinning
from vbusd.decoders.reference import root_motion as displacement
from vbusd.decoders.shaders import ShaderOptions, generate

__all__ = ["SkinnedPose", "validate", "skin", "bone_transform", "root_motion", "shader", "clip_index", "events",
           "blend_points"]

AssetLike = Union[str, os.PathLike, VirtualBonesAsset, VirtualBones]


@dataclass(frozen=True)
class SkinnedPose:
    """One bound mesh skinned at one time.

    Attributes:
        path: The mesh's prim path in the asset.
        points: (V, 3) float64 skinned points in the animation's space.
        normals: Skinned unit normals ((V, 3) vertex or (F, 3) faceVarying), or None when the
            mesh has none.
        previous_positions: (V, 3) float64 skinned points of the previous frame (spec 21), when
            :func:`skin` was asked for them with ``previous=``; None otherwise.
        previous_normals: The previous frame's unit normals, as ``normals``; None without
            ``previous=`` or without normals.
    """

    path: str
    points: np.ndarray
    normals: Optional[np.ndarray]
    previous_positions: Optional[np.ndarray] = None
    previous_normals: Optional[np.ndarray] = None


def validate(path, *, only: Sequence[str] = (), ignore: Sequence[str] = (), max_issues: Optional[int] = None,
             allow_outside_paths: bool = False):
    """Validate an asset (USD layer, texture, sidecar or runtime package) and return its report.

    Args:
        path: The file to check.
        only: Report only these codes or code prefixes.
        ignore: Leave out these codes or code prefixes.
        max_issues: List at most this many findings (the counts still cover all).
        allow_outside_paths: Let the asset reference files outside its folder (as ``read_asset``
            and the other jobs take it); without it each such reference is a ``path.unsafe`` finding.

    Returns:
        A :class:`vbusd.validators.report.Report`; ``report.valid`` is False when any error was found.

    Raises:
        InputError: The file cannot be opened at all.
        OptionsError: An unknown code filter or a negative ``max_issues``.

    Example:
        >>> report = vbusd.validate("out/stadium_crowd.usda")  # doctest: +SKIP
        >>> report.valid
        True
    """

    return _validate(path, only=only, ignore=ignore, max_issues=max_issues, allow_outside_paths=allow_outside_paths)


def _animation(asset: AssetLike, animation: int, what: str) -> VirtualBones:
    if isinstance(asset, VirtualBones):
        return asset
    if not isinstance(asset, VirtualBonesAsset):

        asset = read_asset(asset)
    if isinstance(animation, bool) or not isinstance(animation, (int, np.integer)) \
            or not 0 <= animation < len(asset.animations):
        raise OptionsError(f"animation must be an index 0..{len(asset.animations) - 1}, got {animation!r}",
                           file=what)
    return asset.animations[int(animation)]


def clip_index(vb: VirtualBones, clip, *, what: str = "skin") -> int:
    """The index of a clip given by name or index.

    Args:
        vb: The animation.
        clip: A clip name, or an index into ``vb.clips``.
        what: Names the caller in the error.

    Raises:
        OptionsError: No such clip; the message lists the clips there are.
    """
    names = [c.name for c in vb.clips]
    if isinstance(clip, str):
        if clip in names:
            return names.index(clip)
    elif isinstance(clip, (int, np.integer)) and not isinstance(clip, bool) and 0 <= clip < len(names):
        return int(clip)
    raise OptionsError(f"animation {vb.path} has no clip {clip!r} (clips: {', '.join(names)})", file=what)


def _is_number(value) -> bool:
    """A real number: int, float or a numpy scalar of either; not a bool, a string or None."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _is_index(value) -> bool:
    """An integer index: int or a numpy integer; not a bool, a float (1.0 included) or a string."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _finite_seconds(value, name: str, job: str, rows_per_second: float = 1.0) -> float:
    """A time argument as float seconds; refused (one line naming it) unless it is a finite number
    whose row position ``seconds x rows_per_second`` (spec "Row position") is finite too."""
    seconds = float(value) if _is_number(value) else float("nan")
    if not np.isfinite(seconds):
        raise OptionsError(f"{name} must be a finite number of seconds, got {value!r}", file=job)
    if not np.isfinite(seconds * float(rows_per_second)):
        raise OptionsError(f"{name} {value!r} is out of range: at {rows_per_second:g} rows per second its row "
                           f"position is not a finite number", file=job)
    return seconds


def _weight(value, name: str, job: str) -> float:
    weight = float(value) if _is_number(value) else float("nan")
    if not 0.0 <= weight <= 1.0:
        raise OptionsError(f"{name} must be a number in 0..1, got {value!r}", file=job)
    return weight


def skin(asset: AssetLike, clip=0, time: float = 0.0, *, fade_clip=None, fade_time=None, fade_weight: float = 0.0,
         animation: int = 0, layers=None, blend=None, previous: Optional[float] = None,
         playback_rate: float = 1.0) -> list:
    """Skin every mesh bound to an animation at one clip-local time, with the numpy reference decoder.

    With ``fade_clip`` the mesh plays two clips at once (spec: "Crossfade", format 1.1): ``clip``
    at ``time`` and ``fade_clip`` at ``fade_time``, blended with weight ``fade_weight`` of the fade
    clip (the two skinned poses blended; for the matrix encodings the same as blending each bone's
    two skinning matrices).

    Args:
        asset: A Virtual Bones asset path, a read :class:`~vbusd.format.model.VirtualBonesAsset`, or
            one :class:`~vbusd.format.model.VirtualBones`.
        clip: Clip name or index.
        time: Clip-local time in seconds (a looping clip wraps, a clamped one holds its ends).
        fade_clip: The clip faded in, by name or index; None for no crossfade.
        fade_time: The fade clip's clip-local time in seconds (required with ``fade_clip``).
        fade_weight: Weight of the fade clip, 0..1 (0: ``clip`` alone, 1: ``fade_clip`` alone).
        animation: Which animation of the asset (index), when it holds several.
        layers: Format 1.2 layers (spec "Layers and bone masks"), applied in order on top of the
            clip (and on each side of a crossfade): a list of ``{"clip": name or index, "time":
            clip-local seconds, "weight": 0..1 (default 1), "mask": mask name}``; each overrides
            the bones of its mask in local space (translation and scale lerped, rotation slerped).
            Format 1.3 (spec 23.4): ``"mode": "additive"`` (default ``"override"``) adds the layer
            clip's difference from ``"reference": {"clip": ..., "time": ...}`` (default the layer's
            clip at 0) instead.
        blend: Format 1.3 (spec 23.1 to 23.3): ``{"space": NAME, "x": X, "y": Y, "phase": P}`` (``y``
            and ``phase`` default to 0): the space's clips weighted at ``(X, Y)``, each at ``P`` times
            its duration (from its sync marker when the space has one); ``clip`` and ``time`` are then
            ignored. Not with a crossfade.
        previous: A frame interval ``dt`` in seconds (spec 21, "Previous-frame pose"): each pose also
            carries ``previous_positions`` and ``previous_normals``, the pose at clip-local
            ``time - dt * playback_rate`` (wrapped or clamped as the clip does); the fade time and
            the layer times step back by the same amount (an additive layer's reference pose stays),
            weights are held; a blend's phase steps back by ``dt * playback_rate / sum w D`` (spec
            23.3). None (the default) computes nothing more.
        playback_rate: Clip seconds per scene second of this pose, used only with ``previous``.

    Returns:
        A list of :class:`SkinnedPose`, one per bound mesh in the asset's order, in the
        animation's space.

    Raises:
        InputError: The asset cannot be read, or a layer names a mask it does not store (code
            ``layers.noMask``).
        OptionsError: No such clip or animation, a time that is not a finite number (or whose row
            position, time x rowsPerSecond, is not), a fade weight that is not a number in 0..1, a fade clip without a fade time, or a malformed layer.
            ``previous`` not a finite number above 0, or ``playback_rate`` not a finite number.

    Example:
        >>> poses = vbusd.skin("out/stadium_crowd.usda", "Cheer", 1.5)  # doctest: +SKIP
        >>> poses[0].points.shape
        (202, 3)
        >>> walk_to_run = vbusd.skin("crowd.usda", "walk", 0.8, fade_clip="run", fade_time=0.1,
        ...                          fade_weight=0.25)  # doctest: +SKIP
        >>> waving = vbusd.skin("fox.usda", "Walk", 0.5,
        ...                     layers=[{"clip": "Survey", "time": 1.0, "weight": 1.0, "mask": "upper"}])  # doctest: +SKIP
    """

    vb = _animation(asset, animation, "skin")
    blended = blend_points(vb, blend, "skin") if blend is not None else None
    if blended is None:
        index = clip_index(vb, clip)
        tau = _finite_seconds(time, "time", "skin", vb.clips[index].rows_per_second)
    else:
        index, tau = blended[0][0], float(blended[0][1][0])  # the blend is the base: clip and time are ignored
    weight = _weight(fade_weight, "fade_weight", "skin")
    fade_index = None
    if blended is not None and fade_clip is not None:
        raise OptionsError("blend= and fade_clip= do not combine: a blend space is the base pose", file="skin",
                           code="blend.noSpace")
    if fade_clip is not None:
        fade_index = clip_index(vb, fade_clip)
        if fade_time is None:
            raise OptionsError("fade_clip needs fade_time (the fade clip's clip-local seconds)", file="skin")
        fade_tau = _finite_seconds(fade_time, "fade_time", "skin", vb.clips[fade_index].rows_per_second)
    elif weight > 0.0:
        raise OptionsError(f"fade_weight {weight} needs a fade_clip", file="skin")
    resolved = _layers(vb, layers, "skin")
    step = 0.0
    if previous is not None:
        dt = check_frame_interval(previous, "skin")
        rate = float(playback_rate) if _is_number(playback_rate) else float("nan")
        if not np.isfinite(rate):
            raise OptionsError(f"playback_rate must be a finite number, got {playback_rate!r}", file="skin")
        step = dt * rate
        _finite_seconds(tau - step, "time - previous x playback_rate", "skin", vb.clips[index].rows_per_second)

    previous_blended = blended
    if blended is not None and step != 0.0:
        # The phase advances at rate / sum w D (spec 23.3), so the previous frame is that much phase back.
        weighted = sum(w * vb.clips[c].duration for c, _, w in blended)
        if weighted > 0.0:
            previous_blended = blend_points(vb, {**blend, "phase": float(blend.get("phase", 0.0)) - step / weighted},
                                            "skin")

    def pose(mesh, back: float):
        # a layer's clip time steps back; an additive layer's reference pose (its fifth element) stays
        shifted = [(layer[0], layer[1] - back) + tuple(layer[2:]) for layer in resolved]
        if resolved or blended is not None:
            # with a blend, its points are the base (index and tau only give the shape)
            return skin_mesh_layered(vb, mesh, index, np.array([tau - back]), shifted, fade_clip=fade_index,
                                     fade_tau=None if fade_index is None else np.array([fade_tau - back]),
                                     fade_weight=weight, blend=blended if back == 0.0 else previous_blended)
        if fade_index is None:
            return skin_mesh(vb, mesh, index, np.array([tau - back]))
        return skin_mesh_crossfade(vb, mesh, index, np.array([tau - back]), fade_index,
                                   np.array([fade_tau - back]), weight)

    poses = []
    for mesh in vb.meshes:
        points, normals = pose(mesh, 0.0)
        previous_points = previous_normals = None
        if previous is not None:
            previous_points, previous_normals = pose(mesh, step)
            previous_points = previous_points[0]
            previous_normals = None if previous_normals is None else previous_normals[0]
        poses.append(SkinnedPose(mesh.path, points[0], None if normals is None else normals[0],
                                 previous_points, previous_normals))
    return poses


_PER_INSTANCE = ("positions", "orientations", "scales", "clip", "time_offset", "playback_rate", "fade_clip",
                 "fade_time_offset", "fade_playback_rate", "fade_weight", "layer_clip", "layer_time_offset",
                 "layer_playback_rate", "layer_weight", "layer_mask", "layer_mode", "layer_reference_clip",
                 "layer_reference_time", "blend_space", "blend_x", "blend_y", "blend_phase", "tint", "variant",
                 "parts")


_LAYER_KEYS = ("clip", "time", "weight", "mask", "mode", "reference")
_BLEND_KEYS = ("space", "x", "y", "phase")


def blend_points(vb: VirtualBones, blend, job: str = "skin") -> list:
    """A ``blend`` dict (spec 23.1 to 23.3) resolved to the space's weighted points in its order,
    ``[(clip index, times (1,), weight)]``, as :func:`~vbusd.decoders.reference.layered_skinning` takes them.

    Raises:
        OptionsError: Not a dict with ``space`` (and numbers ``x``, ``y``, ``phase``), or a space the
            animation does not store (code ``blend.noSpace``).
    """
    if not isinstance(blend, dict) or "space" not in blend or any(k not in _BLEND_KEYS for k in blend):
        raise OptionsError(f"blend must be a dict with keys {', '.join(_BLEND_KEYS)} (space required), got "
                           f"{blend!r:.80}", file=job, code="blend.noSpace")
    spaces = {space.name: space for space in vb.blend_spaces}
    if blend["space"] not in spaces:
        have = (f"spaces: {', '.join(spaces)}" if spaces
                else "it stores none (format 1.3): reconvert with --blend-space NAME=CLIP@X,...")
        raise OptionsError(f"animation {vb.path} has no blend space {blend['space']!r} ({have})", file=job,
                           code="blend.noSpace")
    space = spaces[blend["space"]]
    values = {}
    for key in ("x", "y", "phase"):
        value = blend.get(key, 0.0)
        if not _is_number(value) or not np.isfinite(float(value)):
            raise OptionsError(f"blend {key} must be a finite number, got {value!r}", file=job, code="blend.noSpace")
        values[key] = float(value)
    durations = {c.name: c.duration for c in vb.clips}
    times = phase_times(space, durations, vb.markers, values["phase"])
    return [(clip_index(vb, space.clips[k], what=job), np.array([times[k]]), w)
            for k, w in blend_weights(space, values["x"], values["y"])]


def events(asset: AssetLike, clip, t0: float, t1: float, *, animation: int = 0) -> list:
    """The markers of a clip crossed between two clip-local times (format 1.3, spec 23.5).

    Forward (``t1 >= t0``): every marker time in ``(t0, t1]``, a looping clip's markers once per
    loop, in increasing time; backward (``t1 < t0``): those in ``[t1, t0)``, in decreasing time.

    Args:
        asset: A Virtual Bones asset path, a read asset or one :class:`~vbusd.format.model.VirtualBones`.
        clip: Clip name or index.
        t0: Clip-local start time in seconds (excluded).
        t1: Clip-local end time in seconds (included).
        animation: Which animation of the asset (index).

    Returns:
        ``[{"name": marker name, "time": unwrapped clip-local time}]`` in the order crossed.

    Raises:
        InputError: The asset cannot be read.
        OptionsError: No such clip or animation, or a time that is not a finite number.

    Example:
        >>> vbusd.events("fox.usda", "Walk", 0.0, 2.0)  # doctest: +SKIP
        [{'name': 'footL', 'time': 0.2}, {'name': 'footL', 'time': 0.9083333}, ...]
    """
    vb = _animation(asset, animation, "events")
    index = clip_index(vb, clip, what="events")
    c = vb.clips[index]
    return crossed_markers(vb.markers, c.name, c.duration, c.loop, _finite_seconds(t0, "t0", "events"),
                           _finite_seconds(t1, "t1", "events"))


def _layers(vb: VirtualBones, layers, job: str) -> list:
    """Layers given as dicts, checked and resolved to ``(clip index, times, weight, mask weights)``."""

    if layers is None:
        return []
    if isinstance(layers, dict) or not isinstance(layers, (list, tuple)):
        raise OptionsError(f"layers must be a list of dicts with keys {', '.join(_LAYER_KEYS)}, got "
                           f"{type(layers).__name__}", file=job)
    resolved = []
    for j, layer in enumerate(layers):
        if not isinstance(layer, dict):
            raise OptionsError(f"layers[{j}] must be a dict with keys {', '.join(_LAYER_KEYS)}, got "
                               f"{type(layer).__name__}", file=job)
        unknown = sorted(str(k) for k in layer if k not in _LAYER_KEYS)
        mode = layer.get("mode", "override")
        if mode not in ("override", "additive"):
            raise OptionsError(f"layers[{j}]: mode must be 'override' or 'additive', got {mode!r}", file=job,
                               code="blend.noSpace")
        if "reference" in layer and mode != "additive":
            raise OptionsError(f"layers[{j}]: a reference needs mode 'additive'", file=job, code="blend.noSpace")
        missing = [k for k in ("clip", "time", "mask") if k not in layer]
        if unknown or missing:
            raise OptionsError(f"layers[{j}]: " + "; ".join(
                ([f"unknown keys {', '.join(unknown)}"] if unknown else [])
                + ([f"missing {', '.join(missing)}"] if missing else []))
                + f" (keys: {', '.join(_LAYER_KEYS)}; weight defaults to 1)", file=job)
        weight = _weight(layer.get("weight", 1.0), f"layers[{j}]: weight", job)
        clip = clip_index(vb, layer["clip"], what=job)
        seconds = _finite_seconds(layer["time"], f"layers[{j}] time", job, vb.clips[clip].rows_per_second)
        mask = mask_weights(vb, layer["mask"], what=job)
        if mode == "additive":
            reference = layer.get("reference", {"clip": clip, "time": 0.0})
            if not isinstance(reference, dict) or set(reference) - {"clip", "time"}:
                raise OptionsError(f"layers[{j}]: reference must be a dict with keys clip, time, got {reference!r:.60}",
                                   file=job, code="blend.noSpace")
            reference_clip = clip_index(vb, reference.get("clip", clip), what=job)
            reference_time = _finite_seconds(reference.get("time", 0.0), f"layers[{j}] reference time", job,
                                             vb.clips[reference_clip].rows_per_second)
            resolved.append((clip, np.array([seconds]), weight, mask,
                             Additive((reference_clip, np.array([reference_time])))))
        else:
            resolved.append((clip, np.array([seconds]), weight, mask))
    return resolved


def bone_index(vb: VirtualBones, bone, *, what: str = "bone_transform") -> int:
    """The index of a bone given by name (as in ``vb:bones``), by its last path element, or by index.

    Raises:
        OptionsError: No such bone, or a short name that several bones share.
    """
    names = list(vb.bones)
    if isinstance(bone, str):
        if bone in names:
            return names.index(bone)
        tails = [i for i, name in enumerate(names) if name.rsplit("/", 1)[-1] == bone]
        if len(tails) == 1:
            return tails[0]
        if len(tails) > 1:
            raise OptionsError(f"bone name {bone!r} is ambiguous: {', '.join(names[i] for i in tails)}", file=what)
    elif isinstance(bone, (int, np.integer)) and not isinstance(bone, bool) and 0 <= bone < len(names):
        return int(bone)
    shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
    raise OptionsError(f"animation {vb.path} has no bone {bone!r} (bones: {shown})", file=what)


def bone_transform(asset: AssetLike, bone, clip=0, time: float = 0.0, *, animation: int = 0,
                   instance: Optional[int] = None, crowd: int = 0, layers=None, blend=None) -> np.ndarray:
    """A joint's transform in the animation's space at one clip time: where to attach a prop (a socket).

    Returns ``J = M B`` (spec "Sockets", format 1.1): the bone's decoded skinning transform ``M`` at
    the clip time (interpolated between rows as the decoders interpolate) times the joint's bind
    transform ``B`` stored in the asset. A prop modelled in the joint's own space follows the hand
    with ``p' = J[:3, :3] @ p + J[:3, 3]``; for a crowd instance, apply the instance's placement
    after it (:func:`vbusd.decoders.reference.crowd_joint_transforms` does both).

    Args:
        asset: A Virtual Bones asset path, a read asset or one :class:`~vbusd.format.model.VirtualBones`.
        bone: Bone name (full ``vb:bones`` entry, or its last path element when unique) or index.
        clip: Clip name or index.
        time: Clip-local time in seconds; with ``instance``, the scene time.
        animation: Which animation of the asset (index).
        instance: Per instance of a crowd: the index of the instance in crowd ``crowd`` of the
            asset; ``clip`` is then the instance's own (and its crossfade), ``time`` the scene time,
            and the result is in the instancer's local space (the instance's placement applied;
            the instancer's own transform, as for its points, is not).
        crowd: Which crowd of the asset (index), with ``instance``.
        layers: Format 1.2 layers, as in :func:`skin` (not with ``instance``): the joint of the
            layered pose, ``J'_b`` (spec "Layers and bone masks").
        blend: Format 1.3 blend, as in :func:`skin` (not with ``instance``): the joint of the
            blended (and layered) pose.

    Returns:
        (4, 4) float64 matrix for column vectors, ``p' = M[:3, :3] @ p + M[:3, 3]``.

    Raises:
        InputError: The asset cannot be read or stores no bind transforms (an asset converted
            before format 1.1: reconvert it).
        OptionsError: No such bone, clip, animation, crowd or instance (``instance`` and ``crowd``
            must be integers), or a time that is not a finite number or whose row is not.

    Example:
        >>> hand = vbusd.bone_transform("out/stadium_crowd.usda", "R_hand", "Cheer", 2.5)  # doctest: +SKIP
        >>> hand[:3, 3]   # the hand's position in animation space
    """

    job = "bone_transform"
    if instance is not None and layers:
        raise OptionsError("layers apply to one animation's clip, not with instance= (a crowd's layers are its "
                           "primvars)", file=job)
    if instance is not None and not _is_index(instance):
        raise OptionsError(f"instance must be an integer index of an instance, got {instance!r}", file=job)
    if not _is_index(crowd):
        raise OptionsError(f"crowd must be an integer index of a crowd, got {crowd!r}", file=job)
    if instance is not None:
        if not isinstance(asset, VirtualBonesAsset):

            asset = read_asset(asset)
        if not 0 <= crowd < len(asset.crowds):
            raise OptionsError(f"crowd must be an index 0..{len(asset.crowds) - 1}, got {crowd!r}", file=job)
        crowd_data = asset.crowds[int(crowd)]
        if not 0 <= instance < crowd_data.instance_count:
            raise OptionsError(f"instance must be an index 0..{crowd_data.instance_count - 1}, got {instance!r}",
                               file=job)
        vb = asset.animations[int(asset.crowd_animation[int(crowd)])]
        single = dataclasses.replace(crowd_data, **{name: np.asarray(getattr(crowd_data, name))[[int(instance)]]
                                                   for name in _PER_INSTANCE if getattr(crowd_data, name) is not None})
        if crowd_data.fade_samples:
            single = dataclasses.replace(single, fade_samples={
                key: (times, np.asarray(values)[:, [int(instance)]])
                for key, (times, values) in crowd_data.fade_samples.items()})
        seconds = _finite_seconds(time, "time", job)
        # The instance's clip-local times, offset + rate x time, at the fastest clip's rows per second
        # (spec "Instancing"): finite, or the time is out of range for this instance.
        offsets = [abs(float(v)) for name in ("time_offset", "fade_time_offset", "layer_time_offset")
                   if getattr(single, name) is not None for v in np.ravel(getattr(single, name))]
        rates = [abs(float(v)) for name in ("playback_rate", "fade_playback_rate", "layer_playback_rate")
                 if getattr(single, name) is not None for v in np.ravel(getattr(single, name))]
        local = max(offsets, default=0.0) + max(rates, default=1.0) * abs(seconds)
        if not np.isfinite(local * max(c.rows_per_second for c in vb.clips)):
            raise OptionsError(f"time {time!r} is out of range: instance {instance}'s clip-local time "
                               f"(offset + rate x time) has no finite row position", file=job)
        return crowd_joint_transforms(vb, single, bone_index(vb, bone), seconds)[0]
    vb = _animation(asset, animation, job)
    index = bone_index(vb, bone)
    points = blend_points(vb, blend, job) if blend is not None else None
    if points is None:
        clip_number = clip_index(vb, clip, what=job)
        tau = _finite_seconds(time, "time", job, vb.clips[clip_number].rows_per_second)
    else:
        clip_number, tau = points[0][0], float(points[0][1][0])
    resolved = _layers(vb, layers, "bone_transform")
    if resolved or points is not None:
        return layered_skinning(vb, clip_number, np.array([tau]), resolved, blend=points)[1][0, index]
    return joint_transforms(vb, clip_number, np.array([tau]))[0, index]


def root_motion(asset: AssetLike, clip=0, t0: float = 0.0, t1: float = 0.0, *, animation: int = 0) -> np.ndarray:
    """How far a clip baked in place moves the character between two clip times (spec "Root motion").

    For an asset converted with ``--root-motion extract`` (or ``extractYaw``) the clips play in
    place and each keeps its root track ``D(t)``; this returns ``D(t1) D(t0)^-1``, the displacement
    (translation, and the turn about the up axis with ``extractYaw``) to apply to an instance's
    placement, in the animation's space. Looping clips accumulate: two loops of a walk move twice
    as far. An animation without a root track returns the identity.

    Args:
        asset: A Virtual Bones asset path, a read asset or one :class:`~vbusd.format.model.VirtualBones`.
        clip: Clip name or index.
        t0: Clip-local start time in seconds.
        t1: Clip-local end time in seconds.
        animation: Which animation of the asset (index).

    Returns:
        (4, 4) float64 matrix for column vectors.

    Raises:
        InputError: The asset cannot be read.
        OptionsError: No such clip or animation, or a time that is not a finite number (or whose row
            position, time x rowsPerSecond, is not).

    Example:
        >>> step = vbusd.root_motion("walk.usda", "walk", 0.0, 1.0)  # doctest: +SKIP
        >>> step[:3, 3]   # metres walked in the first second
    """

    vb = _animation(asset, animation, "root_motion")
    index = clip_index(vb, clip, what="root_motion")
    rate = vb.clips[index].rows_per_second
    return displacement(vb, index, _finite_seconds(t0, "t0", "root_motion", rate),
                        _finite_seconds(t1, "t1", "root_motion", rate))


def shader(lang: str = "glsl", encoding="crossMatrix", texel_format="float16", *, max_influences: int = 4,
           max_clips: int = 16, main: bool = True, skin: str = "attributes", layers: bool = False,
           crossfade: bool = False, previous: bool = False) -> str:
    """The reference vertex-shader module for one encoding and texel format (what ``vbusd shader`` prints).

    Args:
        lang: ``glsl``, ``hlsl`` or ``wgsl``.
        encoding: Bone encoding token (``crossMatrix``, ``affineMatrix``, ``quatTranslation``, ``dualQuat``).
        texel_format: ``float16``, ``float32`` or ``unorm16``.
        max_influences: Influences per vertex, 1..8.
        max_clips: Size of the clip table uniform array.
        main: Also emit an entry point that writes the skinned position and normal.
        skin: ``attributes`` (bone indices and weights as vertex attributes) or ``pulled`` (read by
            vertex index from skin records, ``vbusd.decoders.shaders.pack_skin``; spec/shaders.md).
        layers: Also emit the format 1.2 layer functions (``vbSkinLayered``; spec/shaders.md, Layers).
        crossfade: The example entry point reads the crossfade inputs and calls ``vbSkinCrossfade``.
        previous: The previous-frame pose: ``vb_previousTime`` and the entry point's
            ``vb_previousPosition`` (spec/shaders.md, Previous pose).

    Returns:
        The shader source text.

    Raises:
        OptionsError: An unknown language, encoding, texel format or skin binding, or a count out of range.
    """

    return generate(ShaderOptions(lang=lang, encoding=encoding, texel_format=texel_format,
                                  max_influences=max_influences, max_clips=max_clips, main=main, skin=skin,
                                  layers=layers, crossfade=crossfade, previous=previous))
