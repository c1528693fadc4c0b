"""Texture containers: which file types hold which texel formats, the default, and file names.

Each rule is stated here once (spec/virtual-bones.md, "Texture files", and spec/ktx2.md); the
converter's options, the command line's help, the texture writer and the readers ask for it.
"""

from __future__ import annotations

from vbusd.format.layout import TexelFormat

__all__ = ["CONTAINERS", "CONTAINER_OF_SUFFIX", "containers_of", "default_container", "container_error",
           "texture_file_name"]

CONTAINERS = ("exr", "png", "ktx2")
"""Every container a Virtual Bones texture may be written in."""

CONTAINER_OF_SUFFIX = {".exr": "exr", ".png": "png", ".ktx2": "ktx2"}
"""The container a file name's suffix (lower case) names."""

_HOLDS = {TexelFormat.FLOAT16: ("exr", "ktx2"), TexelFormat.FLOAT32: ("exr", "ktx2"),
          TexelFormat.UNORM16: ("png", "ktx2"), TexelFormat.UINT32: ("exr", "ktx2")}


def containers_of(texel_format) -> tuple:
    """The containers that hold ``texel_format``, the default first (KTX 2.0 holds every format)."""
    return _HOLDS[TexelFormat(texel_format)]


def default_container(texel_format) -> str:
    """The container a writer picks when none is asked for: ``png`` for unorm16, else ``exr``."""
    return containers_of(texel_format)[0]


def container_error(container: str, texel_format):
    """``None`` when ``container`` holds ``texel_format``, else the one-line reason (the caller adds
    its own file and, for the command line, its option names)."""
    texel_format = TexelFormat(texel_format)
    if container not in CONTAINERS:
        return f"container must be one of {', '.join(CONTAINERS)}, got {container!r}"
    if container in containers_of(texel_format):
        return None
    if texel_format is TexelFormat.UINT32:
        return ("texel format uint32 (compactQuatTranslation) cannot be stored in PNG, which has no "
                "32-bit channels: use exr or ktx2")
    if container == "png":
        return f"the png container holds 16-bit integers only: use texel format unorm16 (got {texel_format.value})"
    return f"unorm16 textures are 16-bit PNG files: use png or ktx2 (got {container})"


def texture_file_name(stem: str, prim_name: str, container: str) -> str:
    """The texture file beside a layer ``<stem>.usda``: ``<stem>.<prim name>.<container>``."""
    return f"{stem}.{prim_name}.{container}"
