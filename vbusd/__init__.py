"""vbusd: the Virtual Bones animation texture format, its USD schema and toolkit.

The public API lives here and loads lazily: ``import vbusd`` costs numpy only, and each name below
imports its module (pxr, OpenEXR, warp...) on first use. Importing vbusd also makes the USD schema
plugin known to OpenUSD (see :mod:`vbusd.io.usd_plugin`).

Main jobs::

    vbusd.convert(source, output, options)     # UsdSkel / glTF -> Virtual Bones asset
    vbusd.read_asset(path) / vbusd.write_asset(asset, path)
    vbusd.validate(path)                        # a report with .valid and .findings
    vbusd.skin(asset, clip, time)               # numpy skinned points and normals per bound mesh
    vbusd.bone_transform(asset, bone, clip, time)  # a joint's 4x4 transform (sockets, format 1.1)
    vbusd.root_motion(asset, clip, t0, t1)      # root displacement of a clip baked in place (1.1)
    vbusd.decode(asset, output)                 # a time-sampled USD point cache
    vbusd.Decoder(vb, mesh, device="cuda")      # warp decoder
    vbusd.shader("glsl", encoding, texel_format)

docs/api.md shows each with a runnable example.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING


from vbusd.io.generator import VERSION as __version__

# name -> module that defines it; imported on first attribute access (PEP 562).
_EXPORTS = {
    # format
    "FORMAT_VERSION": "vbusd.format.layout",
    "Encoding": "vbusd.format.layout",
    "Layout": "vbusd.format.layout",
    "Padding": "vbusd.format.layout",
    "TexelFormat": "vbusd.format.layout",
    "AnimationClip": "vbusd.format.model",
    "SkinnedMesh": "vbusd.format.model",
    "SkinnedAnimation": "vbusd.format.model",
    "Clip": "vbusd.format.model",
    "BoundMesh": "vbusd.format.model",
    "Crowd": "vbusd.format.model",
    "VirtualBones": "vbusd.format.model",
    "VirtualBonesAsset": "vbusd.format.model",
    "VbusdError": "vbusd.format.errors",
    "InputError": "vbusd.format.errors",
    "OptionsError": "vbusd.format.errors",
    "UnsupportedError": "vbusd.format.errors",
    "VersionError": "vbusd.format.errors",
    # jobs
    "BakeOptions": "vbusd.baking.baker",
    "bake": "vbusd.baking.baker",
    "ConvertOptions": "vbusd.jobs.conversion",
    "convert": "vbusd.jobs.conversion",
    "read_asset": "vbusd.io.usd",
    "write_asset": "vbusd.io.usd",
    "read_texture": "vbusd.io.textures",
    "write_texture": "vbusd.io.textures",
    "validate": "vbusd.api",
    "skin": "vbusd.api",
    "bone_transform": "vbusd.api",
    "root_motion": "vbusd.api",
    "events": "vbusd.api",
    "shader": "vbusd.api",
    "build_crowd": "vbusd.jobs.crowd",
    "CrowdOptions": "vbusd.jobs.crowd",
    "CrowdLayer": "vbusd.jobs.crowd",
    "decode": "vbusd.jobs.pointcache",
    "Decoder": "vbusd.decoders.warp",
    "prepare": "vbusd.jobs.warmup",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'vbusd' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from vbusd.api import bone_transform, root_motion, shader, skin, validate
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.jobs.conversion import ConvertOptions, convert
    from vbusd.jobs.crowd import CrowdLayer, CrowdOptions, build_crowd
    from vbusd.jobs.pointcache import decode
    from vbusd.decoders.warp import Decoder
    from vbusd.jobs.warmup import prepare
    from vbusd.format.errors import InputError, OptionsError, UnsupportedError, VbusdError, VersionError
    from vbusd.format.layout import FORMAT_VERSION, Encoding, Layout, Padding, TexelFormat
    from vbusd.format.model import (AnimationClip, BoundMesh, Clip, Crowd, SkinnedAnimation, SkinnedMesh,
                                    VirtualBones, VirtualBonesAsset)
    from vbusd.io.textures import read_texture, write_texture
    from vbusd.io.usd import read_asset, write_asset

from vbusd.io.usd_plugin import register_on_import as _register_usd_plugin  # noqa: E402

_register_usd_plugin()
