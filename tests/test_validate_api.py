"""The validation library: never raising on bad assets, internal errors, fallbacks, real assets."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from vbusd.cli import main
from vbusd.format.errors import InputError
from vbusd.validators import api as validators_api
from vbusd.validators.api import validate

FIXTURES = Path(__file__).parent / "fixtures" / "validate"


def _copy(name: str, tmp_path: Path) -> Path:
    target = tmp_path / name.replace("/", "_")
    shutil.copytree(FIXTURES / name, target)
    return target / "asset.usda"


def _codes(report):
    return [(f.code, str(f.location)) for f in report.findings]


def test_a_failing_check_becomes_asset_internal_and_the_others_still_run(monkeypatch):
    def broken(prim):
        raise ZeroDivisionError("boom")

    # validate() calls the check by the name vbusd.validators.api imported (at its top).
    monkeypatch.setattr(validators_api, "check_binding_prim", broken)
    report = validate(FIXTURES / "instancer.clip.range" / "asset.usda")
    codes = {f.code for f in report.findings}
    assert "asset.internal" in codes and "instancer.clip.range" in codes
    internal = [f for f in report.findings if f.code == "asset.internal"][0]
    assert "ZeroDivisionError: boom" in internal.message
    assert str(internal.location) == "/VirtualBones/Character/Body"


def test_unreadable_assets_raise_input_error_and_nothing_else(tmp_path):
    with pytest.raises(InputError) as missing:
        validate(tmp_path / "nothere.usda")
    assert missing.value.code == "file.missing"
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\ndef \"\n", encoding="utf-8")
    with pytest.raises(InputError) as syntax:
        validate(bad)
    assert syntax.value.code == "usd.open" and syntax.value.exit_status == 2
    with pytest.raises(InputError):
        validate(tmp_path)  # a folder


def test_an_attribute_left_to_its_schema_fallback_is_reported_once(tmp_path):
    from pxr import Usd

    path = _copy("valid/crossMatrix_float16", tmp_path)
    stage = Usd.Stage.Open(str(path))
    stage.GetPrimAtPath("/VirtualBones/Animation").GetAttribute("vb:encoding").Clear()
    stage.GetRootLayer().Save()
    del stage
    report = validate(path)
    assert _codes(report) == [("prim.attribute.missing", "/VirtualBones/Animation.vb:encoding"),
                              ("texture.padding.fraction", "/VirtualBones/Animation.vb:texture")]
    assert "fallback 'crossMatrix'" in report.findings[0].message


def test_clip_extents_need_two_points_per_clip(tmp_path):
    from pxr import Usd, Vt

    path = _copy("valid/crossMatrix_float16", tmp_path)
    stage = Usd.Stage.Open(str(path))
    attribute = stage.GetPrimAtPath("/VirtualBones/Animation").GetAttribute("vb:clipExtents")
    attribute.Set(Vt.Vec3fArray([(0, 0, 0), (1, 1, 1), (0, 0, 0)]))
    stage.GetRootLayer().Save()
    del stage
    report = validate(path)
    assert ("clip.arrays", "/VirtualBones/Animation.vb:clipExtents") in _codes(report)


def test_all_metadata_schema_violations_are_reported_not_just_the_first(tmp_path):
    path = _copy("valid/crossMatrix_float16", tmp_path)
    sidecar = path.parent / "asset.Animation.exr.json"
    meta = json.loads(sidecar.read_text(encoding="utf-8"))
    meta.update(encoding="euler", texelBytes=7, generator=3)
    del meta["bones"]
    sidecar.write_text(json.dumps(meta), encoding="utf-8")
    report = validate(path)
    pointers = {f.location.pointer for f in report.findings if f.code == "metadata.schema"}
    assert {"/encoding", "/texelBytes", "/generator", ""} <= pointers


def test_samples_validate_without_errors(repo_root):
    assets = sorted(p for p in (repo_root / "samples").rglob("*.usd*")
                    if "VirtualBonesAnimation" in p.read_text(encoding="utf-8", errors="ignore"))
    assert assets, "no Virtual Bones sample asset in samples/"
    for asset in assets:
        report = validate(asset)
        assert report.error_count == 0 and report.counts["warning"] == 0, (asset, _codes(report))


@pytest.mark.slow
def test_converted_third_party_assets(shared_assets, tmp_path, capsys):
    """Real assets through `vbusd convert`, then validated. RecursiveSkeletons' skin 80 carries a
    uniform scale of 0.09 (assets README: nested skeletons scaled by 0.3 twice), which the
    validator must report as an affineMatrix scale hint with those column norms; skin 0 has none."""
    cases = [("usdskel/SkinnedArm/skinnedArm.usda", []),
             ("gltf/CesiumMan/CesiumMan.glb", []),
             ("gltf/RecursiveSkeletons/RecursiveSkeletons.glb", ["--skeleton", "0", "--skeleton", "80"])]
    for source, options in cases:
        out = tmp_path / (Path(source).stem + ".usda")
        assert main(["convert", str(shared_assets / source), "-o", str(out), *options]) == 0
        capsys.readouterr()
        report = validate(out)
        assert report.error_count == 0 and report.counts["warning"] == 0, (source, _codes(report))
        hints = [f for f in report.findings if f.code == "encoding.affine.scale"]
        if "Recursive" in source:
            assert len(hints) == 1
            norms = [float(x) for x in re.search(r"column norms \[([^\]]+)\]", hints[0].message).group(1).split()]
            assert norms == pytest.approx([0.09, 0.09, 0.09], abs=2e-3)
        else:
            assert not hints


def test_textures_inside_a_usdz_package_are_checked(tmp_path):
    from pxr import Sdf, UsdUtils

    for name, expected in (("valid/crossMatrix_float16", set()), ("texture.nonFinite", {"texture.nonFinite"})):
        source = _copy(name, tmp_path)
        package = tmp_path / (source.parent.name + ".usdz")
        assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(source)), str(package))
        alone = tmp_path / "packages" / package.name
        alone.parent.mkdir(exist_ok=True)
        package.rename(alone)  # nothing beside it: the texture can only come from the package
        report = validate(alone)
        errors = {f.code for f in report.findings if f.severity.value == "error"}
        assert errors == expected, _codes(report)
        # The padding info needs the pixels: proof the packaged texture was read.
        assert "texture.padding.fraction" in {f.code for f in report.findings}
    nan = [f for f in report.findings if f.code == "texture.nonFinite"][0]
    assert nan.location.file == f"{alone}[asset.Animation.exr]".rsplit("/", 1)[-1]


def test_instancing_primvar_with_element_size_other_than_1_is_reported(tmp_path):
    """One value per instance means elementSize 1 (vbusd's reader refuses any other); with
    elementSize 3 and one value per instance, counting alone would not notice."""
    from pxr import Usd

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    stage = Usd.Stage.Open(str(asset))
    stage.GetPrimAtPath("/VirtualBones/Crowd").GetAttribute("primvars:vb:playbackRate").SetMetadata("elementSize", 3)
    stage.GetRootLayer().Save()
    assert _codes(validate(asset))[:1] == [("instancer.count", "/VirtualBones/Crowd.primvars:vb:playbackRate")]


def test_authored_types_that_differ_from_the_schema_are_reported(tmp_path):
    """USD composes a schema property with the schema's type whatever a layer authored, and Get()
    returns the authored value: the validator must look at the authored specs (as vbusd's reader
    does), or float[] clip rows and float[] bone indices pass unnoticed."""
    asset = _copy("valid/crossMatrix_float16", tmp_path)
    text = asset.read_text(encoding="utf-8")
    for old, new in (("int[] vb:clipFirstRows", "float[] vb:clipFirstRows"),
                     ('token vb:encoding = "crossMatrix"', 'string vb:encoding = "crossMatrix"'),
                     ("int[] primvars:vb:boneIndices", "float[] primvars:vb:boneIndices"),
                     ("float[] primvars:vb:timeOffset", "double[] primvars:vb:timeOffset")):
        assert old in text, old
        text = text.replace(old, new)
    asset.write_text(text, encoding="utf-8")
    found = set(_codes(validate(asset)))
    assert {("prim.attribute.missing", "/VirtualBones/Animation.vb:clipFirstRows"),
            ("prim.attribute.missing", "/VirtualBones/Animation.vb:encoding"),
            ("binding.primvar.missing", "/VirtualBones/Character/Body.primvars:vb:boneIndices"),
            ("instancer.count", "/VirtualBones/Crowd.primvars:vb:timeOffset")} <= found, found


def test_sidecar_and_embedded_copies_are_compared_on_every_schema_key(tmp_path):
    """Readers refuse a sidecar that differs from the embedded copy in any value (spec "Sidecar
    JSON"); a different generator string used to pass. Every key of the metadata schema is
    compared: the copies are compared as whole JSON documents, as the strict reader compares them."""
    from vbusd.io.textures import json_differences

    schema = json.loads((FIXTURES.parents[2] / "vbusd" / "schema" / "layout-metadata.schema.json").read_text(encoding="utf-8"))
    keys = set(schema["properties"])
    differing = json_differences({k: 1 for k in keys}, {k: 2 for k in keys})
    assert {parts[0] for parts in differing} == keys

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    sidecar = asset.parent / "asset.Animation.exr.json"
    meta = json.loads(sidecar.read_text(encoding="utf-8"))
    meta["generator"] = "someone else 2.0"
    sidecar.write_text(json.dumps(meta), encoding="utf-8")
    assert [c for c in _codes(validate(asset)) if c[0] != "texture.padding.fraction"] == [
        ("metadata.sidecarMismatch", "asset.Animation.exr.json#/generator")]


def test_non_finite_playback_rate_is_reported(tmp_path):
    """The instancer.nonFinite fixture breaks a time offset; rates are checked the same way."""
    from pxr import Usd, Vt

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    stage = Usd.Stage.Open(str(asset))
    rate = stage.GetPrimAtPath("/VirtualBones/Crowd").GetAttribute("primvars:vb:playbackRate")
    values = list(rate.Get())
    values[-1] = float("nan")
    rate.Set(Vt.FloatArray(values))
    stage.GetRootLayer().Save()
    report = validate(asset)
    assert ("instancer.nonFinite", "/VirtualBones/Crowd.primvars:vb:playbackRate") in _codes(report)
    assert f"instance {len(values) - 1} with nan" in report.findings[0].message


def test_only_texture_json_is_the_sidecar(tmp_path):
    """The sidecar of F is F.json (spec "Sidecar JSON"), the only file vbusd's reader compares; the
    validator also read F-without-suffix.json and reported its unrelated content as sidecar errors."""
    asset = _copy("valid/crossMatrix_float16", tmp_path)
    (asset.parent / "asset.Animation.exr.json").unlink()  # the metadata embedded in the EXR suffices
    (asset.parent / "asset.Animation.json").write_text('{"generator": "a pipeline note"}', encoding="utf-8")
    assert [c for c in _codes(validate(asset)) if c[0] != "texture.padding.fraction"] == []
    (asset.parent / "asset.Animation.exr.json").write_text('{"generator": 1', encoding="utf-8")
    assert [c[0] for c in _codes(validate(asset))] == ["metadata.json", "texture.padding.fraction"]


# The spec's list ("OpenEXR": NONE, RLE, ZIPS, ZIP, PIZ are allowed), spelled as OpenEXR names them,
# so the test does not share the validator's (vbusd.io.exr's) list.
@pytest.mark.parametrize("compression,allowed", [
    ("NO_COMPRESSION", True), ("RLE_COMPRESSION", True), ("ZIPS_COMPRESSION", True),
    ("ZIP_COMPRESSION", True), ("PIZ_COMPRESSION", True), ("PXR24_COMPRESSION", False),
    ("B44A_COMPRESSION", False), ("DWAB_COMPRESSION", False), ("ZSTD_COMPRESSION", False)])
def test_exr_compressions_the_spec_allows_pass_and_others_are_refused(tmp_path, compression, allowed):
    import OpenEXR

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    texture = asset.parent / "asset.Animation.exr"
    with OpenEXR.File(str(texture)) as source:
        header = dict(source.header())
        channels = {name: channel.pixels.copy() for name, channel in source.channels().items()}
    header["compression"] = getattr(OpenEXR, compression)
    with OpenEXR.File(header, channels) as out:
        out.write(str(texture))
    found = [c for c in _codes(validate(asset)) if c[0] == "texture.compression"]
    assert found == ([] if allowed else [("texture.compression", "asset.Animation.exr")])


def test_outside_paths_are_refused_naming_the_option_that_allows_them(tmp_path):
    """validate takes allow_outside_paths as every reader does (issue 35 item 17): its
    texture.outside and asset.outside messages say so in the caller's words, and with it the
    outside texture and sublayer are read."""
    from pxr import Sdf, Usd

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    absolute = str(asset.parent / "asset.Animation.exr")
    stage = Usd.Stage.Open(str(asset))
    stage.GetPrimAtPath("/VirtualBones/Animation").GetAttribute("vb:texture").Set(Sdf.AssetPath(absolute))
    stage.GetRootLayer().subLayerPaths.append(str(tmp_path / "elsewhere.usda"))
    (tmp_path / "elsewhere.usda").write_text("#usda 1.0\n", encoding="utf-8")
    stage.GetRootLayer().Save()
    report = validate(asset)
    found = {f.code: f.message for f in report.findings}
    assert {"texture.outside", "asset.outside"} <= set(found)
    for code in ("texture.outside", "asset.outside"):
        assert "absolute paths are not allowed" in found[code]
        assert found[code].endswith("(pass allow_outside_paths=True to allow it)"), found[code]
    allowed = {f.code for f in validate(asset, allow_outside_paths=True).findings}
    assert not {"texture.outside", "asset.outside"} & allowed, allowed


def test_a_sidecar_alone_does_not_make_up_for_missing_embedded_metadata(tmp_path):
    """Writers embed the metadata (spec "Conformance"); the sidecar is an optional copy, and
    vbusd's reader refuses a texture without the embedded one even when the sidecar is there. The
    validator used to accept the sidecar in its place."""
    import OpenEXR

    from vbusd.io.textures import read_texture

    asset = _copy("valid/crossMatrix_float16", tmp_path)
    texture = asset.parent / "asset.Animation.exr"
    with OpenEXR.File(str(texture)) as source:
        header = {k: v for k, v in source.header().items() if k != "vbusd.layout"}
        channels = {name: channel.pixels.copy() for name, channel in source.channels().items()}
    with OpenEXR.File(header, channels) as out:
        out.write(str(texture))
    assert (asset.parent / "asset.Animation.exr.json").is_file()
    with pytest.raises(InputError) as refused:  # the reader's verdict, independent of the validator
        read_texture(texture)
    assert refused.value.code == "metadata.missing"
    report = validate(asset)
    assert ("metadata.missing", "asset.Animation.exr") in _codes(report)
    assert report.exit_status == 1


@pytest.mark.parametrize("primvar, values, type_name, code", [
    ("primvars:vb:fadeClip", [0, 5, 0], "int[]", "instancer.clip.range"),
    ("primvars:vb:fadeWeight", [0.0, float("nan"), 1.0], "float[]", "instancer.nonFinite"),
])
def test_crossfade_primvars_are_checked_like_the_first_clips(tmp_path, primvar, values, type_name, code):
    # Format 1.1 crossfade primvars (spec "Crossfade"): the second clip's index in range, its
    # offset, rate and weight finite, as for vb:clip, vb:timeOffset and vb:playbackRate.
    import shutil

    from pxr import Sdf, Usd, UsdGeom

    folder = tmp_path / "crowd"
    shutil.copytree(Path(__file__).parent / "fixtures" / "validate" / "valid" / "crossMatrix_float16", folder)
    stage = Usd.Stage.Open(str(folder / "asset.usda"))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert instancers, "the valid fixture has a crowd"
    count = len(UsdGeom.PointInstancer(instancers[0]).GetPositionsAttr().Get())
    values = (values * count)[:count]
    UsdGeom.PrimvarsAPI(instancers[0]).CreatePrimvar(
        primvar.split(":", 1)[1], Sdf.ValueTypeNames.Find(type_name), UsdGeom.Tokens.vertex).Set(values)
    # A crossfading instancer binds a format 1.1 animation (else instancer.fade.version).
    for target in UsdGeom.PointInstancer(instancers[0]).GetPrim().GetRelationship("vb:animation").GetTargets():
        stage.GetPrimAtPath(target).GetAttribute("vb:formatMinorVersion").Set(1)
    stage.GetRootLayer().Save()
    report = validate(folder / "asset.usda")
    found = [(f.code, f.location.property) for f in report.findings if f.code.startswith("instancer.")]
    assert found == [(code, primvar)]
