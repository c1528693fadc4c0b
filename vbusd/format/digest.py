"""The content digest of a texture's texels (the ``contentDigest`` key of the layout metadata)."""

from __future__ import annotations

import hashlib

import numpy as np

from vbusd.format.layout import CHANNELS

__all__ = ["DIGEST_PREFIX", "content_digest"]

DIGEST_PREFIX = "sha256:"
"""What every ``contentDigest`` starts with."""


def content_digest(texels: np.ndarray) -> str:
    """SHA-256 of a texel array, as stored in the ``contentDigest`` key.

    The bytes hashed are the whole ``(height, width, 4)`` array, padding included, in C order
    (row 0 = first scanline), each channel little-endian in the array's own dtype (``<f2``,
    ``<f4`` or ``<u2``), so the digest is the same on every machine. uint32 texels (format 1.2)
    are hashed as the files store them: channels R, G, B only (12 bytes a texel, spec 9.4).

    Args:
        texels: ``(height, width, 4)`` array.

    Returns:
        ``"sha256:"`` followed by 64 lowercase hex digits.

    Raises:
        ValueError: ``texels`` is not a ``(height, width, 4)`` array.
    """
    texels = np.asarray(texels)
    if texels.ndim != 3 or texels.shape[2] != CHANNELS:
        raise ValueError(f"texels must have shape (height, width, {CHANNELS}), got {texels.shape}")
    # Hashed through a memoryview: tobytes() would copy the whole texture (128 MiB at 4096 x 4096
    # float16) next to the texels; only a big-endian or strided array is copied, once.
    if texels.dtype.kind == "u" and texels.dtype.itemsize == 4:
        texels = texels[..., :3]  # uint32: the three stored words, not the in-memory A = 0
    little = np.ascontiguousarray(texels.astype(texels.dtype.newbyteorder("<"), copy=False))
    return DIGEST_PREFIX + hashlib.sha256(memoryview(little).cast("B")).hexdigest()
