"""The pure data model: what converters produce and what writers, validators and decoders consume.

Two halves:

* the *source* side, :class:`SkinnedAnimation`: bones, rest meshes and clips whose skinning matrices
  can be sampled at any time (a converter's output, before any texture exists);
* the *baked* side, :class:`VirtualBones` (one texture and the meshes bound to it) grouped in a
  :class:`VirtualBonesAsset` (what one USD file holds).

Conventions used everywhere in vbusd (spec/virtual-bones.md, "Coordinate conventions"):

* matrices are float64 ``(..., 4, 4)`` acting on column vectors, ``p' = M[:3, :3] @ p + M[:3, 3]``;
  USD's row-vector matrices are transposed on the way in and out;
* quaternions are ``(x, y, z, w)``;
* times are seconds on the source's timeline.

Nothing here does I/O.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from vbusd.format.digest import content_digest
from vbusd.format.layout import Layout
from vbusd.format.rootmotion import RootMotion
import dataclasses

__all__ = ["AnimationClip", "SkinnedMesh", "SkinnedAnimation", "Clip", "BoundMesh", "Crowd",
           "LevelsOfDetail", "VirtualBones", "VirtualBonesAsset", "ReadOptions", "SourceScene"]

MatrixSampler = Callable[[np.ndarray], np.ndarray]
"""``sample(times) -> (len(times), bone_count, 4, 4)`` float64 skinning matrices at source times (s)."""


def _frozen_array(value, dtype, ndim: int, name: str) -> np.ndarray:
    array = np.array(value, dtype=dtype, copy=True)
    if array.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {array.shape}")
    array.setflags(write=False)
    return array


# --------------------------------------------------------------------------------------------
# Source side
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AnimationClip:
    """One source animation clip whose skinning matrices can be sampled at any time.

    Attributes:
        name: Clip name (unique within its animation).
        start_time: Source time of the clip's first pose, seconds.
        end_time: Source time of the clip's last pose, seconds (>= start_time).
        sample: Skinning matrices at given source times, see :data:`MatrixSampler`. Times outside
            [start_time, end_time] hold the first or last pose.
        native_rate: Keys per second of the source (the default rows per second), or None.
        loop: True, False, or None to let the baker decide (loops when the first and last poses
            agree).
        key_times: The source's own key times (seconds), used to report and to resample exactly.
    """

    name: str
    start_time: float
    end_time: float
    sample: MatrixSampler
    native_rate: Optional[float] = None
    loop: Optional[bool] = None
    key_times: Optional[np.ndarray] = None

    @property
    def duration(self) -> float:
        """end_time - start_time, seconds."""
        return float(self.end_time - self.start_time)


@dataclass(frozen=True)
class SkinnedMesh:
    """A rest mesh bound to the bones of a :class:`SkinnedAnimation`.

    Points and normals are in the animation's space at bind pose (any geomBindTransform already
    applied), so that ``deformed = sum_i w_i * M_i @ p``.

    Attributes:
        path: Prim path the mesh has (or gets) in USD, absolute, e.g. ``/Character/Body``.
        points: (V, 3) rest positions.
        face_vertex_counts: (F,) vertices per face.
        face_vertex_indices: (sum counts,) point index of each face-vertex.
        bone_indices: (V, K) indices into the animation's bones.
        bone_weights: (V, K) weights, each row summing to one (K may exceed the bake's maximum).
        normals: (V, 3) or (face-vertices, 3) rest normals, or None.
        normals_interpolation: ``vertex`` or ``faceVarying``.
        source_path: Where the mesh came from in its source, for messages.
        lod: The level of detail the source gives the mesh (glTF ``MSFT_lod``; format 1.2), 0 otherwise.
    """

    path: str
    points: np.ndarray
    face_vertex_counts: np.ndarray
    face_vertex_indices: np.ndarray
    bone_indices: np.ndarray
    bone_weights: np.ndarray
    normals: Optional[np.ndarray] = None
    normals_interpolation: str = "vertex"
    source_path: Optional[str] = None
    lod: int = 0


@dataclass(frozen=True)
class SkinnedAnimation:
    """A converter's output: bones, rest meshes and clips of one skeleton.

    Attributes:
        name: Name for the animation prim.
        path: Prim path of the animation prim to write, e.g. ``/Character/Anim``.
        bones: Bone names in texture order (UsdSkel joint paths or glTF node names).
        clips: One or more clips; each becomes a run of rows of the same texture.
        meshes: Meshes bound to these bones.
        source: The file the animation came from, for messages.
        bind_transforms: (bones, 4, 4) column-vector bind (rest) transforms ``B_b`` of the joints
            in animation space, so that a joint's transform is ``J_b = M_b B_b`` (spec "Bone
            transforms"; format 1.1, for sockets), or None when the converter does not know them.
        lod_screen_sizes: When the source gives its meshes levels of detail (``SkinnedMesh.lod``),
            the screen sizes below which LOD 1, 2, ... take over (spec "Levels of detail"), else None.
        lods: The source's own UsdLod root when the meshes' paths already lie under its levels
            (a USD source), kept as it is; None otherwise.
        bone_parents: (bones,) index of each bone's parent bone, -1 for a root (format 1.2, for
            layers and masks), or None when the converter does not know them.
    """

    name: str
    path: str
    bones: tuple
    clips: tuple
    meshes: tuple = ()
    source: Optional[str] = None
    bind_transforms: Optional[np.ndarray] = None
    lod_screen_sizes: Optional[tuple] = None
    lods: Optional["LevelsOfDetail"] = None
    bone_parents: Optional[tuple] = None

    @property
    def bone_count(self) -> int:
        """Number of bones."""
        return len(self.bones)


# --------------------------------------------------------------------------------------------
# Baked side
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Clip:
    """A run of texture rows holding one animation clip (spec: "Clips").

    Attributes:
        name: Clip name.
        first_row: Texture row of the clip's first keyframe.
        row_count: Rows of the clip (N >= 1).
        rows_per_second: Playback rate of rows, > 0.
        loop: Looping clips wrap from their last row to their first; others clamp.
        start_time: Source time (seconds) of the clip's first row.
    """

    name: str
    first_row: int
    row_count: int
    rows_per_second: float
    loop: bool
    start_time: float = 0.0

    @property
    def duration(self) -> float:
        """Seconds the clip plays: N / rate when looping, (N - 1) / rate when clamped."""
        spans = self.row_count if self.loop else self.row_count - 1
        return spans / self.rows_per_second

    def row_time(self, row: int) -> float:
        """Source time (seconds) of clip row ``row`` (0-based within the clip)."""
        return self.start_time + row / self.rows_per_second


@dataclass(frozen=True)
class BoundMesh:
    """A rest mesh bound to a Virtual Bones texture (VirtualBonesBindingAPI).

    Attributes:
        path: Absolute prim path of the mesh.
        points: (V, 3) float32 rest positions in the animation's space.
        face_vertex_counts: (F,) int32.
        face_vertex_indices: (sum counts,) int32.
        bone_indices: (V, K) int32 indices into the texture's bones.
        bone_weights: (V, K) float32 weights, rows summing to one.
        normals: (V, 3) or (face-vertices, 3) float32 rest normals, or None.
        normals_interpolation: ``vertex`` or ``faceVarying``.
        lod: Level of detail the mesh belongs to (format 1.2, spec "Levels of detail"): 0 unless its
            animation has :class:`LevelsOfDetail`, whose root's child ``lod`` holds the mesh.
    """

    path: str
    points: np.ndarray
    face_vertex_counts: np.ndarray
    face_vertex_indices: np.ndarray
    bone_indices: np.ndarray
    bone_weights: np.ndarray
    normals: Optional[np.ndarray] = None
    normals_interpolation: str = "vertex"
    lod: int = 0

    @property
    def max_influences(self) -> int:
        """K: influences per vertex."""
        return int(self.bone_indices.shape[1])


@dataclass(frozen=True)
class Crowd:
    """Instances of one animation's meshes on a point instancer (VirtualBonesInstancingAPI).

    Per-instance clip time: ``tau = time_offset + playback_rate * t`` (spec: "Instancing").

    Attributes:
        path: Prim path of the UsdGeomPointInstancer.
        positions: (N, 3) float32.
        orientations: (N, 4) float32 unit quaternions (x, y, z, w).
        scales: (N, 3) float32, or None for 1.
        clip: (N,) int32 clip index of each instance.
        time_offset: (N,) float32 seconds.
        playback_rate: (N,) float32.
        fade_clip: (N,) int32 fade clip of each instance (format 1.1, spec "Crossfade"), or None
            for clip 0.
        fade_time_offset: (N,) float32 seconds of the fade clip at stage time 0, or None for 0.
        fade_playback_rate: (N,) float32 rate of the fade clip, or None for 1.
        fade_weight: (N,) float32 weight of the fade clip in [0, 1], or None for 0 (no crossfade).
        fade_samples: Time-sampled fade primvars (spec "Instancing": a crowd switches clips over
            time): ``{field: (stage times in seconds (S,), values (S, N))}`` for any of the four
            fields above; :meth:`at` evaluates them. None when none is time-sampled.
        layer_clip: (N, L) int32 clip of each instance's ``L`` layers (format 1.2, spec "Layers and
            bone masks"), or None for no layers.
        layer_time_offset: (N, L) float32 clip-local seconds of each layer at stage time 0.
        layer_playback_rate: (N, L) float32 clip seconds per stage second of each layer.
        layer_weight: (N, L) float32 weight of each layer in [0, 1] (0: the layer slot is unused).
        layer_mask: (N, L) int32 mask of each layer, an index into the animation's masks.
        layer_mode: (N, L) int32 mode of each layer (format 1.3, spec 23.4): 0 override, 1 additive;
            None: every layer overrides.
        layer_reference_clip: (N, L) int32 clip of each additive layer's reference pose, or None for
            the layer's own clip.
        layer_reference_time: (N, L) float32 clip-local seconds of the reference pose, or None for 0.
        blend_space: (N,) int32 blend space each instance plays (format 1.3, spec 23.7), an index into the
            animation's blend spaces, -1 for none (the instance plays its clip); None for none.
        blend_x: (N,) float32 blend parameter x, or None for 0.
        blend_y: (N,) float32 blend parameter y, or None for 0.
        blend_phase: (N,) float32 phase at stage time 0, or None for 0; the phase advances by
            ``playbackRate / sum w D`` per second (spec 23.3, 23.7).
        tint: (N, 3) float32 linear-RGB multiplier of each instance's base colour (format 1.3, spec
            "Crowd variety"), or None for (1, 1, 1).
        variant: (N,) int32 material variant of each instance, an index into ``variant_names``, or
            None for none (each mesh keeps its own material).
        variant_names: Names of the material variants, in order (empty: none).
        variant_colors: (V, 3) float32 linear base colour of each variant's material (what engines
            without USD's shading carry over), or None.
        parts: (N,) int32 parts mask of each instance, bit j showing part j, or None for every part.
        part_names: Names of the prototype's optional parts (its children of those names).
    """

    path: str
    positions: np.ndarray
    orientations: np.ndarray
    clip: np.ndarray
    time_offset: np.ndarray
    playback_rate: np.ndarray
    scales: Optional[np.ndarray] = None
    fade_clip: Optional[np.ndarray] = None
    fade_time_offset: Optional[np.ndarray] = None
    fade_playback_rate: Optional[np.ndarray] = None
    fade_weight: Optional[np.ndarray] = None
    fade_samples: Optional[dict] = None
    layer_clip: Optional[np.ndarray] = None
    layer_time_offset: Optional[np.ndarray] = None
    layer_playback_rate: Optional[np.ndarray] = None
    layer_weight: Optional[np.ndarray] = None
    layer_mask: Optional[np.ndarray] = None
    layer_mode: Optional[np.ndarray] = None
    layer_reference_clip: Optional[np.ndarray] = None
    layer_reference_time: Optional[np.ndarray] = None
    blend_space: Optional[np.ndarray] = None
    blend_x: Optional[np.ndarray] = None
    blend_y: Optional[np.ndarray] = None
    blend_phase: Optional[np.ndarray] = None

    @property
    def blended(self) -> bool:
        """Whether any instance plays a blend space (format 1.3, spec 23.7)."""
        return self.blend_space is not None and bool(np.any(np.asarray(self.blend_space) >= 0))

    tint: Optional[np.ndarray] = None
    variant: Optional[np.ndarray] = None
    variant_names: tuple = ()
    variant_colors: Optional[np.ndarray] = None
    parts: Optional[np.ndarray] = None
    part_names: tuple = ()

    @property
    def varied(self) -> bool:
        """Whether the crowd authors any variety (a format 1.3 instancer, spec "Crowd variety")."""
        return (self.tint is not None or self.variant is not None or self.parts is not None
                or bool(self.variant_names) or bool(self.part_names))

    def variety_arrays(self) -> tuple:
        """(tint (N, 3) float32, variant (N,) int32 (-1: none), parts (N,) int32) with defaults filled in:
        tint (1, 1, 1), no variant, every part shown."""
        n = self.instance_count
        tint = (np.ones((n, 3), np.float32) if self.tint is None
                else np.asarray(self.tint, np.float32).reshape(n, 3))
        variant = (np.full(n, -1, np.int32) if self.variant is None
                   else np.asarray(self.variant, np.int32).reshape(n))
        parts = (np.full(n, (1 << len(self.part_names)) - 1, np.int32) if self.parts is None
                 else np.asarray(self.parts, np.int32).reshape(n))
        return tint, variant, parts

    @property
    def layered(self) -> bool:
        """Whether any instance has a layer of weight above 0 (a format 1.2 crowd)."""
        return self.layer_weight is not None and bool(np.any(np.asarray(self.layer_weight) > 0))

    def at(self, t: float) -> "Crowd":
        """This crowd with its time-sampled fade primvars evaluated at stage time ``t`` (seconds).

        As USD resolves samples: floats interpolate linearly between the samples around ``t``,
        integers (the fade clip) hold the sample at or before ``t``; before the first and after the
        last sample the end sample holds. A crowd without samples is returned as it is.
        """
        if not self.fade_samples:
            return self

        values = {}
        for field_name, (times, samples) in self.fade_samples.items():
            times = np.asarray(times, dtype=np.float64)
            samples = np.asarray(samples)
            if field_name in ("fade_clip", "layer_clip", "layer_mask"):
                index = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 1))
                values[field_name] = samples[index].astype(np.int32)
            else:
                # (S, N) fade samples or (S, N, L) layer samples: each value interpolated on its own.
                flat = samples.reshape(len(times), -1).astype(np.float64)
                columns = [np.interp(t, times, flat[:, i]) for i in range(flat.shape[1])]
                values[field_name] = np.asarray(columns, dtype=np.float32).reshape(samples.shape[1:])
        return dataclasses.replace(self, fade_samples=None, **values)

    @property
    def crossfades(self) -> bool:
        """Whether any instance has a fade weight above 0 (a format 1.1 crowd)."""
        return self.fade_weight is not None and bool(np.any(np.asarray(self.fade_weight) > 0))

    def fade_arrays(self) -> tuple:
        """(fade clip, fade time offset, fade playback rate, fade weight) per instance, defaults filled in."""
        n = self.instance_count
        def filled(value, default, dtype):
            return np.full(n, default, dtype) if value is None else np.asarray(value, dtype).reshape(n)
        return (filled(self.fade_clip, 0, np.int64), filled(self.fade_time_offset, 0.0, np.float64),
                filled(self.fade_playback_rate, 1.0, np.float64), filled(self.fade_weight, 0.0, np.float64))

    @property
    def instance_count(self) -> int:
        """N: number of instances."""
        return int(self.positions.shape[0])


@dataclass(frozen=True)
class LevelsOfDetail:
    """The levels of detail of one animation's meshes (format 1.2, spec "Levels of detail").

    Every level is bound to the same texture; a mesh's level is :attr:`BoundMesh.lod`.

    Attributes:
        root: Prim path of the UsdLod ``LODRootAPI`` prim whose children, in order, are the levels.
        screen_sizes: The ``LODScreenSizeHeuristic`` thresholds, one per level after the first,
            strictly descending in (0, 1]: an instance whose screen size ``s`` is at most
            ``screen_sizes[i]`` uses a level past ``i``.
        item_names: Names of the root's children (the levels), in order (default ``lod0``, ``lod1``, ...).
    """

    root: str
    screen_sizes: tuple
    item_names: tuple = ()

    @property
    def level_count(self) -> int:
        """n: number of levels (thresholds + 1)."""
        return len(self.screen_sizes) + 1

    def item_name(self, level: int) -> str:
        """The name of the root's child holding ``level``."""
        return self.item_names[level] if self.item_names else f"lod{level}"

    def item_path(self, level: int) -> str:
        """Prim path of the root's child holding ``level``."""
        return f"{self.root.rstrip('/')}/{self.item_name(level)}"


@dataclass(frozen=True)
class VirtualBones:
    """One baked Virtual Bones animation: a layout, its texels and what is bound to it.

    Attributes:
        layout: Sizes.
        texels: ``layout.shape`` array of ``layout.texel_format.numpy_dtype``, read-only; padding
            texels are zero.
        bones: Bone names, ``layout.bone_count`` of them.
        clips: Clips, in row order.
        unorm_ranges: The texel format's ranges (uint32, format 1.2: the (B, 7, 2) compactRanges of spec 5.6).
            For unorm16, (T, 4, 2) float64 ``[min, max]`` per texel slot and channel;
            None otherwise.
        meshes: Bound meshes.
        path: Prim path of the VirtualBonesAnimation prim.
        texture: Texture file name relative to the USD layer (set by writers and readers).
        clip_extents: (clips, 2, 3) float32 bounds of the skinned meshes per clip, or None.
        bind_transforms: (bones, 4, 4) float64 column-vector bind transforms of the joints in
            animation space (format 1.1, sockets: ``J_b = M_b B_b``), or None when not stored.
    """

    layout: Layout
    texels: np.ndarray
    bones: tuple
    clips: tuple
    unorm_ranges: Optional[np.ndarray] = None
    meshes: tuple = ()
    path: str = "/VirtualBones/Animation"
    texture: Optional[str] = None
    clip_extents: Optional[np.ndarray] = None
    bind_transforms: Optional[np.ndarray] = None
    root_motion: Optional[RootMotion] = None
    """Format 1.1: a :class:`vbusd.format.rootmotion.RootMotion` (clips baked in place, spec "Root motion"), or None."""
    lods: Optional[LevelsOfDetail] = None
    """Format 1.2: the meshes' levels of detail (spec "Levels of detail"), or None for one level."""
    bone_parents: Optional[tuple] = None
    """Format 1.2: per bone, the index of its parent bone or -1 (spec "Layers and bone masks"), or None."""
    masks: tuple = ()
    """Format 1.2: the named bone masks, ``(name, (bones,) float64 weights in [0, 1])`` pairs (spec
    "Layers and bone masks"); stored only with ``bone_parents`` and ``bind_transforms``."""
    blend_spaces: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.BlendSpace` objects (spec 23); stored only with
    ``bone_parents`` and ``bind_transforms``."""
    markers: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.Marker` objects, the clips' named times (spec 23.4)."""

    def __post_init__(self) -> None:
        if self.blend_spaces and (self.bone_parents is None or self.bind_transforms is None):
            raise ValueError("blend spaces need bone parents and bind transforms (spec 23)")
        if self.texels.shape != self.layout.shape:
            raise ValueError(f"texels shape {self.texels.shape} != layout shape {self.layout.shape}")
        if self.texels.dtype != np.dtype(self.layout.texel_format.numpy_dtype):
            raise ValueError(f"texels dtype {self.texels.dtype} does not match {self.layout.texel_format}")
        if len(self.bones) != self.layout.bone_count:
            raise ValueError(f"{len(self.bones)} bone names for {self.layout.bone_count} bones")
        rows = sum(c.row_count for c in self.clips)
        if rows != self.layout.row_count:
            raise ValueError(f"clips hold {rows} rows, layout says {self.layout.row_count}")
        if self.bind_transforms is not None and np.shape(self.bind_transforms) != (self.layout.bone_count, 4, 4):
            raise ValueError(f"bind transforms {np.shape(self.bind_transforms)} for {self.layout.bone_count} bones")
        if self.bone_parents is not None and len(self.bone_parents) != self.layout.bone_count:
            raise ValueError(f"{len(self.bone_parents)} bone parents for {self.layout.bone_count} bones")
        if self.masks and (self.bone_parents is None or self.bind_transforms is None):
            raise ValueError("bone masks need bone parents and bind transforms (spec 8.6)")
        for name, weights in self.masks:
            if np.shape(weights) != (self.layout.bone_count,):
                raise ValueError(f"mask {name!r} holds {np.shape(weights)} weights for {self.layout.bone_count} bones")

    @functools.cached_property
    def content_digest(self) -> str:
        """The texels' ``contentDigest`` (:func:`vbusd.format.digest.content_digest`), hashed once:
        the writer needs it for the layer, the texture's metadata and the sidecar."""
        return content_digest(self.texels)


@dataclass(frozen=True)
class VirtualBonesAsset:
    """What one Virtual Bones USD file holds: animations, their meshes, crowds and stage metadata.

    Attributes:
        animations: One :class:`VirtualBones` per skeleton.
        crowds: Point instancers, each with the index of the animation it instances.
        crowd_animation: For each crowd, the index into ``animations`` of what it instances.
        up_axis: ``Y`` or ``Z``.
        meters_per_unit: Scene units.
        time_codes_per_second: Of the source timeline (decoded caches use it).
        default_prim: Name of the stage's default prim.
    """

    animations: tuple
    crowds: tuple = ()
    crowd_animation: tuple = ()
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    time_codes_per_second: float = 24.0
    default_prim: str = "VirtualBones"
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Converter contract
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReadOptions:
    """Options every converter's ``read(path, options)`` accepts; checked before any work starts.

    Attributes:
        skeletons: Select skeletons (UsdSkel Skeleton prim paths, glTF skin names or indices as
            strings); empty selects all.
        clips: Select clips (glTF animation names or indices; UsdSkel: clip names, which are the
            Skeleton prims' names); empty selects all; a name that selects nothing is an error.
        time_range: (start, end) in the source's time unit (USD time codes, glTF seconds), or None
            for the whole animation.
        allow_outside_paths: Let referenced files resolve outside the asset's folder.
        strict_weights: Refuse weights that do not sum to one instead of renormalizing them as
            engines do (glTF; spec/gltf-conversion.md, Meshes).
    """

    skeletons: tuple = ()
    clips: tuple = ()
    time_range: Optional[tuple] = None
    allow_outside_paths: bool = False
    strict_weights: bool = False


@dataclass(frozen=True)
class SourceScene:
    """What a converter returns: the skinned animations of one file and its stage metadata.

    Attributes:
        animations: One :class:`SkinnedAnimation` per skeleton (skin).
        up_axis: ``Y`` or ``Z``.
        meters_per_unit: Scene units in metres.
        time_codes_per_second: Of the source timeline (glTF: 1 time code per second unless chosen).
        default_prim: Name for the output stage's default prim.
        warnings: One-line warnings (for example "morph targets ignored on /Mesh").
        source: The file read.
    """

    animations: tuple
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    time_codes_per_second: float = 24.0
    default_prim: str = "VirtualBones"
    warnings: tuple = ()
    source: Optional[str] = None
