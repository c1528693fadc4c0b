"""``vbusd info``: layout of textures, sidecars and USD assets, against hand-computed numbers."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vbusd.io import textures
from vbusd.cli import main
from vbusd.format.layout import Layout
from vbusd.format.metadata import content_digest
from vbusd.format.model import Clip, VirtualBones

from tests.helpers.capabilities import require

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd"

REQUIRED = {"encoding", "texelFormat", "boneCount", "rowCount", "usedWidth", "width", "height",
            "texelBytes", "clips"}


def talk_vb(encoding="crossMatrix", texel_format="float16", rows=512):
    """The talk's rig: 18 bones, 512 rows (a 10 s cheer at 51.2 rows/s)."""
    layout = Layout(encoding, texel_format, 18, rows)
    texels = np.zeros(layout.shape, layout.texel_format.numpy_dtype)
    texels[:, :layout.used_width] = 1
    ranges = None
    if texel_format == "unorm16":
        ranges = np.zeros((layout.texels_per_bone, 4, 2))
        ranges[..., 1] = 1
    return VirtualBones(layout, texels, tuple(f"j{i}" for i in range(18)),
                        (Clip("cheer", 0, rows, 51.2, True),), unorm_ranges=ranges)


def run_json(capsys, *args):
    assert main(["info", *map(str, args), "--format", "json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_json_of_the_talks_texture(tmp_path, capsys):
    path = tmp_path / "crowd.exr"
    textures.write_texture(path, talk_vb())
    out = run_json(capsys, path)
    assert REQUIRED <= set(out) and out["kind"] == "texture" and out["file"] == str(path)
    # 18 bones x 3 texels = 54 columns, padded to 64; 64 x 512 x 4 channels x 2 bytes.
    assert (out["usedWidth"], out["width"], out["height"]) == (54, 64, 512)
    assert out["texelBytes"] == 262144
    assert out["paddingBytes"] == (64 - 54) * 512 * 8 == 40960
    assert out["paddingFraction"] == pytest.approx(10 / 64)
    assert (out["encoding"], out["texelFormat"], out["boneCount"], out["rowCount"]) == \
        ("crossMatrix", "float16", 18, 512)
    assert out["texelsPerBone"] == 3 and out["texture"] == "crowd.exr" and out["path"] is None
    (clip,) = out["clips"]
    assert clip == {"name": "cheer", "firstRow": 0, "rowCount": 512, "rowsPerSecond": 51.2,
                    "loop": True, "startTime": 0.0, "duration": pytest.approx(10.0)}
    assert len(out["animations"]) == 1 and out["animations"][0]["width"] == 64
    # Exactly the keys `vbusd info --help` documents (copied here by hand from the help text).
    assert set(out["animations"][0]) == {
        "path", "texture", "formatVersion", "formatMinorVersion", "version", "masks", "blendSpaces", "markers",
        "encoding", "texelFormat",
        "boneCount", "texelsPerBone",
        "bones", "rowCount", "usedWidth", "width", "height", "horizontalPadding", "verticalPadding",
        "texelBytes", "usedTexelBytes", "bytesPerBoneKey", "fetchesPerBoneAndRow", "paddingBytes",
        "paddingFraction", "contentDigest", "clips", "container", "compression", "warnings"}
    assert (out["bytesPerBoneKey"], out["fetchesPerBoneAndRow"]) == (24, 3)  # 3 RGBA float16 texels


def test_json_of_quaternion_unorm16_png_and_sidecar(tmp_path, capsys):
    path = tmp_path / "q.png"
    textures.write_texture(path, talk_vb("quatTranslation", "unorm16", rows=300))
    for source in (path, tmp_path / "q.png.json"):
        out = run_json(capsys, source)
        # 18 x 2 = 36 columns, padded to 64; 300 rows unpadded; unorm16 = 2 bytes per channel.
        assert (out["usedWidth"], out["width"], out["height"]) == (36, 64, 300)
        assert out["texelBytes"] == 64 * 300 * 8 == 153600
        assert out["paddingBytes"] == 28 * 300 * 8
        assert out["clips"][0]["duration"] == pytest.approx(300 / 51.2)
    assert out["kind"] == "sidecar" and out["texture"] == "q.png"


def test_text_table(tmp_path, capsys):
    path = tmp_path / "crowd.exr"
    textures.write_texture(path, talk_vb())
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    for expected in ("crossMatrix", "float16", "18 x 3 texels", "512", "54 used, 64 padded",
                     "256.0 KiB, 262,144 bytes", "15.62% (40.0 KiB, 40,960 bytes)", "cheer", "51.2", "yes", "10"):
        assert expected in text, expected


def _usd_asset(tmp_path):
    """A Virtual Bones USD layer written with pxr by hand (two animations), and their textures.

    Every attribute is authored, as the spec requires of writers (readers do not use fallbacks).
    info describes the layout from the attributes but refuses a missing or unreadable texture, so
    each animation gets a texture of its layout (zero texels; info reads only the header).
    """
    from pxr import Sdf, Usd, Vt

    import vbusd.io.usd_plugin  # noqa: F401  registers the schema

    path = tmp_path / "crowd.usda"
    stage = Usd.Stage.CreateNew(str(path))
    # Sizes by hand: T = 3 and 18 x 3 = 54 -> 64 wide; T = 2 and 5 x 2 = 10 -> 16 wide.
    for name, encoding, bones, rows, texels, width, clips in (
            ("Spectator", "crossMatrix", 18, 512, 3, 64, [("cheer", 0, 512, 51.2, True, 0.0)]),
            ("Mascot", "dualQuat", 5, 40, 2, 16, [("jump", 0, 30, 30.0, False, 0.0),
                                                 ("wave", 30, 10, 10.0, True, 2.0)])):
        prim = stage.DefinePrim(f"/Crowd/{name}", "VirtualBonesAnimation")
        values = {
            "vb:formatVersion": (Sdf.ValueTypeNames.Int, 1),
            "vb:texelsPerBone": (Sdf.ValueTypeNames.Int, texels),
            "vb:textureWidth": (Sdf.ValueTypeNames.Int, width),
            "vb:textureHeight": (Sdf.ValueTypeNames.Int, rows),
            "vb:horizontalPadding": (Sdf.ValueTypeNames.Token, "powerOfTwo"),
            "vb:verticalPadding": (Sdf.ValueTypeNames.Token, "none"),
            "vb:texture": (Sdf.ValueTypeNames.Asset, Sdf.AssetPath(f"./{name}.exr")),
            "vb:encoding": (Sdf.ValueTypeNames.Token, encoding),
            "vb:texelFormat": (Sdf.ValueTypeNames.Token, "float32"),
            "vb:boneCount": (Sdf.ValueTypeNames.Int, bones),
            "vb:rowCount": (Sdf.ValueTypeNames.Int, rows),
            "vb:bones": (Sdf.ValueTypeNames.TokenArray, Vt.TokenArray([f"b{i}" for i in range(bones)])),
            "vb:clipNames": (Sdf.ValueTypeNames.TokenArray, Vt.TokenArray([c[0] for c in clips])),
            "vb:clipFirstRows": (Sdf.ValueTypeNames.IntArray, Vt.IntArray([c[1] for c in clips])),
            "vb:clipRowCounts": (Sdf.ValueTypeNames.IntArray, Vt.IntArray([c[2] for c in clips])),
            "vb:clipRowsPerSecond": (Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray([c[3] for c in clips])),
            "vb:clipLoops": (Sdf.ValueTypeNames.BoolArray, Vt.BoolArray([c[4] for c in clips])),
            "vb:clipStartTimes": (Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray([c[5] for c in clips])),
            "vb:contentDigest": (Sdf.ValueTypeNames.String, content_digest(np.zeros(
                Layout(encoding, "float32", bones, rows).shape, np.float32))),
        }
        for attribute, (type_name, value) in values.items():
            prim.CreateAttribute(attribute, type_name).Set(value)
        layout = Layout(encoding, "float32", bones, rows)
        textures.write_texture(tmp_path / f"{name}.exr", VirtualBones(
            layout, np.zeros(layout.shape, np.float32), tuple(f"b{i}" for i in range(bones)),
            tuple(Clip(c[0], c[1], c[2], c[3], c[4], c[5]) for c in clips)))
    stage.GetRootLayer().Save()
    return path


def test_usd_asset_with_two_animations(tmp_path, capsys):
    path = _usd_asset(tmp_path)
    out = run_json(capsys, path)
    assert out["kind"] == "usd" and "width" not in out  # several animations: no top-level copy
    spectator, mascot = out["animations"]
    assert spectator["path"] == "/Crowd/Spectator" and spectator["texture"] == "./Spectator.exr"
    # float32: 64 x 512 x 4 x 4 bytes.
    assert (spectator["usedWidth"], spectator["width"], spectator["texelBytes"]) == (54, 64, 524288)
    # dualQuat: 5 x 2 = 10 columns -> 16; 40 rows; 16 x 40 x 16 bytes.
    assert (mascot["usedWidth"], mascot["width"], mascot["height"]) == (10, 16, 40)
    assert mascot["texelBytes"] == 10240 and mascot["horizontalPadding"] == "powerOfTwo"
    assert [c["duration"] for c in mascot["clips"]] == pytest.approx([29 / 30, 1.0])
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "/Crowd/Spectator" in text and "/Crowd/Mascot" in text and "wave" in text


@pytest.mark.parametrize("attribute, change, code", [
    ("vb:verticalPadding", None, "prim.attribute.missing"),  # left to the schema's fallback: not authored
    ("vb:boneCount", "uniform string vb:boneCount = \"eighteen\"", "prim.attribute.missing"),
    ("vb:clipRowsPerSecond", "uniform double[] vb:clipRowsPerSecond = [nan]", "clip.rate"),
    ("vb:textureWidth", "uniform int vb:textureWidth = 32", "layout.width"),
])
def test_usd_attributes_are_checked_as_the_reader_checks_them(tmp_path, capsys, attribute, change, code):
    # Spec 13: every attribute authored with its schema type, sizes derived from the layout,
    # finite positive rates; info reports the first problem as one line at the prim and attribute.
    path = _usd_asset(tmp_path)
    lines = path.read_text().splitlines()
    (index,) = [i for i, line in enumerate(lines)
                if f" {attribute} = " in line and i < next(j for j, l in enumerate(lines) if "Mascot" in l)]
    if change is None:
        del lines[index]
    else:
        lines[index] = "        " + change
    path.write_text("\n".join(lines) + "\n")
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f": /Crowd/Spectator.{attribute}: {code}: " in err


def test_usd_asset_written_by_usd_io(tmp_path, capsys):
    from vbusd.io import usd as usd_io
    from vbusd.format.model import VirtualBonesAsset

    vb = talk_vb()
    path = tmp_path / "crowd.usda"
    usd_io.write_asset(VirtualBonesAsset(animations=(vb,)), path)
    out = run_json(capsys, path)
    assert (out["width"], out["height"], out["texelBytes"], out["usedWidth"]) == (64, 512, 262144, 54)
    assert out["path"] == vb.path and out["clips"][0]["rowCount"] == 512


def test_errors_are_one_line_with_exit_status_2(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.exr")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.exr: file.missing: no such file" in err
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    assert main(["info", str(other)]) == 2
    assert "not a Virtual Bones asset" in capsys.readouterr().err
    usd = tmp_path / "empty.usda"
    usd.write_text("#usda 1.0\ndef Xform \"World\" {}\n")
    assert main(["info", str(usd)]) == 2
    assert "no VirtualBonesAnimation prim" in capsys.readouterr().err
    broken = tmp_path / "broken.usda"
    broken.write_text("#usda 1.0\ndef Xform \"World\" {\n")
    assert main(["info", str(broken)]) == 2
    err = capsys.readouterr().err
    # USD's own place of the parse error (line 3: the file ends inside the prim) is the location.
    assert err.startswith(f"vbusd: {broken}: line 3 column ") and ": usd.open: " in err
    assert err.count("\n") == 1 and "Traceback" not in err
    # A named pipe is refused before any read (reading it would block forever).
    import os

    pipe = tmp_path / "pipe.exr"
    os.mkfifo(pipe)
    assert main(["info", str(pipe)]) == 2
    err = capsys.readouterr().err
    assert err == f"vbusd: {pipe}: file: file.kind: not a regular file (a pipe, device or socket)\n"
    # A folder is one vbusd line too (click's own check would print a three-line usage error).
    assert main(["info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vbusd: {tmp_path}: file: file.kind: is a folder; expected ") and err.count("\n") == 1


def _sample_with_texture_path(tmp_path, authored: str, folder: str = "."):
    """A copy of the stadium sample's USD layer whose vb:texture is ``authored``."""
    text = (SAMPLE / "stadium_crowd_vb.usda").read_text()
    assert "@./stadium_crowd_vb.Cheer.exr@" in text
    target = tmp_path / folder / "crowd.usda"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text.replace("@./stadium_crowd_vb.Cheer.exr@", f"@{authored}@"))
    return target


@pytest.mark.parametrize("authored, why", [
    ("../stadium_crowd_vb.Cheer.exr", "'..' leads outside the asset's folder"),
    (str(SAMPLE / "stadium_crowd_vb.Cheer.exr"), "absolute paths are not allowed"),
    ("https://example.com/a.exr", "URI scheme 'https' is not allowed"),
])
def test_texture_path_leaving_the_folder_is_refused(tmp_path, capsys, authored, why):
    # Spec 13: vb:texture must resolve inside the asset's folder, even though info does not read
    # the texture (a path is checked, never followed).
    usd = _sample_with_texture_path(tmp_path, authored, folder="inner")
    for name in ("stadium_crowd_vb.Cheer.exr", "stadium_crowd_vb.Cheer.exr.json"):  # what '..' names
        (tmp_path / name).write_bytes((SAMPLE / name).read_bytes())
    assert main(["info", str(usd)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"vbusd: {usd}: /StadiumCrowd/Cheer.vb:texture: texture.outside: ") and why in err
    if not authored.startswith("https"):
        # Allowed on request; the layout is then printed as usual.
        assert main(["info", str(usd), "--allow-outside-paths", "--format", "json"]) == 0
        assert json.loads(capsys.readouterr().out)["texture"] == authored


def test_sublayer_outside_the_folder_is_refused(tmp_path, capsys):
    # info opens the stage; a sublayer outside the asset's folder must not even be opened.
    outside = tmp_path / "outside.usda"
    outside.write_text("#usda 1.0\n")
    usd = tmp_path / "inner" / "crowd.usda"
    usd.parent.mkdir()
    usd.write_text('#usda 1.0\n(\n    subLayers = [@../outside.usda@]\n)\n')
    assert main(["info", str(usd)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "asset.outside" in err and "outside.usda" in err


@pytest.mark.cli
def test_subprocess_json(tmp_path):
    path = tmp_path / "crowd.exr"
    textures.write_texture(path, talk_vb())
    result = subprocess.run([sys.executable, "-m", "vbusd", "info", str(path), "--format", "json"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["texelBytes"] == 262144
    result = subprocess.run([sys.executable, "-m", "vbusd", "info", "--help"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "jq .width" in result.stdout


def test_the_stadium_crowd_sample(capsys):
    """The talk's numbers: 18 bones, crossMatrix float16, 512 rows over 10 s -> 64x512, 262,144 B."""
    usd = run_json(capsys, SAMPLE / "stadium_crowd_vb.usda")
    texture = run_json(capsys, SAMPLE / usd["texture"])
    for out in (usd, texture):
        assert (out["encoding"], out["texelFormat"], out["boneCount"]) == ("crossMatrix", "float16", 18)
        assert (out["usedWidth"], out["width"], out["height"], out["rowCount"]) == (54, 64, 512, 512)
        assert out["texelBytes"] == 262144 and out["verticalPadding"] == "powerOfTwo"
        assert out["clips"][0]["duration"] == pytest.approx(10.0)
    assert usd["contentDigest"] == texture["contentDigest"]
    # The sample's texture passes every reader check, digest included.
    data = textures.read_texture(SAMPLE / usd["texture"])
    assert data.info.content_digest == usd["contentDigest"]


def test_info_shows_the_minor_version_masks_and_bone_names(tmp_path, capsys):
    """Issue 35 item 15: a format 1.2 asset (a bone mask) is described as 1.2 in JSON and text, as
    the USD prim and the sidecar say, with its masks and the bone names the text form lacked."""
    from pxr import Usd

    out = tmp_path / "layers.usda"
    assert main(["convert", str(SAMPLE / "stadium_crowd.usda"), "-o", str(out), "--mask", "upper=spine", "-q"]) == 0
    sidecar = json.loads(next(tmp_path.glob("*.exr.json")).read_text())
    stage = Usd.Stage.Open(str(out))
    prim = next(p for p in stage.Traverse() if p.GetTypeName() == "VirtualBonesAnimation")
    authored = (prim.GetAttribute("vb:formatVersion").Get(), prim.GetAttribute("vb:formatMinorVersion").Get())
    assert authored == (sidecar["formatVersion"], sidecar["formatMinorVersion"]) == (1, 2)
    upper = ["hips/spine", "hips/spine/chest", "hips/spine/chest/head"] + [
        f"hips/spine/chest/{side}_shoulder" + tail for side in "LR"
        for tail in ("", f"/{side}_upperArm", f"/{side}_upperArm/{side}_forearm",
                     f"/{side}_upperArm/{side}_forearm/{side}_hand")]
    for asset in (out, next(tmp_path.glob("*.exr")), next(tmp_path.glob("*.exr.json"))):
        assert main(["info", str(asset), "--format", "json"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert (info["formatVersion"], info["formatMinorVersion"], info["version"]) == (1, 2, "1.2"), asset
        (mask,) = info["masks"]
        assert mask["name"] == "upper" and sorted(mask["bones"]) == sorted(upper), asset
        assert main(["info", str(asset)]) == 0
        text = capsys.readouterr().out
        assert re.search(r"^format\s+1\.2\s*$", text, flags=re.M), text
        assert "bone names: hips, hips/spine, hips/spine/chest," in text
        assert "mask upper (11 of 18 bones): hips/spine, " in text


def test_info_shows_the_levels_of_detail_of_a_package(tmp_path, capsys):
    """Issue 35 item 15: a package's MSFT_lod levels (count and screen coverage, read here from the
    glTF JSON itself) are in info, as a USD asset's UsdLod levels are."""
    require("lod")
    usd, crowd, package = tmp_path / "lod.usda", tmp_path / "crowd.usda", tmp_path / "crowd.glb"
    assert main(["convert", str(SAMPLE / "stadium_crowd.usda"), "-o", str(usd), "--lod-ratios", "0.5,0.2",
                 "-q"]) == 0
    assert main(["crowd", str(usd), "-o", str(crowd), "--count", "3", "-q"]) == 0
    assert main(["export", str(crowd), "-o", str(package), "-q"]) == 0
    data = package.read_bytes()
    gltf = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
    (node,) = [n for n in gltf["nodes"] if "MSFT_lod" in (n.get("extensions") or {})]
    coverage = node["extras"]["MSFT_screencoverage"]
    assert main(["info", str(package), "--format", "json"]) == 0
    lods = json.loads(capsys.readouterr().out)["levelsOfDetail"]
    assert lods["levels"] == len(node["extensions"]["MSFT_lod"]["ids"]) + 1 == 3
    assert lods["screenSizes"] == coverage[:-1] == pytest.approx([0.01, 0.001]) and lods["root"] == node["name"]
    assert main(["info", str(package)]) == 0
    assert re.search(r"levels of detail\s+3 under ", capsys.readouterr().out)
