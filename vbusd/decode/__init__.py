"""Decoders: the numpy reference, the warp kernels (CPU and CUDA), the reference shaders and the
USD point cache built from them."""

from vbusd._callable import make_callable as _make_callable

__all__ = ["bounds", "pointcache", "reference", "shaders", "warp", "warp_kernels"]

# vbusd.decode(asset, output) is the point cache job whatever the import order (vbusd/_callable.py).
_make_callable(__name__, "vbusd.decode.pointcache.decode")
