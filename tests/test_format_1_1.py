"""Format 1.1 (spec virtual-bones.md 16.1): what is stored, which version is written, who refuses what.

* A 1.0 asset (the committed stadium sample) reads and decodes unchanged, and written again it
  stays 1.0: no ``formatMinorVersion`` anywhere (writers write the lowest version that holds it).
* A converted asset stores the joints' bind transforms (``vb:bindTransforms``, metadata
  ``bindTransforms``) and is 1.1; sockets read back from the files equal those of the bake.
* A reader that knows only 1.0 refuses a 1.1 asset and names what it does not know: the
  ``bindTransforms`` key, or the crossfade primvars of the instancer that plays the animation.
* The crossfade primvars round-trip through USD, time samples included, and ``vbusd decode``
  honours them: the point cache equals the blend, computed here by hand from single-clip poses,
  of the two clips with the fade weight interpolated between the authored samples.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.format import versioning
from vbusd.format.errors import VersionError
from vbusd.format.model import Crowd
from pxr import Usd, UsdGeom  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
SOURCE = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    assert SOURCE.is_file(), f"the committed sample {SOURCE} is missing"
    out = tmp_path_factory.mktemp("v11") / "stadium.usda"
    vbusd.convert(SOURCE, out, vbusd.ConvertOptions(texel_format="float32", check_rows=0))
    return out


def _sidecar(layer: Path) -> dict:
    (sidecar,) = layer.parent.glob("*.json")
    return json.loads(sidecar.read_text())


def test_a_1_0_asset_reads_decodes_and_writes_back_as_1_0(tmp_path):
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    assert "formatMinorVersion" not in SAMPLE.read_text()
    asset = vbusd.read_asset(SAMPLE)
    vb = asset.animations[0]
    assert vb.bind_transforms is None and not asset.crowds[0].crossfades
    # Decoded unchanged: the sample's crowd (1,200 instances) equals the single-clip formula by hand.
    from vbusd.decoders.reference import skin_crowd, skin_mesh

    crowd = asset.crowds[0]
    world, _ = skin_crowd(vb, vb.meshes[0], crowd, 3.3)
    for i in (0, 599, 1199):
        tau = float(crowd.time_offset[i]) + float(crowd.playback_rate[i]) * 3.3
        local, _ = skin_mesh(vb, vb.meshes[0], int(crowd.clip[i]), [tau])
        x, y, z, w = np.asarray(crowd.orientations[i], np.float64) / np.linalg.norm(crowd.orientations[i])
        rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        scale = np.ones(3) if crowd.scales is None else np.asarray(crowd.scales[i], np.float64)
        expected = (local[0] * scale) @ rotation.T + np.asarray(crowd.positions[i], np.float64)
        np.testing.assert_allclose(world[i], expected, atol=1e-9)
    out = tmp_path / "again.usda"
    vbusd.write_asset(asset, out)
    assert "formatMinorVersion" not in out.read_text()
    assert "formatMinorVersion" not in _sidecar(out) and "bindTransforms" not in _sidecar(out)


def test_converted_asset_is_1_1_with_bind_transforms(converted):
    text = converted.read_text()
    assert "uniform int vb:formatMinorVersion = 1" in text and "vb:bindTransforms" in text
    meta = _sidecar(converted)
    assert meta["formatMinorVersion"] == 1 and len(meta["bindTransforms"]) == meta["boneCount"]
    asset = vbusd.read_asset(converted)
    vb = asset.animations[0]
    assert vb.bind_transforms is not None
    # The metadata copy (column-major, glTF style) and the USD copy (row-vector Gf.Matrix4d) agree.
    np.testing.assert_array_equal(np.array(meta["bindTransforms"]).reshape(-1, 4, 4).transpose(0, 2, 1),
                                  vb.bind_transforms)
    hand = vbusd.bone_transform(converted, "R_hand", 0, 2.5)
    assert hand.shape == (4, 4) and np.allclose(hand[3], [0, 0, 0, 1])


def test_a_1_0_reader_refuses_bind_transforms_by_name(converted, monkeypatch):
    meta = _sidecar(converted)
    with pytest.raises(VersionError, match=r"format version 1\.1 is newer than this reader \(version 1\.0\); "
                                           r"it uses bindTransforms"):
        versioning.upgrade(meta, current=(1, 0))
    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 0))
    with pytest.raises(VersionError, match="bindTransforms"):
        vbusd.read_asset(converted)


def _fading_asset(tmp_path):
    asset = vbusd.read_asset(SAMPLE)
    vb = dataclasses.replace(asset.animations[0], clips=asset.animations[0].clips)
    n = 4
    crowd = Crowd("/StadiumCrowd/Fading", positions=np.array([[0, 0, 0], [2, 0, 0], [4, 0, 0], [6, 0, 0]], np.float32),
                  orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), clip=np.zeros(n, np.int32),
                  time_offset=np.array([0.0, 1.0, 2.0, 3.0], np.float32), playback_rate=np.ones(n, np.float32),
                  fade_clip=np.zeros(n, np.int32), fade_time_offset=np.array([5.0, 6.0, 7.0, 8.0], np.float32),
                  fade_playback_rate=np.full(n, 0.5, np.float32), fade_weight=np.zeros(n, np.float32),
                  fade_samples={"fade_weight": (np.array([0.5, 1.5]),
                                                np.array([[0, 0, 0.2, 1], [1, 0.5, 0.2, 0]], np.float32))})
    fading = dataclasses.replace(asset, animations=(vb,), crowds=(crowd,), crowd_animation=(0,))
    path = tmp_path / "fading.usda"
    vbusd.write_asset(fading, path)
    return path, crowd


def test_a_1_0_reader_refuses_a_crossfading_crowd_by_name(tmp_path, monkeypatch):
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    path, _ = _fading_asset(tmp_path)
    assert "uniform int vb:formatMinorVersion = 1" in path.read_text()
    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 0))
    with pytest.raises(VersionError, match=r"newer than this reader \(version 1\.0\).*primvars:vb:fadeWeight"):
        vbusd.read_asset(path)


@pytest.mark.slow
def test_crossfade_primvars_round_trip_and_decode_honours_them(tmp_path):
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    from vbusd.jobs.pointcache import decode
    from vbusd.decoders.reference import skin_mesh

    path, authored = _fading_asset(tmp_path)
    back = vbusd.read_asset(path).crowds[0]
    times, weights = back.fade_samples["fade_weight"]
    np.testing.assert_array_equal(times, [0.5, 1.5])
    np.testing.assert_array_equal(weights, authored.fade_samples["fade_weight"][1])
    np.testing.assert_array_equal(back.fade_time_offset, authored.fade_time_offset)
    cache = tmp_path / "cache.usda"
    decode(path, cache, crowds=True)
    stage = Usd.Stage.Open(str(cache))
    vb = vbusd.read_asset(path).animations[0]
    mesh = vb.meshes[0]
    tcps = stage.GetTimeCodesPerSecond()
    cache_mesh = next(p for p in stage.Traverse() if str(p.GetPath()).startswith("/StadiumCrowd/Fading/"))
    points_attr = UsdGeom.Mesh(cache_mesh).GetPointsAttr()
    codes = [c for c in points_attr.GetTimeSamples() if 0.2 <= c / tcps <= 1.8][::7]
    assert codes
    for code in codes:
        t = code / tcps
        got = np.array(points_attr.Get(code), dtype=np.float64).reshape(4, -1, 3)
        for i in range(4):
            w = np.interp(t, [0.5, 1.5], authored.fade_samples["fade_weight"][1][:, i].astype(np.float64))
            a, _ = skin_mesh(vb, mesh, 0, [float(authored.time_offset[i]) + t])
            b, _ = skin_mesh(vb, mesh, 0, [float(authored.fade_time_offset[i]) + 0.5 * t])
            expected = (1 - w) * a[0] + w * b[0] + authored.positions[i]
            np.testing.assert_allclose(got[i], expected, atol=2e-5, err_msg=f"instance {i} at t = {t}")
