"""Crossfades, layers and their time samples in the glTF runtime package (spec/runtime-package.md 5.1).

A crowd made by ``vbusd crowd --fade-clips ... --fade-window ... --layer ...`` is exported with
``vbusd export``; what the package holds is compared with the instancer's primvars as USD itself
reads them (pxr, :func:`tests.helpers.crowds.primvars`, not vbusd's reader): every ``_VB_FADE_*``
and ``_VB_LAYER_*_j`` value bit for bit in float32, the time-sampled fade weight as the node's
samples. The Khronos glTF-Validator reports no error on it, and ``vbusd validate`` refuses a
package whose crossfade or layers are broken, naming the place.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.cli import main
from vbusd.format.diagnostics import Diagnostics
from vbusd.io.package_reader import read_package

from tests.helpers.crowds import chain_character, primvars
from tests.helpers import node as node_tools
from tests.helpers.capabilities import REPO
from tests.helpers.node import gltf_check

FADES = ("_VB_FADE_CLIP", "_VB_FADE_TIME_OFFSET", "_VB_FADE_PLAYBACK_RATE", "_VB_FADE_WEIGHT")
LAYERS = {"layerClip": "_VB_LAYER_CLIP", "layerTimeOffset": "_VB_LAYER_TIME_OFFSET",
          "layerPlaybackRate": "_VB_LAYER_PLAYBACK_RATE", "layerWeight": "_VB_LAYER_WEIGHT",
          "layerMask": "_VB_LAYER_MASK"}


def make_crowd(folder: Path, *window) -> Path:
    """12 instances of the chain character walking, fading into run or wave (over ``window`` when
    given, else with a constant weight), two layers over the masks ``upper`` and ``tip``."""
    character = chain_character(folder, masks=(("upper", "b1"), ("tip", "b2")))
    out = folder / "crowd.usda"
    fade = ["--fade-window", *window] if window else ["--fade-weight", "0.1", "0.9"]
    assert main(["crowd", str(character), "-o", str(out), "--count", "12", "--seed", "5", "--clips", "walk",
                 "--fade-clips", "run:2,wave", *fade, "--layer", "upper", "wave", "--layer", "tip", "run,wave",
                 "--layer-weight", "0.25", "0.75", "--layer-rate", "1", "1.5"]) == 0
    return out


@pytest.fixture(scope="module")
def crowds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("blending")
    return {"constant": make_crowd(folder / "constant"), "window": make_crowd(folder / "window", "0.5", "1.5")}


def read(path: Path):
    return read_package(path, Diagnostics(str(path), strict=True))


@pytest.mark.parametrize("kind", ["constant", "window"])
@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_fades_and_layers_travel_in_the_package(crowds, tmp_path, capsys, kind, suffix):
    source = crowds[kind]
    out = tmp_path / f"crowd{suffix}"
    assert main(["export", str(source), "-o", str(out)]) == 0, capsys.readouterr().err
    usd = primvars(source)
    (crowd,) = read(out).crowds
    assert crowd.fades and crowd.layers == 2
    # Constant primvars: the values USD reads; a time-sampled one: its first sample.
    for name, key in zip(FADES, ("fadeClip", "fadeTimeOffset", "fadePlaybackRate", "fadeWeight")):
        expected = usd[key + ".samples"][min(usd[key + ".samples"])] if key + ".samples" in usd else usd[key]
        np.testing.assert_array_equal(crowd.playback[name], np.float32(expected), err_msg=name)
    for key, stem in LAYERS.items():
        for j in range(2):
            np.testing.assert_array_equal(crowd.playback[f"{stem}_{j}"], np.float32(usd[key][:, j]), err_msg=stem)
    assert usd["layerWeight"].shape == (12, 2) and np.all(usd["layerWeight"] > 0)
    if kind == "window":
        times, values = crowd.samples["_VB_FADE_WEIGHT"]
        expected = usd["fadeWeight.samples"]
        np.testing.assert_array_equal(times, sorted(expected))
        np.testing.assert_array_equal(values, np.float32([expected[t] for t in sorted(expected)]))
        assert list(times) == [0.5, 1.5] and np.all(values[0] == 0) and np.all(values[1] == 1)
    else:
        assert crowd.samples == {}
    assert vbusd.validate(out).valid


@pytest.mark.node
def test_the_glTF_validator_reports_no_error_on_a_fading_layered_crowd(crowds, tmp_path):
    for kind, source in crowds.items():
        out = tmp_path / f"{kind}.glb"
        assert main(["export", str(source), "-o", str(out)]) == 0
        result = gltf_check(out)  # fails on any validator error or warning
        assert result["validator"]["issues"]["numErrors"] == 0


def damaged(crowds, tmp_path, damage) -> Path:
    out = tmp_path / "crowd.gltf"
    assert main(["export", str(crowds["window"]), "-o", str(out)]) == 0
    gltf = json.loads(out.read_text(encoding="utf-8"))
    node = next(n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    damage(gltf, node)
    out.write_text(json.dumps(gltf), encoding="utf-8")
    return out


def _drop_fade_clip(gltf, node):
    del node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["_VB_FADE_CLIP"]


def _drop_layer_mask(gltf, node):
    del node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["_VB_LAYER_MASK_1"]


def _mask_as_clip(gltf, node):
    # Layer 1's mask reads layer 0's clip column: every value is 2 (wave), and there are two masks.
    attributes = node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    attributes["_VB_LAYER_MASK_1"] = attributes["_VB_LAYER_CLIP_0"]


def _times_backwards(gltf, node):
    node["extensions"]["VBUSD_virtual_bones"]["samples"]["_VB_FADE_WEIGHT"]["times"] = [1.5, 0.5]


def _samples_of_nothing(gltf, node):
    samples = node["extensions"]["VBUSD_virtual_bones"]["samples"]
    samples["_VB_LAYER_WEIGHT_7"] = samples["_VB_FADE_WEIGHT"]


def _short_samples(gltf, node):
    samples = node["extensions"]["VBUSD_virtual_bones"]["samples"]
    samples["_VB_FADE_WEIGHT"]["times"] = [0.5, 1.0, 1.5]


def _not_a_sample_name(gltf, node):
    samples = node["extensions"]["VBUSD_virtual_bones"]["samples"]
    samples["_VB_CLIP"] = samples.pop("_VB_FADE_WEIGHT")


@pytest.mark.parametrize("damage, code, pointer", [
    (_drop_fade_clip, "package.instances", "/EXT_mesh_gpu_instancing/attributes"),
    (_drop_layer_mask, "package.instances", "/EXT_mesh_gpu_instancing/attributes"),
    (_mask_as_clip, "package.instances", "/attributes/_VB_LAYER_MASK_1"),
    (_times_backwards, "package.instances", "/samples/_VB_FADE_WEIGHT/times"),
    (_samples_of_nothing, "package.instances", "/samples/_VB_LAYER_WEIGHT_7"),
    (_short_samples, "package.instances", "/samples/_VB_FADE_WEIGHT/values"),
    (_not_a_sample_name, "package.extension", "/extensions/VBUSD_virtual_bones/samples"),
])
def test_a_broken_crossfade_or_layer_is_a_finding_and_view_refuses_it(crowds, tmp_path, capsys, damage, code,
                                                                      pointer):
    out = damaged(crowds, tmp_path, damage)
    report = vbusd.validate(out)
    assert not report.valid
    found = [f for f in report.findings if f.code == code]
    assert found, report.findings
    assert any(pointer in str(f.location) for f in found), found
    # Strict readers (vbusd info, vbusd view): one line, exit 2.
    assert main(["info", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f": {code}: " in err[0], err


@pytest.mark.node
def test_fades_layers_and_time_samples_survive_gltf_transform(crowds, tmp_path, capsys):
    """glTF-Transform with the VBUSD_virtual_bones extension (web/gltf-transform: dedup, prune,
    flatten, weld renumber accessors and nodes) keeps every _VB_FADE_ / _VB_LAYER_ attribute and
    the node's time samples: the rewritten package reads as the primvars do."""
    node = node_tools.require_packages("@gltf-transform/core", "@gltf-transform/functions", folder="web/gltf-transform")
    source = tmp_path / "crowd.glb"
    assert main(["export", str(crowds["window"]), "-o", str(source)]) == 0, capsys.readouterr().err
    out = tmp_path / "transformed.glb"
    result = subprocess.run([node, "test/transform_file.mjs", str(source), str(out)], cwd=REPO / "web" / "gltf-transform",
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    (before,), (after,) = read(source).crowds, read(out).crowds
    assert sorted(after.playback) == sorted(before.playback) and after.layers == 2
    for name, values in before.playback.items():
        np.testing.assert_array_equal(after.playback[name], values, err_msg=name)
    usd = primvars(crowds["window"])["fadeWeight.samples"]
    times, values = after.samples["_VB_FADE_WEIGHT"]
    np.testing.assert_array_equal(times, sorted(usd))
    np.testing.assert_array_equal(values, np.float32([usd[t] for t in sorted(usd)]))
    assert vbusd.validate(out).valid
