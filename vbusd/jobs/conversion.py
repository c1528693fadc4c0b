"""Library side of ``vbusd convert``: read a source, bake every animation, check, write.

The steps, each reported to an optional progress callback:

1. :class:`ConvertOptions` are checked before any file is opened (:class:`~vbusd.format.errors.OptionsError`);
   an existing output is refused unless ``force`` is set.
2. The converter that reads the source is picked by :mod:`vbusd.converters.registry` (UsdSkel, glTF
   or a plugin) and returns a :class:`~vbusd.format.model.SourceScene`.
3. Each skinned animation is baked (:func:`vbusd.baking.baker.bake`). ``encoding="auto"`` picks
   crossMatrix when every bone transform is rigid and affineMatrix otherwise, and dualQuat when the
   source asks for dual-quaternion skinning; the report states the choice and why.
4. Every bound mesh is decoded with the numpy reference decoder at the checked rows and compared
   with the source's own skinning (for UsdSkel, ``UsdSkel.SkinningQuery.ComputeSkinnedPoints``), so
   the report holds the largest position error per mesh, and separately the part of it that comes
   from dropping influences beyond ``max_influences``.
5. The asset, its texture and its sidecar are written by :func:`vbusd.io.usd.write_asset`, which
   writes beside the target and renames: a failure leaves no partial output and never clobbers an
   existing file.

pxr is imported only by the converters and the USD writer, not here.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FuturesTimeout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from vbusd.jobs import warmup
from vbusd.baking.baker import BakeOptions, bake
from vbusd.format.errors import FORCE_HINT, InputError, OptionsError, UnsupportedError, VbusdError
from vbusd.format.jsonform import is_unicode_text, json_ready
from vbusd.format.motion import BlendSpace, Marker, parse_blend_space, parse_marker
from vbusd.format.containers import container_error, default_container, texture_file_name
from vbusd.format.layout import Encoding, Padding, TexelFormat, pairing_error, texel_formats_of
from vbusd.format.model import ReadOptions, SkinnedAnimation, SourceScene, VirtualBones, VirtualBonesAsset
from vbusd.io.files import make_folders, remove_folders
from vbusd.baking.lod import check_screen_sizes, parse_ratios
from vbusd.format.rootmotion import check_mode
from vbusd.io.files import journal_path, recover
from vbusd.io.usd import asset_files_in_use
from vbusd.format.encoding import BoneTransforms
from vbusd.decoders.reference import skin
from vbusd.kernels import bake as bake_kernels
from vbusd.decoders.reference import bone_transforms, normal_point_indices
from vbusd.format.rootmotion import at as root_at
from vbusd.io import usd_probe
from vbusd.io.usd import write_asset
from vbusd.converters import registry
from vbusd.baking.lod import levels_from_names
from vbusd.baking.lod import adopt_levels
from vbusd.baking.lod import add_levels
from vbusd.io.paths import OUTPUT_SUFFIXES, check_output_path

__all__ = ["AUTO", "parse_masks", "with_syncs", "OUTPUT_SUFFIXES", "BAD_CLIP_POLICIES", "DEFAULT_CHECK_ROWS",
           "ConvertOptions", "MeshReport", "SkippedClip", "ClipReport", "AnimationReport",
           "ConvertReport", "check_output", "bake_animation",
           "bake_with_clip_policy", "measure_errors", "convert"]

AUTO = "auto"
"""The encoding choice that lets vbusd pick per animation."""

BAD_CLIP_POLICIES = ("error", "skip")
"""What ``vbusd convert --on-bad-clip`` does with a clip the encoding cannot hold."""
DEFAULT_CHECK_ROWS = 256
"""Rows per clip compared with the source's own skinning by default (all rows when fewer)."""

Progress = Callable[[str, int, int], None]
"""``progress(step, done, total)``: a step name (``read``, ``bake``, ``check``, ``write``) and counts."""


@dataclass(frozen=True)
class ConvertOptions:
    """Options of a conversion; checked on construction, before any work starts.

    Attributes:
        encoding: ``auto`` or an :class:`~vbusd.format.layout.Encoding` token.
        texel_format: ``float16``, ``float32``, ``unorm16`` or ``uint32`` (only with
            compactQuatTranslation, format 1.2; with ``auto`` it picks that encoding).
        rows_per_second: Rows per second of every clip; None keeps the source's rate (for UsdSkel,
            one row per time code).
        horizontal_padding: ``powerOfTwo`` or ``none``.
        vertical_padding: ``none`` or ``powerOfTwo`` (resample clips to fill a power of two).
        max_influences: Influences kept per vertex (the largest, renormalized).
        skeletons: Skeletons (UsdSkel paths, glTF skin names or indices) to convert; empty: all.
        frame_range: (start, end) in the source's time unit (USD time codes), or None.
        container: Texture container, ``exr`` (float16, float32), ``png`` (unorm16) or ``ktx2``
            (any; spec/ktx2.md), or None to follow the texel format.
        allow_outside_paths: Let the source reference files outside its folder.
        force: Replace an existing output.
        check_rows: Rows per clip compared with the source's skinning: None for all rows, 0 to skip;
            otherwise that many rows spread evenly (first and last included).
        converter: Force a converter by name (``usdskel``, ``gltf``); None picks by the file.
        loop: Force looping (True) or clamping (False); None lets the baker decide.
        clips: Clips to convert (glTF animation names or indices, UsdSkel Skeleton prim names);
            empty: all. A name that selects nothing is an error.
        on_bad_clip: ``error`` (default): a clip the chosen encoding cannot hold stops the
            conversion with a line naming it; ``skip``: it is left out (listed in the report's
            ``skipped_clips``) and the others are converted.
        strict_weights: Refuse glTF weights that do not sum to one instead of renormalizing them.
        root_motion: ``keep`` (default), ``extract`` (bake every clip in place and keep the root
            joint's horizontal translation as a root track, format 1.1, spec "Root motion") or
            ``extractYaw`` (also its rotation about the up axis).
        lod_ratios: Triangle ratios of generated levels of detail 1, 2, ... (strictly descending in
            (0, 1); format 1.2, spec "Levels of detail"), or empty for none. Needs meshoptimizer.
        lod_screen_sizes: Screen-size thresholds of those levels (one per ratio), or None for
            :func:`vbusd.baking.lod.default_screen_sizes`.
        masks: Format 1.2 bone masks for layers (spec "Layers and bone masks"): ``(name, bone)``
            pairs or ``"NAME=BONE"`` strings, each weighing ``bone`` and every bone below it.
        blend_spaces: Format 1.3 blend spaces (spec 23): ``"NAME=CLIP@X,..."`` / ``"NAME=CLIP@X:Y,..."``
            strings or :class:`~vbusd.format.motion.BlendSpace` objects.
        markers: Format 1.3 clip markers (spec 23.4): ``"CLIP:NAME@SECONDS"`` strings or
            :class:`~vbusd.format.motion.Marker` objects.
        blend_syncs: ``"SPACE=MARKER"`` strings: the space plays its clips' phases from that marker (spec 23.3).
    """

    encoding: str = AUTO
    texel_format: str = "float16"
    rows_per_second: Optional[float] = None
    horizontal_padding: str = "powerOfTwo"
    vertical_padding: str = "none"
    max_influences: int = 4
    skeletons: tuple = ()
    frame_range: Optional[tuple] = None
    container: Optional[str] = None
    allow_outside_paths: bool = False
    force: bool = False
    check_rows: Optional[int] = DEFAULT_CHECK_ROWS
    converter: Optional[str] = None
    loop: Optional[bool] = None
    clips: tuple = ()
    on_bad_clip: str = "error"
    strict_weights: bool = False
    root_motion: str = "keep"
    lod_ratios: tuple = ()
    lod_screen_sizes: Optional[tuple] = None
    masks: tuple = ()
    blend_spaces: tuple = ()
    markers: tuple = ()
    blend_syncs: tuple = ()

    def __post_init__(self) -> None:
        where = "convert"
        object.__setattr__(self, "masks", parse_masks(self.masks))
        spaces = tuple(s if isinstance(s, BlendSpace) else parse_blend_space(s) for s in self.blend_spaces)
        object.__setattr__(self, "markers", tuple(m if isinstance(m, Marker) else parse_marker(m)
                                                  for m in self.markers))
        object.__setattr__(self, "blend_spaces", with_syncs(spaces, self.blend_syncs))

        ratios = self.lod_ratios
        if isinstance(ratios, str):
            ratios = parse_ratios(ratios) if ratios else ()
        elif ratios:
            ratios = parse_ratios(",".join(str(r) for r in ratios))
        object.__setattr__(self, "lod_ratios", tuple(ratios or ()))
        if self.lod_screen_sizes is not None:
            sizes = self.lod_screen_sizes
            if isinstance(sizes, str):
                try:
                    sizes = [float(v) for v in sizes.split(",")]
                except ValueError:
                    raise OptionsError(f"--lod-screen-sizes takes numbers separated by commas, got {sizes!r}",
                                       file=where) from None
            if not self.lod_ratios:
                raise OptionsError("--lod-screen-sizes needs --lod-ratios (the levels they select)", file=where)
            object.__setattr__(self, "lod_screen_sizes",
                               check_screen_sizes(sizes, len(self.lod_ratios) + 1))
        object.__setattr__(self, "root_motion", check_mode(self.root_motion))
        if self.on_bad_clip not in BAD_CLIP_POLICIES:
            raise OptionsError(f"on_bad_clip must be one of {', '.join(BAD_CLIP_POLICIES)}, got "
                               f"{self.on_bad_clip!r}", file=where)
        object.__setattr__(self, "clips", tuple(str(c) for c in self.clips))
        encoding = str(getattr(self.encoding, "value", self.encoding))
        if encoding != AUTO:
            try:
                Encoding(encoding)
            except ValueError:
                allowed = ", ".join([AUTO] + [e.value for e in Encoding])
                raise OptionsError(f"encoding must be one of {allowed}, got {self.encoding!r}", file=where) from None
        object.__setattr__(self, "encoding", encoding)
        for name, kind in (("texel_format", TexelFormat), ("horizontal_padding", Padding),
                           ("vertical_padding", Padding)):
            value = str(getattr(getattr(self, name), "value", getattr(self, name)))
            try:
                kind(value)
            except ValueError:
                allowed = ", ".join(e.value for e in kind)
                raise OptionsError(f"{name} must be one of {allowed}, got {value!r}", file=where) from None
            object.__setattr__(self, name, value)
        if self.encoding == AUTO:
            # a texel format that holds one encoding only (uint32: the compact one) decides "auto"
            only = [e for e in Encoding if texel_formats_of(e) == (TexelFormat(self.texel_format),)]
            if only:
                object.__setattr__(self, "encoding", only[0].value)
        elif pairing_error(self.encoding, self.texel_format):
            raise OptionsError(pairing_error(self.encoding, self.texel_format), file=where)
        if self.container is None:
            object.__setattr__(self, "container", default_container(self.texel_format))
        mismatch = container_error(self.container, self.texel_format)
        if mismatch:
            raise OptionsError(mismatch, file=where)
        rate = self.rows_per_second
        if rate is not None:
            if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
                raise OptionsError(f"rows per second must be a positive number, got {rate!r}", file=where)
        k = self.max_influences
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= 64:
            raise OptionsError(f"max influences must be an integer in 1..64, got {k!r}", file=where)
        if self.frame_range is not None:
            try:
                start, end = (float(v) for v in self.frame_range)
            except (TypeError, ValueError):
                raise OptionsError(f"frame range must be START END, got {self.frame_range!r}", file=where) from None
            if not (math.isfinite(start) and math.isfinite(end)) or end < start:
                raise OptionsError(f"frame range must be finite with START <= END, got {start:g} {end:g}",
                                   file=where)
            object.__setattr__(self, "frame_range", (start, end))
        if self.check_rows is not None and (isinstance(self.check_rows, bool) or int(self.check_rows) < 0):
            raise OptionsError(f"check rows must be a non-negative integer, got {self.check_rows!r}", file=where)
        object.__setattr__(self, "skeletons", tuple(str(s) for s in self.skeletons))

    def bake_options(self, encoding: Encoding, up_axis: str = "Y") -> BakeOptions:
        """The :class:`BakeOptions` for one animation baked with ``encoding`` (``up_axis``: the scene's)."""
        return BakeOptions(encoding=encoding, texel_format=self.texel_format,
                           rows_per_second=self.rows_per_second, horizontal_padding=self.horizontal_padding,
                           vertical_padding=self.vertical_padding, max_influences=int(self.max_influences),
                           loop=self.loop, root_motion=self.root_motion,
                           up_axis="Z" if str(up_axis).upper() == "Z" else "Y", masks=self.masks,
                           blend_spaces=self.blend_spaces, markers=self.markers)


def with_syncs(spaces: tuple, syncs) -> tuple:
    """``spaces`` with the sync markers of ``--blend-sync SPACE=MARKER`` values (spec 23.3).

    Raises:
        OptionsError: Not SPACE=MARKER, or a space not given (code ``convert.blendSpace``).
    """
    spaces = list(spaces)
    for text in syncs or ():
        name, _, marker = str(text).partition("=")
        found = [k for k, s in enumerate(spaces) if s.name == name]
        if not marker or not found:
            raise OptionsError(f"--blend-sync takes SPACE=MARKER for a --blend-space SPACE, got {text!r}",
                               file="convert", code="convert.blendSpace")
        spaces[found[0]] = dataclasses.replace(spaces[found[0]], sync_marker=marker)
    return tuple(spaces)


def parse_masks(masks) -> tuple:
    """``--mask`` values as ``(name, bone)`` pairs: each a ``"NAME=BONE"`` string or a pair.

    Raises:
        OptionsError: A value that is not ``NAME=BONE`` with both parts non-empty (code ``convert.mask``).
    """
    pairs = []
    for mask in masks or ():
        if isinstance(mask, str):
            name, _, bone = mask.partition("=")
        else:
            try:
                name, bone = mask
            except (TypeError, ValueError):
                name, bone = "", ""
        name, bone = str(name).strip(), str(bone).strip()
        if not name or not bone:
            raise OptionsError(f"--mask must be NAME=BONE (a mask name and the bone it starts at), got {mask!r}",
                               file="convert", code="convert.mask")
        for part, text in (("name", name), ("bone", bone)):
            # A byte that is not UTF-8 on the command line arrives as a lone surrogate, which no
            # sidecar (JSON, UTF-8) or USD token can hold (spec "Layers and bone masks").
            if not is_unicode_text(text):
                raise OptionsError(f"--mask {mask!r}: the mask {part} is not UTF-8 text", file="convert",
                                   code="convert.mask")
        pairs.append((name, bone))
    return tuple(pairs)


@dataclass
class MeshReport:
    """Accuracy of one converted mesh against the source's own skinning.

    Attributes:
        path: Prim path.
        points: Vertex count.
        source_influences: Influences per vertex in the source.
        kept_influences: Influences per vertex in the texture binding.
        max_error: Largest distance (scene units) between decoded and reference points over the
            checked rows; None when not checked.
        max_error_fraction: ``max_error`` over the diagonal of the reference points' bounding box.
        influence_error: Largest distance that dropping influences alone adds (exact matrices, all
            influences vs kept influences), scene units.
        max_normal_error_degrees: Largest angle between decoded and reference normals, or None.
        rows_checked: Rows compared.
        renormalization_error: For a glTF mesh whose weights did not sum to one: the largest
            distance between skinning with the weights as stored and with the renormalized ones
            (what renormalizing changes; the reference is the renormalized source, as engines
            show it), scene units; None otherwise.
    """

    path: str
    points: int
    source_influences: int
    kept_influences: int
    max_error: Optional[float] = None
    max_error_fraction: Optional[float] = None
    influence_error: Optional[float] = None
    max_normal_error_degrees: Optional[float] = None
    rows_checked: int = 0
    renormalization_error: Optional[float] = None


@dataclass
class SkippedClip:
    """A clip ``--on-bad-clip skip`` left out: the animation prim, the clip and the bake error."""

    animation: str
    clip: str
    reason: str


@dataclass
class ClipReport:
    """One clip of a baked animation: its rows, rate, looping and start on the source's timeline."""

    name: str
    rows: int
    rows_per_second: float
    loop: bool
    start_time: float


@dataclass
class AnimationReport:
    """What one baked animation holds (``clips``: :class:`ClipReport` objects)."""

    path: str
    encoding: str
    encoding_reason: str
    texel_format: str
    bones: int
    rows: int
    clips: list
    width: int
    height: int
    texel_bytes: int
    used_texel_bytes: int
    padding_fraction: float
    meshes: list = field(default_factory=list)


@dataclass
class ConvertReport:
    """The summary ``vbusd convert`` prints (as a table or JSON).

    Attributes:
        source: Input file.
        output: Written USD file.
        converter: Converter name.
        reference: What the errors are measured against.
        meters_per_unit: The scene unit of every distance in the report (the stage's metersPerUnit).
        animations: One :class:`AnimationReport` per skeleton.
        warnings: The converter's and the conversion's warnings.
        files: Files written, with their sizes in bytes.
        seconds: Wall time per step.
        skipped_clips: :class:`SkippedClip` objects (``--on-bad-clip skip``).
        up_axis: The stage's up axis (``Y`` or ``Z``).
    """

    source: str
    output: str
    converter: str
    reference: str
    meters_per_unit: Optional[float] = None
    animations: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    files: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    skipped_clips: list = field(default_factory=list)
    up_axis: Optional[str] = None

    def to_dict(self) -> dict:
        """The report as ``vbusd convert --format json`` prints it: camelCase keys, times rounded
        (:func:`vbusd.format.jsonform.json_ready`)."""
        return json_ready(self)


# --------------------------------------------------------------------------------------------


def check_output(source: Path, output: Path, options: ConvertOptions) -> None:
    """Refuse an output that cannot be written, or exists without ``force`` (before any work):
    :func:`vbusd.io.paths.check_output_path` with the options' ``force``.

    Raises:
        OptionsError: Wrong suffix, missing folder, output is the source, or exists without force.
    """
    check_output_path(source, output, force=options.force)


def _dual_quaternion_meshes(scene: SourceScene, index: int, animation: SkinnedAnimation) -> tuple[list, list]:
    methods = getattr(scene, "skinning_methods", ())
    if index >= len(methods):
        return [], [m.path for m in animation.meshes]
    dqs = [m.path for m, method in zip(animation.meshes, methods[index]) if method == "dualQuaternion"]
    lbs = [m.path for m, method in zip(animation.meshes, methods[index]) if method != "dualQuaternion"]
    return dqs, lbs


def _texture_files(scene: SourceScene, output: Path, options: ConvertOptions) -> list:
    """The texture and sidecar files the writer will create (``<stem>.<animation prim name>.<ext>``)."""
    files = []
    for animation in scene.animations:
        prim_name = animation.path.rstrip('/').rsplit('/', 1)[-1]
        texture = output.parent / texture_file_name(output.stem, prim_name, options.container)
        files += [texture, texture.with_name(texture.name + ".json")]
    return files


def _check_texture_files(scene: SourceScene, output: Path, options: ConvertOptions) -> None:
    """Without ``force``, refuse to replace a texture or sidecar that already lies beside the output."""
    if options.force:
        return

    if journal_path(output).exists():  # a killed run's files are removed first, not taken for ours

        recover(output, in_use=asset_files_in_use)
    for path in _texture_files(scene, output, options):
        if path.exists():
            raise OptionsError(f"{path.name} exists beside the output and would be replaced; {FORCE_HINT}",
                               file=str(output))


def bake_animation(scene: SourceScene, index: int, options: ConvertOptions) -> tuple[VirtualBones, str, list]:
    """Bake one animation, choosing the encoding when ``options.encoding`` is ``auto``.

    Returns:
        (baked animation, why this encoding, warnings).

    Raises:
        UnsupportedError: The chosen encoding cannot hold the animation, or the source mixes
            skinning methods the format cannot hold in one texture.
    """
    animation = scene.animations[index]  # bake refuses too many rows before sampling any
    dqs, lbs = _dual_quaternion_meshes(scene, index, animation)
    warnings = []
    if dqs and lbs:
        raise UnsupportedError(f"meshes bound to one skeleton mix dual-quaternion skinning ({dqs[0]}) and "
                               f"linear blend skinning ({lbs[0]}); one Virtual Bones texture decodes with one "
                               "method", file=scene.source, location=animation.path, code="convert.mixedSkinning")
    if options.encoding == AUTO:
        if dqs:
            return bake(animation, options.bake_options(Encoding.DUAL_QUAT, scene.up_axis)), \
                "auto: the source uses dual-quaternion skinning (skel:skinningMethod)", warnings
        try:
            return bake(animation, options.bake_options(Encoding.CROSS_MATRIX, scene.up_axis)), \
                "auto: every bone transform is rigid", warnings
        except UnsupportedError as error:
            if error.code != "encoding.nonRigid":
                raise
            reason = f"auto: crossMatrix cannot hold it ({error.message.split(';')[0]})"
            return bake(animation, options.bake_options(Encoding.AFFINE_MATRIX, scene.up_axis)), reason, warnings
    encoding = Encoding(options.encoding)
    if dqs and encoding is not Encoding.DUAL_QUAT:
        raise UnsupportedError(f"{dqs[0]} uses skel:skinningMethod dualQuaternion, which {encoding.value} "
                               "decodes with linear blend skinning; use --encoding dualQuat (or auto)",
                               file=scene.source, location=dqs[0], code="convert.dualQuaternion")
    if encoding is Encoding.DUAL_QUAT and not dqs:
        warnings.append(f"{animation.path}: the source skins with linear blend skinning; dualQuat decodes "
                        "with dual-quaternion skinning (the error report shows the difference)")
    return bake(animation, options.bake_options(encoding, scene.up_axis)), "requested", warnings


def _clip_at_fault(error: VbusdError, animation: SkinnedAnimation) -> Optional[str]:
    """The clip a bake error names (its message says ``clip 'NAME'``), or None."""
    for clip in animation.clips:
        if f"clip '{clip.name}'" in error.message:
            return clip.name
    return None


def _with_animation(scene: SourceScene, index: int, animation: SkinnedAnimation) -> SourceScene:
    animations = list(scene.animations)
    animations[index] = animation
    return dataclasses.replace(scene, animations=tuple(animations))


def bake_with_clip_policy(scene: SourceScene, index: int, options: ConvertOptions,
                          skipped: list) -> Optional[tuple]:
    """Bake one animation under ``options.on_bad_clip`` (spec: usd-conversion.md, Clips).

    A bake error that names a clip (``encoding.nonRigid``, a singular or overflowing transform) is,
    with ``error``, raised with a hint to ``--on-bad-clip skip`` and ``--clips`` when the scene has
    more than one clip. With ``skip`` every clip is baked alone to find each one that fails; those
    are left out (appended to ``skipped`` as :class:`SkippedClip`) and the rest are baked together.

    Returns:
        ``(scene, baked, reason, warnings)`` where ``scene`` holds the animation with the clips
        that were baked; None when every clip of the animation was skipped.

    Raises:
        VbusdError: An error that names no clip, or a bad clip under ``error``.
    """
    original = scene.animations[index]
    # Every bake below (auto's second encoding, each clip alone under skip) reuses the poses the
    # first one sampled: a source is sampled once per clip and time, however often it is baked.
    animation = dataclasses.replace(original, clips=tuple(dataclasses.replace(c, sample=_SampledOnce(c.sample))
                                                          for c in original.clips))
    scene = _with_animation(scene, index, animation)
    try:
        return _released(bake_animation(scene, index, options), scene, index, original)
    except (UnsupportedError, InputError) as error:
        bad_clip = _clip_at_fault(error, animation)
        if bad_clip is None:
            raise
        if options.on_bad_clip == "error":
            if sum(len(a.clips) for a in scene.animations) > 1:
                error.message += (f" (clip '{bad_clip}' stops the whole file: convert the other clips with "
                                  "--on-bad-clip skip, or choose clips with --clips)")
            raise
        first_error = error
    bad = {}
    for clip in animation.clips:
        alone = dataclasses.replace(animation, clips=(clip,))
        try:
            bake_animation(_with_animation(scene, index, alone), index, options)
        except (UnsupportedError, InputError) as error:
            if _clip_at_fault(error, alone) != clip.name:
                raise
            bad[clip.name] = f"{error.code}: {error.message}"
    if not bad:
        raise first_error
    for name, reason in bad.items():
        skipped.append(SkippedClip(animation=animation.path, clip=name, reason=reason))
    kept = tuple(c for c in animation.clips if c.name not in bad)
    if not kept:
        return None
    scene = _with_animation(scene, index, dataclasses.replace(animation, clips=kept))
    return _released(bake_animation(scene, index, options), scene, index,
                     dataclasses.replace(original, clips=tuple(c for c in original.clips if c.name not in bad)))


class _SampledOnce:
    """A clip's sampler that keeps what it sampled: asked again for the same times (the same rows of
    a second bake), it answers from memory instead of evaluating the source again."""

    def __init__(self, sample) -> None:
        self._sample = sample
        self._kept: dict = {}

    @property
    def on_progress(self):
        return getattr(self._sample, "on_progress", None)

    @on_progress.setter
    def on_progress(self, callback) -> None:
        if hasattr(self._sample, "on_progress"):
            self._sample.on_progress = callback

    def __call__(self, times):
        times = np.asarray(times, dtype=np.float64)
        key = (times.shape, times.tobytes())
        if key not in self._kept:
            poses = np.asarray(self._sample(times), dtype=np.float64)
            poses.setflags(write=False)
            self._kept[key] = poses
        return self._kept[key]


def _released(outcome: tuple, scene: SourceScene, index: int, original: SkinnedAnimation) -> tuple:
    """``(scene, *outcome)`` with the animation's own samplers back (the kept poses are let go)."""
    return (_with_animation(scene, index, original),) + outcome


def _checked_rows(row_count: int, check_rows: Optional[int]) -> np.ndarray:
    if check_rows is None or check_rows >= row_count:
        return np.arange(row_count)
    if check_rows == 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, row_count - 1, int(check_rows))).astype(np.int64))


def _source_lbs(matrices: np.ndarray, points: np.ndarray, indices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Float64 LBS with exact source matrices (n, B, 4, 4): the influence-reduction yardstick.

    The reference skinning of :mod:`vbusd.decoders.reference`, fed the source's matrices instead of decoded
    ones, with the weights normalized as the baker normalizes them.
    """

    linear = matrices[..., :3, :3]
    transforms = BoneTransforms(linear=linear, translation=matrices[..., :3, 3], normal=linear)
    w = np.asarray(weights, dtype=np.float64)
    return skin(transforms, Encoding.AFFINE_MATRIX, points, indices, w / w.sum(axis=1, keepdims=True))[0]


def _skin_checked(transforms, encoding: Encoding, bound, normal_points) -> tuple:
    """The reference decoder's skinning of a bound mesh; linear blend skinning of many points runs
    compiled (:func:`vbusd.kernels.bake.skin_lbs`, the same sums in the same order)."""

    if encoding is not Encoding.DUAL_QUAT:
        indices, weights = np.asarray(bound.bone_indices), np.asarray(bound.bone_weights)
        normal_indices = indices if normal_points is None else indices[normal_points]
        normal_weights = weights if normal_points is None else weights[normal_points]
        compiled = bake_kernels.skin_lbs(transforms.linear, transforms.translation, transforms.normal, bound.points,
                                         indices, weights, bound.normals, normal_indices, normal_weights)
        if compiled is not None:
            return compiled
    return skin(transforms, encoding, bound.points, bound.bone_indices, bound.bone_weights, bound.normals,
                normal_points)


def _largest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance between matching (..., 3) points (0 for none), without per-point norms."""
    d = a - b
    d *= d
    return float(np.sqrt((d[..., 0] + d[..., 1] + d[..., 2]).max(initial=0.0)))


def _box_of(points: np.ndarray) -> tuple:
    """``(low (3,), high (3,))`` of (..., 3) points, one axis at a time (a reduction over the
    points' axis with 3-wide rows is several times slower)."""
    return (np.array([points[..., i].min(initial=np.inf) for i in range(3)]),
            np.array([points[..., i].max(initial=-np.inf) for i in range(3)]))


def _raw_weights(scene: SourceScene, index: int, mesh_index: int):
    """``(weights, joints)`` as stored for a mesh whose weights were renormalized, else None."""
    table = getattr(scene, "raw_weights", ())
    if index < len(table) and mesh_index < len(table[index]):
        return table[index][mesh_index]
    return None


def _chunks(total: int, size: int):
    for start in range(0, total, size):
        yield slice(start, min(total, start + size))


def measure_errors(scene: SourceScene, index: int, vb: VirtualBones, check_rows: Optional[int],
                   progress: Optional[Progress] = None) -> list:
    """Compare every bound mesh of one baked animation with the source's own skinning.

    Args:
        scene: The source scene (its ``reference`` callable, when present, is the yardstick; else
            float64 LBS of the source matrices with all influences).
        index: Animation index.
        vb: The baked animation.
        check_rows: See :attr:`ConvertOptions.check_rows`.
        progress: Progress callback.

    Returns:
        One :class:`MeshReport` per mesh.
    """

    animation = scene.animations[index]
    reference = getattr(scene, "reference", None)
    reports = []
    for mesh_index, (source_mesh, bound) in enumerate(zip(animation.meshes, vb.meshes)):
        reports.append(MeshReport(path=bound.path, points=int(bound.points.shape[0]),
                                  source_influences=int(np.asarray(source_mesh.bone_indices).shape[1]),
                                  kept_influences=bound.max_influences))
    if check_rows == 0:
        return reports
    plans = [(ci, clip, _checked_rows(clip.row_count, check_rows)) for ci, clip in enumerate(vb.clips)]
    total = sum(len(rows) for _, _, rows in plans) * max(1, len(vb.meshes))
    done = 0
    lows = [np.full(3, np.inf) for _ in vb.meshes]
    highs = [np.full(3, -np.inf) for _ in vb.meshes]
    for clip_index, clip, rows in plans:
        source_clip = animation.clips[clip_index]
        for mesh_index, (source_mesh, bound) in enumerate(zip(animation.meshes, vb.meshes)):
            report = reports[mesh_index]
            vertex_count = bound.points.shape[0]
            chunk = max(1, int(2_000_000 // max(1, vertex_count * bound.max_influences)))
            for part in _chunks(len(rows), chunk):
                chosen = rows[part]
                tau = chosen / clip.rows_per_second
                times = clip.start_time + tau
                transforms = bone_transforms(vb, clip_index, tau)
                decoded, decoded_normals = _skin_checked(transforms, vb.layout.encoding, bound,
                                                         normal_point_indices(bound))
                if vb.root_motion is not None:
                    # Clips baked in place (spec "Root motion"): the root track gives back the source motion.

                    moves = np.stack([root_at(vb.root_motion.tracks[clip_index], clip, t, vb.root_motion.up_axis)
                                      for t in tau])
                    decoded = np.einsum("nij,nvj->nvi", moves[:, :3, :3], decoded) + moves[:, None, :3, 3]
                    if decoded_normals is not None:
                        decoded_normals = np.einsum("nij,nvj->nvi", moves[:, :3, :3], decoded_normals)
                # Dropping influences only matters when the source has more than were kept; then
                # compare exact-matrix LBS with all influences and with the kept ones.
                reduced = report.source_influences > report.kept_influences
                raw = _raw_weights(scene, index, mesh_index)
                full = None
                if reduced or reference is None or raw is not None:
                    exact = np.asarray(source_clip.sample(times), dtype=np.float64)
                    full = _source_lbs(exact, source_mesh.points, np.asarray(source_mesh.bone_indices),
                                       np.asarray(source_mesh.bone_weights))
                if reference is not None:
                    ref_points, ref_normals = reference(index, mesh_index, times)
                else:
                    ref_points, ref_normals = full, None
                error = _largest_distance(decoded, ref_points)
                dropped = 0.0
                if reduced:
                    kept = _source_lbs(exact, source_mesh.points, bound.bone_indices, bound.bone_weights)
                    dropped = _largest_distance(kept, full)
                if raw is not None:
                    # With the weights as stored, summing to s, LBS gives s times the renormalized
                    # point: renormalizing moves each vertex by |1 - s| times its distance from the origin.
                    sums = np.asarray(raw[0], dtype=np.float64).sum(axis=1)
                    moved = np.abs(1.0 - sums)[None, :] * np.linalg.norm(full, axis=-1)
                    report.renormalization_error = max(report.renormalization_error or 0.0,
                                                       float(moved.max(initial=0.0)))
                report.max_error = max(report.max_error or 0.0, error)
                report.influence_error = max(report.influence_error or 0.0, dropped)
                low, high = _box_of(ref_points)
                lows[mesh_index] = np.minimum(lows[mesh_index], low)
                highs[mesh_index] = np.maximum(highs[mesh_index], high)
                if ref_normals is not None and decoded_normals is not None and ref_normals.shape == decoded_normals.shape:
                    # arccos falls as the cosine rises: the largest angle is that of the smallest cosine
                    cosine = np.einsum("nvi,nvi->nv", decoded_normals, ref_normals).min(initial=1.0)
                    angle = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
                    report.max_normal_error_degrees = max(report.max_normal_error_degrees or 0.0, angle)
                report.rows_checked += len(chosen)
                done += len(chosen)
                if progress:
                    progress("check", done, total)
    for report, low, high in zip(reports, lows, highs):
        if report.max_error is not None:
            diagonal = float(np.linalg.norm(high - low)) if np.all(np.isfinite(low)) else 0.0
            report.max_error_fraction = report.max_error / diagonal if diagonal > 0 else 0.0
    return reports


LARGE_SOURCE_BYTES = 2 << 20
"""A source file this large is likely to bake enough matrices for :mod:`vbusd.kernels.bake`."""


def _prepare_for(source: Path) -> None:
    """Load everything the conversion and its helper threads will use, before any helper starts
    (vbusd/process/threads.py): the modules, USD's plugins and, for a large source, the compiled bake
    kernels. A large crate source is probed meanwhile: the request goes to the probe server, whose
    child reads the file while this thread loads, and the answer is read after (no thread: the
    reader's own probe of the file is then a lookup)."""

    try:
        large = source.stat().st_size >= LARGE_SOURCE_BYTES
    except OSError:
        large = False  # the reader says why, in its words
    pending = None
    if large:

        pending = usd_probe.start_probe(source)
    try:
        warmup.prepare("convert", kernels=large)
    except BaseException:
        if pending is not None:
            pending.cancel()  # interrupted: do not wait for the answer
        raise
    if pending is not None:
        pending.result()  # its problem, if any, is reported by the reader's own probe


class _CheckStopped(Exception):
    """Ends an accuracy check whose conversion was interrupted (never reaches the caller)."""


def _write_checked(scene: SourceScene, baked: list, output: Path, options: ConvertOptions, check_result,
                   seconds: dict, progress: Optional[Progress]) -> list:
    """Write the converted asset; its commit waits for the accuracy check (``check_result()``)."""

    asset = VirtualBonesAsset(animations=tuple(baked), up_axis=scene.up_axis,
                              meters_per_unit=scene.meters_per_unit,
                              time_codes_per_second=scene.time_codes_per_second,
                              default_prim=scene.default_prim)
    clock = time.perf_counter()
    if progress:
        progress("write", 0, 1)
    if output.exists() and not options.force:  # it may have appeared while we worked
        raise OptionsError(f"the output exists; {FORCE_HINT}", file=str(output))
    _check_texture_files(scene, output, options)
    created = make_folders(output.parent)
    try:
        # replace=force: the existence check is repeated under the output lock, so two runs
        # without --force cannot both create the output (the second is refused).
        written = write_asset(asset, output, texture_container=options.container, replace=options.force,
                              before_commit=check_result)
    except BaseException as error:
        remove_folders(created)  # the transaction left nothing in them; leave no trace
        if isinstance(error, OSError):  # disk full, permission denied: one line, not a traceback
            raise VbusdError(f"cannot write the output (nothing was written): "
                             f"{error.strerror or error}", file=str(output), code="convert.write") from None
        raise
    seconds["write"] = time.perf_counter() - clock
    if progress:
        progress("write", 1, 1)
    return written


def convert(source, output, options: ConvertOptions = ConvertOptions(),
            progress: Optional[Progress] = None) -> ConvertReport:
    """Convert a skinned source file into a Virtual Bones USD asset.

    Args:
        source: Input file (UsdSkel .usd/.usda/.usdc/.usdz, glTF .gltf/.glb, or a plugin's format).
        output: The USD layer to write (.usda, .usd or .usdc); the texture and sidecar go beside it.
        options: Conversion options (checked before any work).
        progress: Optional ``progress(step, done, total)`` callback.

    Returns:
        The :class:`ConvertReport` summary.

    Raises:
        OptionsError: Bad options or output path (before any work).
        InputError: The source is unreadable or breaks its format's rules.
        UnsupportedError: The source holds what the format cannot (the message names the prim).
    """

    if not isinstance(options, ConvertOptions):
        raise OptionsError(f"options must be ConvertOptions, got {type(options).__name__}", file="convert")
    source, output = Path(source), Path(output)
    check_output(source, output, options)
    seconds = {}

    clock = time.perf_counter()
    if progress:
        progress("read", 0, 1)
    converter = registry.find_converter(registry.check_source(source), options.converter)
    _prepare_for(source)
    read_options = ReadOptions(skeletons=options.skeletons, time_range=options.frame_range,
                               allow_outside_paths=options.allow_outside_paths, clips=options.clips,
                               strict_weights=options.strict_weights)
    scene = converter.read(source, read_options)
    seconds["read"] = time.perf_counter() - clock
    if progress:
        progress("read", 1, 1)

    _check_texture_files(scene, output, options)

    clock = time.perf_counter()
    baked, reasons, warnings, kept, skipped = [], [], list(scene.warnings), [], []
    for index in range(len(scene.animations)):
        if progress:  # long clips: let a sampler that evaluates row by row report as it goes
            for clip in scene.animations[index].clips:
                if hasattr(clip.sample, "on_progress"):
                    clip.sample.on_progress = lambda done, total: progress("bake", done, total)
        outcome = bake_with_clip_policy(scene, index, options, skipped)
        for clip in scene.animations[index].clips:
            if getattr(clip.sample, "on_progress", None) is not None:
                clip.sample.on_progress = None
        if outcome is None:
            warnings.append(f"{scene.animations[index].path}: every clip was skipped (--on-bad-clip skip); "
                            "the animation and its meshes are left out")
            continue
        scene, vb, reason, extra = outcome
        extra = list(extra)
        if not any(m.lod for m in vb.meshes):

            # Meshes named for their level (Body_LOD0, Body_LOD1: spec 20.3) are levels too.
            vb = levels_from_names(vb) or vb
        source_levels = any(m.lod for m in vb.meshes)
        if source_levels and options.lod_ratios:
            raise OptionsError(f"{vb.path}: the source has levels of detail already (glTF MSFT_lod); leave "
                               "out --lod-ratios to keep them", file=str(source), location="--lod-ratios",
                               code="options.invalid")
        if source_levels and scene.animations[index].lods is not None:
            # A USD source's UsdLod root: the meshes already lie under its levels (spec 20.3).
            vb = dataclasses.replace(vb, lods=scene.animations[index].lods)
        elif source_levels:

            # The source's own levels (spec 20.3), every one bound to the one texture.
            vb = adopt_levels(vb, scene.animations[index].lod_screen_sizes)
        elif options.lod_ratios:

            # After the bake: every level shares the texture and its clip extents (spec 20.3).
            vb = add_levels(vb, options.lod_ratios, screen_sizes=options.lod_screen_sizes, warnings=extra)
        kept.append(index)
        baked.append(vb)
        reasons.append(reason)
        warnings.extend(extra)
        if progress:
            progress("bake", index + 1, len(scene.animations))
    seconds["bake"] = time.perf_counter() - clock

    for item in skipped:
        warnings.append(f"{item.animation}: clip '{item.clip}' skipped (--on-bad-clip skip): {item.reason}")
    if not baked:
        first = skipped[0] if skipped else None
        raise UnsupportedError("every clip was skipped, nothing to convert"
                               + (f" (first: clip '{first.clip}': {first.reason})" if first else ""),
                               file=str(source), location=first.animation if first else None,
                               code="convert.nothingConverted")

    interrupted = threading.Event()
    counts: dict = {}

    def check_progress(step: str, done: int, total: int) -> None:
        if interrupted.is_set():  # Ctrl-C or SIGTERM in the command: stop at the next chunk
            raise _CheckStopped()
        counts[step] = (done, total)  # reported by the calling thread (a callback may import)

    def check() -> list:
        started = time.perf_counter()
        reports = [measure_errors(scene, i, vb, options.check_rows, check_progress) for i, vb in zip(kept, baked)]
        seconds["check"] = time.perf_counter() - started
        return reports

    def check_result() -> list:
        """The check's reports, waited for in the calling thread, passing its progress on."""
        while True:
            try:
                return checking.result(timeout=0.2)
            except FuturesTimeout:
                if progress:
                    for step, (done, total) in list(counts.items()):
                        progress(step, done, total)

    # The accuracy check runs while the textures are compressed and staged; the write waits for it
    # before its commit point, so a check that fails still leaves nothing written. Everything the
    # check and the write use is loaded before the check's thread starts (vbusd/process/threads.py).
    warmup.prepare("convert")
    pool = ThreadPoolExecutor(1, thread_name_prefix="vbusd-check")
    checking = pool.submit(check)
    try:
        written = _write_checked(scene, baked, output, options, check_result, seconds, progress)
    except Exception:
        failed = checking.exception()  # the check's own error came first, as before the overlap
        if failed is not None:
            raise failed from None
        raise
    except BaseException:
        interrupted.set()
        raise
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    mesh_reports = check_result()

    files = {str(path): Path(path).stat().st_size for path in written}  # the layer, then texture, sidecar
    reference_name = getattr(scene, "reference_name", None) if getattr(scene, "reference", None) else None
    report = ConvertReport(
        source=str(source), output=str(output), converter=converter.NAME,
        reference=reference_name or "source skinning matrices, float64 LBS with all influences",
        meters_per_unit=scene.meters_per_unit, up_axis=scene.up_axis, skipped_clips=skipped,
        warnings=warnings, files=files, seconds={k: round(v, 4) for k, v in seconds.items()})
    for vb, reason, meshes in zip(baked, reasons, mesh_reports):
        layout = vb.layout
        report.animations.append(AnimationReport(
            path=vb.path, encoding=layout.encoding.value, encoding_reason=reason,
            texel_format=layout.texel_format.value, bones=layout.bone_count, rows=layout.row_count,
            clips=[ClipReport(name=c.name, rows=c.row_count, rows_per_second=c.rows_per_second, loop=c.loop,
                              start_time=c.start_time) for c in vb.clips],
            width=layout.width, height=layout.height, texel_bytes=layout.texel_bytes,
            used_texel_bytes=layout.used_texel_bytes, padding_fraction=layout.padding_fraction,
            meshes=meshes))
    return report
