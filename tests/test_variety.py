"""Crowd variety (spec virtual-bones.md 22, format 1.3): tints, material variants and parts masks.

Checked against things vbusd does not compute itself: the USD file read back with pxr alone (the
primvars, the instancer's version, the variant materials' UsdPreviewSurface colours), the palette's
linear values computed by hand from the sRGB transfer function (tests/helpers/variety.py), the
shares of instances drawn against the weights and probabilities asked for (binomial bounds), and
the motion of a varied crowd against the same crowd without variety (spec 22.5: variety is drawn
after every other choice, so positions, clips and times are unchanged, bit for bit).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import vbusd
from vbusd.format import versioning
from vbusd.format.errors import OptionsError, VersionError
from vbusd.jobs.crowd import CrowdOptions

from tests.helpers import cli
from tests.helpers.variety import PARTS, TINTS, TINTS_LINEAR, VARIANTS, modular_character, varied_crowd


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("variety")
    modular_character(path)
    return path


def _instancer(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    found = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert len(found) == 1
    return stage, found[0]


def test_usd_holds_the_variety_pxr_reads(folder):
    from pxr import UsdGeom, UsdShade

    crowd = varied_crowd(folder, count=400)
    stage, prim = _instancer(crowd)
    n = len(prim.GetAttribute("positions").Get())
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 3
    primvars = UsdGeom.PrimvarsAPI(prim)
    tint = primvars.GetPrimvar("vb:tint")
    assert tint.GetInterpolation() == "vertex" and tint.GetTypeName() == "color3f[]" and not tint.IsIndexed()
    tints = np.asarray(tint.Get(), dtype=np.float64)
    assert tints.shape == (n, 3)
    # Every tint is one of the palette's colours, in linear RGB (by hand, tests/helpers/variety.py).
    distance = np.abs(tints[:, None, :] - np.asarray(TINTS_LINEAR)[None]).max(axis=2)
    assert np.all(distance.min(axis=1) < 1e-6)
    picked = distance.argmin(axis=1)
    assert set(picked) == {0, 1, 2}
    # Each colour about a third: binomial, 5 standard deviations.
    for k in range(3):
        share = np.mean(picked == k)
        assert abs(share - 1 / 3) < 5 * math.sqrt(1 / 3 * 2 / 3 / n), (k, share)
    names = list(prim.GetAttribute("vb:variantNames").Get())
    assert names == list(VARIANTS)
    variant = np.asarray(primvars.GetPrimvar("vb:variant").Get())
    assert set(variant) <= {0, 1}
    assert abs(np.mean(variant == 0) - 0.75) < 5 * math.sqrt(0.75 * 0.25 / n)
    materials = prim.GetRelationship("vb:variantMaterials").GetTargets()
    assert [m.name for m in materials] == names
    colours = []
    for target in materials:
        material = UsdShade.Material(stage.GetPrimAtPath(target))
        shader = material.ComputeSurfaceSource()[0]
        assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
        colours.append(tuple(shader.GetInput("diffuseColor").Get()))
    assert colours[0] != colours[1]
    assert list(prim.GetAttribute("vb:partNames").Get()) == ["Hat"]
    parts = np.asarray(primvars.GetPrimvar("vb:parts").Get())
    assert set(parts) <= {0, 1}
    assert abs(np.mean(parts == 1) - PARTS["Hat"]) < 5 * math.sqrt(0.4 * 0.6 / n)
    # The part is the prototype's child of that name (spec 22.3): the referenced Hat mesh.
    prototype = stage.GetPrimAtPath(prim.GetRelationship("prototypes").GetTargets()[0])
    assert {c.GetName() for c in prototype.GetChildren()} == {"Body", "Hat", "Flag"}  # the Flag: named by no --parts, always drawn

    # vbusd's reader gives the same values.
    read = vbusd.read_asset(crowd).crowds[0]
    np.testing.assert_array_equal(read.tint, tints.astype(np.float32))
    np.testing.assert_array_equal(read.variant, variant)
    np.testing.assert_array_equal(read.parts, parts)
    assert read.variant_names == tuple(names) and read.part_names == ("Hat",)
    np.testing.assert_allclose(read.variant_colors, np.asarray(colours), atol=0)


def test_same_seed_same_file_and_motion_unchanged(folder):
    first = varied_crowd(folder, name="a.usda")
    again = varied_crowd(folder, name="b.usda")
    other = varied_crowd(folder, name="c.usda", seed=8)
    plain = varied_crowd(folder, name="plain.usda", tints=(), variants={}, parts={})
    assert first.read_bytes() == again.read_bytes()
    assert first.read_bytes() != other.read_bytes()
    varied, bare = vbusd.read_asset(first).crowds[0], vbusd.read_asset(plain).crowds[0]
    for name in ("positions", "orientations", "scales", "clip", "time_offset", "playback_rate"):
        np.testing.assert_array_equal(getattr(varied, name), getattr(bare, name))
    # A crowd without variety stays what it was: no 1.3 property on its instancer.
    text = plain.read_text()
    assert "vb:tint" not in text and "vb:formatMinorVersion" not in text.split("PointInstancer", 1)[1]
    assert not bare.varied


def test_validate_is_clean(folder, capfd):
    crowd = varied_crowd(folder, name="valid.usda")
    result = cli.run(capfd, "validate", str(crowd))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 error(s), 0 warning(s)" in result.stdout


def _mutate(path, name, values, type_name="IntArray", vt_name=None):
    from pxr import Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.Open(str(path))
    prim = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)][0]
    UsdGeom.PrimvarsAPI(prim).CreatePrimvar(name, getattr(Sdf.ValueTypeNames, type_name),
                                            UsdGeom.Tokens.vertex).Set(getattr(Vt, vt_name or type_name)(values))
    stage.GetRootLayer().Save()


@pytest.mark.parametrize("primvar, change, code", [
    ("vb:variant", lambda v: v.__setitem__(3, 2), "variety.variant"),     # variant 2 of 2
    ("vb:parts", lambda v: v.__setitem__(5, 2), "variety.parts"),         # bit 1: no second part
    ("vb:parts", lambda v: v.__setitem__(5, -1), "variety.parts"),
])
def test_bad_variety_is_refused_in_one_line(folder, capfd, primvar, change, code):
    from pxr import UsdGeom

    crowd = varied_crowd(folder, name="bad.usda", count=12)
    _, prim = _instancer(crowd)
    values = list(UsdGeom.PrimvarsAPI(prim).GetPrimvar(primvar).Get())
    change(values)
    _mutate(crowd, primvar, values)
    result = cli.run(capfd, "validate", str(crowd))
    assert result.returncode == 1 and code in result.stdout
    result = cli.run(capfd, "info", str(crowd))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and f": {code}: " in lines[0], result.stderr
    assert "Traceback" not in result.stderr


def test_bad_tint_is_refused(folder, capfd):
    crowd = varied_crowd(folder, name="badtint.usda", count=4)
    _mutate(crowd, "vb:tint", [(1, 1, 1), (1, float("nan"), 0), (1, 1, 1), (0, 0, 0)], "Color3fArray", "Vec3fArray")
    result = cli.run(capfd, "info", str(crowd))
    assert result.returncode == 2 and ": variety.tint: " in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_a_1_2_reader_refuses_a_varied_crowd_by_name(folder, monkeypatch):
    crowd = varied_crowd(folder, name="newer.usda", count=4)
    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 2))
    with pytest.raises(VersionError) as error:
        vbusd.read_asset(crowd)
    message = str(error.value)
    assert "format.version" in message and "1.3 is newer than this reader (version 1.2)" in message
    assert "primvars:vb:tint" in message and "vb:partNames" in message


@pytest.mark.parametrize("args, words", [
    (("--tints", "red"), "--tints colour 'red'"),
    (("--tints", "#12345"), "--tints colour"),
    (("--variants", "home"), "--variants entry 'home' is not NAME=NUMBER"),
    (("--variants", "home=-1"), "--variants weight"),
    (("--parts", "Hat=1.5"), "--parts probability of 'Hat'"),
    (("--parts", "Scarf=0.5"), "--parts names 'Scarf', which is no mesh"),
])
def test_bad_options_one_line(folder, capfd, args, words):
    result = cli.run(capfd, "crowd", str(modular_character(folder)), "-o", str(folder / "opt.usda"), "--count", "4",
                     "--force", *args)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and words in lines[0], result.stderr
    assert not (folder / "opt.usda").exists()


def test_cli_and_api_agree(folder, capfd):
    api = varied_crowd(folder, name="api.usda", count=30, seed=3)
    result = cli.run(capfd, "crowd", str(modular_character(folder)), "-o", str(folder / "cli.usda"), "--count", "30",
                     "--seed", "3", "--tints", ",".join(TINTS), "--variants", "home=3,away=1", "--parts", "Hat=0.4",
                     "--force")
    assert result.returncode == 0, result.stderr
    assert (folder / "cli.usda").read_bytes() == api.read_bytes()


def test_options_check_values():
    with pytest.raises(OptionsError):
        CrowdOptions(tints=((1.0, -1.0, 0.0),))
    with pytest.raises(OptionsError):
        CrowdOptions(variants={"bad name": 1.0})
    options = CrowdOptions(tints=("#ff8000", (0.5, 0.5, 0.5)))
    np.testing.assert_allclose(options.tints, [TINTS_LINEAR[1], (0.5, 0.5, 0.5)], atol=1e-7)


def test_writer_refuses_a_part_the_prototype_lacks(folder, tmp_path):
    asset = vbusd.read_asset(varied_crowd(folder, name="src.usda", count=3))
    crowd = dataclasses.replace(asset.crowds[0], part_names=("Scarf",))
    with pytest.raises(OptionsError) as error:
        vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,)), tmp_path / "out.usda")
    assert error.value.code == "variety.parts"


def test_usdskel_fallback_keeps_tints_variants_and_parts(folder, capfd):
    """The fallback (one prim per instance) shows the same variety to any USD viewer, read with pxr alone:
    the Hat of an instance is visible exactly when its mask's bit 0 is set, the meshes inherit a
    displayColor of the variant's UsdPreviewSurface colour times the tint, and resolve (UsdShade's own
    binding resolution) to the variant's material."""
    from pxr import Usd, UsdGeom, UsdShade

    crowd = varied_crowd(folder, name="fallback_src.usda", count=40)
    stage, prim = _instancer(crowd)
    primvars = UsdGeom.PrimvarsAPI(prim)
    tints = np.asarray(primvars.GetPrimvar("vb:tint").Get(), dtype=np.float64)
    variant = np.asarray(primvars.GetPrimvar("vb:variant").Get())
    parts = np.asarray(primvars.GetPrimvar("vb:parts").Get())
    names = list(prim.GetAttribute("vb:variantNames").Get())
    colours = [UsdShade.Material(stage.GetPrimAtPath(t)).ComputeSurfaceSource()[0].GetInput("diffuseColor").Get()
               for t in prim.GetRelationship("vb:variantMaterials").GetTargets()]
    output = folder / "fallback.usda"
    result = cli.run(capfd, "export", str(crowd), "-o", str(output), "--as", "usdskel", "--force")
    assert result.returncode == 0, result.stderr
    fallback = Usd.Stage.Open(str(output))
    instances = sorted((p for p in fallback.Traverse() if p.GetName().startswith("i") and p.GetChild("Body")),
                       key=lambda p: p.GetName())
    assert len(instances) == len(tints)
    for i, instance in enumerate(instances):
        body, hat = instance.GetChild("Body"), instance.GetChild("Hat")
        visible = UsdGeom.Imageable(hat).ComputeVisibility() != UsdGeom.Tokens.invisible
        assert visible == bool(parts[i] & 1), i
        assert UsdGeom.Imageable(body).ComputeVisibility() != UsdGeom.Tokens.invisible
        display = UsdGeom.PrimvarsAPI(body).FindPrimvarWithInheritance("displayColor").Get()
        np.testing.assert_allclose(display[0], np.asarray(colours[variant[i]]) * tints[i], rtol=1e-6, atol=1e-7)
        material = UsdShade.MaterialBindingAPI(body).ComputeBoundMaterial()[0]
        assert material.GetPrim().GetName() == names[variant[i]], i
        assert UsdShade.MaterialBindingAPI(hat).ComputeBoundMaterial()[0].GetPath() == material.GetPath()


def _glb(path):
    """The JSON and BIN chunks of a .glb, read here with struct (not vbusd's reader)."""
    import json
    import struct

    data = path.read_bytes()
    (json_length,) = struct.unpack_from("<I", data, 12)
    gltf = json.loads(data[20:20 + json_length])
    bin_at = 20 + json_length
    (bin_length,) = struct.unpack_from("<I", data, bin_at)
    return gltf, data, bin_at + 8


def _accessor(gltf, data, bin_start, index):
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor["type"]]
    assert accessor["componentType"] == 5126 and "byteStride" not in view
    start = bin_start + view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    return np.frombuffer(data, dtype="<f4", count=accessor["count"] * width, offset=start).reshape(-1, width), start


def test_gltf_package_carries_the_variety(folder, capfd):
    """Instance attributes _VB_TINT / _VB_VARIANT / _VB_PARTS, KHR_materials_variants and the primitives'
    part bits, read from the GLB bytes, equal what pxr reads from the USD crowd; glTF-Validator reports no
    error or warning (where Node is installed); a variant out of range is refused by vbusd validate."""
    from pxr import UsdGeom, UsdShade

    crowd = varied_crowd(folder, name="pkg_src.usda", count=50)
    stage, prim = _instancer(crowd)
    primvars = UsdGeom.PrimvarsAPI(prim)
    tints = np.asarray(primvars.GetPrimvar("vb:tint").Get(), dtype=np.float32)
    variant = np.asarray(primvars.GetPrimvar("vb:variant").Get())
    parts = np.asarray(primvars.GetPrimvar("vb:parts").Get())
    names = list(prim.GetAttribute("vb:variantNames").Get())
    colours = [UsdShade.Material(stage.GetPrimAtPath(t)).ComputeSurfaceSource()[0].GetInput("diffuseColor").Get()
               for t in prim.GetRelationship("vb:variantMaterials").GetTargets()]
    package = folder / "crowd.glb"
    result = cli.run(capfd, "export", str(crowd), "-o", str(package), "--force")
    assert result.returncode == 0, result.stderr
    gltf, data, bin_start = _glb(package)
    assert "KHR_materials_variants" in gltf["extensionsUsed"]
    variants = [v["name"] for v in gltf["extensions"]["KHR_materials_variants"]["variants"]]
    assert variants == names
    (node,) = [n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {})]
    attributes = node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    got_tint, _ = _accessor(gltf, data, bin_start, attributes["_VB_TINT"])
    np.testing.assert_array_equal(got_tint, tints)
    got_variant, _ = _accessor(gltf, data, bin_start, attributes["_VB_VARIANT"])
    assert [variants[int(v)] for v in got_variant[:, 0]] == [names[v] for v in variant]
    got_parts, _ = _accessor(gltf, data, bin_start, attributes["_VB_PARTS"])
    primitives = gltf["meshes"][node["mesh"]]["primitives"]
    hat = [p for p in primitives if p["extensions"]["VBUSD_virtual_bones"]["path"].endswith("/Hat")]
    body = [p for p in primitives if p["extensions"]["VBUSD_virtual_bones"]["path"].endswith("/Body")]
    assert len(hat) == 1 and "part" not in body[0]["extensions"]["VBUSD_virtual_bones"]
    bit = hat[0]["extensions"]["VBUSD_virtual_bones"]["part"]
    np.testing.assert_array_equal((got_parts[:, 0].astype(np.int64) >> bit) & 1, parts & 1)
    for primitive in primitives:
        mappings = primitive["extensions"]["KHR_materials_variants"]["mappings"]
        for mapping in mappings:
            (k,) = mapping["variants"]
            factor = gltf["materials"][mapping["material"]]["pbrMetallicRoughness"]["baseColorFactor"]
            np.testing.assert_allclose(factor, [*colours[k], 1.0], rtol=1e-6)
    assert cli.run(capfd, "validate", str(package)).returncode == 0

    bad = folder / "bad_pkg.glb"
    _, start = _accessor(gltf, data, bin_start, attributes["_VB_VARIANT"])
    changed = bytearray(data)
    changed[start:start + 4] = np.float32(5).tobytes()
    bad.write_bytes(bytes(changed))
    result = cli.run(capfd, "validate", str(bad))
    assert result.returncode == 1 and "package.instances" in result.stdout and "_VB_VARIANT" in result.stdout


def test_gltf_validator_accepts_the_varied_package(folder, capfd):
    """The Khronos glTF-Validator: no error and no warning (only the infos every vbusd package has), and
    three.js's GLTFLoader loads the variety attributes as instanced attributes."""
    from tests.helpers import node as node_tools

    package = folder / "validator.glb"
    assert cli.run(capfd, "export", str(varied_crowd(folder, name="val_src.usda", count=20)), "-o", str(package),
                   "--force").returncode == 0
    result = node_tools.gltf_check(package)
    for mesh in result["three"]["meshes"]:
        for key in ("_VB_TINT", "_VB_VARIANT", "_VB_PARTS"):
            assert mesh["attributes"][key]["instanced"] and mesh["attributes"][key]["count"] == 20


def test_report_counts_what_the_file_holds(folder):
    """CrowdReport.variety counts the instances per colour, variant and part as the file holds them (pxr)."""
    from pxr import UsdGeom

    output = folder / "report.usda"
    report = vbusd.build_crowd([modular_character(folder)], output, CrowdOptions(
        count=80, tints=TINTS, variants=VARIANTS, parts=PARTS, seed=5, force=True))
    (variety,) = report.variety
    _, prim = _instancer(output)
    primvars = UsdGeom.PrimvarsAPI(prim)
    tints = np.asarray(primvars.GetPrimvar("vb:tint").Get(), dtype=np.float64)
    variant = np.asarray(primvars.GetPrimvar("vb:variant").Get())
    parts = np.asarray(primvars.GetPrimvar("vb:parts").Get())
    assert variety["tints"] == [int(np.sum(np.abs(tints - np.asarray(c)).max(axis=1) < 1e-6)) for c in TINTS_LINEAR]
    assert variety["variants"] == {"home": int(np.sum(variant == 0)), "away": int(np.sum(variant == 1))}
    assert variety["parts"] == {"Hat": int(np.sum(parts & 1))}
    assert sum(variety["tints"]) == 80
