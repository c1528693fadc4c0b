"""glTF compression that vbusd's readers meet in packages from glTF pipelines (spec/runtime-package.md,
"Pipelines"): ``EXT_meshopt_compression`` is decoded here, ``KHR_draco_mesh_compression`` is refused
with the command that decompresses it.

meshopt: each compressed buffer view (``bufferViews[i].extensions.EXT_meshopt_compression``:
``buffer``, ``byteOffset``, ``byteLength``, ``byteStride``, ``count``, ``mode`` ``ATTRIBUTES``,
``TRIANGLES`` or ``INDICES``, ``filter`` ``NONE``, ``OCTAHEDRAL``, ``QUATERNION`` or
``EXPONENTIAL``) is decoded with meshoptimizer's own decoder (the ``meshoptimizer`` Python package,
imported here only) into ``count x byteStride`` bytes, which become a buffer of their own that the
view then names, so every later read (accessors, the texture's view) sees plain glTF. A buffer that
is only the extension's fallback (``buffers[j].extensions.EXT_meshopt_compression.fallback``, no
data) reads as empty. Sizes are checked before anything is allocated.

Draco: vbusd has no Draco decoder; the one line names the glTF-Transform command of
web/gltf-transform (``vbusd-decompress``) that writes the same package uncompressed.
"""

from __future__ import annotations

import ctypes

import numpy as np

from vbusd.format.errors import InputError, UnsupportedError

__all__ = ["MESHOPT", "DRACO", "DECOMPRESS_COMMAND", "decoder_missing", "is_fallback_buffer", "decompress_views",
           "refuse_draco", "refuse_meshopt"]

MESHOPT = "EXT_meshopt_compression"
DRACO = "KHR_draco_mesh_compression"

DECOMPRESS_COMMAND = ("npx --prefix web/gltf-transform gltf-transform vbusd-decompress IN.glb OUT.glb "
                      "--config web/gltf-transform/gltf-transform.config.mjs")
"""What writes a compressed package uncompressed (after ``npm ci`` in web/gltf-transform)."""

_MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
_FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL")


def _library():
    """meshoptimizer's C library (through its Python package), or None when it is not installed."""
    try:
        from meshoptimizer._loader import lib
    except ImportError:
        return None
    return lib


def decoder_missing() -> bool:
    """Whether meshopt-compressed packages cannot be decoded here (no meshoptimizer package)."""
    return _library() is None


def refuse_draco(file: str, location: str) -> None:
    """Raise the one line for a Draco-compressed package.

    Raises:
        UnsupportedError: code ``gltf.extension.required``.
    """
    raise UnsupportedError(f"the package is Draco-compressed ({DRACO}), which vbusd does not decode; write it "
                           f"uncompressed with: {DECOMPRESS_COMMAND}", file=file, location=location,
                           code="gltf.extension.required")


def refuse_meshopt(file: str, location: str) -> None:
    """Raise the one line for a meshopt-compressed package when meshoptimizer is not installed."""
    raise UnsupportedError(f"the package is meshopt-compressed ({MESHOPT}); decoding it needs meshoptimizer "
                           f"(pip install 'vbusd[lod]', built from source with a C++ compiler), or write it "
                           f"uncompressed with: {DECOMPRESS_COMMAND}", file=file, location=location,
                           code="gltf.extension.required")


def _extension(element, name: str):
    extensions = getattr(element, "extensions", None)
    value = extensions.get(name) if isinstance(extensions, dict) else None
    return value if isinstance(value, dict) else None


def is_fallback_buffer(buffer) -> bool:
    """A buffer that only stands in for meshopt data (``fallback: true``): it may hold no bytes."""
    value = _extension(buffer, MESHOPT)
    return bool(value and value.get("fallback") is True)


def _int(value, where: str, file: str, minimum: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise InputError(f"must be an integer {minimum} or more, found {value!r:.40}", file=file, location=where,
                         code="gltf.value")
    return value


def decompress_views(gltf, buffers: list, file: str, limit: int) -> list:
    """Decode every meshopt-compressed buffer view in place (see the module's text).

    Args:
        gltf: The pygltflib document; its compressed views are rewritten to name the decoded bytes.
        buffers: The bytes of every buffer (fallback buffers as ``b""``); decoded views are appended.
        file: The glTF file, for messages.
        limit: The most bytes all decoded views may take together.

    Returns:
        ``buffers`` with the decoded views appended.

    Raises:
        InputError: A malformed extension object, sizes past ``limit``, or data meshoptimizer's
            decoder refuses (codes ``gltf.value``, ``gltf.buffer.limit``, ``gltf.meshopt``).
        UnsupportedError: meshoptimizer is not installed (``gltf.extension.required``).
    """
    compressed = [(i, view, _extension(view, MESHOPT)) for i, view in enumerate(gltf.bufferViews or [])]
    compressed = [(i, view, ext) for i, view, ext in compressed if ext is not None]
    if not compressed:
        return buffers
    lib = _library()
    if lib is None:
        refuse_meshopt(file, f"/bufferViews/{compressed[0][0]}/extensions/{MESHOPT}")
    total = 0
    for i, view, ext in compressed:
        where = f"/bufferViews/{i}/extensions/{MESHOPT}"
        source = _int(ext.get("buffer"), f"{where}/buffer", file)
        if source >= len(buffers):
            raise InputError(f"buffer {source} does not exist (the file has {len(buffers)})", file=file,
                             location=f"{where}/buffer", code="gltf.index")
        offset = _int(ext.get("byteOffset", 0), f"{where}/byteOffset", file)
        length = _int(ext.get("byteLength"), f"{where}/byteLength", file, minimum=1)
        stride = _int(ext.get("byteStride"), f"{where}/byteStride", file, minimum=1)
        count = _int(ext.get("count"), f"{where}/count", file, minimum=1)
        mode = ext.get("mode")
        filter_name = ext.get("filter", "NONE")
        if mode not in _MODES:
            raise InputError(f"mode must be one of {', '.join(_MODES)}, found {mode!r:.40}", file=file,
                             location=f"{where}/mode", code="gltf.value")
        if filter_name not in _FILTERS or (filter_name != "NONE" and mode != "ATTRIBUTES"):
            raise InputError(f"filter {filter_name!r:.40} is not one of {', '.join(_FILTERS)} for mode {mode}",
                             file=file, location=f"{where}/filter", code="gltf.value")
        if mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
            raise InputError(f"byteStride {stride} of ATTRIBUTES must be a multiple of 4 up to 256", file=file,
                             location=f"{where}/byteStride", code="gltf.value")
        if mode != "ATTRIBUTES" and stride not in (2, 4):
            raise InputError(f"byteStride {stride} of {mode} must be 2 or 4", file=file,
                             location=f"{where}/byteStride", code="gltf.value")
        if mode == "TRIANGLES" and count % 3:
            raise InputError(f"count {count} of TRIANGLES is not a multiple of 3", file=file,
                             location=f"{where}/count", code="gltf.value")
        size = count * stride
        total += size
        if total > limit:
            raise InputError(f"the decoded buffer views would take {total} bytes, past the limit of {limit}",
                             file=file, location=where, code="gltf.buffer.limit")
        data = buffers[source]
        if offset + length > len(data):
            raise InputError(f"bytes [{offset}, {offset + length}) lie outside buffer {source} ({len(data)} bytes)",
                             file=file, location=where, code="gltf.bufferView.bounds")
        encoded = np.frombuffer(data, dtype=np.uint8, count=length, offset=offset)
        decoded = np.zeros(size, dtype=np.uint8)
        function = {"ATTRIBUTES": lib.meshopt_decodeVertexBuffer, "TRIANGLES": lib.meshopt_decodeIndexBuffer,
                    "INDICES": lib.meshopt_decodeIndexSequence}[mode]
        status = function(decoded.ctypes.data_as(ctypes.c_void_p), count, stride,
                          encoded.ctypes.data_as(ctypes.POINTER(ctypes.c_ubyte)), length)
        if status != 0:
            raise InputError(f"meshoptimizer cannot decode this {mode} data (error {status})", file=file,
                             location=where, code="gltf.meshopt")
        if filter_name != "NONE":
            name = {"OCTAHEDRAL": "meshopt_decodeFilterOct", "QUATERNION": "meshopt_decodeFilterQuat",
                    "EXPONENTIAL": "meshopt_decodeFilterExp"}[filter_name]
            if (filter_name == "OCTAHEDRAL" and stride not in (4, 8)) or (filter_name == "QUATERNION" and stride != 8):
                raise InputError(f"filter {filter_name} needs byteStride {'4 or 8' if stride != 8 else 8}, found "
                                 f"{stride}", file=file, location=f"{where}/filter", code="gltf.value")
            getattr(lib, name)(decoded.ctypes.data_as(ctypes.c_void_p), ctypes.c_size_t(count),
                               ctypes.c_size_t(stride))
        declared = view.byteLength
        if declared != size:
            raise InputError(f"the bufferView's byteLength {declared!r:.40} is not count x byteStride ({size})",
                             file=file, location=f"/bufferViews/{i}/byteLength", code="gltf.value")
        buffers.append(decoded.tobytes())
        view.buffer, view.byteOffset = len(buffers) - 1, 0
        view.extensions = {k: v for k, v in view.extensions.items() if k != MESHOPT}
    return buffers
