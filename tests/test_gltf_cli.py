"""End to end: `vbusd convert` on the hand-built bar (.glb), read back, decode, compare with the
hand-computed points of tests/test_gltf_reader.py; a bad file gives one line and no output. The
command runs in this process (tests.helpers.cli: its output captured at the file descriptors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
BEND_1 = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 1.5, 0], [-1, 1, 0], [-1, 2, 0]]
CUBIC_HALF = [[0, 0, 0], [1, 0, 0], [0.578125, 1, 0], [1.578125, 1, 0], [1.15625, 2, 0],
              [2.15625, 2, 0]]

from tests.helpers import cli



@pytest.mark.slow
def test_convert_glb_round_trip(tmp_path, capfd):
    from vbusd.decoders.reference import skin_mesh
    from vbusd.io.usd import read_asset

    out = tmp_path / "bar.usda"
    result = cli.run(capfd, "convert", str(FIXTURES / "bar.glb"), "-o", str(out), "--texel-format",
                    "float32", "--encoding", "affineMatrix", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "not identity" in result.stderr          # the ignored skinned-node transform is reported
    asset = read_asset(out)
    assert (asset.up_axis, asset.meters_per_unit, asset.time_codes_per_second) == ("Y", 1.0, 24.0)
    assert asset.default_prim == "BarScene"
    (vb,) = asset.animations
    assert vb.path == "/BarScene/Bar_Anim" and tuple(vb.bones) == ("Bone0", "Bone1")
    names = [c.name for c in vb.clips]
    assert names == ["Bend", "Slide", "Step", "Cubic", "Grow"]
    (mesh,) = vb.meshes
    assert mesh.path == "/BarScene/Bar"
    # Clip-local times that fall on rows (30 rows/s): Bend t=1 is row 30, Cubic t=0.5 row 15.
    points, _ = skin_mesh(vb, mesh, names.index("Bend"), np.array([1.0]))
    np.testing.assert_allclose(points[0], BEND_1, atol=1e-5)
    points, _ = skin_mesh(vb, mesh, names.index("Cubic"), np.array([0.5]))
    np.testing.assert_allclose(points[0], CUBIC_HALF, atol=1e-5)
    # The written asset passes vbusd's own validator (another helper's command) with no errors.
    assert cli.run(capfd, "validate", out).returncode == 0


@pytest.mark.slow
def test_convert_bad_glb_one_line_no_output(tmp_path, capfd):
    out = tmp_path / "out.usda"
    result = cli.run(capfd, "convert", str(FIXTURES / "bad" / "glb_truncated.glb"), "-o", str(out),
                    cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "byte 8: gltf.glb:" in lines[0]
    assert "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_merged_joint_sets_report_the_added_error(tmp_path, capsys):
    """JOINTS_0/JOINTS_1 merged (8 influences), one kept: the summary reports the added error.

    Worked by hand on bar_joints2 (vertices 2 and 3 are half Bone0 in set 0, half Bone1 in set 1):
    keeping either bone alone, clip Cubic moves Bone1's points by x(t) in x while the blend moves
    them by x(t)/2, so the error is x/2, largest after the last key (x = 2): 1.0. Bend adds at most
    |(cos a - 1, sin a)| / 2 = sqrt(2)/2 at 90 degrees; Slide and Grow move both bones alike.
    """
    import json

    from vbusd import cli

    out = tmp_path / "j2.usda"
    status = cli.main(["convert", str(FIXTURES / "bar_joints2.gltf"), "-o", str(out),
                       "--max-influences", "1", "--texel-format", "float32", "--format", "json"])
    assert status == 0
    report = json.loads(capsys.readouterr().out)
    (mesh,) = report["animations"][0]["meshes"]
    assert (mesh["sourceInfluences"], mesh["keptInfluences"]) == (8, 1)
    assert mesh["influenceError"] == pytest.approx(1.0, abs=1e-6)
