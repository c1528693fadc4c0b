"""Reading the glTF runtime package that ``vbusd export`` writes (spec/runtime-package.md).

:func:`read_package` reads a ``.glb`` or ``.gltf`` and reports what is wrong into a
:class:`~vbusd.format.diagnostics.Diagnostics` list, as the texture and USD readers do: strict for
``vbusd info`` and ``vbusd view`` (the first error raises), lenient for ``vbusd validate`` (every
problem is a finding), so that the three accept and refuse the same packages. It checks

* the container and the glTF JSON with the glTF container reader the converter uses
  (:func:`vbusd.io.gltf.load`: GLB chunks, JSON types, buffers and their URIs);
* the ``VBUSD_virtual_bones`` extension: listed in ``extensionsUsed``, never required, the root
  object and every primitive object against ``vbusd/schema/VBUSD_virtual_bones.schema.json`` (the layout
  against the layout metadata schema it references) (``package.extension``, ``metadata.schema``);
* each animation's texture: its buffer view (no stride, no target, 16-byte aligned in a ``.glb``;
  ``package.texture``), the KTX2 file's header (:func:`vbusd.io.ktx2.scan_bytes`: identifier,
  format, sides of 1..16384 texels, regions; ``ktx2.*``, ``texture.*``), its ``vbusd.layout`` entry
  and the extension's ``layout`` against it (``package.layout``); the level data (digest, texels)
  is ``vbusd validate``'s (:func:`vbusd.validators.checks_texture.check_texture_file`);
* every primitive: every accessor it names read within the glTF reader's bounds
  (``gltf.accessor.*``), a ``POSITION``, vertex indices below the vertex count
  (``package.primitive``);
* each bound primitive: its animation exists, its ``_VB_JOINTS_n`` / ``_VB_WEIGHTS_n`` pairs are
  there for its influences, with as many vertices as ``POSITION`` and bone indices below the
  animation's bone count (``package.primitive``);
* each crowd node (``EXT_mesh_gpu_instancing`` on a mesh bound to an animation): every instance
  attribute read within its bounds, the three ``_VB_`` instance attributes, one value per instance,
  clips that the animation has, finite times and rates (``package.instances``).

Locations are JSON pointers into the package's JSON (the ``.gltf``, or the ``.glb``'s JSON chunk).
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from vbusd.format.diagnostics import Diagnostics, FileLocation, JsonPointer
from vbusd.format.errors import InputError, VbusdError
from vbusd.format import metadata as md
from vbusd.format.metadata import json_kind, json_pointer
from vbusd.io import ktx2, textures
from vbusd.io.gltf import json_text_of, load
from vbusd.io.gltf_accessors import AccessorReader
from vbusd.io.textures import json_differences
import importlib.resources
import re
import jsonschema
import referencing
import urllib.parse
from vbusd.format.model import ReadOptions

__all__ = ["SUFFIXES", "PackageAnimation", "PackageCrowd", "Package", "read_package"]

SUFFIXES = (".glb", ".gltf")
EXTENSION = "VBUSD_virtual_bones"
INSTANCING = "EXT_mesh_gpu_instancing"
INSTANCE_ATTRIBUTES = ("_VB_CLIP", "_VB_TIME_OFFSET", "_VB_PLAYBACK_RATE")
VARIETY_ATTRIBUTES = ("_VB_TINT", "_VB_VARIANT", "_VB_PARTS")
"""Format 1.3 crowd variety (spec/runtime-package.md 13): optional instance attributes."""
_ROOT = f"/extensions/{EXTENSION}"


@dataclass
class PackageAnimation:
    """One entry of the root object's ``animations``.

    Attributes:
        index: Its index.
        name: Its name.
        path: The USD prim path it came from, if given.
        layout: The layout metadata document of the extension.
        texture: How findings name its KTX2 file (the ``.ktx2`` beside a ``.gltf``, or
            ``PACKAGE.glb[bufferView N]``).
        ktx2: The KTX2 file's bytes, when its buffer view could be read.
    """

    index: int
    name: str
    path: Optional[str]
    layout: dict
    texture: str = ""
    ktx2: Optional[bytes] = None


@dataclass
class PackageCrowd:
    """A node instancing a bound mesh with ``EXT_mesh_gpu_instancing``.

    Attributes:
        node: The node's name.
        mesh: The mesh's name (the prototype every instance draws).
        animation: The index of the animation its primitives play.
        instances: The instance count.
        clips: The clip index of each instance (None when ``_VB_CLIP`` is missing).
        playback: The ``_VB_`` instance attributes read (clip, times and rates; the crossfade's
            ``_VB_FADE_*`` and the layers' ``_VB_LAYER_*_j``, spec/runtime-package.md 5.1), by name.
        samples: Time samples of fade and layer attributes: ``{name: (times in seconds (S,), (S, N))}``.
        tint: (N, 3) tints (format 1.3), or None.
        variant: (N,) variant indices into the root ``KHR_materials_variants``, or None.
        parts: (N,) parts masks, or None.
    """

    node: str
    mesh: str
    animation: int
    instances: int
    clips: Optional[np.ndarray] = None
    playback: dict = field(default_factory=dict)
    samples: dict = field(default_factory=dict)

    @property
    def fades(self) -> bool:
        """Whether the crowd carries a crossfade (``_VB_FADE_*``)."""
        return "_VB_FADE_WEIGHT" in self.playback

    @property
    def layers(self) -> int:
        """Layers per instance (``_VB_LAYER_WEIGHT_j`` for j below it)."""
        return sum(1 for name in self.playback if name.startswith("_VB_LAYER_WEIGHT_"))
    tint: Optional[np.ndarray] = None
    variant: Optional[np.ndarray] = None
    parts: Optional[np.ndarray] = None


@dataclass
class Package:
    """What :func:`read_package` read.

    Attributes:
        file: The package as findings name it.
        container: ``glb`` or ``gltf``.
        version: The extension's version.
        animations: The root object's animations whose entry follows the schema.
        meshes: Per mesh, ``(name, primitive count, vertex count, animation index or None)``.
        crowds: The crowd nodes.
        characters: Nodes drawing a bound mesh once (no instancing), by name.
        lods: Format 1.2 levels of detail (``MSFT_lod``): per node that lists levels, ``{"node",
            "animation", "levels", "screenSizes"}`` (``levels`` counts LOD 0; ``screenSizes`` the
            ``MSFT_screencoverage`` thresholds of LOD 1 and on, the trailing 0 left out).
    """

    file: str
    container: str
    version: Optional[int] = None
    animations: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    crowds: list = field(default_factory=list)
    characters: list = field(default_factory=list)
    lods: list = field(default_factory=list)
    extensions_used: list = field(default_factory=list)
    """The file's ``extensionsUsed`` (strings only), e.g. to tell a meshopt-compressed package."""


@functools.lru_cache(maxsize=1)
def _validators():
    """JSON Schema validators of the root object, ``$defs/primitive`` and ``$defs/node`` (schema checked once)."""

    schemas = [json.loads((importlib.resources.files("vbusd.schema") / name).read_text(encoding="utf-8"))
               for name in ("VBUSD_virtual_bones.schema.json", "layout-metadata.schema.json")]
    for schema in schemas:
        jsonschema.Draft202012Validator.check_schema(schema)
    registry = referencing.Registry().with_resources(
        [(s["$id"], referencing.Resource.from_contents(s)) for s in schemas])
    root = jsonschema.Draft202012Validator(schemas[0], registry=registry)
    primitive = jsonschema.Draft202012Validator({"$ref": schemas[0]["$id"] + "#/$defs/primitive"},
                                                registry=registry)
    node = jsonschema.Draft202012Validator({"$ref": schemas[0]["$id"] + "#/$defs/node"}, registry=registry)
    return root, primitive, node


def _schema(validator, value, pointer: str, file: str, diagnostics: Diagnostics) -> bool:
    """Report every schema violation under ``pointer``; the layout's own as ``metadata.schema``."""
    errors = sorted(validator.iter_errors(value), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    for error in errors:
        parts = list(error.absolute_path)
        in_layout = len(parts) >= 3 and parts[0] == "animations" and parts[2] == "layout"
        message = " ".join(error.message.split())
        message = (message[:297] + "...") if len(message) > 300 else message
        diagnostics.report("metadata.schema" if in_layout else "package.extension",
                           f"{message} (schema rule {error.validator})",
                           JsonPointer(file, pointer + json_pointer(parts)))
    return not errors


def _parse(path: Path, file: str) -> dict:
    """The package's JSON as parsed by the glTF reader (a bad container or JSON raises: exit 2)."""
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(f"cannot read the file: {error.strerror or error}", file=file, code="file.unreadable") \
            from None
    text = json_text_of(data, file)
    try:
        root = json.loads(text)
    except (ValueError, RecursionError) as error:
        raise InputError(f"not valid JSON: {getattr(error, 'msg', error)}", file=file, code="gltf.json") from None
    if not isinstance(root, dict):
        raise InputError(f"a glTF document is a JSON object; this is JSON {json_kind(root)}", file=file,
                         location="/", code="gltf.json")
    return root


def _check_extension(root: dict, file: str, diagnostics: Diagnostics) -> Optional[dict]:
    """The extension's listing and objects; returns the root object when it follows the schema."""
    used = root.get("extensionsUsed")
    if not (isinstance(used, list) and EXTENSION in used):
        diagnostics.report("package.extension", f"{EXTENSION} is not listed in extensionsUsed",
                           JsonPointer(file, "/extensionsUsed"))
    required = root.get("extensionsRequired")
    if isinstance(required, list) and EXTENSION in required:
        diagnostics.report("package.extension", f"{EXTENSION} is listed in extensionsRequired; it must only be "
                           "used, so that a loader without it still draws the rest pose",
                           JsonPointer(file, f"/extensionsRequired/{required.index(EXTENSION)}"))
    root_validator, primitive_validator, node_validator = _validators()
    nodes = root.get("nodes")
    for n, node in enumerate(nodes if isinstance(nodes, list) else ()):
        extensions = node.get("extensions") if isinstance(node, dict) else None
        if isinstance(extensions, dict) and EXTENSION in extensions:  # time samples (spec 5.1)
            _schema(node_validator, extensions[EXTENSION], f"/nodes/{n}/extensions/{EXTENSION}", file, diagnostics)
    meshes = root.get("meshes")
    for m, mesh in enumerate(meshes if isinstance(meshes, list) else ()):
        primitives = mesh.get("primitives") if isinstance(mesh, dict) else None
        for p, primitive in enumerate(primitives if isinstance(primitives, list) else ()):
            extensions = primitive.get("extensions") if isinstance(primitive, dict) else None
            if isinstance(extensions, dict) and EXTENSION in extensions:
                _schema(primitive_validator, extensions[EXTENSION],
                        f"/meshes/{m}/primitives/{p}/extensions/{EXTENSION}", file, diagnostics)
    extensions = root.get("extensions")
    if not isinstance(extensions, dict) or EXTENSION not in extensions:
        where = "/extensions" if isinstance(extensions, dict) or "extensions" in root else ""
        diagnostics.report("package.extension", f"no {EXTENSION} object at the root: this is not a Virtual Bones "
                           "runtime package (vbusd convert reads a glTF character; vbusd export writes the "
                           "package)", JsonPointer(file, where or "/extensions"))
        return None
    value = extensions[EXTENSION]
    if not isinstance(value, dict):
        diagnostics.report("package.extension", f"{EXTENSION} must be an object, found JSON {json_kind(value)}",
                           JsonPointer(file, _ROOT))
        return None
    if _schema(root_validator, value, _ROOT, file, diagnostics):
        for entry in value["animations"]:
            _integers(entry["texture"], ("bufferView",))
    return value


def _integers(obj: dict, keys) -> None:
    """The members ``keys`` of a schema-checked object as Python ints: JSON Schema counts ``3.0`` an
    integer (runtime-package.md 3), which as a float cannot index a list or count a range."""
    for key in keys:
        value = obj.get(key)
        if isinstance(value, float) and value.is_integer():
            obj[key] = int(value)


def _texture_name(gltf, view_index: int, data: bytes, file: str) -> str:
    """How findings name a texture: the ``.ktx2`` file a whole external buffer is, else the view."""

    view = gltf.bufferViews[view_index]
    buffer = gltf.buffers[view.buffer] if view.buffer < len(gltf.buffers) else None
    uri = getattr(buffer, "uri", None)
    if uri and not uri.startswith("data:") and not (view.byteOffset or 0) and buffer.byteLength == len(data):
        return urllib.parse.unquote(uri)
    return f"{file}[bufferView {view_index}]"


def _read_texture(gltf, reader, entry: dict, index: int, binary: bool, file: str,
                  diagnostics: Diagnostics) -> tuple[Optional[bytes], str]:
    """The bytes of one animation's KTX2 file, with its buffer view checked (``package.texture``)."""
    where = f"{_ROOT}/animations/{index}/texture/bufferView"
    view_index = entry["texture"]["bufferView"]
    if view_index >= len(gltf.bufferViews):
        diagnostics.report("package.texture", f"buffer view {view_index} does not exist (the package has "
                           f"{len(gltf.bufferViews)})", JsonPointer(file, where))
        return None, ""
    view = gltf.bufferViews[view_index]
    at_view = JsonPointer(file, f"/bufferViews/{view_index}")
    if view.byteStride is not None or view.target is not None:
        diagnostics.report("package.texture", "the texture's buffer view has a byteStride or a target: it holds "
                           "a whole KTX2 file, not vertex data", at_view)
    if binary and view.buffer == 0 and (view.byteOffset or 0) % 16:
        diagnostics.report("package.texture", f"the texture's buffer view starts at byte {view.byteOffset} of the "
                           "BIN chunk, not at a multiple of 16", at_view)
    try:
        data = bytes(reader.view(view_index, where)[0])
    except InputError as error:
        diagnostics.report(error.code, error.message, JsonPointer(file, error.location or where))
        return None, ""
    return data, _texture_name(gltf, view_index, data, file)


def _count(root: dict, accessor) -> Optional[int]:
    """The ``count`` of accessor ``accessor`` in the raw JSON, or None for a bad index."""
    accessors = root.get("accessors") or []
    if isinstance(accessor, int) and not isinstance(accessor, bool) and 0 <= accessor < len(accessors):
        return accessors[accessor].get("count")
    return None


def _read(reader, accessor, pointer: str, file: str, diagnostics: Diagnostics, failed: set):
    """Accessor ``accessor``'s values with every bound of the glTF reader checked, or None (its
    problem reported once, however many primitives or nodes name it)."""
    key = accessor if isinstance(accessor, (int, float)) else repr(accessor)
    if key in failed:
        return None
    try:
        return reader.read(accessor, pointer)
    except InputError as error:
        failed.add(key)
        diagnostics.report(error.code, error.message, JsonPointer(file, error.location or pointer))
        return None


def _check_geometry(root: dict, reader, primitive: dict, where: str, file: str, diagnostics: Diagnostics,
                    failed: set) -> None:
    """Every accessor of a primitive read (attributes, morph targets, indices: the ``gltf.accessor.*``
    bounds), its ``POSITION`` present and its vertex indices below the vertex count
    (``package.primitive``): what a loader reads to draw it."""
    attributes = primitive.get("attributes") or {}
    if "POSITION" not in attributes:
        diagnostics.report("package.primitive", "the primitive has no POSITION attribute: nothing to draw",
                           JsonPointer(file, f"{where}/attributes"))
    for name, accessor in attributes.items():
        _read(reader, accessor, f"{where}/attributes{json_pointer([name])}", file, diagnostics, failed)
    for t, target in enumerate(primitive.get("targets") or ()):
        for name, accessor in target.items():
            _read(reader, accessor, f"{where}/targets/{t}{json_pointer([name])}", file, diagnostics, failed)
    if primitive.get("indices") is None:
        return
    indices = _read(reader, primitive["indices"], f"{where}/indices", file, diagnostics, failed)
    vertices = _count(root, attributes.get("POSITION"))
    if indices is None or not isinstance(vertices, int):
        return
    bad = (indices < 0) | (indices >= vertices)
    if bad.any():
        first = int(np.argmax(bad))
        diagnostics.report("package.primitive", f"{int(np.count_nonzero(bad))} vertex index(es) are not below the "
                           f"vertex count {vertices}; the first, index {first}, is {int(indices[first])}",
                           JsonPointer(file, f"{where}/indices"))


def _check_primitives(root: dict, reader, animations: list, file: str, diagnostics: Diagnostics,
                      package: Package, failed: set) -> dict:
    """Every primitive's accessors (:func:`_check_geometry`) and ``package.primitive`` for every bound
    primitive; returns mesh index -> animation index."""
    bound = {}
    entries = root["extensions"][EXTENSION].get("animations")
    declared = len(entries) if isinstance(entries, list) else 0  # not an array: a schema finding already
    for m, mesh in enumerate(root.get("meshes") or []):
        vertices, playing = 0, None
        primitives = mesh.get("primitives") or []
        for p, primitive in enumerate(primitives):
            ext = (primitive.get("extensions") or {}).get(EXTENSION)
            attributes = primitive.get("attributes") or {}
            count = _count(root, attributes.get("POSITION")) or 0
            vertices += count
            _check_geometry(root, reader, primitive, f"/meshes/{m}/primitives/{p}", file, diagnostics, failed)
            if not isinstance(ext, dict) or not _validators()[1].is_valid(ext):
                continue  # not bound, or its object broke the schema (reported)
            _integers(ext, ("animation", "influences"))
            where = f"/meshes/{m}/primitives/{p}"
            index = ext["animation"]
            if index >= declared:
                diagnostics.report("package.primitive", f"animation {index} does not exist (the package has "
                                   f"{declared})", JsonPointer(file, f"{where}/extensions/{EXTENSION}/animation"))
                continue
            playing = index
            animation = next((a for a in animations if a.index == index), None)
            bones = animation.layout.get("boneCount") if animation is not None else None
            for n in range(-(-ext["influences"] // 4)):
                for name in (f"_VB_JOINTS_{n}", f"_VB_WEIGHTS_{n}"):
                    accessor = attributes.get(name)
                    if accessor is None:
                        diagnostics.report("package.primitive", f"{ext['influences']} influences need {name}, which "
                                           "the primitive does not have", JsonPointer(file, f"{where}/attributes"))
                        continue
                    at = JsonPointer(file, f"{where}/attributes/{name}")
                    values = _count(root, accessor)
                    if values is None:
                        continue  # the glTF reader reports a bad index
                    if values != count:
                        diagnostics.report("package.primitive", f"{name} has {values} values for {count} vertices", at)
                    elif name.startswith("_VB_JOINTS") and isinstance(bones, int):
                        indices = _read(reader, accessor, f"/accessors/{accessor}", file, diagnostics, failed)
                        if indices is None:
                            continue
                        bad = (indices < 0) | (indices >= bones)
                        if bad.any():
                            vertex = int(np.argwhere(bad)[0][0])
                            diagnostics.report("package.primitive", f"bone index {int(indices[bad].flat[0])} of "
                                               f"vertex {vertex} is outside 0..{bones - 1}", at)
        package.meshes.append((mesh.get("name") or f"mesh{m}", len(primitives), vertices, playing))
        if playing is not None:
            bound[m] = playing
    return bound


def _check_nodes(root: dict, reader, bound: dict, animations: list, file: str, diagnostics: Diagnostics,
                 package: Package, failed: set) -> None:
    """``package.instances`` for every crowd node, every instance attribute read within its bounds;
    collects crowds and single characters."""
    nodes = root.get("nodes") or []
    # MSFT_lod (format 1.2): the nodes another node lists are its levels, drawn instead of it per
    # instance, not more characters or crowds; their instance attributes are still checked.
    levels = {i for node in nodes if isinstance(node, dict)
              for i in (((node.get("extensions") or {}).get("MSFT_lod") or {}).get("ids") or [])
              if isinstance(i, int)}
    for n, node in enumerate(nodes):
        if node.get("mesh") not in bound:
            continue
        name = node.get("name") or f"node{n}"
        ids = ((node.get("extensions") or {}).get("MSFT_lod") or {}).get("ids")
        if isinstance(ids, list) and ids:
            # glTF lets extras be any JSON value (an object only SHOULD): MSFT_lod's screen coverage
            # is read from an object's member, and no object means none is given.
            extras = node.get("extras")
            coverage = extras.get("MSFT_screencoverage") if isinstance(extras, dict) else None
            sizes = [float(c) for c in coverage if isinstance(c, (int, float)) and not isinstance(c, bool)] \
                if isinstance(coverage, list) else []
            package.lods.append({"node": name, "animation": bound[node["mesh"]], "levels": len(ids) + 1,
                                 "screenSizes": sizes[:len(ids)]})
        mesh = int(node["mesh"])
        mesh_name = package.meshes[mesh][0]
        ext = (node.get("extensions") or {}).get(INSTANCING)
        if not isinstance(ext, dict) or not isinstance(ext.get("attributes"), dict):
            if n not in levels:
                package.characters.append(name)
            continue
        where = f"/nodes/{n}/extensions/{INSTANCING}/attributes"
        attributes = ext["attributes"]
        counts = {k: c for k, c in ((k, _count(root, v)) for k, v in attributes.items()) if c is not None}
        instances = counts.get("TRANSLATION", max(counts.values(), default=0))
        for key, count in counts.items():
            if count != instances:
                diagnostics.report("package.instances", f"{key} has {count} values for {instances} instances",
                                   JsonPointer(file, f"{where}/{key}"))
        animation = next((a for a in animations if a.index == bound[mesh]), None)
        clip_count = len(animation.layout.get("clips") or ()) if animation is not None else None
        masks = animation.layout.get("masks") if animation is not None else None
        mask_count = len(masks) if isinstance(masks, list) else 0
        spaces = animation.layout.get("blendSpaces") if animation is not None else None
        space_count = len(spaces) if isinstance(spaces, list) else (0 if animation is not None else None)
        if isinstance(masks, list) and isinstance(spaces, list):
            mask_count += 1  # blends play as layers under a mask of every bone (spec 23.1)
        playback_names = [k for k in attributes if k.startswith("_VB_") and k not in VARIETY_ATTRIBUTES]
        for key, accessor in attributes.items():  # TRANSLATION, ROTATION, SCALE: what a loader reads
            if key not in playback_names + list(VARIETY_ATTRIBUTES):
                _read(reader, accessor, f"{where}{json_pointer([key])}", file, diagnostics, failed)
        for problem in _playback_problems(playback_names):
            diagnostics.report("package.instances", problem, JsonPointer(file, where))
        if any(k.startswith("_VB_LAYER_") for k in playback_names) and animation is not None and not mask_count:
            diagnostics.report("package.instances", "the crowd plays layers but its animation's layout has no masks "
                               "(format 1.2 layers need them)", JsonPointer(file, where))
        values = {}
        for key in INSTANCE_ATTRIBUTES:
            if key not in attributes:
                diagnostics.report("package.instances", f"the crowd has no {key} (every crowd node carries "
                                   f"{', '.join(INSTANCE_ATTRIBUTES)})", JsonPointer(file, where))
        for key in playback_names:
            if counts.get(key) != instances:
                continue
            array = _read(reader, attributes[key], f"{where}{json_pointer([key])}", file, diagnostics, failed)
            if array is not None:
                values[key] = array.reshape(-1)
                _check_playback(key, values[key], clip_count, mask_count, f"{where}{json_pointer([key])}",
                                "instance", file, diagnostics, space_count)
        samples = _check_samples(root, reader, node, n, attributes, instances, clip_count, mask_count, file,
                                 diagnostics, failed)
        clips = values.get("_VB_CLIP")
        variety = _check_variety(root, reader, node, mesh, attributes, counts, instances, where, file, diagnostics,
                                 failed)
        if n in levels:
            continue  # a level of another crowd node: the same instances, not another crowd
        package.crowds.append(PackageCrowd(node=name, mesh=mesh_name, animation=bound[mesh],
                                           instances=int(instances),
                                           clips=None if clips is None else np.round(clips).astype(np.int64),
                                           playback=values, samples=samples, **variety))


_FADE_NAMES = ("_VB_FADE_CLIP", "_VB_FADE_TIME_OFFSET", "_VB_FADE_PLAYBACK_RATE", "_VB_FADE_WEIGHT")
_LAYER_STEMS = ("_VB_LAYER_CLIP", "_VB_LAYER_TIME_OFFSET", "_VB_LAYER_PLAYBACK_RATE", "_VB_LAYER_WEIGHT",
                "_VB_LAYER_MASK")
_ADDITIVE_STEMS = ("_VB_LAYER_MODE", "_VB_LAYER_REFERENCE_CLIP", "_VB_LAYER_REFERENCE_TIME")
"""Format 1.3 additive layers (spec/runtime-package.md 5.1): all three of every layer, or none."""
_BLEND_NAMES = ("_VB_BLEND_SPACE", "_VB_BLEND_X", "_VB_BLEND_Y", "_VB_BLEND_PHASE")
"""Format 1.3 blend spaces per instance (spec/runtime-package.md 5.1): all four, or none."""
_LAYER_NAME = re.compile(r"^(_VB_LAYER_[A-Z_]+?)_(0|[1-9][0-9]*)$")


def _playback_problems(names: list) -> list:
    """What is wrong with the set of ``_VB_`` instance attribute names (spec/runtime-package.md 5.1)."""
    problems = []
    unknown = [k for k in names if k not in INSTANCE_ATTRIBUTES and k not in _FADE_NAMES and k not in _BLEND_NAMES
               and not (_LAYER_NAME.match(k) and _LAYER_NAME.match(k).group(1) in _LAYER_STEMS + _ADDITIVE_STEMS)]
    if unknown:
        problems.append(f"unknown Virtual Bones instance attribute {unknown[0]} (spec/runtime-package.md 5.1)")
    fades = [k for k in _FADE_NAMES if k in names]
    if fades and len(fades) != len(_FADE_NAMES):
        problems.append(f"the crowd's crossfade needs all of {', '.join(_FADE_NAMES)}; it has "
                        f"{', '.join(fades)}")
    layers = {int(m.group(2)) for m in map(_LAYER_NAME.match, names) if m and m.group(1) in _LAYER_STEMS}
    for j in range(max(layers) + 1 if layers else 0):
        missing = [f"{stem}_{j}" for stem in _LAYER_STEMS if f"{stem}_{j}" not in names]
        if missing:
            problems.append(f"layer {j} lacks {', '.join(missing)} (layers 0 .. {max(layers)} each carry all five)")
            break
    additive = [k for k in names if _LAYER_NAME.match(k) and _LAYER_NAME.match(k).group(1) in _ADDITIVE_STEMS]
    if additive:
        expected = [f"{stem}_{j}" for j in range(max(layers) + 1 if layers else 0) for stem in _ADDITIVE_STEMS]
        if sorted(additive) != sorted(expected):
            problems.append(f"additive layers carry all of {', '.join(_ADDITIVE_STEMS)} for every layer "
                            f"(_j for each j of the layers), or none; the crowd has {', '.join(sorted(additive))}")
    blends = [k for k in _BLEND_NAMES if k in names]
    if blends and len(blends) != len(_BLEND_NAMES):
        problems.append(f"the crowd's blends need all of {', '.join(_BLEND_NAMES)}; it has {', '.join(blends)}")
    return problems


def _check_playback(key: str, array: np.ndarray, clip_count, mask_count: int, pointer: str, what: str, file: str,
                    diagnostics: Diagnostics, space_count=None) -> None:
    """Finite values; clip and mask indices that are integers the animation has."""
    bad = ~np.isfinite(array)
    limit, noun = None, ""
    low = 0
    if key in ("_VB_CLIP", "_VB_FADE_CLIP") or key.startswith(("_VB_LAYER_CLIP_", "_VB_LAYER_REFERENCE_CLIP_")):
        limit, noun = clip_count, "clips"
    elif key.startswith("_VB_LAYER_MASK_"):
        limit, noun = mask_count, "masks"
    elif key.startswith("_VB_LAYER_MODE_"):
        limit, noun = 2, "modes: 0 override, 1 additive"
    elif key == "_VB_BLEND_SPACE":
        limit, noun, low = space_count, "blend spaces, or -1 for none", -1
    if isinstance(limit, int):
        bad |= (array != np.round(array)) | (array < low) | (array >= limit)
    if bad.any():
        first = int(np.argmax(bad))
        diagnostics.report("package.instances", f"{what} {first} has {key} {float(array[first])!r}"
                           + (f" ({noun} {low}..{limit - 1})" if isinstance(limit, int) else " (not finite)"),
                           JsonPointer(file, pointer))


def _check_samples(root: dict, reader, node: dict, n: int, attributes: dict, instances: int, clip_count,
                   mask_count: int, file: str, diagnostics: Diagnostics, failed: set) -> dict:
    """The crowd node's time samples (spec/runtime-package.md 5.1): ``{name: (times, (S, N) values)}``."""
    ext = (node.get("extensions") or {}).get(EXTENSION)
    if not isinstance(ext, dict) or not _validators()[2].is_valid(ext):
        return {}  # none, or reported against the schema
    out = {}
    for name, entry in ext["samples"].items():
        where = f"/nodes/{n}/extensions/{EXTENSION}/samples{json_pointer([name])}"
        if name not in attributes:
            diagnostics.report("package.instances", f"time samples of {name}, which the node's "
                               f"{INSTANCING} does not carry", JsonPointer(file, where))
            continue
        times = np.asarray(entry["times"], dtype=np.float64)
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            diagnostics.report("package.instances", f"the sample times of {name} must be finite and strictly "
                               "increasing", JsonPointer(file, f"{where}/times"))
            continue
        accessors = root.get("accessors") if isinstance(root.get("accessors"), list) else []
        accessor = accessors[entry["values"]] if entry["values"] < len(accessors) else None
        if not isinstance(accessor, dict) or accessor.get("type") != "SCALAR" or \
                accessor.get("componentType") != 5126 or accessor.get("count") != times.size * instances:
            diagnostics.report("package.instances", f"the samples of {name} must be a SCALAR FLOAT accessor of "
                               f"{times.size} x {instances} values", JsonPointer(file, f"{where}/values"))
            continue
        values = _read(reader, entry["values"], f"{where}/values", file, diagnostics, failed)
        if values is None:
            continue
        values = values.reshape(times.size, instances)
        _check_playback(name, values.reshape(-1), clip_count, mask_count, f"{where}/values", "sample value",
                        file, diagnostics)
        out[name] = (times, values)
    return out


def _check_variety(root: dict, reader, node: dict, mesh: int, attributes: dict, counts: dict, instances: int,
                   where: str, file: str, diagnostics: Diagnostics, failed: set) -> dict:
    """The optional format 1.3 variety attributes of a crowd node (spec/runtime-package.md 13), checked:
    finite, tints >= 0, variants integers in the root KHR_materials_variants, masks integers >= 0 naming
    only parts the mesh's primitives have. Returns the PackageCrowd fields read."""
    variants = ((root.get("extensions") or {}).get("KHR_materials_variants") or {}).get("variants")
    variant_count = len(variants) if isinstance(variants, list) else 0
    primitives = ((root.get("meshes") or [])[mesh] or {}).get("primitives") or []
    part_bits = [((p.get("extensions") or {}).get(EXTENSION) or {}).get("part") for p in primitives
                 if isinstance(p, dict)]
    part_count = max([b + 1 for b in part_bits if isinstance(b, int) and not isinstance(b, bool)], default=0)
    out = {}
    for key, field_name, width in (("_VB_TINT", "tint", 3), ("_VB_VARIANT", "variant", 1), ("_VB_PARTS", "parts", 1)):
        if key not in attributes or counts.get(key) != instances:
            continue
        array = _read(reader, attributes[key], f"{where}/{key}", file, diagnostics, failed)
        if array is None:
            continue
        array = np.asarray(array, dtype=np.float64).reshape(instances, width)
        bad = ~np.all(np.isfinite(array), axis=1)
        if key == "_VB_TINT":
            bad |= np.any(array < 0, axis=1)
            why = "(tints are three finite numbers 0 or more)"
        else:
            flat = array[:, 0]
            limit = variant_count if key == "_VB_VARIANT" else 1 << min(part_count, 31)
            bad |= (flat != np.round(flat)) | (flat < 0) | (flat >= limit)
            why = (f"(variants 0..{variant_count - 1} of KHR_materials_variants)" if key == "_VB_VARIANT"
                   else f"(masks of the {part_count} part(s) of the mesh's primitives)")
        if bad.any():
            first = int(np.argmax(bad))
            diagnostics.report("package.instances", f"instance {first} has {key} "
                               f"{array[first].tolist() if width > 1 else float(array[first, 0])!r} {why}",
                               JsonPointer(file, f"{where}/{key}"))
            continue
        out[field_name] = array.astype(np.float32) if width > 1 else np.round(array[:, 0]).astype(np.int64)
    return out


def read_package(path, diagnostics: Diagnostics, *, allow_outside_paths: bool = False) -> Optional[Package]:
    """Read and check a runtime package (see the module docstring).

    ``vbusd info``, ``vbusd view`` (strict lists) and ``vbusd validate`` (a lenient list) all read
    through here, so they accept and refuse the same packages; only the KTX2 files' level data
    (content digest, texels) is left to ``validate`` (:mod:`vbusd.validators.checks_package`).

    Args:
        path: The ``.glb`` or ``.gltf``.
        diagnostics: Where problems go (strict: the first error raises).
        allow_outside_paths: Let buffer URIs resolve outside the package's folder.

    Returns:
        What could be read, or None when not even the glTF reader could read the file's buffers.

    Raises:
        InputError: The container or the JSON cannot be read at all (whatever ``diagnostics``).
    """

    path = Path(path)
    file = str(path)
    root = _parse(path, file)
    binary = path.read_bytes()[:4] == b"glTF"
    package = Package(file=file, container="glb" if binary else "gltf")
    used = root.get("extensionsUsed") if isinstance(root, dict) else None
    package.extensions_used = [u for u in used if isinstance(u, str)] if isinstance(used, list) else []
    extension = _check_extension(root, file, diagnostics)
    try:
        gltf, buffers = load(path, ReadOptions(allow_outside_paths=allow_outside_paths))
    except VbusdError as error:  # InputError, or UnsupportedError for a required extension
        seen = {str(getattr(f.location, "pointer", "")) for f in diagnostics.findings}
        if not any(error.location and p and p.startswith(error.location) for p in seen):
            diagnostics.report(error.code, error.message, JsonPointer(file, error.location) if error.location and
                               error.location.startswith("/") else FileLocation(file, part=error.location))
        return None
    if extension is None:
        return package
    package.version = extension.get("version")
    reader = AccessorReader(gltf, buffers, file)
    entries = extension.get("animations") if isinstance(extension.get("animations"), list) else []
    root_validator = _validators()[0]
    for index, entry in enumerate(entries):
        # Only entries that follow the schema are read further (the others were reported).
        if not root_validator.is_valid({"version": 1, "animations": [entry]}):
            continue
        animation = PackageAnimation(index=index, name=entry["name"], path=entry.get("path"), layout=entry["layout"])
        animation.ktx2, animation.texture = _read_texture(gltf, reader, entry, index, binary, file, diagnostics)
        if animation.ktx2 is not None and not _check_ktx2(animation, file, diagnostics):
            animation.ktx2 = None  # its header is reported; validate has nothing more to read
        package.animations.append(animation)
    failed: set = set()
    bound = _check_primitives(root, reader, package.animations, file, diagnostics, package, failed)
    _check_nodes(root, reader, bound, package.animations, file, diagnostics, package, failed)
    return package


def _check_ktx2(animation: PackageAnimation, file: str, diagnostics: Diagnostics) -> bool:
    """The KTX2 file's header (every check :func:`vbusd.io.ktx2.scan` makes before the level is read),
    its ``vbusd.layout`` entry and the file against it (size, texel format), and the extension's
    ``layout`` against that entry (``package.layout``).

    A header that cannot be read is reported and False returned. What is wrong with the
    ``vbusd.layout`` entry or between it and the file is reported here for strict readers only:
    ``vbusd validate`` reports it, with the rest of the KTX2 file's checks, from
    :func:`vbusd.validators.checks_texture.check_texture_file`, so it is not reported twice.
    """
    image = textures.read_ktx2_bytes(animation.ktx2, diagnostics, animation.texture)
    if image is None:
        return False
    local = Diagnostics(animation.texture)
    document = None
    if not image.metadata:
        local.report("metadata.missing", f"the KTX2 file has no {ktx2.METADATA_KEY} key/value entry: the "
                     "layout metadata every Virtual Bones texture embeds",
                     FileLocation(animation.texture, part=image.metadata_part))
    else:
        document = md.parse_document(image.metadata[0][0], local, file=animation.texture,
                                     within=image.metadata_part)
    if isinstance(document, dict) and diagnostics.strict:
        # Step 7 of a KTX2 reader (spec/ktx2.md "Reading safely"): the layout metadata parsed,
        # version-checked and validated, as a KTX2 file on its own is (vbusd validate reports the
        # same from check_texture_file); the first problem raises.
        md.from_dict(document, file=animation.texture, location_prefix=image.metadata_part)
    if isinstance(document, dict):
        texel_format = document.get("texelFormat")
        width, height = document.get("width"), document.get("height")
        textures.check_image(image, local, width=width if isinstance(width, int) else None,
                             height=height if isinstance(height, int) else None,
                             texel_format=texel_format if isinstance(texel_format, str)
                             and texel_format in textures.CONTAINERS["ktx2"].pixel_types else None,
                             format_location=JsonPointer(animation.texture, "/texelFormat", image.metadata_part))
    if diagnostics.strict:
        for item in local.findings:
            diagnostics.add(item)
    if not isinstance(document, dict):
        return True
    for parts in json_differences(animation.layout, document):
        pointer = f"{_ROOT}/animations/{animation.index}/layout{json_pointer(parts)}"
        diagnostics.report("package.layout", f"the layout differs from the vbusd.layout entry of its KTX2 texture "
                           f"{animation.texture} at {json_pointer(parts) or '/'}; the two must be equal (export "
                           "the package again)", JsonPointer(file, pointer))
    return True
