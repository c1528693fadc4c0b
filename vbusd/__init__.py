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


def _alias_checkout_folders() -> None:
    """Import ``vbusd.converters``, ``vbusd.validators`` and ``vbusd.schema`` from a checkout.

    The wheel maps the repository's folders ``converters/``, ``validators/`` and ``schema/`` into
    the package (pyproject.toml, ``package-dir``). Python run from the repository's root (what
    docs/api.md tells a reader to do) imports this checkout's ``vbusd/`` folder instead of the
    installed package, and there those three folders are siblings of ``vbusd/``, not inside it:
    this finder maps exactly those three names to them, so the checkout imports the same way as
    the installed package (and never half from another installed copy). Installed, the folders
    are inside the package and nothing is added.
    """
    import importlib.abc
    import importlib.util
    import sys
    from pathlib import Path

    package = Path(__file__).resolve().parent
    root = package.parent
    folders = {f"{__name__}.{name}": root / name for name in ("converters", "validators", "schema")
               if not (package / name).exists() and (root / name / "__init__.py").is_file()}
    if not folders or not (root / "pyproject.toml").is_file():
        return

    class _CheckoutFolders(importlib.abc.MetaPathFinder):
        """``vbusd.<folder>`` -> the checkout's ``<folder>/`` (its submodules then load normally)."""

        def find_spec(self, fullname, path=None, target=None):
            folder = folders.get(fullname)
            if folder is None:
                return None
            return importlib.util.spec_from_file_location(fullname, folder / "__init__.py",
                                                          submodule_search_locations=[str(folder)])

    if not any(type(finder).__name__ == "_CheckoutFolders" for finder in sys.meta_path):
        sys.meta_path.insert(0, _CheckoutFolders())


_alias_checkout_folders()

try:
    from importlib.metadata import version as _dist_version

    __version__ = _dist_version("vbusd")
except Exception:  # pragma: no cover - running from a source tree without installing
    __version__ = "1.0.0.dev0"

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
    "BakeOptions": "vbusd.bake",
    "bake": "vbusd.bake",
    "ConvertOptions": "vbusd.convert",
    "convert": "vbusd.convert",
    "read_asset": "vbusd.io.usd",
    "write_asset": "vbusd.io.usd",
    "read_texture": "vbusd.io.textures",
    "write_texture": "vbusd.io.textures",
    "validate": "vbusd.api",
    "skin": "vbusd.api",
    "bone_transform": "vbusd.api",
    "root_motion": "vbusd.api",
    "shader": "vbusd.api",
    "build_crowd": "vbusd.crowd",
    "CrowdOptions": "vbusd.crowd",
    "decode": "vbusd.decode.pointcache",
    "Decoder": "vbusd.decode.warp",
    "prepare": "vbusd._threads",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


# Jobs named after the module that holds them: vbusd.<name> is that module, made callable as the
# job (vbusd/_callable.py), so that it is the same object whichever is imported first and
# ``import vbusd.decode.reference`` keeps working.
_CALLABLE_MODULES = {"bake": "vbusd.bake", "convert": "vbusd.convert", "decode": "vbusd.decode"}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'vbusd' has no attribute {name!r}")
    if name in _CALLABLE_MODULES:
        value = importlib.import_module(_CALLABLE_MODULES[name])
        importlib.import_module(module)  # the job's own module, so that the call needs no import
    else:
        value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from vbusd.api import bone_transform, root_motion, shader, skin, validate
    from vbusd.bake import BakeOptions, bake
    from vbusd.convert import ConvertOptions, convert
    from vbusd.crowd import CrowdOptions, build_crowd
    from vbusd.decode.pointcache import decode
    from vbusd.decode.warp import Decoder
    from vbusd._threads import prepare
    from vbusd.format.errors import InputError, OptionsError, UnsupportedError, VbusdError, VersionError
    from vbusd.format.layout import FORMAT_VERSION, Encoding, Layout, Padding, TexelFormat
    from vbusd.format.model import (AnimationClip, BoundMesh, Clip, Crowd, SkinnedAnimation, SkinnedMesh,
                                    VirtualBones, VirtualBonesAsset)
    from vbusd.io.textures import read_texture, write_texture
    from vbusd.io.usd import read_asset, write_asset

from vbusd.io.usd_plugin import register_on_import as _register_usd_plugin  # noqa: E402

_register_usd_plugin()
