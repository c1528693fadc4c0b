"""Additive layers and blend spaces per instance in the glTF runtime package (format 1.3,
spec/runtime-package.md 5.1): ``vbusd export`` of the chain crowd of tests/helpers/crowds.py (override
and additive layers, one instance playing a synced 1D blend space) writes ``_VB_LAYER_MODE_j``,
``_VB_LAYER_REFERENCE_CLIP_j``, ``_VB_LAYER_REFERENCE_TIME_j`` and ``_VB_BLEND_*`` equal, bit for bit
in float32, to the instancer's primvars as USD itself reads them (pxr); the Khronos glTF-Validator
reports no error on it; ``vbusd validate`` reads it clean and refuses a broken one at its place. The
engines' glTF loaders draw it: tests/test_browser_parity.py::test_additive_layers."""

from __future__ import annotations

import json

import numpy as np
import pytest

import vbusd
from vbusd.cli import main

from tests.helpers.crowds import additive_chain
from tests.helpers.node import gltf_check


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("motion")
    source = additive_chain(folder, blends=True)
    out = folder / "crowd.gltf"
    assert main(["export", str(source), "-o", str(out)]) == 0
    return source, out


def _instance_attributes(out):
    gltf = json.loads(out.read_text(encoding="utf-8"))
    node = next(n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    binary = out.with_suffix(".bin").read_bytes()
    values = {}
    for name, index in node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"].items():
        accessor = gltf["accessors"][index]
        view = gltf["bufferViews"][accessor["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor["type"]]
        values[name] = np.frombuffer(binary, np.float32, accessor["count"] * width,
                                     view.get("byteOffset", 0) + accessor.get("byteOffset", 0))
    return gltf, values


def test_the_package_carries_additive_layers_and_blends_as_the_primvars(exported):
    from pxr import Usd

    source, out = exported
    stage = Usd.Stage.Open(str(source))
    prim = stage.GetPrimAtPath("/Chain/Crowd")
    read = lambda name: np.asarray(prim.GetAttribute(f"primvars:vb:{name}").Get(), np.float32)  # noqa: E731
    _, values = _instance_attributes(out)
    for stem, name in (("_VB_LAYER_MODE", "layerMode"), ("_VB_LAYER_REFERENCE_CLIP", "layerReferenceClip"),
                       ("_VB_LAYER_REFERENCE_TIME", "layerReferenceTime")):
        primvar = read(name).reshape(-1, 2)
        for j in range(2):
            np.testing.assert_array_equal(values[f"{stem}_{j}"], primvar[:, j])
    for stem, name in (("_VB_BLEND_SPACE", "blendSpace"), ("_VB_BLEND_X", "blendX"), ("_VB_BLEND_Y", "blendY"),
                       ("_VB_BLEND_PHASE", "blendPhase")):
        np.testing.assert_array_equal(values[stem], read(name))
    assert values["_VB_LAYER_MODE_0"].tolist() == [1, 1, 0, 1]
    report = vbusd.validate(out)
    assert report.valid, [(f.code, str(f.location)) for f in report.findings]


@pytest.mark.node
def test_the_glTF_validator_reports_no_error_on_additive_layers_and_blends(exported, tmp_path):
    source, _ = exported
    out = tmp_path / "crowd.glb"
    assert main(["export", str(source), "-o", str(out)]) == 0
    result = gltf_check(out)  # fails on any validator error or warning
    assert result["validator"]["issues"]["numErrors"] == 0


@pytest.mark.parametrize("damage, expected", [
    (lambda attributes: attributes.pop("_VB_LAYER_REFERENCE_TIME_1"), "additive layers carry all of"),
    (lambda attributes: attributes.pop("_VB_BLEND_Y"), "blends need all of"),
])
def test_a_broken_package_is_refused_at_the_crowd(exported, tmp_path, damage, expected):
    _, out = exported
    gltf = json.loads(out.read_text(encoding="utf-8"))
    n, node = next((i, n) for i, n in enumerate(gltf["nodes"]) if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    damage(node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"])
    broken = out.parent / "broken.gltf"
    broken.write_text(json.dumps(gltf), encoding="utf-8")
    report = vbusd.validate(broken)
    found = [f for f in report.findings if f.code == "package.instances"]
    assert found and expected in found[0].message, [(f.code, f.message) for f in report.findings]
    assert str(found[0].location).endswith(f"/nodes/{n}/extensions/EXT_mesh_gpu_instancing/attributes")


def test_a_bad_layer_mode_or_blend_space_value_is_refused(exported, tmp_path):
    _, out = exported
    gltf, values = _instance_attributes(out)
    binary = bytearray(out.with_suffix(".bin").read_bytes())
    node = next(n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    attributes = node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    for name, bad in (("_VB_LAYER_MODE_0", 2.0), ("_VB_BLEND_SPACE", 5.0)):
        accessor = gltf["accessors"][attributes[name]]
        offset = gltf["bufferViews"][accessor["bufferView"]].get("byteOffset", 0) + accessor.get("byteOffset", 0)
        damaged = bytearray(binary)
        damaged[offset:offset + 4] = np.float32(bad).tobytes()
        (tmp_path / "crowd.bin").write_bytes(damaged)
        (tmp_path / "crowd.gltf").write_text(json.dumps(gltf), encoding="utf-8")
        for texture in out.parent.glob("crowd.*.ktx2"):
            (tmp_path / texture.name).write_bytes(texture.read_bytes())
        report = vbusd.validate(tmp_path / "crowd.gltf")
        found = [f for f in report.findings if f.code == "package.instances"]
        assert found and name in found[0].message, (name, [(f.code, f.message) for f in report.findings])
