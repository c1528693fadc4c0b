"""Bound-checked decoding of glTF 2.0 buffers, buffer views and accessors into numpy arrays.

pygltflib parses the JSON into objects but checks nothing, so every number that decides a size
or an offset is checked here *before* any array is allocated (spec/gltf-conversion.md, "Reading"):

* buffer views lie inside their buffer, strides are 4..252 and multiples of 4;
* an accessor's ``byteOffset + stride * (count - 1) + elementSize`` lies inside its buffer view,
  its byteOffset is a multiple of its component size, and ``count`` is below :data:`MAX_ELEMENTS`;
* sparse indices and values lie inside their views, indices are strictly increasing and below the
  accessor's count.

Values come back as float64 (or int64 for integer data that is not normalized), with glTF's
normalized-integer rule applied (``max(c / (2^(n-1) - 1), -1)`` signed, ``c / (2^n - 1)``
unsigned) and matrices turned into column-vector ``(count, 4, 4)`` arrays.

Every problem raises :class:`vbusd.format.errors.InputError` with a JSON pointer.
"""

from __future__ import annotations

import numpy as np

from vbusd.format.errors import InputError

__all__ = ["MAX_ELEMENTS", "MAX_VALUES", "MAX_TOTAL_VALUES", "COMPONENT_TYPES", "COMPONENT_NAMES",
           "TYPE_SHAPES", "is_int", "require_int", "require_index", "element_layout",
           "AccessorReader", "MODE_NAMES", "triangles"]

MAX_ELEMENTS = 1 << 24
"""Largest accessor count accepted (16 Mi elements): refuses absurd sizes before allocating."""

MAX_VALUES = 1 << 27
"""Largest number of components one accessor may decode to (1 GiB of float64)."""

MAX_TOTAL_VALUES = 1 << 29
"""Largest number of components all accessors of one file may decode to together (4 GiB of float64)."""

COMPONENT_TYPES = {
    5120: np.dtype("<i1"),
    5121: np.dtype("<u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
"""glTF componentType -> little-endian numpy dtype."""

COMPONENT_NAMES = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                   5125: "UNSIGNED_INT", 5126: "FLOAT"}

TYPE_SHAPES = {"SCALAR": (1,), "VEC2": (2,), "VEC3": (3,), "VEC4": (4,),
               "MAT2": (2, 2), "MAT3": (3, 3), "MAT4": (4, 4)}
"""glTF accessor type -> element shape (matrices: columns x rows, glTF stores columns)."""


def is_int(value) -> bool:
    """True for a JSON integer (bool excluded)."""
    return isinstance(value, int) and not isinstance(value, bool)


def require_int(value, pointer: str, file: str, *, minimum: int = 0, maximum: int | None = None,
                code: str = "gltf.value") -> int:
    """Check that a JSON value is an integer within bounds and return it.

    Args:
        value: The value read by pygltflib (anything the JSON held).
        pointer: JSON pointer of the value, for the message.
        file: The glTF file, for the message.
        minimum: Smallest allowed value.
        maximum: Largest allowed value, or None.
        code: Error code when out of bounds.

    Raises:
        InputError: When the value is not an integer or out of bounds.
    """
    if not is_int(value):
        raise InputError(f"expected an integer, found {value!r}", file=file, location=pointer,
                         code="gltf.value")
    if value < minimum or (maximum is not None and value > maximum):
        bound = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
        raise InputError(f"value {value} is not {bound}", file=file, location=pointer, code=code)
    return value


def require_index(value, count: int, pointer: str, file: str, what: str) -> int:
    """Check an index into a top-level array (e.g. a node index) and return it.

    Raises:
        InputError: ``gltf.index`` when it is not an integer in ``[0, count)``.
    """
    if not is_int(value) or not 0 <= value < count:
        raise InputError(f"{what} index {value!r} is out of range (there are {count})", file=file,
                         location=pointer, code="gltf.index")
    return value


def element_layout(component_type: int, type_name: str) -> tuple[int, int, int, tuple]:
    """Byte layout of one accessor element.

    Matrix columns of 1- and 2-byte components start on 4-byte boundaries (glTF 2.0, "Data
    Alignment"), so a MAT3 of bytes is 3 columns of 3 bytes each padded to 4.

    Returns:
        (element_size, column_size_padded, column_size, shape) in bytes; for non-matrix types the
        whole element is one "column".
    """
    comp = COMPONENT_TYPES[component_type].itemsize
    shape = TYPE_SHAPES[type_name]
    if len(shape) == 1:
        size = shape[0] * comp
        return size, size, size, shape
    columns, rows = shape
    column = rows * comp
    padded = (column + 3) // 4 * 4
    return columns * padded, padded, column, shape


class AccessorReader:
    """Decodes accessors of one glTF document with every bound checked before allocation.

    Args:
        gltf: The pygltflib document.
        buffers: The bytes of every buffer (index -> bytes, exactly byteLength long).
        file: The glTF file, for messages.
    """

    def __init__(self, gltf, buffers: list, file: str) -> None:
        self.gltf = gltf
        self.buffers = buffers
        self.file = file
        self._views: dict[int, memoryview] = {}
        self._cache: dict[tuple, np.ndarray] = {}
        self._decoded_values = 0

    # -- buffer views ---------------------------------------------------------------------------

    def view(self, index: int, pointer: str) -> tuple[memoryview, int | None]:
        """Return the bytes of buffer view ``index`` and its byteStride (None when absent).

        Raises:
            InputError: ``gltf.index`` for a bad index, ``gltf.bufferView.bounds`` when the view
                leaves its buffer, ``gltf.bufferView.stride`` for a bad stride.
        """
        views = self.gltf.bufferViews or []
        require_index(index, len(views), pointer, self.file, "bufferView")
        bv = views[index]
        where = f"/bufferViews/{index}"
        buffer = require_index(bv.buffer, len(self.buffers), f"{where}/buffer", self.file, "buffer")
        offset = require_int(bv.byteOffset if bv.byteOffset is not None else 0,
                             f"{where}/byteOffset", self.file)
        length = require_int(bv.byteLength, f"{where}/byteLength", self.file, minimum=1)
        data = self.buffers[buffer]
        if offset + length > len(data):
            raise InputError(
                f"buffer view bytes [{offset}, {offset + length}) lie outside buffer {buffer} "
                f"({len(data)} bytes)", file=self.file, location=where, code="gltf.bufferView.bounds")
        stride = bv.byteStride
        if stride is not None:
            require_int(stride, f"{where}/byteStride", self.file, minimum=4, maximum=252,
                        code="gltf.bufferView.stride")
            if stride % 4:
                raise InputError(f"byteStride {stride} is not a multiple of 4", file=self.file,
                                 location=f"{where}/byteStride", code="gltf.bufferView.stride")
        if index not in self._views:
            self._views[index] = memoryview(data)[offset:offset + length]
        return self._views[index], stride

    def _strided(self, view_index: int, byte_offset: int, count: int, component_type: int,
                 type_name: str, pointer: str, allow_stride: bool = True) -> np.ndarray:
        """Read ``count`` raw elements from a buffer view, checking bounds first."""
        data, stride = self.view(view_index, f"{pointer}/bufferView")
        element, padded, column, shape = element_layout(component_type, type_name)
        dtype = COMPONENT_TYPES[component_type]
        if byte_offset % dtype.itemsize:
            raise InputError(f"byteOffset {byte_offset} is not a multiple of the component size "
                             f"{dtype.itemsize}", file=self.file, location=f"{pointer}/byteOffset",
                             code="gltf.accessor.alignment")
        if stride is None or not allow_stride:
            stride = element
        elif stride < element:
            raise InputError(f"byteStride {stride} of buffer view {view_index} is smaller than the "
                             f"element size {element}", file=self.file, location=pointer,
                             code="gltf.accessor.bounds")
        end = byte_offset + stride * (count - 1) + element
        if end > len(data):
            raise InputError(
                f"{count} elements of {element} bytes (stride {stride}) from byte {byte_offset} need "
                f"{end} bytes; buffer view {view_index} has {len(data)}", file=self.file,
                location=pointer, code="gltf.accessor.bounds")
        raw = np.ndarray((count, element), dtype=np.uint8, buffer=data, offset=byte_offset,
                         strides=(stride, 1)).copy()
        if len(shape) == 2 and padded != column:
            columns = shape[0]
            raw = raw.reshape(count, columns, padded)[:, :, :column].reshape(count, columns * column)
        values = raw.view(dtype).reshape((count,) + shape)
        return values

    # -- accessors ------------------------------------------------------------------------------

    def header(self, index: int, pointer: str) -> tuple:
        """Check an accessor's declaration; return (accessor, componentType, type, count).

        Raises:
            InputError: For a bad index, componentType, type, count or normalized flag.
        """
        accessors = self.gltf.accessors or []
        require_index(index, len(accessors), pointer, self.file, "accessor")
        acc = accessors[index]
        where = f"/accessors/{index}"
        if acc.componentType not in COMPONENT_TYPES:
            raise InputError(f"unknown componentType {acc.componentType!r}", file=self.file,
                             location=f"{where}/componentType", code="gltf.accessor.format")
        if acc.type not in TYPE_SHAPES:
            raise InputError(f"unknown accessor type {acc.type!r}", file=self.file,
                             location=f"{where}/type", code="gltf.accessor.format")
        count = require_int(acc.count, f"{where}/count", self.file, minimum=1)
        if count > MAX_ELEMENTS:
            raise InputError(f"count {count} exceeds the limit of {MAX_ELEMENTS} elements",
                             file=self.file, location=f"{where}/count", code="gltf.accessor.limit")
        values = count * int(np.prod(TYPE_SHAPES[acc.type]))
        if values > MAX_VALUES:
            raise InputError(f"{count} {acc.type} elements ({values} values) exceed the limit of "
                             f"{MAX_VALUES} values per accessor", file=self.file,
                             location=f"{where}/count", code="gltf.accessor.limit")
        if acc.normalized not in (None, False, True):
            raise InputError(f"normalized must be a boolean, found {acc.normalized!r}",
                             file=self.file, location=f"{where}/normalized", code="gltf.value")
        if acc.normalized and acc.componentType in (5125, 5126):
            raise InputError(f"normalized is not allowed with {COMPONENT_NAMES[acc.componentType]}",
                             file=self.file, location=f"{where}/normalized",
                             code="gltf.accessor.format")
        return acc, acc.componentType, acc.type, count

    def read(self, index: int, pointer: str) -> np.ndarray:
        """Decode accessor ``index`` (sparse substitution and normalization applied).

        Args:
            index: Accessor index.
            pointer: JSON pointer of the property that references it (for a bad index).

        Returns:
            float64 array of shape ``(count,)`` for SCALAR, ``(count, n)`` for VECn and
            ``(count, 4, 4)`` etc. for matrices in column-vector form (``M @ p``). Integer data that
            is not normalized comes back as int64.

        Raises:
            InputError: Any bound, format or value problem, with the accessor's JSON pointer.
        """
        key = ("acc", index)
        if key in self._cache:
            return self._cache[key]
        acc, ctype, tname, count = self.header(index, pointer)
        where = f"/accessors/{index}"
        shape = TYPE_SHAPES[tname]
        self._decoded_values += count * int(np.prod(shape))
        if self._decoded_values > MAX_TOTAL_VALUES:
            raise InputError(f"decoding this accessor takes the file past the limit of "
                             f"{MAX_TOTAL_VALUES} decoded values", file=self.file, location=where,
                             code="gltf.accessor.limit")
        offset = acc.byteOffset if acc.byteOffset is not None else 0
        require_int(offset, f"{where}/byteOffset", self.file)
        if acc.bufferView is not None:
            values = self._strided(acc.bufferView, offset, count, ctype, tname, where)
        else:
            values = np.zeros((count,) + shape, dtype=COMPONENT_TYPES[ctype])
        if acc.sparse is not None:
            values = self._apply_sparse(acc, index, values, ctype, tname, count)
        result = self._convert(values, ctype, bool(acc.normalized), where)
        if len(shape) == 2:
            # glTF stores matrices column by column: element [c][r]; ours is [r][c].
            result = np.swapaxes(result, -1, -2)
        if len(shape) == 1 and shape[0] == 1:
            result = result.reshape(count)
        result = np.ascontiguousarray(result)
        result.setflags(write=False)
        self._cache[key] = result
        return result

    def _apply_sparse(self, acc, index: int, values: np.ndarray, ctype: int, tname: str,
                      count: int) -> np.ndarray:
        sparse = acc.sparse
        where = f"/accessors/{index}/sparse"
        n = require_int(sparse.count, f"{where}/count", self.file, minimum=1, maximum=count,
                        code="gltf.accessor.sparse")
        if sparse.indices is None or sparse.values is None:
            raise InputError("sparse accessor needs both indices and values", file=self.file,
                             location=where, code="gltf.accessor.sparse")
        ind = sparse.indices
        if ind.componentType not in (5121, 5123, 5125):
            raise InputError(f"sparse indices componentType {ind.componentType!r} is not "
                             "UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT", file=self.file,
                             location=f"{where}/indices/componentType", code="gltf.accessor.sparse")
        ioff = require_int(ind.byteOffset if ind.byteOffset is not None else 0,
                           f"{where}/indices/byteOffset", self.file)
        voff = require_int(sparse.values.byteOffset if sparse.values.byteOffset is not None else 0,
                           f"{where}/values/byteOffset", self.file)
        # Sparse index and value views are tightly packed: byteStride does not apply.
        indices = self._strided(ind.bufferView, ioff, n, ind.componentType, "SCALAR",
                                f"{where}/indices", allow_stride=False).reshape(n).astype(np.int64)
        if n > 1 and np.any(np.diff(indices) <= 0):
            bad = int(np.nonzero(np.diff(indices) <= 0)[0][0]) + 1
            raise InputError(f"sparse index {bad} ({indices[bad]}) is not greater than the one "
                             f"before ({indices[bad - 1]})", file=self.file,
                             location=f"{where}/indices", code="gltf.accessor.sparse")
        if indices[-1] >= count:
            raise InputError(f"sparse index {int(indices[-1])} is not below the accessor count "
                             f"{count}", file=self.file, location=f"{where}/indices",
                             code="gltf.accessor.sparse")
        replacement = self._strided(sparse.values.bufferView, voff, n, ctype, tname,
                                    f"{where}/values", allow_stride=False)
        values = np.array(values, copy=True)
        values[indices] = replacement
        return values

    def _convert(self, values: np.ndarray, ctype: int, normalized: bool, where: str) -> np.ndarray:
        if ctype == 5126:
            # A signalling NaN (a corrupt buffer's bytes) raises the invalid flag as it widens: numpy
            # warns on stderr, a raw line; NaN is refused below with its element.
            with np.errstate(invalid="ignore"):
                out = values.astype(np.float64)
            if not np.all(np.isfinite(out)):
                bad = int(np.nonzero(~np.isfinite(out.reshape(len(out), -1)).all(axis=1))[0][0])
                raise InputError(f"element {bad} holds a NaN or infinite value", file=self.file,
                                 location=where, code="gltf.accessor.nonFinite")
            return out
        if not normalized:
            return values.astype(np.int64)
        dtype = COMPONENT_TYPES[ctype]
        bits = dtype.itemsize * 8
        if dtype.kind == "u":
            return values.astype(np.float64) / float(2 ** bits - 1)
        return np.maximum(values.astype(np.float64) / float(2 ** (bits - 1) - 1), -1.0)


# -- primitive topology -------------------------------------------------------------------------

MODE_NAMES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
              5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}


def triangles(mode: int, indices: np.ndarray) -> np.ndarray:
    """Turn a triangle list, strip or fan into an ``(F, 3)`` triangle list (glTF 2.0, 3.7.2.1).

    Strip triangle i is ``(v_i, v_{i+1+i%2}, v_{i+2-i%2})``; fan triangle i is
    ``(v_{i+1}, v_{i+2}, v_0)``. Degenerate strip and fan triangles (two equal vertex indices,
    used to stitch strips) are dropped; a triangle list is kept as it is.

    Args:
        mode: 4, 5 or 6.
        indices: (n,) vertex indices in drawing order.

    Returns:
        (F, 3) int64 vertex indices.
    """
    n = len(indices)
    if mode == 4:
        return indices.reshape(-1, 3)
    if n < 3:
        return np.zeros((0, 3), dtype=np.int64)
    i = np.arange(n - 2)
    if mode == 5:
        odd = i % 2
        tris = np.stack([indices[i], indices[i + 1 + odd], indices[i + 2 - odd]], axis=1)
    else:
        tris = np.stack([indices[i + 1], indices[i + 2], np.full(n - 2, indices[0])], axis=1)
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    return tris[keep]
