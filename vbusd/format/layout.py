"""The texture layout of a Virtual Bones animation: every size of the format, derived in one place.

A :class:`Layout` is frozen and computed from five choices (encoding, texel format, bone count,
row count, padding). Writers, readers, validators and decoders take sizes from it and nowhere else.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from vbusd.format.errors import OptionsError

__all__ = ["FORMAT_VERSION", "CHANNELS", "MAX_TEXTURE_DIMENSION", "Encoding", "TexelFormat",
           "Padding", "next_power_of_two", "texel_formats_of", "default_texel_format", "pairs", "pairing_error",
           "Layout"]

FORMAT_VERSION = 1
"""The format version this library writes (spec/virtual-bones.md, "Versioning")."""

CHANNELS = 4
"""Every texel is RGBA."""

MAX_TEXTURE_DIMENSION = 16384
"""Largest width or height a conforming writer produces and a reader accepts by default."""


class Encoding(str, enum.Enum):
    """How one bone transform is stored in its run of texels (USD token names)."""

    CROSS_MATRIX = "crossMatrix"
    AFFINE_MATRIX = "affineMatrix"
    QUAT_TRANSLATION = "quatTranslation"
    DUAL_QUAT = "dualQuat"
    COMPACT_QUAT_TRANSLATION = "compactQuatTranslation"
    """Format 1.2 (spec 5.6): one 96-bit uint32 texel per bone and row."""

    def __str__(self) -> str:
        return self.value

    @property
    def texels_per_bone(self) -> int:
        """Texels one bone occupies in a row (T in the spec)."""
        if self is Encoding.COMPACT_QUAT_TRANSLATION:
            return 1
        return 3 if self in (Encoding.CROSS_MATRIX, Encoding.AFFINE_MATRIX) else 2

    @property
    def value_texels(self) -> int:
        """Texel slots of the float64 channel values before quantization: T, except the compact
        encoding, whose quaternion and translation (two slots, as quatTranslation) share one texel."""
        return 2 if self is Encoding.COMPACT_QUAT_TRANSLATION else self.texels_per_bone


class TexelFormat(str, enum.Enum):
    """How each channel value is stored."""

    FLOAT16 = "float16"
    FLOAT32 = "float32"
    UNORM16 = "unorm16"
    UINT32 = "uint32"
    """Format 1.2: three 32-bit unsigned integer channels (R32G32B32_UINT), only with
    compactQuatTranslation. In memory (and on upload where RGB32UI cannot be sampled) the texel is
    widened to RGBA with A = 0; files store three channels."""

    def __str__(self) -> str:
        return self.value

    @property
    def bytes_per_channel(self) -> int:
        """Bytes of one channel of one texel."""
        return 4 if self in (TexelFormat.FLOAT32, TexelFormat.UINT32) else 2

    @property
    def stored_channels(self) -> int:
        """Channels a file stores per texel: 3 for uint32 (R, G, B), else 4."""
        return 3 if self is TexelFormat.UINT32 else CHANNELS

    @property
    def numpy_dtype(self) -> str:
        """The numpy dtype of stored texels (little-endian)."""
        return {"float16": "<f2", "float32": "<f4", "unorm16": "<u2", "uint32": "<u4"}[self.value]


class Padding(str, enum.Enum):
    """Padding of one texture dimension."""

    NONE = "none"
    POWER_OF_TWO = "powerOfTwo"

    def __str__(self) -> str:
        return self.value


def texel_formats_of(encoding) -> tuple:
    """The texel formats ``encoding`` may be stored in (spec 5.6: uint32 is the compact encoding's
    only texel format, and holds no other encoding)."""
    if Encoding(encoding) is Encoding.COMPACT_QUAT_TRANSLATION:
        return (TexelFormat.UINT32,)
    return (TexelFormat.FLOAT16, TexelFormat.FLOAT32, TexelFormat.UNORM16)


def default_texel_format(encoding) -> TexelFormat:
    """The texel format a writer picks when none is asked for: the first of :func:`texel_formats_of`
    (float16; uint32 for compactQuatTranslation)."""
    return texel_formats_of(encoding)[0]


def pairs() -> list:
    """Every valid ``(encoding, texel format)`` pair, in enum order."""
    return [(e, t) for e in Encoding for t in texel_formats_of(e)]


def pairing_error(encoding, texel_format):
    """``None`` when the pair is valid, else the one-line reason (for an OptionsError of the caller's)."""
    if TexelFormat(texel_format) in texel_formats_of(encoding):
        return None
    return (f"encoding compactQuatTranslation and texel format uint32 go together (spec 5.6), "
            f"got {Encoding(encoding).value} with {TexelFormat(texel_format).value}")


def next_power_of_two(n: int) -> int:
    """Smallest power of two >= n (1 for n <= 1): the talk's "closest power of two", rounded up."""
    return 1 if n <= 1 else 1 << (int(n) - 1).bit_length()


def _coerce(enum_type, value, what: str):
    if isinstance(value, enum_type):
        return value
    try:
        return enum_type(value)
    except ValueError:
        allowed = ", ".join(e.value for e in enum_type)
        raise OptionsError(f"{what} must be one of {allowed}, got {value!r}", file="layout") from None


@dataclass(frozen=True)
class Layout:
    """Sizes of a Virtual Bones texture.

    Attributes:
        encoding: Bone transform encoding.
        texel_format: Channel storage.
        bone_count: Number of bones (B).
        row_count: Rows holding keyframes, all clips together (R).
        horizontal_padding: ``powerOfTwo`` rounds the width up to a power of two.
        vertical_padding: ``powerOfTwo`` rounds the height up to a power of two.
    """

    encoding: Encoding
    texel_format: TexelFormat
    bone_count: int
    row_count: int
    horizontal_padding: Padding = Padding.POWER_OF_TWO
    vertical_padding: Padding = Padding.NONE

    def __post_init__(self) -> None:
        object.__setattr__(self, "encoding", _coerce(Encoding, self.encoding, "encoding"))
        object.__setattr__(self, "texel_format", _coerce(TexelFormat, self.texel_format, "texelFormat"))
        object.__setattr__(self, "horizontal_padding",
                           _coerce(Padding, self.horizontal_padding, "horizontalPadding"))
        object.__setattr__(self, "vertical_padding",
                           _coerce(Padding, self.vertical_padding, "verticalPadding"))
        for name in ("bone_count", "row_count"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise OptionsError(f"{name} must be a positive integer, got {value!r}", file="layout")
            object.__setattr__(self, name, int(value))
        mismatch = pairing_error(self.encoding, self.texel_format)
        if mismatch:
            raise OptionsError(mismatch, file="layout")
        if self.width > MAX_TEXTURE_DIMENSION or self.height > MAX_TEXTURE_DIMENSION:
            raise OptionsError(
                f"texture of {self.width}x{self.height} exceeds the limit of {MAX_TEXTURE_DIMENSION} "
                f"texels per side ({self.bone_count} bones, {self.row_count} rows)", file="layout")

    @property
    def texels_per_bone(self) -> int:
        """T: texels per bone (3 for the matrix encodings, 2 for the quaternion ones)."""
        return self.encoding.texels_per_bone

    @property
    def used_width(self) -> int:
        """Columns holding bone data: B x T."""
        return self.bone_count * self.texels_per_bone

    @property
    def width(self) -> int:
        """Texture width in texels, after horizontal padding."""
        if self.horizontal_padding is Padding.POWER_OF_TWO:
            return next_power_of_two(self.used_width)
        return self.used_width

    @property
    def height(self) -> int:
        """Texture height in texels, after vertical padding."""
        if self.vertical_padding is Padding.POWER_OF_TWO:
            return next_power_of_two(self.row_count)
        return self.row_count

    @property
    def shape(self) -> tuple[int, int, int]:
        """numpy shape of the texel array: (height, width, 4)."""
        return (self.height, self.width, CHANNELS)

    @property
    def texel_bytes(self) -> int:
        """Bytes of all texels, padding included."""
        return self.width * self.height * self.texel_format.stored_channels * self.texel_format.bytes_per_channel

    @property
    def used_texel_bytes(self) -> int:
        """Bytes of the texels that hold bone data."""
        return (self.used_width * self.row_count * self.texel_format.stored_channels
                * self.texel_format.bytes_per_channel)

    @property
    def padding_fraction(self) -> float:
        """Fraction of the texture that is padding (0 when nothing is padded)."""
        return 1.0 - (self.used_width * self.row_count) / (self.width * self.height)

    def column(self, bone: int, texel: int) -> int:
        """Column of texel ``texel`` (0..T-1) of bone ``bone``: bone x T + texel."""
        return bone * self.texels_per_bone + texel
