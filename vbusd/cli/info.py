"""``vbusd info ASSET``: print the texture layout of a Virtual Bones asset, texture or sidecar.

ASSET may be:

* a Virtual Bones USD file (``.usd``, ``.usda``, ``.usdc``, ``.usdz``): every
  ``VirtualBonesAnimation`` prim is described from its ``vb:*`` attributes (the source of truth
  inside USD; the texture's header and metadata are read, and must agree with the prim as every
  reader requires, but its pixels are not decoded; its path, like the layer's sublayers,
  references and payloads, must stay inside the asset's folder unless ``--allow-outside-paths``);
* a texture (``.exr``, ``.png`` or ``.ktx2``, recognized by its magic bytes): described from its embedded
  metadata; the header is checked but pixels are not decoded (``vbusd validate`` checks them);
* a sidecar ``<texture>.json``;
* the runtime package ``vbusd export`` writes (``.glb``, ``.gltf``): its animations (from the
  ``VBUSD_virtual_bones`` extension), meshes and crowds (spec/runtime-package.md).

USD files and packages also list their crowds: each point instancer (USD) or
``EXT_mesh_gpu_instancing`` node (glTF) with its instance count, prototypes and clips played.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import click

from vbusd.cli import common
from vbusd.format.errors import MISSING_FILE, InputError
from vbusd.format import metadata as md
from vbusd.format.layout import Layout
from vbusd.format.motion import markers_to_dict, spaces_to_dict
from vbusd.io.usd_reader import read_summary, texture_disagreements
from vbusd.format.diagnostics import Diagnostics
from vbusd.io.package_reader import EXTENSION, read_package
from pxr import UsdGeom
from vbusd.io.usd_reader import stage_for_reading
from vbusd.io import textures
from rich.markup import escape
from rich.table import Table

__all__ = ["USD_SUFFIXES", "PACKAGE_SUFFIXES", "describe", "asset_info", "command"]

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
PACKAGE_SUFFIXES = (".glb", ".gltf")
EXTENSION_NAME = "VBUSD_virtual_bones"

_HELP = """Print the texture layout of a Virtual Bones asset.

ASSET is a Virtual Bones USD file (every VirtualBonesAnimation prim is described from its vb:*
attributes), a texture (.exr, .png or .ktx2, from its embedded metadata; pixels are not decoded), a
sidecar <texture>.json, or the runtime package vbusd export writes (.glb, .gltf). USD files and
packages also list their crowds: instances, prototypes and the clips they play.

The text form shows, per animation: format version (major.minor), encoding, texel format, bones and
their names, bone masks (format 1.2), rows, used and padded width, height, texel bytes, padding
waste, levels of detail and the clips.

The JSON form (--format json) is one object:

\b
  {"file": ASSET, "kind": "usd" | "texture" | "sidecar" | "package",
   "animations": [{"path", "texture", "formatVersion",
                   "formatMinorVersion", "version" ("1.2"), "encoding",
                   "texelFormat", "boneCount", "texelsPerBone", "bones",
                   "rowCount", "usedWidth", "width", "height",
                   "horizontalPadding", "verticalPadding", "texelBytes",
                   "usedTexelBytes", "bytesPerBoneKey",
                   "fetchesPerBoneAndRow", "paddingBytes", "paddingFraction",
                   "contentDigest", "masks": [{"name", "bones",
                   "weights"}], "blendSpaces": [{"name", "dimensions",
                   "points", "syncMarker"?}], "markers": [{"clip",
                   "name", "time"}], "clips": [{"name", "firstRow",
                   "rowCount", "rowsPerSecond", "loop", "startTime",
                   "duration"}]}, ...]}
  A texture's animation also has "container" (exr | png | ktx2),
  "compression" and "warnings" (notes that did not stop reading).
  A USD asset also has "upAxis" (Y | Z) and "metersPerUnit": the
  stage's scene units (text: "scene: Z up, 1 unit = 0.01 m"); an
  animation with levels of detail (format 1.2) has "levelsOfDetail":
  {"root", "levels", "screenSizes"}.
  A USD asset or package also has "instances" (all crowds) and
  "crowds": [{"path", "animation", "instances",
              "prototypes": [{"path", "instances"}],
              "clips": {NAME: instances}}].
  A package also has "container" (glb | gltf), "extensionVersion",
  "meshes": [{"name", "primitives", "vertices", "animation"}],
  "characters" (nodes drawing one character) and, per animation,
  "name" and, with MSFT_lod levels, "levelsOfDetail" (root: the
  first node listing them).

When there is exactly one animation its keys are repeated at the top level, so
`vbusd info anim.exr --format json | jq .width` works; with several, use
`.animations[i].width`. "path" is the prim path (null for a texture or sidecar), "texture" the
texture file as written in the asset.
"""


def describe(layout: Layout, clips, *, bones=(), path: Optional[str] = None,
             texture: Optional[str] = None, format_version: Optional[int] = None,
             content_digest: Optional[str] = None, format_minor_version: int = 0, masks=(), blend_spaces=(),
             markers=()) -> dict:
    """The JSON description of one animation's layout (keys as in the command help).

    Args:
        layout: Sizes.
        clips: :class:`vbusd.format.model.Clip` objects.
        bones: Bone names.
        path: Prim path of the animation, if it came from USD.
        texture: Texture file name as written in the asset.
        format_version: The metadata's formatVersion (the major version).
        content_digest: The texels' digest.
        format_minor_version: The metadata's formatMinorVersion (absent: 0).
        masks: Format 1.2 bone masks, ``(name, weights)`` pairs: listed with the bones they weigh.
        blend_spaces: Format 1.3 blend spaces, as the metadata's ``blendSpaces`` holds them.
        markers: Format 1.3 clip markers, as the metadata's ``markers`` holds them.
    """
    bones = [str(b) for b in bones]
    return {
        "path": path,
        "texture": texture,
        "formatVersion": format_version,
        "formatMinorVersion": int(format_minor_version or 0),
        "version": None if format_version is None else f"{format_version}.{int(format_minor_version or 0)}",
        **md.layout_fields(layout),
        "bones": bones,
        "masks": [{"name": str(name), "bones": [b for b, w in zip(bones, weights) if float(w) > 0],
                   "weights": [float(w) for w in weights]} for name, weights in masks],
        "blendSpaces": list(blend_spaces or ()),
        "markers": list(markers or ()),
        "usedTexelBytes": layout.used_texel_bytes,
        # bytes and texel fetches one bone costs per row (12 and 1 for the compact encoding)
        "bytesPerBoneKey": layout.texels_per_bone * layout.texel_format.stored_channels
        * layout.texel_format.bytes_per_channel,
        "fetchesPerBoneAndRow": layout.texels_per_bone,
        "paddingBytes": layout.texel_bytes - layout.used_texel_bytes,
        "paddingFraction": layout.padding_fraction,
        "contentDigest": content_digest,
        "clips": [
            {"name": c.name, "firstRow": c.first_row, "rowCount": c.row_count,
             "rowsPerSecond": c.rows_per_second, "loop": c.loop, "startTime": c.start_time,
             "duration": c.duration}
            for c in clips
        ],
    }


def _describe_info(info, *, texture: Optional[str], path: Optional[str] = None) -> dict:
    return describe(info.layout, info.clips, bones=info.bones, texture=texture, path=path,
                    format_version=info.format_version, content_digest=info.content_digest,
                    format_minor_version=info.format_minor_version, masks=info.masks,
                    blend_spaces=spaces_to_dict(info.blend_spaces), markers=markers_to_dict(info.markers))


# --------------------------------------------------------------------------------------------
# USD
# --------------------------------------------------------------------------------------------


def _usd_animations(path: Path, *, allow_outside_paths: bool = False) -> list:
    """Describe every VirtualBonesAnimation prim of a USD file from its vb:* attributes.

    The prims are read and checked exactly as ``vbusd.io.usd`` reads them (every attribute authored
    with its schema type, consistent sizes and clips, layers and ``vb:texture`` inside the asset's
    folder), but the textures are not opened.
    """

    animations, crowds = read_summary(path, allow_outside_paths=allow_outside_paths)
    for animation in animations:
        _check_texture(path, animation)
    described = [describe(a.layout, a.clips, bones=a.bones, path=a.path, texture=a.texture,
                          format_version=a.format_version, content_digest=a.content_digest,
                          format_minor_version=a.format_minor_version,
                          masks=[(m["name"], m["weights"]) for m in (a.declared.values.get("masks") or ())],
                          blend_spaces=a.declared.values.get("blendSpaces") or (),
                          markers=a.declared.values.get("markers") or ())
                 for a in animations]
    for entry, a in zip(described, animations):
        if a.lods is not None:  # format 1.2
            entry["levelsOfDetail"] = {"root": a.lods.root, "levels": a.lods.level_count,
                                       "screenSizes": [float(t) for t in a.lods.screen_sizes]}
    return described, [{"path": c.path, "animation": c.animation, "instances": c.instances,
                        "prototypes": [{"path": p, "instances": n} for p, n in c.prototypes], "clips": c.clips}
                       for c in crowds]


# --------------------------------------------------------------------------------------------
# Runtime package (.glb, .gltf)
# --------------------------------------------------------------------------------------------


def _package(path: Path, *, allow_outside_paths: bool = False) -> dict:
    """Describe a runtime package: its animations (layouts from the extension), meshes and crowds.

    Read strictly with :func:`vbusd.io.package_reader.read_package`, the reader ``vbusd validate``
    and ``vbusd view`` use (its structure, the extension against its schema, each KTX2 texture's
    header and layout, every accessor, the primitives and the crowds' instance attributes); the KTX2
    level data is not decoded (``vbusd validate`` checks the texels).
    """

    file = str(path)
    package = read_package(path, Diagnostics(file, strict=True), allow_outside_paths=allow_outside_paths)
    animations = []
    for animation in package.animations:
        info = md.from_dict(animation.layout, file=file,
                            location_prefix=f"/extensions/{EXTENSION}/animations/{animation.index}/layout")
        entry = {"name": animation.name, **_describe_info(info, texture=animation.texture, path=animation.path)}
        lods = [lod for lod in package.lods if lod["animation"] == animation.index]
        if lods:  # format 1.2: MSFT_lod nodes; every node of an animation lists the same levels
            entry["levelsOfDetail"] = {"root": lods[0]["node"], "levels": lods[0]["levels"],
                                       "screenSizes": lods[0]["screenSizes"]}
        animations.append(entry)
    names = {a.index: a.name for a in package.animations}
    crowds = []
    for crowd in package.crowds:
        clips = animations[[a.index for a in package.animations].index(crowd.animation)]["clips"] \
            if crowd.animation in names else []
        counts = {}
        if crowd.clips is not None and clips:
            counts = {c["name"]: int((crowd.clips == i).sum()) for i, c in enumerate(clips)}
        crowds.append({"path": crowd.node, "animation": names.get(crowd.animation), "instances": crowd.instances,
                       "prototypes": [{"path": crowd.mesh, "instances": crowd.instances}], "clips": counts})
    return {"animations": animations, "crowds": crowds, "container": package.container,
            "extensionVersion": package.version,
            "meshes": [{"name": name, "primitives": primitives, "vertices": vertices,
                        "animation": names.get(animation)} for name, primitives, vertices, animation in package.meshes],
            "characters": package.characters}


def _stage_units(path: Path) -> dict:
    """The stage's ``upAxis`` and ``metersPerUnit`` (spec: usd-conversion.md, Scene units), read from
    the root layer's metadata with UsdGeom's fallbacks when not authored."""

    with stage_for_reading(path, allow_outside_paths=True) as stage:  # paths were checked already
        root = stage.GetRootLayer().pseudoRoot
        up = root.GetInfo("upAxis") if root.HasInfo("upAxis") else UsdGeom.GetFallbackUpAxis()
        metres = root.GetInfo("metersPerUnit") if root.HasInfo("metersPerUnit") else 0.01
    return {"upAxis": str(up), "metersPerUnit": float(metres)}


def _check_texture(asset: Path, animation) -> None:
    """Refuse to describe a layout whose texture is missing or unreadable (its header, not its pixels),
    or whose metadata disagrees with the prim.

    A layout of a texture nobody can load is no answer to "what is in this asset"; the one line
    names the prim's ``vb:texture`` and what is wrong with the file it names.
    """

    location = f"{animation.path}.vb:texture"
    texture = Path(animation.texture_file)
    if not texture.is_file():
        why = "does not exist" if not texture.exists() else "is not a regular file"
        raise InputError(f"the texture {animation.texture} ({texture}) {why}", file=str(asset),
                         location=location, code="texture.missing")
    try:
        header = textures.read_texture_header(texture)
    except InputError as error:
        raise InputError(f"the texture {animation.texture} cannot be read ({error})", file=str(asset),
                         location=location, code="texture.unreadable") from None
    except OSError as error:
        raise InputError(f"the texture {animation.texture} cannot be read ({error.strerror or error})",
                         file=str(asset), location=location, code="texture.unreadable") from None
    # Its metadata must say what the prim says, as every reader of the asset requires (metadata.mismatch).
    diagnostics = Diagnostics(str(asset), strict=True)
    for item in texture_disagreements(animation, header.info, str(texture)):
        diagnostics.add(item)


# --------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------


def asset_info(asset, *, allow_outside_paths: bool = False) -> dict:
    """The JSON description ``vbusd info --format json`` prints for ASSET.

    Args:
        asset: A USD file, a texture or a sidecar.
        allow_outside_paths: Let a USD asset's layers and ``vb:texture`` lie outside its folder.

    Raises:
        InputError: The file is missing (``file.missing``), a folder, pipe or device or of an
            unknown kind (``file.kind``), unsafe or unreadable.
    """

    path = Path(asset)
    file = str(asset)
    if path.is_dir():
        raise InputError("is a folder; expected a USD file (.usd, .usda, .usdc), an EXR, PNG or KTX2 "
                         "texture, a sidecar .json or a runtime package (.glb, .gltf)", file=file, location="file", code="file.kind")
    if not path.exists():
        raise InputError(MISSING_FILE, file=file, code="file.missing")
    if not path.is_file():  # a named pipe would block the first read; devices are no assets
        raise InputError("not a regular file (a pipe, device or socket)", file=file,
                         location="file", code="file.kind")
    suffix = path.suffix.lower()
    crowds, extra = None, {}
    if suffix == ".json":
        kind = "sidecar"
        info = textures.read_sidecar(path)
        texture = path.name[:-len(".json")] if path.name.lower().endswith(".json") else None
        animations = [_describe_info(info, texture=texture)]
    elif suffix in USD_SUFFIXES:
        kind = "usd"
        animations, crowds = _usd_animations(path, allow_outside_paths=allow_outside_paths)
    elif suffix in PACKAGE_SUFFIXES:
        kind = "package"
        extra = _package(path, allow_outside_paths=allow_outside_paths)
        animations, crowds = extra.pop("animations"), extra.pop("crowds")
    else:
        try:
            container = textures.sniff_container(path)
        except InputError:
            raise InputError("not a Virtual Bones asset: expected a USD file (.usd, .usda, .usdc, "
                             ".usdz), an EXR, PNG or KTX2 texture, a sidecar .json or a runtime package "
                             "(.glb, .gltf)", file=file,
                             location="byte 0", code="file.kind") from None
        kind = "texture"
        header = textures.read_texture_header(path)
        animations = [_describe_info(header.info, texture=path.name)]
        animations[0]["container"] = container
        animations[0]["compression"] = header.compression
        animations[0]["warnings"] = list(header.warnings)
    result = {"file": file, "kind": kind, "animations": animations}
    if crowds is not None:
        result["crowds"] = crowds
        result["instances"] = sum(c["instances"] for c in crowds)
    result.update(extra)
    if kind == "usd":
        result.update(_stage_units(path))
    if len(animations) == 1:
        for key, value in animations[0].items():
            result.setdefault(key, value)
    return result


def _print_text(result: dict) -> None:
    console = common.console()
    console.print(f"[bold]{result['file']}[/bold] ({result['kind']}, "
                  f"{len(result['animations'])} animation{'s' if len(result['animations']) != 1 else ''})")
    if "upAxis" in result:
        console.print(f"scene: {result['upAxis']} up, 1 unit = {result['metersPerUnit']:g} m")
    if result["kind"] == "package":
        meshes = result["meshes"]
        console.print(f"package: {result['container']}, {EXTENSION_NAME} version {result['extensionVersion']}, "
                      f"{len(meshes)} mesh{'es' if len(meshes) != 1 else ''} "
                      f"({sum(m['primitives'] for m in meshes)} primitives, {sum(m['vertices'] for m in meshes):,} "
                      "vertices)", markup=False)
    for animation in result["animations"]:
        # The name or path on a line of its own: a table title would wrap at the table's width.
        console.print(animation.get("name") or animation["path"] or animation["texture"] or "animation", markup=False)
        table = Table(show_header=False, box=None, pad_edge=False)
        table.add_column("key", style="bold", no_wrap=True)
        table.add_column("value", overflow="fold")  # wraps at spaces, never an ellipsis
        if animation["path"] and animation["texture"]:
            table.add_row("texture", escape(animation["texture"]))  # "PACKAGE.glb[bufferView 3]" is no markup
        if animation.get("version"):
            table.add_row("format", animation["version"])
        if animation.get("container"):
            table.add_row("container", f"{animation['container']} ({animation['compression']})")
        table.add_row("encoding", animation["encoding"])
        table.add_row("texel format", animation["texelFormat"])
        table.add_row("bones", f"{animation['boneCount']} x {animation['texelsPerBone']} texels")
        if "bytesPerBoneKey" in animation:
            table.add_row("bone-key", f"{animation['bytesPerBoneKey']} bytes, "
                                              f"{animation['fetchesPerBoneAndRow']} texel fetch(es)")
        table.add_row("rows", str(animation["rowCount"]))
        table.add_row("width", f"{animation['usedWidth']} used, {animation['width']} padded "
                               f"(horizontal padding {animation['horizontalPadding']})")
        table.add_row("height", f"{animation['height']} (vertical padding "
                                f"{animation['verticalPadding']})")
        table.add_row("texel bytes", common.human_bytes(animation["texelBytes"], exact=True))
        table.add_row("padding waste", f"{animation['paddingFraction'] * 100:.2f}% "
                                       f"({common.human_bytes(animation['paddingBytes'], exact=True)})")
        lods = animation.get("levelsOfDetail")
        if lods:
            table.add_row("levels of detail", escape(f"{lods['levels']} under {lods['root']}, screen sizes "
                                                     + ", ".join(f"{t:g}" for t in lods["screenSizes"])))
        for warning in animation.get("warnings", ()):
            table.add_row("warning", warning)
        console.print(table)
        # Lists of names on lines of their own: in the table one long row would pad every other row.
        if animation.get("bones"):
            console.print("bone names: " + ", ".join(animation["bones"]), markup=False)
        for mask in animation.get("masks", ()):
            console.print(f"mask {mask['name']} ({len(mask['bones'])} of {len(animation['bones'])} bones): "
                          + ", ".join(mask["bones"]), markup=False)
        for space in animation.get("blendSpaces", ()):  # format 1.3
            points = ", ".join(f"{p['clip']}@{p['x']:g}" + (f":{p['y']:g}" if "y" in p else "") for p in space["points"])
            sync = f", in phase from marker {space['syncMarker']}" if space.get("syncMarker") else ""
            console.print(f"blend space {space['name']} ({space['dimensions']}D{sync}): {points}", markup=False)
        if animation.get("markers"):
            console.print("markers: " + ", ".join(f"{m['clip']}:{m['name']}@{m['time']:g}"
                                                  for m in animation["markers"]), markup=False)
        clips = common.table("name", "first row", "rows", "rows/s", "loop", "duration s", title="clips",
                             right=("first row", "rows", "rows/s", "loop", "duration s"), pad_edge=False)
        for clip in animation["clips"]:
            clips.add_row(clip["name"], str(clip["firstRow"]), str(clip["rowCount"]),
                          f"{clip['rowsPerSecond']:g}", "yes" if clip["loop"] else "no",
                          f"{clip['duration']:.4g}")
        console.print(clips)
    _print_crowds(console, result)


def _print_crowds(console, result: dict) -> None:
    """The crowds table (USD files and packages): instances, prototypes, clips played."""

    if "crowds" not in result:
        return
    crowds = result["crowds"]
    console.print(f"crowds: {len(crowds)}, {result['instances']:,} instances", markup=False)
    if not crowds:
        return
    grid = common.table("crowd", "instances", "animation", "prototypes", "clips", right=("instances",),
                        pad_edge=False)
    for crowd in crowds:
        prototypes = ", ".join(f"{p['path']} ({p['instances']:,})" for p in crowd["prototypes"])
        clips = ", ".join(f"{name} {n:,}" for name, n in crowd["clips"].items())
        grid.add_row(*(escape(text) for text in (crowd["path"], f"{crowd['instances']:,}", str(crowd["animation"]),
                                                 prototypes, clips)))
    console.print(grid)


@click.command("info", help=_HELP)
# A plain path: asset_info reports a missing file or a folder as one vbusd error line (exit 2),
# where click.Path would print its own three-line usage error.
@click.argument("asset", type=click.Path(path_type=str))
@common.format_option
@click.option("--allow-outside-paths", is_flag=True,
              help="Let a USD asset's layers and vb:texture lie outside its folder.")
@common.quiet_option
def command(asset: str, output_format: str, allow_outside_paths: bool, quiet: bool) -> int:
    """Print the texture layout of ASSET (see the module docstring)."""
    result = asset_info(asset, allow_outside_paths=allow_outside_paths)
    if quiet:  # it could be read and described: exit 0 (an unreadable asset was one line, exit 2)
        return 0
    if output_format == "json":
        common.echo_json(result)
    else:
        _print_text(result)
    return 0
