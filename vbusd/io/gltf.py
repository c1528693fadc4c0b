"""The glTF 2.0 container reader: .gltf and .glb files checked and parsed, their buffers loaded.

The one container walk of glTF in vbusd (spec/gltf-conversion.md, "Reading: containers, buffers
and accessors"): the glTF converter (:mod:`vbusd.converters.gltf`), the runtime package reader
(:mod:`vbusd.io.package_reader`), the runtime package writer (:mod:`vbusd.io.gltf_package`) and the
batch cache read through it.

* :func:`json_text_of`: the JSON text of a .gltf or of a .glb's JSON chunk (the GLB header and chunk
  table checked);
* :func:`load`: the document as pygltflib's objects, built (:func:`_document`) after the checks
  pygltflib does not make on the raw JSON (types of the properties the converter reads, array
  bounds, ``extensions``), the version and required extensions checked, every buffer loaded (GLB
  BIN chunk, base64 ``data:`` URIs, external files inside the asset's folder) at exactly its
  ``byteLength``. The objects are the ones ``pygltflib.GLTF2.gltf_from_json`` builds, built here in
  time proportional to the document (pygltflib's decoder costs about a millisecond per object);
* :func:`referenced_uris`: the buffer and image URIs a file names.

Accessors are read through :class:`vbusd.io.gltf_accessors.AccessorReader`. Every problem raises
:class:`vbusd.format.errors.InputError` (or :class:`~vbusd.format.errors.UnsupportedError` for a
required extension) with a JSON pointer.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import functools
import os
import re
import struct
import typing
import urllib.parse
from pathlib import Path

from vbusd.format.errors import InputError, UnsupportedError
from vbusd.format.metadata import json_pointer
from vbusd.format.model import ReadOptions
from vbusd.io.gltf_accessors import require_int
from vbusd.io import gltf_meshopt
from vbusd.io.files import resolve_inside
from reprlib import repr as short
from vbusd.format.layout import MAX_TEXTURE_DIMENSION, Encoding
from vbusd.format.metadata import json_kind
import json
import pygltflib

__all__ = ["MAX_FILE_BYTES", "MAX_ARRAY_ENTRIES", "GLB_MAGIC", "load", "json_text_of", "referenced_uris"]

MAX_FILE_BYTES = 1 << 31
"""Largest .gltf/.glb or external buffer accepted (2 GiB), checked before reading."""

GLB_MAGIC = b"glTF"
"""The first four bytes of a GLB file (a file starting otherwise is read as JSON text)."""

_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942

_ALLOWED_REQUIRED = ("KHR_mesh_quantization", "KHR_texture_transform", "KHR_texture_basisu",
                     "KHR_lights_punctual", "EXT_texture_webp", "EXT_texture_avif")
"""Required extensions we can honour: geometry ones we implement, and ones that only touch
materials, textures or lights (which a Virtual Bones texture does not carry)."""


# ------------------------------------------------------------------------------------------------
# Loading: container, version, buffers
# ------------------------------------------------------------------------------------------------


def _parse_glb(data: bytes, file: str) -> tuple[str, bytes | None]:
    """Check a GLB header and chunk table; return the JSON text and the BIN chunk (or None)."""
    if len(data) < 20:
        raise InputError(f"GLB file of {len(data)} bytes is shorter than its 12-byte header and "
                         "first chunk header", file=file, location="byte 0", code="gltf.glb")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if version != 2:
        raise InputError(f"GLB container version {version} is not 2", file=file, location="byte 4",
                         code="gltf.asset.version")
    if length != len(data):
        raise InputError(f"GLB header declares {length} bytes, the file has {len(data)}",
                         file=file, location="byte 8", code="gltf.glb")
    offset, json_text, binary = 12, None, None
    index = 0
    while offset < length:
        if offset + 8 > length:
            raise InputError("truncated chunk header", file=file, location=f"byte {offset}",
                             code="gltf.glb")
        chunk_length, chunk_type = struct.unpack_from("<II", data, offset)
        start = offset + 8
        if start + chunk_length > length:
            raise InputError(f"chunk {index} of {chunk_length} bytes runs past the end of the file "
                             f"({length} bytes)", file=file, location=f"byte {offset}",
                             code="gltf.glb")
        chunk = data[start:start + chunk_length]
        if index == 0:
            if chunk_type != _CHUNK_JSON:
                raise InputError("the first chunk is not JSON", file=file,
                                 location=f"byte {offset + 4}", code="gltf.glb")
            try:
                json_text = chunk.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise InputError(f"JSON chunk is not UTF-8 ({exc.reason} at byte "
                                 f"{start + exc.start})", file=file, location=f"byte {start + exc.start}",
                                 code="gltf.json") from None
        elif chunk_type == _CHUNK_BIN:
            if index != 1:
                raise InputError("BIN chunk is not the second chunk", file=file,
                                 location=f"byte {offset}", code="gltf.glb")
            binary = chunk
        # Other chunk types are skipped, as the GLB specification requires.
        offset = start + chunk_length
        index += 1
    if json_text is None:
        raise InputError("GLB has no JSON chunk", file=file, location="byte 12", code="gltf.glb")
    return json_text, binary


def _check_version(gltf, file: str) -> None:
    asset = gltf.asset
    version = getattr(asset, "version", None) if asset is not None else None
    match = re.fullmatch(r"(\d+)\.(\d+)", version) if isinstance(version, str) else None
    if match is None:
        raise InputError(f"asset.version {version!r} is not of the form MAJOR.MINOR", file=file,
                         location="/asset/version", code="gltf.asset.version")
    if int(match.group(1)) != 2:
        raise InputError(f"glTF version {version} is not supported (this reader knows 2.x)",
                         file=file, location="/asset/version", code="gltf.asset.version")
    minimum = getattr(asset, "minVersion", None)
    if minimum is not None:
        m = re.fullmatch(r"(\d+)\.(\d+)", minimum) if isinstance(minimum, str) else None
        if m is None or (int(m.group(1)), int(m.group(2))) > (2, 0):
            raise InputError(f"asset.minVersion {minimum!r} is newer than 2.0", file=file,
                             location="/asset/minVersion", code="gltf.asset.version")


def _decode_data_uri(uri: str, pointer: str, file: str) -> bytes:
    header, comma, payload = uri.partition(",")
    if not comma or not header.endswith(";base64"):
        raise InputError("data URI is not base64 (expected data:<type>;base64,<data>)", file=file,
                         location=pointer, code="gltf.buffer.base64")
    bad = re.search(r"[^A-Za-z0-9+/=]", payload)
    if bad:
        raise InputError(f"data URI holds {bad.group(0)!r}, not a base64 character, at character "
                         f"{len(header) + 1 + bad.start()} of the URI", file=file, location=pointer,
                         code="gltf.buffer.base64")
    try:
        return base64.b64decode(payload, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InputError(f"data URI is not valid base64: {exc}", file=file, location=pointer,
                         code="gltf.buffer.base64") from None


def _read_external(uri: str, folder: Path, length: int, pointer: str, file: str,
                   allow_outside: bool) -> bytes:

    relative = urllib.parse.unquote(uri)
    path = resolve_inside(folder, relative, file=file, location=pointer, allow_outside=allow_outside)
    try:
        size = os.stat(path).st_size
        if size < length:
            raise InputError(f"buffer file {relative!r} holds {size} bytes, byteLength declares "
                             f"{length}", file=file, location=pointer.rsplit("/", 1)[0],
                             code="gltf.buffer.length")
        with open(path, "rb") as stream:
            return stream.read(length)
    except OSError as exc:
        raise InputError(f"cannot read buffer file {relative!r}: {exc.strerror}", file=file,
                         location=pointer, code="gltf.buffer.missing") from None


def _load_buffers(gltf, binary: bytes | None, folder: Path, file: str,
                  options: ReadOptions) -> list:
    buffers = []
    for i, buf in enumerate(gltf.buffers or []):
        where = f"/buffers/{i}"
        length = require_int(buf.byteLength, f"{where}/byteLength", file, minimum=1)
        if length > MAX_FILE_BYTES:
            raise InputError(f"byteLength {length} exceeds the limit of {MAX_FILE_BYTES} bytes",
                             file=file, location=f"{where}/byteLength", code="gltf.buffer.limit")
        uri = buf.uri
        if uri is None and gltf_meshopt.is_fallback_buffer(buf) and (i != 0 or binary is None):
            buffers.append(b"")  # stands in for meshopt data only (decompress_views); no bytes to read
            continue
        if uri is None:
            if i != 0 or binary is None:
                raise InputError("buffer has no uri and there is no GLB BIN chunk for it", file=file,
                                 location=where, code="gltf.buffer.missing")
            data = binary
        elif not isinstance(uri, str):
            raise InputError(f"uri must be a string, found {uri!r}", file=file,
                             location=f"{where}/uri", code="gltf.value")
        elif uri.startswith("data:"):
            data = _decode_data_uri(uri, f"{where}/uri", file)
        else:
            data = _read_external(uri, folder, length, f"{where}/uri", file,
                                  options.allow_outside_paths)
        if len(data) < length:
            raise InputError(f"buffer holds {len(data)} bytes, byteLength declares {length}",
                             file=file, location=where, code="gltf.buffer.length")
        buffers.append(bytes(data[:length]))
    return buffers


_TOP_LEVEL_ARRAYS = ("accessors", "animations", "buffers", "bufferViews", "cameras", "images",
                     "materials", "meshes", "nodes", "samplers", "scenes", "skins", "textures")


_NESTED = {
    "animations": (("samplers", list), ("channels", list)),
    "meshes": (("primitives", list),),
    "accessors": (("sparse", dict),),
}
"""Arrays of objects / objects inside top-level elements that the converter reads."""

_NESTED_IN_ELEMENT = {"channels": ("target",), "primitives": ("attributes",),
                      "sparse": ("indices", "values")}


def _locate_structure_error(root) -> str | None:
    """The JSON pointer of the first object-valued glTF property that is not an object (or array).

    pygltflib keeps such values as they are (or fails with a bare exception); this finds them in
    the parsed JSON ``root`` so that the error can name the place. pygltflib still does the parsing.
    """
    if not isinstance(root, dict):
        return ""
    for key in _TOP_LEVEL_ARRAYS:
        value = root.get(key)
        if value is None:
            continue
        if not isinstance(value, list):
            return f"/{key}"
        for i, item in enumerate(value):
            if not isinstance(item, dict):
                return f"/{key}/{i}"
            # Nested objects pygltflib would keep as raw values.
            for member, kind in _NESTED.get(key, ()):
                child = item.get(member)
                where = f"/{key}/{i}/{member}"
                if child is None:
                    continue
                if kind is list:
                    if not isinstance(child, list):
                        return where
                    for k, element in enumerate(child):
                        if not isinstance(element, dict):
                            return f"{where}/{k}"
                        for sub in _NESTED_IN_ELEMENT.get(member, ()):
                            if sub in element and not isinstance(element[sub], dict):
                                return f"{where}/{k}/{sub}"
                elif not isinstance(child, dict):
                    return where
                else:
                    for sub in _NESTED_IN_ELEMENT.get(member, ()):
                        if sub in child and not isinstance(child[sub], dict):
                            return f"{where}/{sub}"
    if not isinstance(root.get("asset"), dict):
        return "/asset"
    return None


# JSON types of the properties the converter reads (glTF 2.0 JSON schema). pygltflib converts
# typed fields with int()/float()/bool() as it parses: 1.5 would become 1, true a 1, "3" a 3, and
# "x" an exception without a place. So these are checked on the raw JSON first, with their pointer.
_INT, _NUM, _STR, _BOOL = "integer", "number", "string", "boolean"
_INTS, _NUMS, _STRS = ("array", _INT), ("array", _NUM), ("array", _STR)
_INT_MAP = ("map", _INT)
_REQUIRED = "required"   # ("required", kind): the property must be present (pygltflib needs it)
_SPARSE = {"count": _INT, "indices": {"bufferView": _INT, "byteOffset": _INT, "componentType": _INT},
           "values": {"bufferView": _INT, "byteOffset": _INT}}
_TYPES = {
    "scene": _INT,
    "extensionsUsed": _STRS,
    "extensionsRequired": _STRS,
    "asset": {"version": _STR, "minVersion": _STR},
    "accessors": ("array", {"bufferView": _INT, "byteOffset": _INT, "componentType": _INT,
                            "normalized": _BOOL, "count": _INT, "type": _STR, "sparse": _SPARSE,
                            "min": _NUMS, "max": _NUMS}),
    "animations": ("array", {
        "channels": ("array", {"sampler": _INT, "target": {"node": _INT, "path": _STR}}),
        "samplers": ("array", {"input": _INT, "output": _INT, "interpolation": _STR})}),
    "buffers": ("array", {"uri": _STR, "byteLength": _INT}),
    "bufferViews": ("array", {"buffer": _INT, "byteOffset": _INT, "byteLength": _INT,
                              "byteStride": _INT, "target": _INT}),
    "meshes": ("array", {"primitives": ("array", {"attributes": (_REQUIRED, _INT_MAP),
                                                  "indices": _INT,
                                                  "mode": _INT,
                                                  "targets": ("array", _INT_MAP)}),
                         "weights": _NUMS}),
    "nodes": ("array", {"children": _INTS, "skin": _INT, "mesh": _INT, "camera": _INT,
                        "matrix": _NUMS, "rotation": _NUMS, "scale": _NUMS, "translation": _NUMS,
                        "weights": _NUMS, "name": _STR,
                        # The extensions a runtime package's nodes carry (MSFT_lod's and
                        # EXT_mesh_gpu_instancing's own schemas): a reader walks them.
                        "extensions": {"MSFT_lod": {"ids": _INTS},
                                       "EXT_mesh_gpu_instancing": {"attributes": _INT_MAP}}}),
    "scenes": ("array", {"nodes": _INTS}),
    "skins": ("array", {"inverseBindMatrices": _INT, "skeleton": _INT, "joints": _INTS}),
}


def _type_error(value, kind, pointer: str):
    """(pointer, problem) of the first value below ``value`` that is not of ``kind``, or None."""
    if kind == _INT:
        # JSON Schema: 3.0 is an integer; 1.5, true and "3" are not.
        ok = ((isinstance(value, int) and not isinstance(value, bool))
              or (isinstance(value, float) and value.is_integer()))
        return None if ok else (pointer, f"expected an integer, found {short(value)}")
    if kind == _NUM:
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
              and value == value and value not in (float("inf"), float("-inf")))
        return None if ok else (pointer, f"expected a finite number, found {short(value)}")
    if kind == _STR:
        return None if isinstance(value, str) else (pointer,
                                                    f"expected a string, found {short(value)}")
    if kind == _BOOL:
        return None if isinstance(value, bool) else (pointer, f"expected true or false, found "
                                                               f"{short(value)}")
    if isinstance(kind, tuple) and kind[0] == _REQUIRED:
        return _type_error(value, kind[1], pointer)
    if isinstance(kind, tuple):
        container, item = kind
        if container == "array":
            if not isinstance(value, list):
                return pointer, f"expected an array, found {short(value)}"
            pairs = ((str(i), v) for i, v in enumerate(value))
        else:
            if not isinstance(value, dict):
                return pointer, f"expected an object, found {short(value)}"
            pairs = value.items()
        for key, child in pairs:
            found = _type_error(child, item, pointer + json_pointer([key]))
            if found:
                return found
        return None
    if not isinstance(value, dict):
        return pointer, f"expected an object, found {short(value)}"
    for key, child_kind in kind.items():
        child = value.get(key)
        if child is not None:
            found = _type_error(child, child_kind, f"{pointer}/{key}")
            if found:
                return found
        elif isinstance(child_kind, tuple) and child_kind[0] == _REQUIRED:
            return (f"{pointer}/{key}" if key in value else pointer or "/",
                    f"{key} is required" + (", found null" if key in value else " and missing"))
        elif key in value and not isinstance(child_kind, str):
            # A null scalar reads as absent (as pygltflib does, the converter then asks for what
            # it needs); a null array or object makes pygltflib fail, so it is named here.
            return f"{pointer}/{key}", "expected an array or object, found null"
    return None


MAX_ARRAY_ENTRIES = 1 << 18
"""Entries of one top-level glTF array (nodes, meshes, accessors...) the reader accepts: counted on
the raw JSON before an object is built per entry (:func:`_document`; a million nodes take
gigabytes)."""


def _check_counts(root, file: str) -> None:
    """Bound the top-level arrays and every skin's joint list on the raw JSON (spec: reading)."""

    if not isinstance(root, dict):
        return
    for key, value in root.items():
        if isinstance(value, list) and len(value) > MAX_ARRAY_ENTRIES:
            raise InputError(f"{key} holds {len(value)} entries; the reader accepts at most {MAX_ARRAY_ENTRIES}",
                             file=file, location=f"/{key}", code="gltf.json.limit")
    most_bones = MAX_TEXTURE_DIMENSION // min(e.texels_per_bone for e in Encoding)
    skins = root.get("skins")
    for index, skin in enumerate(skins if isinstance(skins, list) else ()):
        joints = skin.get("joints") if isinstance(skin, dict) else None
        if isinstance(joints, list) and len(joints) > most_bones:
            raise InputError(f"the skin lists {len(joints)} joints; a Virtual Bones texture holds at most "
                             f"{most_bones} bones ({MAX_TEXTURE_DIMENSION} texels per row)", file=file,
                             location=f"/skins/{index}/joints", code="layout.size")


def _extension_error(root) -> tuple | None:
    """(pointer, problem) of the first ``extensions`` that is not an object of objects, or None.

    glTF 2.0's schema makes every ``extensions`` property an object whose values (one per
    extension) are objects; ``null`` is neither, so it is named here instead of reading as absent.
    ``extras`` (application data, any JSON value) are not entered.
    """

    pending = [("", root)]
    while pending:   # iterative: JSON nesting must not become Python recursion
        pointer, value = pending.pop()
        if isinstance(value, list):
            pending += [(f"{pointer}/{i}", item) for i, item in reversed(list(enumerate(value)))]
            continue
        if not isinstance(value, dict):
            continue
        children = []
        for key, child in value.items():
            where = pointer + json_pointer([key])
            if key == "extras":
                continue
            if key == "extensions":
                if not isinstance(child, dict):
                    return where, f"extensions must be an object, found JSON {json_kind(child)}"
                for name, body in child.items():
                    if not isinstance(body, dict):
                        return (where + json_pointer([name]),
                                f"extension {name!r} must be an object, found JSON {json_kind(body)}")
            children.append((where, child))
        pending += reversed(children)
    return None


def _drop_foreign_extras(root: dict) -> bool:
    """Remove, in place, every ``extras`` that is not an object; returns whether any was.

    ``extras`` may hold any JSON value (glTF 2.0), but pygltflib reads them as objects and fails
    on a list or a number with a bare exception; the converter never reads them.
    """
    dropped = False
    pending = [root]
    while pending:   # iterative: JSON nesting must not become Python recursion
        value = pending.pop()
        if isinstance(value, list):
            pending += value
        elif isinstance(value, dict):
            if "extras" in value and not isinstance(value["extras"], dict):
                del value["extras"]
                dropped = True
            pending += [child for key, child in value.items() if key != "extras"]
    return dropped


# ------------------------------------------------------------------------------------------------
# Building pygltflib's objects from the checked JSON
# ------------------------------------------------------------------------------------------------

_PLANS: dict = {}
"""pygltflib dataclass -> ((field name, converter, default factory), ...), built once per class."""


def _plan(cls) -> tuple:
    """How :func:`_build` fills each field of a pygltflib dataclass (its type hints read once)."""
    plan = _PLANS.get(cls)
    if plan is None:
        hints = typing.get_type_hints(cls)
        steps = []
        for item in dataclasses.fields(cls):
            if item.default is not dataclasses.MISSING:
                default = functools.partial(_same, item.default)
            elif item.default_factory is not dataclasses.MISSING:
                default = item.default_factory
            else:
                default = functools.partial(_same, None)
            steps.append((item.name, _converter(hints[item.name]), default))
        plan = _PLANS[cls] = tuple(steps)
    return plan


def _same(value):
    return value


def _coerce(kind, value):
    return value if isinstance(value, kind) else kind(value)


def _converter(kind):
    """The function that turns a JSON value that is not null into a field of type ``kind``, as
    pygltflib's decoder (dataclasses_json, ``infer_missing=True``) turns it: dataclasses built,
    lists converted item by item, ``int``/``float``/``str``/``bool`` coerced, anything else
    (``Dict[str, Any]``, ``Attributes``) kept as read, a mapping copied."""
    origin, arguments = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Union:
        inner = [a for a in arguments if a is not type(None)]
        return _converter(inner[0]) if len(inner) == 1 else _same
    if dataclasses.is_dataclass(kind):
        return functools.partial(_build, kind)
    if origin is list:
        item = _item_converter(arguments[0]) if arguments else _same
        return lambda value: [item(x) for x in value]
    if origin is dict:
        return lambda value: dict(value.items())
    if kind in (int, float, str, bool):
        return functools.partial(_coerce, kind)
    return _same


def _item_converter(kind):
    """:func:`_converter` for the items of a list, where a null is decoded too (as dataclasses_json
    does: an object of defaults for a dataclass, ``int(None)`` fails, ``None`` for a generic)."""
    if dataclasses.is_dataclass(kind) or kind in (int, float, str, bool):
        return _converter(kind)
    convert = _converter(kind)
    if convert is _same:
        return _same
    return lambda value: None if value is None else convert(value)


def _build(cls, value):
    """A pygltflib object of ``cls`` from a parsed JSON object: each field from its member (a null
    member is None, an absent one the field's default), the others left out.

    The same objects ``pygltflib.GLTF2.gltf_from_json`` builds from the same JSON, in time
    proportional to the document: pygltflib's decoder resolves every field's type hints again for
    each object, about a millisecond an object, so 200,000 nodes took minutes (issue 35 item 1).
    """
    if value is None:
        value = {}
    if isinstance(value, cls):
        return value
    if not isinstance(value, dict):
        raise TypeError(f"expected a JSON object for {cls.__name__}, found {json_kind(value)}")
    fields = {}
    for name, convert, default in _plan(cls):
        if name in value:
            member = value[name]
            fields[name] = None if member is None else convert(member)
        else:
            fields[name] = default()
    return cls(**fields)


def _document(root: dict):
    """The pygltflib document of a checked glTF JSON object (:func:`_check_raw_structure`).

    Equivalent to ``pygltflib.GLTF2.gltf_from_json`` on the same JSON (tests/test_gltf_reader.py
    compares the two on every glTF file of the test fixtures and shared assets), without its cost
    per object: a non-empty ``attributes`` object of a primitive becomes an ``Attributes``, as
    pygltflib makes it after decoding.
    """
    gltf = _build(pygltflib.GLTF2, root)
    for mesh in gltf.meshes or ():
        for primitive in mesh.primitives or ():
            raw = primitive.attributes
            if raw:
                primitive.attributes = pygltflib.Attributes(**raw)
    return gltf


def _check_raw_structure(json_text: str, file: str, json_start: int = 0) -> dict:
    """Checks pygltflib cannot make, on the raw JSON, before it builds its objects.

    pygltflib fills a missing ``asset`` or ``asset.version`` with defaults and coerces typed
    properties with ``int()``/``float()``; here the required ``asset.version``, the kinds of the
    arrays and objects, and the JSON types of every property the converter reads (:data:`_TYPES`)
    are checked. Values are read through pygltflib's objects afterwards.

    Args:
        json_text: The JSON text (of the .gltf, or of the GLB's JSON chunk).
        file: The file, for messages.
        json_start: Byte offset of ``json_text`` in the file (20 in a GLB), for syntax errors.

    Returns:
        The parsed document without its ``extras`` that are not objects
        (:func:`_drop_foreign_extras`), for :func:`_document`.
    """

    try:
        root = json.loads(json_text)
    except RecursionError:
        raise InputError("JSON nests too deeply", file=file, code="gltf.json") from None
    except ValueError as exc:
        # json reports a character index into the text; the message names the byte of the file
        # (the JSON chunk of a GLB starts at byte 20, and non-ASCII characters take several bytes).
        at = json_start + len(json_text[:getattr(exc, "pos", 0)].encode("utf-8"))
        raise InputError(f"not valid JSON: {getattr(exc, 'msg', exc)}", file=file,
                         location=f"byte {at}", code="gltf.json") from None
    if not isinstance(root, dict):
        raise InputError(f"a glTF document is a JSON object; this is JSON {json_kind(root)}", file=file,
                         location="/", code="gltf.json")
    if not isinstance(root.get("asset"), dict):
        raise InputError("asset is missing or not an object", file=file, location="/asset",
                         code="gltf.asset.version")
    _check_counts(root, file)
    location = _locate_structure_error(root)
    if location is not None:
        raise InputError("a glTF property that must be an object or an array is not one",
                         file=file, location=location, code="gltf.json")
    found = _type_error(root, _TYPES, "")
    if found is not None:
        location, problem = found
        raise InputError(problem, file=file, location=location, code="gltf.value")
    if "version" not in root["asset"]:
        raise InputError("asset.version is missing", file=file, location="/asset",
                         code="gltf.asset.version")
    found = _extension_error(root)
    if found is not None:
        location, problem = found
        raise InputError(problem, file=file, location=location, code="gltf.value")
    _drop_foreign_extras(root)
    return root


def json_text_of(data: bytes, file: str) -> str:
    """The JSON text of a .gltf or .glb file's bytes: the GLB container checked chunk by chunk
    (:func:`_parse_glb`), or the whole file decoded as UTF-8. The one container walk of glTF in
    vbusd: the converter, the batch cache and the runtime package writer all read through it.

    Raises:
        InputError: A malformed GLB container or text that is not UTF-8 (``gltf.glb``, ``gltf.json``).
    """
    if data[:4] == GLB_MAGIC:
        return _parse_glb(data, file)[0]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"not a GLB and not UTF-8 JSON ({exc.reason})", file=file,
                         location=f"byte {exc.start}", code="gltf.json") from None


def referenced_uris(path, *, limit: int = MAX_FILE_BYTES) -> list:
    """The ``uri`` of every buffer and image of a .gltf or .glb file, as written (``data:`` URIs
    included), or an empty list when the file cannot be read as glTF JSON (the converter says
    why when it reads the file)."""

    path = Path(path)
    try:
        if path.stat().st_size > limit:
            return []
        document = json.loads(json_text_of(path.read_bytes(), str(path)))
        entries = list(document.get("buffers") or []) + list(document.get("images") or [])
    except (OSError, ValueError, AttributeError, TypeError, RecursionError, InputError):
        return []
    return [e["uri"] for e in entries if isinstance(e, dict) and isinstance(e.get("uri"), str) and e["uri"]]


def load(path, options: ReadOptions | None = None):
    """Parse a .gltf or .glb file with pygltflib and load its buffers, checking the container.

    The container kind is taken from the file's first four bytes (``glTF`` = GLB), not its suffix.

    Args:
        path: The file.
        options: Read options (``allow_outside_paths`` applies to buffer URIs).

    Returns:
        (gltf, buffers): the pygltflib document and the bytes of every buffer, each exactly
        ``byteLength`` long.

    Raises:
        InputError: Unreadable file, bad GLB container, bad JSON, unknown major version,
            unsupported required extension, unsafe or bad buffer URIs, short buffers.
    """

    options = options or ReadOptions()
    path = Path(path)
    file = str(path)
    try:
        size = os.stat(path).st_size
        if size > MAX_FILE_BYTES:
            raise InputError(f"file of {size} bytes exceeds the limit of {MAX_FILE_BYTES}",
                             file=file, code="gltf.file.limit")
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", file=file, code="gltf.file") from None
    binary = None
    try:
        if data[:4] == GLB_MAGIC:
            json_text, binary = _parse_glb(data, file)
            root = _check_raw_structure(json_text, file, json_start=20)   # after header + chunk header
            # The document is built from the JSON chunk found by the checked chunk walk above.
            # pygltflib's own load_from_bytes walks the chunks again without those checks: it
            # decodes every chunk type as UTF-8 text (an unknown type such as b"\\x80..." escapes
            # as a bare UnicodeDecodeError) and re-parses any later chunk that calls itself JSON.
            gltf = _document(root)
        else:
            gltf = _document(_check_raw_structure(json_text_of(data, file), file))
    except InputError:
        raise
    except Exception as exc:  # a value the raw checks do not type that no pygltflib field can hold
        # The raw checks above have located every misplaced value they know of; what building the
        # objects still trips over has no better place than the file.
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"not valid glTF JSON: {detail}", file=file, code="gltf.json") from None
    # The raw checks made these arrays (or absent); absent ones read as empty.
    for key in ("accessors", "animations", "bufferViews", "buffers", "meshes", "nodes", "scenes",
                "skins", "extensionsRequired", "extensionsUsed"):
        if getattr(gltf, key, None) is None:
            setattr(gltf, key, [])
    _check_version(gltf, file)
    for i, name in enumerate(gltf.extensionsRequired):
        if name == gltf_meshopt.DRACO:
            gltf_meshopt.refuse_draco(file, f"/extensionsRequired/{i}")
        if name == gltf_meshopt.MESHOPT:
            if gltf_meshopt.decoder_missing():
                gltf_meshopt.refuse_meshopt(file, f"/extensionsRequired/{i}")
            continue  # decoded below
        if name not in _ALLOWED_REQUIRED and not str(name).startswith("KHR_materials_"):
            raise UnsupportedError(f"required extension {name!r} is not supported",
                                   file=file, location=f"/extensionsRequired/{i}",
                                   code="gltf.extension.required")
    if gltf_meshopt.DRACO in gltf.extensionsUsed:  # Draco data has no plain buffer view to read instead
        gltf_meshopt.refuse_draco(file, f"/extensionsUsed/{gltf.extensionsUsed.index(gltf_meshopt.DRACO)}")
    buffers = _load_buffers(gltf, binary, path.parent, file, options)
    buffers = gltf_meshopt.decompress_views(gltf, buffers, file, MAX_FILE_BYTES)
    return gltf, buffers
