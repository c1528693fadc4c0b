"""Crowd variety (format 1.3, spec/virtual-bones.md section 22): the rules, as data and numpy.

A tint per instance multiplies its base colour; a material variant per instance picks one of the
instancer's named materials; a parts mask per instance shows a subset of the prototype's optional
parts. This module holds what every reader and writer shares: the checks of the per-instance values
(:func:`problems`), ``#rrggbb`` to linear RGB (:func:`hex_to_linear`), the base colours ``vbusd
crowd`` gives the variant materials it authors (:data:`VARIANT_COLORS`) and the colour a variant
material without a UsdPreviewSurface ``diffuseColor`` has (:data:`DEFAULT_BASE_COLOR`), and the rest
pose of a prop attached at a socket (:func:`socket_prop`).
"""

from __future__ import annotations

import re
from typing import Optional

import numpy as np

__all__ = ["VARIETY_MINOR_VERSION", "VARIANT_COLORS", "DEFAULT_BASE_COLOR", "MAX_PARTS", "hex_to_linear",
           "srgb_to_linear", "problems", "part_visible", "socket_prop",
           "level_part_names"]

VARIETY_MINOR_VERSION = 3
"""The minor format version that defines crowd variety (spec 22.4)."""

MAX_PARTS = 31
"""Optional parts an instancer may name: a mask is a non-negative 32-bit integer."""

VARIANT_COLORS = ((0.8, 0.8, 0.8), (0.2, 0.3, 0.8), (0.8, 0.25, 0.2), (0.25, 0.7, 0.3),
                  (0.85, 0.75, 0.2), (0.6, 0.3, 0.75), (0.2, 0.7, 0.75), (0.45, 0.3, 0.2))
"""Linear base colours of the variant materials ``vbusd crowd`` authors: variant k gets entry k mod 8 (spec 22.2)."""

DEFAULT_BASE_COLOR = (0.18, 0.18, 0.18)
"""A variant material's base colour when it has no UsdPreviewSurface diffuseColor (that input's default)."""

_HEX = re.compile(r"#?([0-9a-fA-F]{6})")


def srgb_to_linear(value: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1), element by element, for values in [0, 1]."""
    c = np.asarray(value, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def hex_to_linear(text: str) -> Optional[tuple]:
    """``#rrggbb`` (sRGB) as a linear-RGB triple of floats, or None when ``text`` is not of that form."""
    match = _HEX.fullmatch(text.strip()) if isinstance(text, str) else None
    if match is None or not text.strip().startswith("#"):
        return None
    digits = match.group(1)
    srgb = np.array([int(digits[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])
    return tuple(float(v) for v in srgb_to_linear(srgb))


def part_visible(parts: np.ndarray, part: int) -> np.ndarray:
    """Whether each instance of a parts mask shows part ``part`` (bit ``part`` set)."""
    return (np.asarray(parts, dtype=np.int64) >> int(part)) & 1 == 1


def problems(n: int, *, tint=None, variant=None, parts=None, variant_count: int = 0,
             part_count: int = 0) -> list:
    """What is wrong with the per-instance variety values of ``n`` instances (spec 22.1-22.3).

    Returns:
        ``(code, which, message)`` per problem: ``which`` is ``"tint"``, ``"variant"`` or ``"parts"``
        (the primvar it is about); empty when the values are good. Never raises.
    """
    out = []
    if tint is not None:
        array = np.asarray(tint, dtype=np.float64)
        if array.size != 3 * n:
            out.append(("variety.tint", "tint", f"{array.size // 3 if array.size % 3 == 0 else array.size / 3:g} "
                        f"tints for {n} instances"))
        else:
            array = array.reshape(n, 3)
            bad = ~np.all(np.isfinite(array) & (array >= 0), axis=1)
            if bad.any():
                first = int(np.argmax(bad))
                out.append(("variety.tint", "tint", f"{int(bad.sum())} tint(s) are not three finite numbers 0 or "
                            f"more; the first is instance {first} with {tuple(float(v) for v in array[first])}"))
    if variant is not None:
        array = np.asarray(variant, dtype=np.int64).reshape(-1)
        if array.size != n:
            out.append(("variety.variant", "variant", f"{array.size} variants for {n} instances"))
        elif variant_count == 0:
            out.append(("variety.variant", "variant", "instances have material variants but the instancer "
                        "names none (vb:variantNames)"))
        else:
            bad = (array < 0) | (array >= variant_count)
            if bad.any():
                first = int(np.argmax(bad))
                out.append(("variety.variant", "variant", f"{int(bad.sum())} variant index(es) outside "
                            f"0..{variant_count - 1}; the first is {int(array[first])} at instance {first}"))
    if parts is not None:
        array = np.asarray(parts, dtype=np.int64).reshape(-1)
        if array.size != n:
            out.append(("variety.parts", "parts", f"{array.size} parts masks for {n} instances"))
        else:
            bad = (array < 0) | (array >> min(part_count, 62) != 0)
            if bad.any():
                first = int(np.argmax(bad))
                named = f"parts 0..{part_count - 1}" if part_count else "no parts (vb:partNames is empty)"
                out.append(("variety.parts", "parts", f"{int(bad.sum())} parts mask(s) name no part; the first is "
                            f"{int(array[first])} at instance {first}, and the instancer has {named}"))
    return out


def socket_prop(bind_transform, points, normals=None) -> tuple:
    """The rest points and normals of a prop part attached at the socket of a bone (spec 22.3, "Props
    at sockets"): ``points`` (and ``normals``) are modelled in the joint's own space, ``bind_transform``
    is the joint's bind transform ``B_b`` (column vectors, 4x4, spec 8.4). The prop is bound rigidly to
    the bone (one influence, weight 1), so its skinned points are ``M_b B_b p = J_b p``: the socket.

    Returns:
        ``(rest_points, rest_normals)``: ``B_b p`` as (V, 3) float64, and the normals turned by the
        inverse transpose of ``B_b``'s linear part and made unit length (None without normals).
    """
    bind = np.asarray(bind_transform, dtype=np.float64).reshape(4, 4)
    local = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rest = local @ bind[:3, :3].T + bind[:3, 3]
    if normals is None:
        return rest, None
    turned = np.asarray(normals, dtype=np.float64).reshape(-1, 3) @ np.linalg.inv(bind[:3, :3])
    return rest, turned / np.linalg.norm(turned, axis=1, keepdims=True)


def level_part_names(mesh_paths, root: str) -> tuple:
    """The names a parts mask may give a part of an animation with levels of detail (spec 22.3, "Parts
    and levels of detail"): the names of the children of its level prims (``<root>/<level>/<name>``),
    which hold that level's meshes of the part, in the order of first appearance. ``mesh_paths`` are the
    animation's bound meshes, ``root`` its UsdLod root's path."""
    out = []
    prefix = root.rstrip("/") + "/"
    for path in mesh_paths:
        rest = str(path)[len(prefix):].split("/") if str(path).startswith(prefix) else []
        if len(rest) >= 2 and rest[1] not in out:
            out.append(rest[1])
    return tuple(out)
