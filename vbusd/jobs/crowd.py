"""Build a USD crowd from converted characters: ``vbusd crowd`` and :func:`build_crowd`.

A crowd file references each character's Virtual Bones asset (its default prim, under
``/Crowd/Characters/<name>``, made invisible so only the instances draw) and holds one
``UsdGeomPointInstancer`` with ``VirtualBonesInstancingAPI`` per character and animation (a
character of several skeletons has several, with the same instances), whose prototype references
that animation's bound meshes. Per instance it chooses position, orientation (a yaw about the
stage's up axis), scale, clip, time offset and playback rate (spec: "Instancing") and, when asked,
a crossfade (a fade clip with its own offset and rate, and a fade weight, constant or ramped over a
window of stage time; spec "Crossfade", format 1.1) and layers (per layer a clip over a named bone
mask, with its own offset, rate and weight; spec "Layers and bone masks", format 1.2) and crowd variety (a
tint from a palette, a material variant and the optional parts shown; spec "Crowd variety", format 1.3,
drawn after every other choice so that a crowd without it is unchanged). This module only
places and chooses; the layer is authored and written by :func:`vbusd.io.usd.write_crowd_layer`,
whose point instancers come from :func:`vbusd.io.usd.write_instancer`, the one author of a Virtual
Bones point instancer (an asset's own crowds are written by it too).

Placement: ``grid`` (rows of ``spacing``), ``disc`` (a sunflower spiral of even density whose
instances stand ``spacing`` apart on average) or ``points`` (a CSV of ``x,y,z`` rows, or a USD file
whose first ``UsdGeomPoints`` / ``PointBased`` prim gives the positions). The default spacing comes
from the characters' size (:class:`CrowdOptions`). Instances are dealt to
characters in proportion to their weights, and clips by name with weights. Everything random comes
from one ``numpy.random.Generator`` seeded with ``seed``, and the layer is written with a fixed
header, so the same inputs and seed give the same file, byte for byte.
"""

from __future__ import annotations

import csv
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from vbusd.format.errors import FORCE_HINT, MISSING_FILE, OUTSIDE_PATHS_HINT, InputError, OptionsError
from vbusd.format import names as vb_names
from vbusd.format.model import Crowd
from vbusd.format.names import unique_names
from vbusd.format import variety
from vbusd.io.usd import CharacterInstancer, CharacterReference, read_asset, write_crowd_layer
from pxr import UsdGeom
from vbusd.io.usd_reader import stage_for_reading
import dataclasses

__all__ = ["CrowdOptions", "CrowdLayer", "CrowdReport", "build_crowd", "parse_weights", "parse_assignments",
           "LAYOUTS", "MAX_INSTANCES"]

LAYOUTS = ("grid", "disc", "points")
MAX_INSTANCES = 10_000_000
"""Refused above this count: 10 M instances are ~600 MB of primvars in the layer."""

CROWD_ROOT = "/Crowd"


def _check_range(name: str, pair, *, positive: bool = False, unit: bool = False) -> None:
    """``pair`` is (MIN, MAX): finite, MIN <= MAX (and positive, or within [0, 1], when asked)."""
    low, high = pair
    if not (math.isfinite(low) and math.isfinite(high) and low <= high) or (positive and low <= 0) or (
            unit and not (0.0 <= low and high <= 1.0)):
        need = " and positive" if positive else " and within 0..1" if unit else ""
        raise OptionsError(f"{name} needs MIN <= MAX, finite{need}; got {low:g} {high:g}", file="crowd")


def _check_weights(name: str, clips: dict) -> None:
    for clip, weight in clips.items():
        if not (math.isfinite(weight) and weight >= 0):
            raise OptionsError(f"{name} weight of {clip!r} must be 0 or more, got {weight!r}", file="crowd")
    if clips and not any(w > 0 for w in clips.values()):
        raise OptionsError(f"{name} weights are all zero", file="crowd")


def _pair(value, name: str) -> Optional[tuple]:
    """A (MIN, MAX) option as a tuple of two floats, or None."""
    if value is None:
        return None
    try:
        low, high = value
        return float(low), float(high)
    except (TypeError, ValueError):
        raise OptionsError(f"{name} needs two numbers MIN MAX, got {value!r}", file="crowd") from None


@dataclass(frozen=True)
class CrowdLayer:
    """One layer every instance plays on top of its clip (format 1.2, spec "Layers and bone masks").

    Per instance a clip is chosen among ``clips`` (by name, with relative weights, as
    :attr:`CrowdOptions.clips`) and plays over the bones of the mask named ``mask`` (the characters'
    ``vbusd convert --mask NAME=BONE``) at its own time offset and rate, with a weight drawn from
    ``weight``. Layers apply in the order given.

    Attributes:
        mask: Name of a bone mask every instanced animation stores.
        clips: Clip name (or index as text) -> relative weight; empty: every clip, equal weights.
        weight: (min, max) layer weight, uniform, within 0..1 (1: the masked bones play the layer's
            clip alone).
        time_offset: (min, max) seconds; None: uniform over each instance's layer clip duration.
        playback_rate: (min, max) rate, uniform.
    """

    mask: str
    clips: dict = field(default_factory=dict)
    weight: tuple = (1.0, 1.0)
    time_offset: Optional[tuple] = None
    playback_rate: tuple = (1.0, 1.0)

    def __post_init__(self) -> None:
        if not isinstance(self.mask, str) or not self.mask:
            raise OptionsError(f"a layer needs the name of a bone mask, got {self.mask!r}", file="crowd")
        if not isinstance(self.clips, dict):
            raise OptionsError(f"a layer's clips are a dict of clip name -> weight, got {self.clips!r}", file="crowd")
        _check_weights(f"--layer {self.mask}", self.clips)
        for name, attribute in (("--layer-weight", "weight"), ("--layer-time-offset", "time_offset"),
                                ("--layer-rate", "playback_rate")):
            object.__setattr__(self, attribute, _pair(getattr(self, attribute), name))
        _check_range("--layer-weight", self.weight, unit=True)
        _check_range("--layer-rate", self.playback_rate)
        if self.time_offset is not None:
            _check_range("--layer-time-offset", self.time_offset)


@dataclass(frozen=True)
class CrowdOptions:
    """What :func:`build_crowd` places; checked on construction.

    Attributes:
        layout: ``grid``, ``disc`` or ``points``.
        count: Number of instances (ignored by ``points``, which places one per point).
        spacing: Distance between neighbours in scene units (grid pitch; disc average spacing).
            None (default): from the characters' size, twice the largest distance of any of their
            skinned meshes (clip extents, else rest points) from the up axis, times the largest
            scale, so that no two instances overlap whatever their yaw.
        points: CSV or USD file of positions for ``layout="points"``.
        clips: Clip name (or index as text) -> relative weight; empty: every clip, equal weights.
            A character without a named clip keeps its own clips' equal weights.
        characters: Relative weight of each character (same order as the inputs); None: equal.
        time_offset: (min, max) seconds; None: uniform over each instance's clip duration.
        playback_rate: (min, max) rate, uniform.
        yaw: (min, max) degrees about the up axis, uniform.
        scale: (min, max) uniform scale.
        fade_clips: Crossfade (format 1.1, spec "Crossfade"): clip name (or index as text) ->
            relative weight of the fade clip each instance also plays; empty (default): no
            crossfade. Every instanced animation must be format 1.1 or later.
        fade_weight: (min, max) fade weight, uniform, within 0..1 (0: the instance's clip alone, 1:
            the fade clip alone); None: (0, 1), unless ``fade_window`` is given.
        fade_window: (start, end) stage seconds: instead of a constant weight, every instance fades
            from its clip (weight 0 until ``start``) to its fade clip (weight 1 from ``end``), the
            fade weight time-sampled at the two times and ramping linearly between them.
        fade_time_offset: (min, max) seconds of the fade clip at stage time 0; None: uniform over
            each instance's fade clip duration.
        fade_playback_rate: (min, max) rate of the fade clip, uniform.
        layers: :class:`CrowdLayer` (or dicts of its fields) every instance plays, in order
            (format 1.2); empty: none. Every instanced animation must store each layer's mask.
        tints: Crowd variety (format 1.3, spec "Crowd variety"): a palette of ``#rrggbb`` colours (sRGB)
            or linear ``(r, g, b)`` triples; each instance picks one (equal chances) as its tint. Empty
            (default): no tint.
        variants: Material variant name -> relative weight; each instance gets one, and each variant
            a UsdPreviewSurface material under ``<instancer>/Variants/<name>``. Empty: no variants.
        parts: Part name (a bound mesh of the characters, by prim name) -> probability in [0, 1] that
            an instance shows it, each part on its own. Empty: every mesh on every instance.
        seed: Seed of every random choice.
        force: Replace an existing output (as :class:`vbusd.jobs.conversion.ConvertOptions`).
        allow_outside_paths: Let the crowd reference characters outside its folder (absolute paths).
    """

    layout: str = "grid"
    count: int = 100
    spacing: Optional[float] = None
    points: Optional[str] = None
    clips: dict = field(default_factory=dict)
    characters: Optional[tuple] = None
    time_offset: Optional[tuple] = None
    playback_rate: tuple = (1.0, 1.0)
    yaw: tuple = (0.0, 360.0)
    scale: tuple = (1.0, 1.0)
    fade_clips: dict = field(default_factory=dict)
    fade_weight: Optional[tuple] = None
    fade_window: Optional[tuple] = None
    fade_time_offset: Optional[tuple] = None
    fade_playback_rate: tuple = (1.0, 1.0)
    layers: tuple = ()
    tints: tuple = ()
    variants: dict = field(default_factory=dict)
    parts: dict = field(default_factory=dict)
    seed: int = 0
    force: bool = False
    allow_outside_paths: bool = False

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise OptionsError(f"--layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}", file="crowd")
        if self.layout == "points" and not self.points:
            raise OptionsError("--layout points needs a FILE of positions (CSV or USD)", file="crowd")
        if self.layout != "points" and (isinstance(self.count, bool) or int(self.count) != self.count
                                        or not 1 <= self.count <= MAX_INSTANCES):
            raise OptionsError(f"--count must be 1..{MAX_INSTANCES}, got {self.count!r}", file="crowd")
        if self.spacing is not None and not (isinstance(self.spacing, (int, float)) and math.isfinite(self.spacing)
                                             and self.spacing > 0):
            raise OptionsError(f"--spacing must be a positive number, got {self.spacing!r}", file="crowd")
        for name, pair, positive in (("--rate", self.playback_rate, False), ("--yaw", self.yaw, False),
                                     ("--scale", self.scale, True), ("--time-offset", self.time_offset, False)):
            if pair is None:
                continue
            low, high = pair
            if not (math.isfinite(low) and math.isfinite(high) and low <= high) or (positive and low <= 0):
                raise OptionsError(f"{name} needs MIN <= MAX, finite{' and positive' if positive else ''}; got "
                                   f"{low:g} {high:g}", file="crowd")
        for name, weight in self.clips.items():
            if not (math.isfinite(weight) and weight >= 0):
                raise OptionsError(f"--clips weight of {name!r} must be 0 or more, got {weight!r}", file="crowd")
        if self.clips and not any(w > 0 for w in self.clips.values()):
            raise OptionsError("--clips weights are all zero", file="crowd")
        if self.characters is not None and (not all(math.isfinite(w) and w >= 0 for w in self.characters)
                                            or not any(w > 0 for w in self.characters)):
            raise OptionsError("character weights must be 0 or more and not all zero", file="crowd")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise OptionsError(f"--seed must be a non-negative integer, got {self.seed!r}", file="crowd")
        if not isinstance(self.fade_clips, dict):
            raise OptionsError(f"fade_clips is a dict of clip name -> weight, got {self.fade_clips!r}", file="crowd")
        _check_weights("--fade-clips", self.fade_clips)
        for name, attribute in (("--fade-weight", "fade_weight"), ("--fade-window", "fade_window"),
                                ("--fade-time-offset", "fade_time_offset"), ("--fade-rate", "fade_playback_rate")):
            value = _pair(getattr(self, attribute), name)
            object.__setattr__(self, attribute, value)
            if value is not None and attribute != "fade_playback_rate" and not self.fade_clips:
                raise OptionsError(f"{name} needs --fade-clips (the clips instances fade into)", file="crowd")
        if self.fade_playback_rate != (1.0, 1.0) and not self.fade_clips:
            raise OptionsError("--fade-rate needs --fade-clips (the clips instances fade into)", file="crowd")
        if self.fade_weight is not None and self.fade_window is not None:
            raise OptionsError("give --fade-weight (a constant weight per instance) or --fade-window (a fade over "
                               "stage time), not both", file="crowd")
        if self.fade_weight is not None:
            _check_range("--fade-weight", self.fade_weight, unit=True)
        if self.fade_window is not None:
            start, end = self.fade_window
            if not (math.isfinite(start) and math.isfinite(end) and start < end):
                raise OptionsError(f"--fade-window needs START < END, finite stage seconds; got {start:g} {end:g}",
                                   file="crowd")
        if self.fade_time_offset is not None:
            _check_range("--fade-time-offset", self.fade_time_offset)
        _check_range("--fade-rate", self.fade_playback_rate)
        if isinstance(self.layers, (CrowdLayer, dict, str)) or not isinstance(self.layers, (list, tuple)):
            raise OptionsError(f"layers is a list of CrowdLayer, got {type(self.layers).__name__}", file="crowd")
        layers = []
        for layer in self.layers:
            if isinstance(layer, dict):
                try:
                    layer = CrowdLayer(**layer)
                except TypeError as error:
                    raise OptionsError(f"a layer has fields mask, clips, weight, time_offset, playback_rate: "
                                       f"{error}", file="crowd") from None
            if not isinstance(layer, CrowdLayer):
                raise OptionsError(f"layers hold CrowdLayer (or dicts of its fields), got {layer!r}", file="crowd")
            layers.append(layer)
        object.__setattr__(self, "layers", tuple(layers))
        self._check_variety()

    def _check_variety(self) -> None:
        """Tints as linear triples (``#rrggbb`` converted), variant weights, part probabilities (spec 22)."""
        if isinstance(self.tints, str) or not isinstance(self.tints, (list, tuple)):
            raise OptionsError(f"--tints is a list of #rrggbb colours, got {self.tints!r}", file="crowd")
        tints = []
        for color in self.tints:
            linear = variety.hex_to_linear(color) if isinstance(color, str) else None
            if linear is None and not isinstance(color, str):
                try:
                    linear = tuple(float(c) for c in color)
                except (TypeError, ValueError):
                    linear = None
                if linear is not None and (len(linear) != 3 or not all(math.isfinite(c) and c >= 0 for c in linear)):
                    linear = None
            if linear is None:
                raise OptionsError(f"--tints colour {color!r} is not #rrggbb (or three finite numbers 0 or more)",
                                   file="crowd")
            tints.append(linear)
        object.__setattr__(self, "tints", tuple(tints))
        for option, table in (("--variants", self.variants), ("--parts", self.parts)):
            if not isinstance(table, dict):
                raise OptionsError(f"{option} is a dict of name -> number, got {table!r}", file="crowd")
        _check_weights("--variants", self.variants)
        for name in self.variants:
            if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
                raise OptionsError(f"--variants name {name!r} must be an identifier (letters, digits, _; it names a "
                                   "USD material)", file="crowd")
        for name, probability in self.parts.items():
            if not (isinstance(probability, (int, float)) and math.isfinite(probability) and 0 <= probability <= 1):
                raise OptionsError(f"--parts probability of {name!r} must be within 0..1, got {probability!r}",
                                   file="crowd")
        if len(self.parts) > variety.MAX_PARTS:
            raise OptionsError(f"--parts names {len(self.parts)} parts; at most {variety.MAX_PARTS}", file="crowd")


@dataclass
class CrowdReport:
    """What :func:`build_crowd` wrote.

    Attributes:
        output: The crowd layer.
        instances: Instances per character (input order).
        clips: Instances per clip name, per character.
        bytes: Size of the layer.
        seconds: Time taken.
        animations: Animations each instance of a character plays together (one point instancer
            each), per character.
        spacing: The spacing used (scene units): the option's, or the one derived from the
            characters' size.
        fade_clips: Instances per fade clip name, per character (empty without a crossfade).
        variety: Per character (format 1.3; empty without variety): instances per palette colour
            (``tints``, in palette order), per variant name (``variants``) and showing each part
            (``parts``).
        layers: Layers each instance plays.
    """

    output: str
    instances: list
    clips: list
    bytes: int = 0
    seconds: float = 0.0
    animations: list = field(default_factory=list)
    spacing: Optional[float] = None
    fade_clips: list = field(default_factory=list)
    layers: int = 0
    variety: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON form (camelCase keys, as the spec's metadata)."""
        return {"output": self.output, "instances": self.instances, "clips": self.clips,
                "animations": self.animations, "spacing": self.spacing, "fadeClips": self.fade_clips,
                "layers": self.layers, "variety": self.variety, "bytes": self.bytes,
                "seconds": round(self.seconds, 3)}


def parse_weights(text: str, *, option: str = "--clips") -> dict:
    """Parse ``NAME[:WEIGHT],...`` (for example ``Walk:3,Idle:1,Cheer``) into a dict.

    Args:
        text: The option's value.
        option: The option named in errors (``--clips``, ``--fade-clips``, ``--layer MASK``).

    Raises:
        OptionsError: A weight that is not a number, or an empty name.
    """
    weights = {}
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, _, weight = part.rpartition(":") if ":" in part else (part, "", "1")
        if not name:
            raise OptionsError(f"{option} entry {part!r} has no clip name", file="crowd")
        try:
            weights[name] = float(weight)
        except ValueError:
            raise OptionsError(f"{option} weight {weight!r} of {name!r} is not a number", file="crowd") from None
    return weights


def parse_assignments(text: str, *, option: str) -> dict:
    """Parse ``NAME=NUMBER,...`` (``--variants home=3,away=1``, ``--parts Hat=0.4``) into a dict.

    Raises:
        OptionsError: An entry without ``=``, an empty name, a repeated name or a value that is not a number.
    """
    values = {}
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, equals, value = part.partition("=")
        name = name.strip()
        if not equals or not name:
            raise OptionsError(f"{option} entry {part!r} is not NAME=NUMBER", file="crowd")
        if name in values:
            raise OptionsError(f"{option} names {name!r} twice", file="crowd")
        try:
            values[name] = float(value)
        except ValueError:
            raise OptionsError(f"{option} value {value!r} of {name!r} is not a number", file="crowd") from None
    return values


# --------------------------------------------------------------------------------------------
# placement
# --------------------------------------------------------------------------------------------


def _plane(up_axis: str, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Ground-plane coordinates (u, v) to 3D points for a Y-up or Z-up stage."""
    zeros = np.zeros_like(u)
    return np.stack([u, zeros, v] if up_axis == "Y" else [u, v, zeros], axis=1)


def grid_positions(count: int, spacing: float, up_axis: str = "Y") -> np.ndarray:
    """``count`` points on a square-ish grid of pitch ``spacing``, centred on the origin."""
    columns = int(math.ceil(math.sqrt(count)))
    rows = int(math.ceil(count / columns))
    i = np.arange(count)
    u = (i % columns - (columns - 1) / 2.0) * spacing
    v = (i // columns - (rows - 1) / 2.0) * spacing
    return _plane(up_axis, u, v)


def disc_positions(count: int, spacing: float, up_axis: str = "Y") -> np.ndarray:
    """``count`` points on a disc of even density (Vogel's sunflower spiral), ``spacing`` apart on average."""
    i = np.arange(count) + 0.5
    radius = spacing * np.sqrt(i / math.pi)
    angle = i * math.pi * (3.0 - math.sqrt(5.0))
    return _plane(up_axis, radius * np.cos(angle), radius * np.sin(angle))


def read_points(path: str) -> np.ndarray:
    """Positions from a CSV (``x,y,z`` per row; a header row is skipped) or a USD points prim.

    Raises:
        InputError: Unreadable file, a row that is not three finite numbers, no points.
    """
    source = Path(path)
    if not source.is_file():
        raise InputError(MISSING_FILE if not source.exists() else "not a regular file", file=str(source),
                         code="file.missing" if not source.exists() else "file.kind")
    if source.suffix.lower() in (".usd", ".usda", ".usdc"):
        return _usd_points(source)
    rows = []
    try:
        with open(source, newline="", encoding="utf-8") as handle:
            for number, row in enumerate(csv.reader(handle), start=1):
                if not row or all(not c.strip() for c in row):
                    continue
                try:
                    values = [float(c) for c in row[:3]]
                except ValueError:
                    if number == 1:
                        continue  # a header
                    raise InputError(f"row {number} is not three numbers: {','.join(row)[:80]!r}",
                                     file=str(source), location=f"line {number}", code="crowd.points") from None
                if len(values) != 3 or not all(math.isfinite(x) for x in values):
                    raise InputError(f"row {number} is not three finite numbers", file=str(source),
                                     location=f"line {number}", code="crowd.points")
                rows.append(values)
                if len(rows) > MAX_INSTANCES:
                    raise InputError(f"more than {MAX_INSTANCES} points", file=str(source),
                                     location=f"line {number}", code="crowd.points")
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {error.start})", file=str(source), code="crowd.points") from None
    if not rows:
        raise InputError("no points in the file", file=str(source), code="crowd.points")
    return np.asarray(rows, dtype=np.float64)


def _usd_points(source: Path) -> np.ndarray:


    with stage_for_reading(source, allow_outside_paths=True) as stage:  # a points file, not an asset
        return _first_points(stage, source, UsdGeom)


def _first_points(stage, source: Path, UsdGeom) -> np.ndarray:
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointBased):
            points = UsdGeom.PointBased(prim).GetPointsAttr().Get()
            if points:
                array = np.asarray(points, dtype=np.float64)
                if not np.all(np.isfinite(array)):
                    raise InputError("points are not finite", file=str(source), location=str(prim.GetPath()),
                                     code="crowd.points")
                return array
    raise InputError("no points prim (UsdGeomPoints or another PointBased prim with points)", file=str(source),
                     code="crowd.points")


# --------------------------------------------------------------------------------------------
# the crowd
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Animation:
    """One animation of a character that the crowd instances, with its bound meshes."""

    path: str
    mesh_paths: tuple
    clip_of: tuple
    """For each of the character's clips (its first animation's), this animation's clip index."""
    mask_names: tuple = ()
    """The bone masks the animation stores (format 1.2), in order: a layer's mask index is into these."""
    part_children: tuple = ()
    """With levels of detail, the names its parts may have: the level prims' children (spec 22.3)."""


@dataclass(frozen=True)
class _Character:
    path: Path
    name: str
    default_prim: str
    up_axis: str
    meters_per_unit: float
    animations: tuple
    """Every animation with a bound mesh (asset order): an instance draws all of them, together."""
    clip_names: tuple
    clip_durations: tuple
    crowd_paths: tuple
    radius: float
    """Largest distance of the skinned meshes from the up axis through the origin (scene units)."""


def _clip_map(lead, vb, file: str) -> tuple:
    """Which clip of ``vb`` plays when an instance plays each clip of ``lead`` (by name, else by index).

    Raises:
        InputError: The clips match neither by name nor in number (``crowd.character``).
    """
    lead_names = tuple(c.name for c in lead.clips)
    names = tuple(c.name for c in vb.clips)
    if all(name in names for name in lead_names):
        return tuple(names.index(name) for name in lead_names)
    if len(names) == len(lead_names):
        return tuple(range(len(names)))
    raise InputError(f"animation {vb.path} has clips ({', '.join(names)}) that match neither by name nor in "
                     f"number those of {lead.path} ({', '.join(lead_names)}): an instance could not play them "
                     "together", file=file, location=vb.path, code="crowd.character")


def _radius(vb, up_axis: str) -> float:
    """Largest distance from the up axis of ``vb``'s skinned meshes: its clip extents' corners, or
    its rest points when the asset stores no extents (0 when neither is finite)."""
    horizontal = [0, 2] if up_axis == "Y" else [0, 1]
    extents = None if vb.clip_extents is None else np.asarray(vb.clip_extents, dtype=np.float64)
    if extents is not None and extents.size and np.all(np.isfinite(extents)):
        farthest = np.max(np.abs(extents[:, :, horizontal]), axis=1)  # per clip, the box's far corner
        return float(np.max(np.linalg.norm(farthest, axis=1)))
    points = [np.asarray(m.points, dtype=np.float64).reshape(-1, 3)[:, horizontal] for m in vb.meshes]
    distances = np.linalg.norm(np.concatenate(points), axis=1) if points else np.zeros(1)
    distances = distances[np.isfinite(distances)]
    return float(distances.max()) if distances.size else 0.0


def _character(path: Path, index: int, used: set) -> _Character:
    asset = read_asset(path)
    if not asset.animations:
        raise InputError("holds no VirtualBonesAnimation to instance", file=str(path), code="crowd.character")
    drawn = [vb for vb in asset.animations if vb.meshes]
    if not drawn:
        raise InputError(f"animation {asset.animations[0].path} has no bound mesh to instance", file=str(path),
                         location=asset.animations[0].path, code="crowd.character")
    root = "/" + asset.default_prim
    for vb in drawn:
        if not vb.path.startswith(root + "/") or any(not m.path.startswith(root + "/") for m in vb.meshes):
            raise InputError(f"the animation and its meshes must lie under the default prim {root}",
                             file=str(path), location=vb.path, code="crowd.character")
    lead = drawn[0]
    # An animation with levels of detail: the prototype references its UsdLod root, which brings every
    # level and the LODRootAPI, so each instance selects its level (spec 20.2).
    animations = tuple(_Animation(path=vb.path, mesh_paths=(vb.lods.root,) if vb.lods is not None else
                                  tuple(m.path for m in vb.meshes),
                                  clip_of=_clip_map(lead, vb, str(path)),
                                  mask_names=tuple(name for name, _ in vb.masks),
                                  part_children=variety.level_part_names([m.path for m in vb.meshes], vb.lods.root)
                                  if vb.lods is not None else ()) for vb in drawn)
    base = "".join(c if c.isalnum() or c == "_" else "_" for c in path.stem) or "Character"
    if base[0].isdigit():
        base = "_" + base
    name, k = base, 1
    while name in used:
        k += 1
        name = f"{base}_{k}"
    used.add(name)
    return _Character(path=path, name=name, default_prim=asset.default_prim, up_axis=asset.up_axis,
                      meters_per_unit=asset.meters_per_unit, animations=animations,
                      clip_names=tuple(c.name for c in lead.clips),
                      clip_durations=tuple(c.row_count / c.rows_per_second for c in lead.clips),
                      crowd_paths=tuple(c.path for c in asset.crowds),
                      radius=max(_radius(vb, asset.up_axis) for vb in drawn))


def _clip_choice(character: _Character, clips: dict, rng: np.random.Generator, n: int) -> np.ndarray:
    weights = np.ones(len(character.clip_names))
    if clips:
        chosen = np.zeros(len(character.clip_names))
        for name, weight in clips.items():
            if name in character.clip_names:
                chosen[character.clip_names.index(name)] = weight
            elif name.isdigit() and int(name) < len(character.clip_names):
                chosen[int(name)] = weight
        if chosen.sum() > 0:
            weights = chosen
    return rng.choice(len(weights), size=n, p=weights / weights.sum()).astype(np.int32)


def _check_clip_names(option: str, clips: dict, cast) -> None:
    """A clip name no character has would silently play every clip: refuse it."""
    for name in clips:
        if not any(name in c.clip_names or (name.isdigit() and int(name) < len(c.clip_names)) for c in cast):
            known = sorted({clip for c in cast for clip in c.clip_names})
            raise OptionsError(f"{option} names clip {name!r}, which no character has (clips: "
                               f"{', '.join(known)}; or an index below {max(len(c.clip_names) for c in cast)})",
                               file="crowd")


def _check_fade_version(character: _Character) -> None:
    """Spec "Instancing": a crossfading instancer binds animations of format 1.1 or later, so that a
    1.0 reader refuses the crowd instead of playing the first clip alone. The crowd layer cannot
    raise a referenced animation's version (its texture's metadata says the same), so a 1.0
    character is refused."""
    attribute = vb_names.BY_KEY["formatMinorVersion"].name
    with stage_for_reading(character.path) as stage:
        for animation in character.animations:
            prim = stage.GetPrimAtPath(animation.path)
            value = prim.GetAttribute(attribute).Get() if prim and prim.GetAttribute(attribute).HasAuthoredValue() else 0
            if not isinstance(value, int) or value < 1:
                raise InputError(f"animation {animation.path} is format 1.{value or 0}; a crossfading crowd (--fade-clips) "
                                 "needs format 1.1 or later: convert the character again with vbusd convert, which "
                                 "writes 1.1", file=str(character.path), location=animation.path,
                                 code="crowd.character")


def _check_masks(layers, cast) -> None:
    """Every instanced animation stores every layer's mask (by name)."""
    for layer in layers:
        for character in cast:
            for animation in character.animations:
                if layer.mask not in animation.mask_names:
                    stored = ", ".join(animation.mask_names) or "none"
                    raise InputError(f"--layer names mask {layer.mask!r}, which animation {animation.path} does not "
                                     f"store (masks: {stored}); convert the character with --mask {layer.mask}=BONE",
                                     file=str(character.path), location=animation.path, code="layers.noMask")


def _prototype_children(animation) -> list:
    """The names the prototype gives the animation's targets (spec 15: named after each, made unique)."""
    if animation.part_children:  # levels of detail: the prototype holds the LOD root, parts sit below its levels
        return list(animation.part_children)
    return unique_names([path.rsplit("/", 1)[-1] for path in animation.mesh_paths])


def _check_parts(parts: dict, cast) -> None:
    """A part (spec 22.3) names a bound mesh of some instanced animation, by prim name."""
    known = sorted({name for c in cast for a in c.animations for name in _prototype_children(a)})
    for part in parts:
        if part not in known:
            raise OptionsError(f"--parts names {part!r}, which is no mesh of the characters (meshes: "
                               f"{', '.join(known)})", file="crowd")


def _variety(options, rng: np.random.Generator, m: int):
    """One character's tints, variants and parts (spec 22.5: in that order, only those asked for)."""
    tint = variant = shown = None
    if options.tints:
        palette = np.asarray(options.tints, dtype=np.float32)
        tint = palette[rng.integers(len(palette), size=m)]
    if options.variants:
        weights = np.asarray(list(options.variants.values()), dtype=np.float64)
        variant = rng.choice(len(weights), size=m, p=weights / weights.sum()).astype(np.int32)
    if options.parts:
        shown = {part: rng.random(size=m) < probability for part, probability in options.parts.items()}
    return tint, variant, shown


def _offsets(rng: np.random.Generator, span: Optional[tuple], durations: np.ndarray) -> np.ndarray:
    """Time offsets: uniform in ``span``, or over each instance's clip duration when it is None."""
    unit = rng.random(size=len(durations))
    if span is None:
        return unit * durations
    return span[0] + unit * (span[1] - span[0])


def _relative_reference(character: Path, output: Path, allow_outside_paths: bool) -> str:
    relative = os.path.relpath(character.resolve(), output.resolve().parent)
    if relative.startswith("..") and not allow_outside_paths:
        raise OptionsError(f"character {character} lies outside the crowd's folder {output.resolve().parent}; "
                           f"write the crowd beside or above its characters, or {OUTSIDE_PATHS_HINT}",
                           file="crowd")
    return Path(relative).as_posix() if not relative.startswith("..") else str(character.resolve())


def build_crowd(characters: Sequence, output, options: CrowdOptions = CrowdOptions(), *,
                force: Optional[bool] = None, allow_outside_paths: Optional[bool] = None) -> CrowdReport:
    """Write a USD crowd of converted characters.

    Args:
        characters: Paths of Virtual Bones assets (what ``vbusd convert`` writes). Every animation
            of a character that has bound meshes is instanced (one point instancer each, the same
            placement, time offset and rate per instance), so a character of several skeletons
            (a rider and its horse, an elephant and its instrument) stays whole; an instance's clip
            is chosen among the first such animation's clips, and the others play theirs of the same
            name (else of the same index).
        output: The crowd layer to write (``.usda``, ``.usdc`` or ``.usd``).
        options: Placement, clips, ranges and seed; ``options.force`` replaces an existing output.
        force: Kept for callers of earlier versions: when given, it sets ``options.force``.
        allow_outside_paths: Likewise for ``options.allow_outside_paths``.

    Returns:
        A :class:`CrowdReport`.

    Raises:
        OptionsError: Bad options, no characters, an existing output without ``options.force``.
        InputError: A character that cannot be read or has nothing to instance, or whose animations'
            clips match neither by name nor in number; bad points file.

    Example:
        >>> vbusd.build_crowd(["out/hero.usda"], "out/crowd.usda",
        ...                   CrowdOptions(layout="disc", count=1000, seed=7))  # doctest: +SKIP
    """
    start = time.perf_counter()
    if force is not None or allow_outside_paths is not None:

        options = dataclasses.replace(options, **{k: bool(v) for k, v in (("force", force), (
            "allow_outside_paths", allow_outside_paths)) if v is not None})
    force, allow_outside_paths = options.force, options.allow_outside_paths
    output = Path(output)
    if not characters:
        raise OptionsError("give at least one character asset", file="crowd")
    if output.suffix.lower() not in (".usda", ".usdc", ".usd"):
        raise OptionsError(f"the crowd must be a .usda, .usdc or .usd file, got {output.name!r}", file="crowd")
    if output.exists() and not force:
        raise OptionsError(f"{output} exists; {FORCE_HINT}", file="crowd")
    if options.characters is not None and len(options.characters) != len(characters):
        raise OptionsError(f"{len(options.characters)} character weights for {len(characters)} characters",
                           file="crowd")
    used: set = set()
    cast = [_character(Path(c), i, used) for i, c in enumerate(characters)]
    up_axis = cast[0].up_axis
    for other in cast[1:]:
        if other.up_axis != up_axis or not math.isclose(other.meters_per_unit, cast[0].meters_per_unit):
            raise InputError(f"up axis {other.up_axis} / metersPerUnit {other.meters_per_unit:g} differ from the "
                             f"first character's ({up_axis} / {cast[0].meters_per_unit:g})", file=str(other.path),
                             code="crowd.character")
    references = [_relative_reference(c.path, output, allow_outside_paths) for c in cast]
    _check_clip_names("--clips", options.clips, cast)
    _check_clip_names("--fade-clips", options.fade_clips, cast)
    for layer in options.layers:
        _check_clip_names(f"--layer {layer.mask}", layer.clips, cast)
    _check_masks(options.layers, cast)
    if options.fade_clips:
        for character in cast:
            _check_fade_version(character)
    _check_parts(options.parts, cast)

    rng = np.random.default_rng(int(options.seed))
    spacing = options.spacing
    if spacing is None:  # from the characters' size: turned any way, two neighbours never overlap
        spacing = 2.0 * max(c.radius for c in cast) * max(options.scale)
        spacing = spacing if math.isfinite(spacing) and spacing > 0 else 1.0
    if options.layout == "points":
        positions = read_points(options.points)
    elif options.layout == "disc":
        positions = disc_positions(int(options.count), float(spacing), up_axis)
    else:
        positions = grid_positions(int(options.count), float(spacing), up_axis)
    n = len(positions)
    weights = np.ones(len(cast)) if options.characters is None else np.asarray(options.characters, dtype=np.float64)
    who = rng.choice(len(cast), size=n, p=weights / weights.sum())
    yaw = np.radians(rng.uniform(options.yaw[0], options.yaw[1], size=n))
    scale = rng.uniform(options.scale[0], options.scale[1], size=n)
    rate = rng.uniform(options.playback_rate[0], options.playback_rate[1], size=n)
    unit = rng.random(size=n)  # time offsets: per instance, scaled to its clip below

    report_instances, report_clips, report_fades, report_variety, instancers = [], [], [], [], []
    # One point instancer per (character, animation): a character's animations play together on the
    # same instances. A character of one animation keeps the name <character>Instances.
    instancer_names = iter(unique_names([
        f"{c.name}Instances" if len(c.animations) == 1 else f"{c.name}_{a.path.rsplit('/', 1)[-1]}Instances"
        for c in cast for a in c.animations]))
    axis = 1 if up_axis == "Y" else 2
    for k, character in enumerate(cast):
        mine = np.flatnonzero(who == k)
        m = len(mine)
        clip = _clip_choice(character, options.clips, rng, m)
        durations = np.asarray(character.clip_durations, dtype=np.float64)[clip]
        if options.time_offset is None:
            offsets = unit[mine] * durations
        else:
            offsets = options.time_offset[0] + unit[mine] * (options.time_offset[1] - options.time_offset[0])
        report_instances.append(m)
        report_clips.append({name: int(np.sum(clip == i)) for i, name in enumerate(character.clip_names)})
        names_here = [next(instancer_names) for _ in character.animations]
        all_durations = np.asarray(character.clip_durations, dtype=np.float64)
        # Crossfade and layers (drawn only when asked, so a crowd without them is what it was).
        fade = None
        if options.fade_clips:
            fade_clip = _clip_choice(character, options.fade_clips, rng, m)
            fade_offsets = _offsets(rng, options.fade_time_offset, all_durations[fade_clip])
            fade_rate = rng.uniform(options.fade_playback_rate[0], options.fade_playback_rate[1], size=m)
            if options.fade_window is None:
                low, high = options.fade_weight if options.fade_weight is not None else (0.0, 1.0)
                fade_weight, fade_samples = rng.uniform(low, high, size=m).astype(np.float32), None
            else:  # 0 until the window opens, 1 once it closes; USD interpolates linearly between
                fade_weight = np.zeros(m, dtype=np.float32)
                fade_samples = {"fade_weight": (np.asarray(options.fade_window, dtype=np.float64),
                                                np.stack([np.zeros(m, np.float32), np.ones(m, np.float32)]))}
            fade = (fade_clip, fade_offsets.astype(np.float32), fade_rate.astype(np.float32), fade_weight, fade_samples)
            report_fades.append({name: int(np.sum(fade_clip == i)) for i, name in enumerate(character.clip_names)})
        layers = []
        for layer in options.layers:
            layer_clip = _clip_choice(character, layer.clips, rng, m)
            layer_offsets = _offsets(rng, layer.time_offset, all_durations[layer_clip])
            layer_rate = rng.uniform(layer.playback_rate[0], layer.playback_rate[1], size=m)
            layer_weight = rng.uniform(layer.weight[0], layer.weight[1], size=m)
            layers.append((layer.mask, layer_clip, layer_offsets, layer_rate, layer_weight))
        tint, variant, shown = _variety(options, rng, m)
        if options.tints or options.variants or options.parts:
            palette = np.asarray(options.tints, dtype=np.float32).reshape(-1, 3)
            report_variety.append({
                "tints": [int(np.sum(np.all(tint == colour, axis=1))) for colour in palette] if tint is not None else [],
                "variants": {name: int(np.sum(variant == k)) for k, name in enumerate(options.variants)}
                if variant is not None else {},
                "parts": {name: int(np.sum(values)) for name, values in shown.items()} if shown is not None else {}})
        if m == 0:
            continue
        quats = np.zeros((m, 4), dtype=np.float32)  # a yaw about the up axis, (x, y, z, w)
        quats[:, axis] = np.sin(yaw[mine] / 2)
        quats[:, 3] = np.cos(yaw[mine] / 2)
        for animation, instancer_name in zip(character.animations, names_here):
            clip_of = np.asarray(animation.clip_of, dtype=np.int32)
            extra = {}
            if fade is not None:
                fade_clip, fade_offsets, fade_rate, fade_weight, fade_samples = fade
                extra.update(fade_clip=clip_of[fade_clip], fade_time_offset=fade_offsets, fade_playback_rate=fade_rate,
                             fade_weight=fade_weight, fade_samples=fade_samples)
            if layers:  # (instances, layers) arrays, element i * L + j is layer j of instance i
                extra.update(
                    layer_clip=np.stack([clip_of[c] for _, c, _, _, _ in layers], axis=1),
                    layer_time_offset=np.stack([o for _, _, o, _, _ in layers], axis=1).astype(np.float32),
                    layer_playback_rate=np.stack([r for _, _, _, r, _ in layers], axis=1).astype(np.float32),
                    layer_weight=np.stack([w for _, _, _, _, w in layers], axis=1).astype(np.float32),
                    layer_mask=np.stack([np.full(m, animation.mask_names.index(mask), np.int32)
                                         for mask, _, _, _, _ in layers], axis=1))
            if tint is not None:
                extra["tint"] = tint
            if variant is not None:
                extra.update(variant=variant, variant_names=tuple(options.variants))
            if shown is not None:
                here = [part for part in options.parts if part in _prototype_children(animation)]
                mask = np.zeros(m, dtype=np.int32)
                for j, part in enumerate(here):
                    mask |= shown[part].astype(np.int32) << j
                if here:
                    extra.update(parts=mask, part_names=tuple(here))
            crowd = Crowd(path=f"{CROWD_ROOT}/{instancer_name}",
                          positions=np.ascontiguousarray(positions[mine], dtype=np.float32), orientations=quats,
                          scales=np.ascontiguousarray(np.repeat(scale[mine, None], 3, axis=1), dtype=np.float32),
                          clip=clip_of[clip], time_offset=offsets.astype(np.float32),
                          playback_rate=rate[mine].astype(np.float32), **extra)
            instancers.append(CharacterInstancer(crowd=crowd, character=character.name, animation=animation.path,
                                                 targets=animation.mesh_paths, mask_count=len(animation.mask_names),
                                                 part_children=animation.part_children))
    characters_held = [CharacterReference(name=c.name, reference=reference, default_prim=c.default_prim,
                                          crowd_paths=c.crowd_paths) for c, reference in zip(cast, references)]
    # One commit as every vbusd output (spec, "File names and the write guarantee"): under the
    # output's lock, staged beside the target and renamed; a failed write is one write.failed line.
    write_crowd_layer(output, characters_held, instancers, up_axis=up_axis, meters_per_unit=cast[0].meters_per_unit,
                      replace=force, root=CROWD_ROOT)
    return CrowdReport(output=str(output), instances=report_instances, clips=report_clips, bytes=output.stat().st_size,
                       seconds=time.perf_counter() - start, animations=[len(c.animations) for c in cast],
                       spacing=None if options.layout == "points" else float(spacing), fade_clips=report_fades,
                       layers=len(options.layers), variety=report_variety)
