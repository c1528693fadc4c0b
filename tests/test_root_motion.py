"""Root motion (spec virtual-bones.md 8.5, format 1.1): clips baked in place plus a root track.

* ``vbusd convert --root-motion extract`` on a UsdSkel rig whose root joint walks forward: the
  decoded in-place pose moved by the root track equals UsdSkel's own skinning of the source at
  every row (the convert report's error, which compares with ``SkinningQuery.ComputeSkinnedPoints``,
  and a check here); the root joint of the in-place clip no longer moves horizontally; the track is
  written to USD (1.1) and read back.
* ``vbusd.root_motion(asset, clip, t0, t1)`` against the spec's worked example by hand (a 1 s loop
  walking 1.5 m/s along +Z), across loops, backwards, and with ``extractYaw`` on a turning walk.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import vbusd
from vbusd.baking.baker import BakeOptions, bake
from vbusd.cli import main
from vbusd.decoders.reference import joint_transforms, skin_mesh
from pxr import Gf, Usd, UsdSkel, Vt  # noqa: E402

HERE = Path(__file__).resolve().parent
from tests.helpers import scenes
from tests.helpers.animations import loop_walk


def _walking_stage(path: Path) -> str:
    """The fixtures' bending column, its root joint walking 0.5 units per time code along +Z and bobbing."""
    rig = scenes.RigSpec(bend=40.0, codes=[1.0, 5.0, 9.0, 13.0, 17.0])
    source = scenes.write_stage(path, [rig])
    stage = Usd.Stage.Open(source)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Root/Skel/Anim"))
    attribute = anim.GetTranslationsAttr()
    for code in attribute.GetTimeSamples():
        values = list(attribute.Get(code))
        values[0] = Gf.Vec3f(0.1 * code, 0.05 * math.sin(code), 0.5 * code)
        attribute.Set(Vt.Vec3fArray(values), code)
    stage.GetRootLayer().Save()
    return source


def test_convert_extract_plays_in_place_and_the_track_gives_back_usdskel(tmp_path, capsys):
    source = _walking_stage(tmp_path / "walk.usda")
    out = tmp_path / "out" / "walk.usda"
    code = main(["convert", source, "-o", str(out), "--texel-format", "float32", "--root-motion", "extract",
                 "--format", "json"])
    assert code == 0, capsys.readouterr().err
    report = __import__("json").loads(capsys.readouterr().out)
    errors = [m["maxError"] for a in report["animations"] for m in a["meshes"]]
    assert errors and max(errors) < 2e-4, errors  # in place + track vs UsdSkel, every row
    assert "vb:clipRootMotion" in out.read_text() and "uniform int vb:formatMinorVersion = 1" in out.read_text()
    asset = vbusd.read_asset(out)
    vb = asset.animations[0]
    assert vb.root_motion is not None and vb.root_motion.up_axis == "Y"
    clip = vb.clips[0]
    taus = np.arange(clip.row_count) / clip.rows_per_second
    # In place: the root joint keeps its start's horizontal position (x, z), its bob (y) stays.
    roots = joint_transforms(vb, 0, taus)[:, 0, :3, 3]
    assert np.abs(roots[:, [0, 2]] - roots[0, [0, 2]]).max() < 1e-5
    assert np.ptp(roots[:, 1]) > 0.05
    # ... and the track holds the walk: 0.5 units along +Z per time code, 24 codes per second.
    step = vbusd.root_motion(asset, 0, taus[0], taus[-1])
    expected_z = 0.5 * (taus[-1] - taus[0]) * 24.0
    np.testing.assert_allclose(step[:3, 3], [0.1 / 0.5 * expected_z, 0.0, expected_z], atol=1e-9)
    # The in-place pose moved by the track equals UsdSkel's points at a row, checked here too.
    stage = Usd.Stage.Open(source)
    query = UsdSkel.Cache().GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Root/Skel")))
    skinning = UsdSkel.Cache()
    skinning.Populate(UsdSkel.Root(stage.GetPrimAtPath("/Root")), Usd.TraverseInstanceProxies())
    target = skinning.GetSkinningQuery(stage.GetPrimAtPath(vb.meshes[0].path))
    row = clip.row_count // 2
    points = Vt.Vec3fArray(stage.GetPrimAtPath(vb.meshes[0].path).GetAttribute("points").Get())
    time = Usd.TimeCode((clip.start_time + taus[row]) * 24.0)
    assert target.ComputeSkinnedPoints(query.ComputeSkinningTransforms(time), points, time)
    inplace, _ = skin_mesh(vb, vb.meshes[0], 0, [taus[row]])
    moved = vbusd.root_motion(asset, 0, 0.0, taus[row])
    np.testing.assert_allclose(inplace[0] @ moved[:3, :3].T + moved[:3, 3], np.array(points), atol=2e-4)


def test_root_motion_is_the_specs_worked_example():
    vb = bake(loop_walk(0.0), BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extract"))
    track = vb.root_motion.tracks[0]
    assert track.shape == (31, 4)  # 30 rows and the loop's end
    np.testing.assert_allclose(track[15], [0, 0, 0.75, 0], atol=1e-12)
    np.testing.assert_allclose(track[30], [0, 0, 1.5, 0], atol=1e-12)
    expected = np.eye(4)
    expected[2, 3] = 3.0
    np.testing.assert_allclose(vbusd.root_motion(vb, "walk", 0.5, 2.5), expected, atol=1e-12)
    expected[2, 3] = -3.0  # backwards in time
    np.testing.assert_allclose(vbusd.root_motion(vb, "walk", 2.5, 0.5), expected, atol=1e-12)


def test_extract_yaw_turns_and_gives_back_the_source():
    animation = loop_walk(0.4)
    vb = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32", root_motion="extractYaw"))
    clip = vb.clips[0]
    source_clip = animation.clips[0]
    for tau in (0.0, 0.3, 0.7, 0.95):
        inplace, _ = skin_mesh(vb, vb.meshes[0], 0, [tau])
        moved = vbusd.root_motion(vb, 0, 0.0, tau)
        source = source_clip.sample([tau])[0, 0]
        expected = vb.meshes[0].points @ source[:3, :3].T + source[:3, 3]
        row = abs(tau * clip.rows_per_second - round(tau * clip.rows_per_second)) < 1e-9
        tolerance = 1e-6 if row else 2e-3  # between rows: the linear blend of the track and the rows
        np.testing.assert_allclose(inplace[0] @ moved[:3, :3].T + moved[:3, 3], expected, atol=tolerance)
    # In place, the root no longer turns: its heading stays that of the first row.
    heading = joint_transforms(vb, 0, np.arange(clip.row_count) / clip.rows_per_second)[:, 0, :3, :3]
    assert np.abs(np.arctan2(heading[:, 0, 2], heading[:, 2, 2])).max() < 1e-6
    turn = vbusd.root_motion(vb, 0, 0.0, 1.0)
    np.testing.assert_allclose(turn[:3, :3], [[math.cos(0.4), 0, math.sin(0.4)], [0, 1, 0],
                                              [-math.sin(0.4), 0, math.cos(0.4)]], atol=1e-9)
