"""Props at sockets (spec virtual-bones.md 22.3, "Props at sockets"), without a browser.

The stadium spectator's ``Flag`` (samples/stadium_crowd.py) is a part bound rigidly to ``R_hand``,
its rest points the flag's joint-space points placed at the joint's bind transform. The numpy
reference decoder skins it (``skin_crowd``: rest points through the decoded skinning transform and
the instance placement), and the socket (``crowd_joint_transforms``: the instance placement times
``M B``) applied to the flag's joint-space points, as the sample writes them (not as vbusd stores
them), must give the same points within 1e-6 of the instance's bounding-box diagonal: in every
encoding, at a row time, between rows, past the loop and through a crossfade. The parts mask of a
``vbusd crowd --parts Flag=P`` crowd shows it on the instances whose bit is set.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vbusd.decoders.reference import crowd_joint_transforms, skin_crowd
from vbusd.format.model import Crowd

from tests.helpers import scripts
from tests.helpers.capabilities import require

TIMES = (0.0, 1.2345, 9.0, 12.05)  # a row time, between rows, the cheer, past the 10 s loop
TOLERANCE = 1e-6  # of the instance's bounding-box diagonal


def _sample():
    return scripts.load("samples/stadium_crowd.py")


def _crowd(n: int = 4) -> Crowd:
    """Instances turned, spread and scaled, at different offsets and rates, half crossfading into
    the cheer at another offset (one clip: the fade is within it, weights 0 to 0.9)."""
    angles = np.linspace(0.0, 2.5, n)
    orientations = np.stack([np.zeros(n), np.sin(angles / 2), np.zeros(n), np.cos(angles / 2)], axis=1)
    return Crowd(path="/Crowd", positions=np.stack([np.linspace(-30, 40, n), np.zeros(n), np.linspace(5, -70, n)], axis=1).astype(np.float32),
                 orientations=orientations.astype(np.float32), scales=np.tile(np.linspace(0.8, 1.3, n)[:, None], (1, 3)).astype(np.float32),
                 clip=np.zeros(n, np.int32), time_offset=np.linspace(0, 3.3, n).astype(np.float32),
                 playback_rate=np.linspace(0.7, 1.4, n).astype(np.float32), fade_clip=np.zeros(n, np.int32),
                 fade_time_offset=np.linspace(2.0, 0.5, n).astype(np.float32), fade_playback_rate=np.ones(n, np.float32),
                 fade_weight=np.linspace(0.0, 0.9, n).astype(np.float32))


@pytest.mark.parametrize("encoding, texel_format", [("crossMatrix", "float16"), ("affineMatrix", "float32"),
                                                     ("quatTranslation", "float16"), ("dualQuat", "float32"),
                                                     ("compactQuatTranslation", "uint32")])
def test_flag_skins_to_the_socket(encoding, texel_format):
    from vbusd.baking.baker import bake

    sample = _sample()
    animation = sample.make_skinned_animation()
    animation = dataclasses.replace(animation, meshes=animation.meshes + (sample.flag_mesh(),),
                                    bind_transforms=sample.bind_matrices())
    vb = bake(animation, sample.reference_bake_options(encoding=encoding, texel_format=texel_format))
    body, flag = vb.meshes[0], [m for m in vb.meshes if m.path.endswith("/Flag")][0]
    bone = sample.JOINT_NAMES.index(sample.FLAG_BONE)
    assert np.all(flag.bone_indices == bone) and np.all(flag.bone_weights == 1)
    local, _, _ = sample.flag_local()
    crowd = _crowd()
    for t in TIMES:
        drawn, _ = skin_crowd(vb, flag, crowd, t)
        bodies, _ = skin_crowd(vb, body, crowd, t)
        sockets = crowd_joint_transforms(vb, crowd, bone, t)
        expected = np.einsum("nij,vj->nvi", sockets[:, :3, :3], local) + sockets[:, None, :3, 3]
        for i in range(crowd.instance_count):
            diagonal = float(np.linalg.norm(bodies[i].max(0) - bodies[i].min(0)))
            error = float(np.abs(drawn[i] - expected[i]).max()) / diagonal
            assert error <= TOLERANCE, (encoding, t, i, error)
    # The flag moves with the hand (the check above is not about a pose that stays put).
    assert np.abs(skin_crowd(vb, flag, crowd, 9.0)[0] - skin_crowd(vb, flag, crowd, 0.0)[0]).max() > 0.05


def test_flag_rest_points_by_hand():
    """The spec's example: R_hand's bind transform is T(-0.71, 1.48, 0), so the pole's foot
    (-0.08, -0.05, 0) in the joint's space rests at (-0.79, 1.43, 0); the normals keep their direction
    (a translation turns nothing)."""
    from vbusd.format.variety import socket_prop

    sample = _sample()
    bind = sample.bind_matrices()[sample.JOINT_NAMES.index(sample.FLAG_BONE)]
    points, normals = socket_prop(bind, [(-0.08, -0.05, 0.0)], [(0.0, 0.0, 2.0)])
    np.testing.assert_allclose(points, [(-0.79, 1.43, 0.0)], atol=1e-12)
    np.testing.assert_allclose(normals, [(0.0, 0.0, 1.0)], atol=1e-12)
    # A turned joint: 90 degrees about Z takes the local X axis to +Y, its normal too.
    turned = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    points, normals = socket_prop(turned, [(0.5, 0.0, 0.0)], [(1.0, 0.0, 0.0)])
    np.testing.assert_allclose(points, [(1.0, 2.5, 3.0)], atol=1e-12)
    np.testing.assert_allclose(normals, [(0.0, 1.0, 0.0)], atol=1e-12)


def test_crowd_parts_mask_shows_the_flag(tmp_path):
    """``vbusd crowd --parts Hat=0.4,Flag=0.5``: the instancer names both parts and each mask's bit 1 is the flag."""
    import vbusd
    from pxr import Usd, UsdGeom

    from tests.helpers.variety import varied_crowd

    path = varied_crowd(tmp_path, count=200, parts={"Hat": 0.4, "Flag": 0.5})
    stage = Usd.Stage.Open(str(path))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert list(prim.GetAttribute("vb:partNames").Get()) == ["Hat", "Flag"]
    masks = np.asarray(UsdGeom.PrimvarsAPI(prim).GetPrimvar("vb:parts").Get())
    shown = (masks >> 1) & 1
    assert 0.3 < shown.mean() < 0.7 and set(masks) <= {0, 1, 2, 3}
    asset = vbusd.read_asset(path)
    flags = [m for m in asset.animations[0].meshes if m.path.endswith("/Flag")]
    assert len(flags) == 1 and asset.animations[0].bind_transforms is not None


def test_parts_of_a_character_with_levels(tmp_path, capfd):
    """Parts and levels of detail (spec 22.3): the modular spectator with generated levels keeps its
    parts' names below every level prim; ``vbusd crowd --parts Hat=...,Flag=...`` names them, the USD
    crowd reads back and validates clean (pxr sees the names under the levels), and a name that no level
    holds is still refused in one line."""
    require("lod")
    import vbusd
    from pxr import Usd
    from vbusd.baking.lod import add_levels

    from tests.helpers import cli
    from tests.helpers.variety import modular_character

    asset = vbusd.read_asset(modular_character(tmp_path))
    character = tmp_path / "lod" / "spectator.usda"
    vbusd.write_asset(dataclasses.replace(asset, animations=(add_levels(asset.animations[0], (0.5, 0.2)),)), character)
    stage = Usd.Stage.Open(str(character))
    for level in ("lod0", "lod1", "lod2"):  # each level holds its own Hat and Flag meshes
        assert {p.GetName() for p in stage.GetPrimAtPath(f"/StadiumCrowd/Cheer_lods/{level}").GetChildren()} == {"Body", "Hat", "Flag"}
    crowd = tmp_path / "crowd.usda"
    result = cli.run(capfd, "crowd", character, "-o", crowd, "--count", "30", "--parts", "Hat=0.5,Flag=0.5", "--seed", "3", "-q")
    assert result.returncode == 0, result.stderr
    read = vbusd.read_asset(crowd)
    assert read.crowds[0].part_names == ("Hat", "Flag") and set(read.crowds[0].parts) == {0, 1, 2, 3}
    result = cli.run(capfd, "validate", crowd)
    assert result.returncode == 0, result.stdout + result.stderr
    result = cli.run(capfd, "crowd", character, "-o", tmp_path / "bad.usda", "--count", "3", "--parts", "Cape=0.5", "-q")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1 and "Cape" in result.stderr


def test_usdskel_fallback_hides_parts_at_every_level(tmp_path):
    """The UsdSkel fallback of a crowd with levels of detail and parts masks (spec runtime-package 11.6,
    virtual-bones 22.3): pxr's own ComputeVisibility of each instance's part meshes, at every level, is
    invisible exactly where the instance's mask leaves the part out; bodies stay visible."""
    require("lod")
    import vbusd
    from pxr import Usd, UsdGeom
    from vbusd.jobs.export_usdskel import export_usdskel

    from tests.helpers import lod_row

    asset, _ = lod_row.make_row_package(tmp_path, modular=True)
    source = tmp_path / "usd" / "row.usda"
    vbusd.write_asset(asset, source)
    out = tmp_path / "fallback.usda"
    export_usdskel(vbusd.read_asset(source), out, source=source)
    stage = Usd.Stage.Open(str(out))
    masks = lod_row.PARTS
    checked = 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh) or "/Row/" not in str(prim.GetPath()):
            continue
        instance = int(str(prim.GetPath()).split("/Row/i")[1].split("/")[0])
        part = prim.GetName().split("_")[0]  # Hat, Hat_2, Hat_3: the part at levels 0, 1, 2
        visible = UsdGeom.Imageable(prim).ComputeVisibility() != UsdGeom.Tokens.invisible
        bit = {"Hat": 0, "Flag": 1}.get(part)
        assert visible == (bit is None or bool(masks[instance] >> bit & 1)), (prim.GetPath(), masks[instance])
        checked += 1
    assert checked == len(masks) * 9  # body, hat and flag at three levels, for every instance
