"""``vbusd crowd`` / ``vbusd.build_crowd``: placement, clip weights, crossfades and layers,
determinism and bad input, read back through USD itself (pxr) and vbusd's reader, and validated
clean. A crossfading, layered crowd plays, instance by instance, what ``vbusd.skin`` gives for the
parameters USD reads from its primvars, given by hand."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest


from vbusd.cli import main  # noqa: E402
from vbusd.jobs.crowd import CrowdOptions, build_crowd, disc_positions, grid_positions  # noqa: E402

import vbusd  # noqa: E402
from tests.helpers.crowds import by_hand, chain_character, primvars  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd"


@pytest.fixture()
def character(tmp_path) -> Path:
    for f in SAMPLE.glob("stadium_crowd_vb*"):
        shutil.copy(f, tmp_path / f.name)
    return tmp_path / "stadium_crowd_vb.usda"


def _first_clip(character: Path) -> str:
    import vbusd

    return vbusd.read_asset(character).animations[0].clips[0].name


def test_grid_and_discby_hand():
    grid = grid_positions(5, 2.0, "Y")  # 3 columns, 2 rows, pitch 2, centred
    assert grid.tolist() == [[-2, 0, -1], [0, 0, -1], [2, 0, -1], [-2, 0, 1], [0, 0, 1]]
    disc = disc_positions(1000, 1.0, "Z")
    assert np.all(disc[:, 2] == 0)
    # Even density: the disc of 1000 instances 1 apart on average has area ~1000 (radius sqrt(1000/pi)).
    assert abs(np.max(np.linalg.norm(disc[:, :2], axis=1)) - np.sqrt(1000 / np.pi)) < 0.05


def test_crowd_reads_back_with_usd_and_vbusd_and_validates(character, tmp_path):
    from pxr import Usd, UsdGeom

    import vbusd

    out = tmp_path / "crowd.usda"
    report = build_crowd([character], out, CrowdOptions(layout="disc", count=500, playback_rate=(0.5, 2.0), seed=4))
    assert report.instances == [500]
    stage = Usd.Stage.Open(str(out))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert len(instancers) == 1
    instancer = UsdGeom.PointInstancer(instancers[0])
    assert len(instancer.GetPositionsAttr().Get()) == 500
    # USD composes the prototype from the character file: its mesh has the character's 202 points.
    xforms = instancer.ComputeInstanceTransformsAtTime(0, 0)
    assert len(xforms) == 500
    prototype = stage.GetPrimAtPath(instancer.GetPrototypesRel().GetTargets()[0])
    meshes = [p for p in Usd.PrimRange(prototype) if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1 and len(UsdGeom.Mesh(meshes[0]).GetPointsAttr().Get()) == 202
    asset = vbusd.read_asset(out)
    crowd = asset.crowds[0]
    assert crowd.instance_count == 500
    assert np.all((crowd.playback_rate >= 0.5) & (crowd.playback_rate <= 2.0))
    clip = asset.animations[asset.crowd_animation[0]].clips[0]
    assert np.all((crowd.time_offset >= 0) & (crowd.time_offset <= clip.row_count / clip.rows_per_second + 1e-3))
    assert vbusd.validate(out).valid


def test_same_seed_same_bytes_other_seed_other_bytes(character, tmp_path):
    options = CrowdOptions(layout="grid", count=300, seed=11)
    build_crowd([character], tmp_path / "a.usda", options)
    build_crowd([character], tmp_path / "b.usda", options)
    build_crowd([character], tmp_path / "c.usda", CrowdOptions(layout="grid", count=300, seed=12))
    assert (tmp_path / "a.usda").read_bytes() == (tmp_path / "b.usda").read_bytes()
    assert (tmp_path / "a.usda").read_bytes() != (tmp_path / "c.usda").read_bytes()


def test_points_layout_from_csv_and_clip_weights(character, tmp_path, capsys):
    points = tmp_path / "seats.csv"
    points.write_text("x,y,z\n" + "\n".join(f"{i},0,{-i}" for i in range(40)) + "\n")
    status = main(["crowd", str(character), "-o", str(tmp_path / "seats.usda"), "--layout", "points",
                   "--points", str(points), "--clips", f"{_first_clip(character)}:1", "--format", "json"])
    assert status == 0
    import json

    report = json.loads(capsys.readouterr().out)
    assert report["instances"] == [40] and report["clips"] == [{_first_clip(character): 40}]
    import vbusd

    crowd = vbusd.read_asset(tmp_path / "seats.usda").crowds[0]
    assert np.allclose(crowd.positions[:, 0], np.arange(40)) and np.allclose(crowd.positions[:, 2], -np.arange(40))


@pytest.mark.parametrize("args, code", [
    (["--layout", "spiral"], "options.invalid"),
    (["--count", "0"], "options.invalid"),
    (["--layout", "points", "--points", "missing.csv"], "file.missing"),
    (["--clips", "cheer:x"], "options.invalid"),
    (["--clips", "Nope"], "options.invalid"),     # a clip no character has: not "play them all"
    (["--clips", "7:1"], "options.invalid"),      # an index past the clips
])
def test_bad_options_are_one_line_and_write_nothing(character, tmp_path, capsys, args, code):
    out = tmp_path / "bad.usda"
    assert main(["crowd", str(character), "-o", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and code in err[0], err
    assert not out.exists()


def test_missing_character_is_one_line(tmp_path, capsys):
    out = tmp_path / "crowd.usda"
    assert main(["crowd", str(tmp_path / "nobody.usda"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nobody.usda" in err[0]
    assert not out.exists()


def test_existing_output_needs_force(character, tmp_path, capsys):
    out = tmp_path / "crowd.usda"
    out.write_text("keep me")
    assert main(["crowd", str(character), "-o", str(out), "--count", "3"]) == 2
    assert out.read_text() == "keep me"
    assert main(["crowd", str(character), "-o", str(out), "--count", "3", "--force"]) == 0
    assert out.read_text() != "keep me"


def test_readme_quick_start_builds_and_exports_the_sample_crowd(tmp_path, capfd):
    """The README's quick-start crowd line, run as written (after its convert line; the commands in
    this process, tests/helpers/cli.py), in a scratch folder; the package it writes is checked with
    pxr's view of the crowd (instances, clip)."""
    import shlex

    from tests.helpers.cli import run

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text().splitlines()
    (convert_line,) = [x for x in readme if "pip install . && " in x and "vbusd convert" in x]
    (crowd_line,) = [x for x in readme if x.startswith("vbusd crowd ") and "vbusd export" in x]
    (tmp_path / "samples").symlink_to(SAMPLE.parent)
    commands = ["vbusd convert" + convert_line.split("vbusd convert", 1)[1]] + crowd_line.split("&&")
    for command in commands + commands:  # twice: the README's commands run again (--force)
        words = shlex.split(command)
        assert words[0] == "vbusd", command
        result = run(capfd, *words[1:], cwd=tmp_path)
        assert result.returncode == 0, (command, result.stderr)
    package = tmp_path / "out" / "crowd.glb"
    length = int.from_bytes(package.read_bytes()[12:16], "little")
    gltf = json.loads(package.read_bytes()[20:20 + length])
    (node,) = [n for n in gltf["nodes"] if "extensions" in n]
    count = gltf["accessors"][node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["_VB_CLIP"]]["count"]
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "out" / "crowd.usda"))
    (instancer,) = [UsdGeom.PointInstancer(p) for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert count == len(instancer.GetPositionsAttr().Get()) == 1200


def test_points_from_a_usd_points_prim_two_characters_and_time_offset_range(character, tmp_path):
    """--layout points with a UsdGeomPoints prim (positions read back with pxr), two characters
    dealt by weight, and time offsets inside the --time-offset range."""
    from pxr import Usd, UsdGeom, Vt

    import vbusd

    seats = tmp_path / "seats.usda"
    stage = Usd.Stage.CreateNew(str(seats))
    expected = np.stack([np.arange(300) * 0.5, np.zeros(300), np.arange(300) % 7], axis=1).astype(np.float32)
    UsdGeom.Points.Define(stage, "/Seats").CreatePointsAttr(Vt.Vec3fArray.FromNumpy(expected))
    stage.Save()
    other = tmp_path / "other.usda"
    shutil.copy(character, other)  # the same asset under another name: a second character
    out = tmp_path / "two.usda"
    report = build_crowd([character, other], out, CrowdOptions(layout="points", points=str(seats), characters=(3, 1),
                                                              time_offset=(2.0, 2.5), seed=5))
    assert sum(report.instances) == 300 and report.instances[0] > 2 * report.instances[1] > 0
    asset = vbusd.read_asset(out)
    positions = np.concatenate([c.positions for c in asset.crowds])
    assert sorted(map(tuple, positions.tolist())) == sorted(map(tuple, expected.tolist()))
    offsets = np.concatenate([c.time_offset for c in asset.crowds])
    assert np.all((offsets >= 2.0) & (offsets <= 2.5)) and np.ptp(offsets) > 0.3


def test_layout_points_takes_its_file_as_the_issue_spells_it(character, tmp_path):
    # `--layout points FILE` and `--layout=points FILE` are `--layout points --points FILE`.
    points = tmp_path / "seats.csv"
    points.write_text("0,0,0\n2,0,0\n4,0,1\n")
    import vbusd

    for i, spelled in enumerate((["--layout", "points", str(points)], [f"--layout=points", str(points)])):
        out = tmp_path / f"seats{i}.usda"
        assert main(["crowd", str(character), *spelled, "-o", str(out)]) == 0
        crowd = vbusd.read_asset(out).crowds[0]
        assert np.allclose(crowd.positions, [[0, 0, 0], [2, 0, 0], [4, 0, 1]])


def test_mesh_names_stay_unique_when_a_suffix_is_taken():
    # Meshes called a, a and a_2 must not give two "a_2" prims under one prototype.
    from vbusd.format.names import unique_names

    assert unique_names(["a", "a", "a_2"]) == ["a", "a_2", "a_2_2"]
    assert len(set(unique_names(["Body"] * 5 + ["Body_3"]))) == 6
    assert unique_names(["hand", "hand", "hand"], suffix=".{:03d}") == ["hand", "hand.002", "hand.003"]


# ------------------------------------------------------------------------------------------------
# Characters of several animations (issue 24): every animation is instanced, together
# ------------------------------------------------------------------------------------------------

GLTF_FIXTURES = Path(__file__).resolve().parent / "fixtures" / "gltf"


def _instancers(path: Path) -> dict:
    """Point instancers of a crowd read with pxr itself: path -> (animation target, arrays, mesh prims)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    found = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.PointInstancer):
            continue
        instancer = UsdGeom.PointInstancer(prim)
        primvars = UsdGeom.PrimvarsAPI(prim)
        (prototype,) = instancer.GetPrototypesRel().GetTargets()
        meshes = [p for p in Usd.PrimRange(stage.GetPrimAtPath(prototype)) if p.IsA(UsdGeom.Mesh)]
        found[str(prim.GetPath())] = {
            "animation": str(prim.GetRelationship("vb:animation").GetTargets()[0]),
            "positions": np.asarray(instancer.GetPositionsAttr().Get()),
            "orientations": np.asarray(instancer.GetOrientationsfAttr().Get()),
            "scales": np.asarray(instancer.GetScalesAttr().Get()),
            "clip": np.asarray(primvars.GetPrimvar("vb:clip").Get()),
            "timeOffset": np.asarray(primvars.GetPrimvar("vb:timeOffset").Get()),
            "playbackRate": np.asarray(primvars.GetPrimvar("vb:playbackRate").Get()),
            "points": [len(UsdGeom.Mesh(m).GetPointsAttr().Get()) for m in meshes],
        }
    return found


def test_every_animation_of_a_character_is_instanced_with_the_same_instances(tmp_path, capsys):
    """two_skins.gltf converts to two animations (Bar_Anim, Second_Anim), each with its own mesh; a
    crowd of it drew only the first. Both play on the same instances, in USD and in the glTF package."""
    character = tmp_path / "two_skins.usda"
    assert main(["convert", str(GLTF_FIXTURES / "two_skins.gltf"), "-o", str(character)]) == 0
    crowd = tmp_path / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "7", "--rate", "0.5", "2", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "2 animations each" in out, out
    found = _instancers(crowd)
    assert sorted(found) == ["/Crowd/two_skins_Bar_AnimInstances", "/Crowd/two_skins_Second_AnimInstances"]
    first, second = found["/Crowd/two_skins_Bar_AnimInstances"], found["/Crowd/two_skins_Second_AnimInstances"]
    assert first["animation"] == "/Crowd/Characters/two_skins/Bar_Anim"
    assert second["animation"] == "/Crowd/Characters/two_skins/Second_Anim"
    for key in ("positions", "orientations", "scales", "clip", "timeOffset", "playbackRate"):
        assert len(first[key]) == 7 and np.array_equal(first[key], second[key]), key
    assert np.ptp(first["playbackRate"]) > 0  # the instances differ; both instancers agree per instance
    # Each prototype holds its own skinned node's mesh (read from the glTF fixture: two skinned nodes).
    fixture = json.loads((GLTF_FIXTURES / "two_skins.gltf").read_text())
    accessors = fixture["accessors"]
    counts = sorted(accessors[fixture["meshes"][n["mesh"]]["primitives"][0]["attributes"]["POSITION"]]["count"]
                    for n in fixture["nodes"] if "skin" in n and "mesh" in n)
    assert sorted(first["points"] + second["points"]) == counts
    import vbusd

    assert vbusd.validate(crowd).valid

    package = tmp_path / "crowd.gltf"
    assert main(["export", str(crowd), "-o", str(package)]) == 0
    gltf = json.loads(package.read_text())
    nodes = [n for n in gltf["nodes"] if "mesh" in n]
    assert len(nodes) == 2 and all("extensions" in n for n in nodes)  # no character left alone at the origin
    translations = [gltf["accessors"][n["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["TRANSLATION"]]
                    for n in nodes]
    assert [a["count"] for a in translations] == [7, 7]


def _two_animation_character(folder: Path, second_clips) -> Path:
    from vbusd.format.layout import Layout
    from vbusd.format.model import BoundMesh, Clip, VirtualBones, VirtualBonesAsset
    from vbusd.io.usd import write_asset

    def animation(name, clips, rows):
        layout = Layout("crossMatrix", "float16", 1, rows)
        texels = np.zeros(layout.shape, dtype=np.float16)
        texels[:, :3] = [[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 0, 1]]  # identity in every row
        mesh = BoundMesh(path=f"/Rig/{name}Mesh", points=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32),
                         face_vertex_counts=np.array([3], np.int32), face_vertex_indices=np.arange(3, dtype=np.int32),
                         bone_indices=np.zeros((3, 1), np.int32), bone_weights=np.ones((3, 1), np.float32))
        return VirtualBones(layout=layout, texels=texels, bones=("root",), clips=clips, meshes=(mesh,),
                            path=f"/Rig/{name}")

    body_clips = (Clip("walk", 0, 2, 24.0, True), Clip("run", 2, 2, 24.0, True))
    asset = VirtualBonesAsset(animations=(animation("Body", body_clips, 4), animation("Prop", second_clips, 4)),
                              up_axis="Y", meters_per_unit=1.0, default_prim="Rig")
    path = folder / "rig.usda"
    write_asset(asset, path)
    return path


def test_a_second_animation_plays_the_clip_of_the_same_name(tmp_path):
    from vbusd.format.model import Clip

    rig = _two_animation_character(tmp_path, (Clip("run", 0, 2, 24.0, True), Clip("walk", 2, 2, 24.0, True)))
    out = tmp_path / "crowd.usda"
    build_crowd([rig], out, CrowdOptions(count=40, seed=2))
    found = _instancers(out)
    body, prop = found["/Crowd/rig_BodyInstances"], found["/Crowd/rig_PropInstances"]
    assert set(body["clip"]) == {0, 1}
    # walk is clip 0 of Body and clip 1 of Prop; run the other way round.
    assert np.array_equal(prop["clip"], 1 - body["clip"])


def test_animations_whose_clips_do_not_match_are_refused_in_one_line(tmp_path, capsys):
    from vbusd.format.model import Clip

    rig = _two_animation_character(tmp_path, (Clip("jump", 0, 4, 24.0, True),))
    out = tmp_path / "crowd.usda"
    assert main(["crowd", str(rig), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "crowd.character" in err[0] and "/Rig/Prop" in err[0], err
    assert not out.exists()


def test_default_spacing_comes_from_the_characters_size(character, tmp_path):
    """Without --spacing the grid pitch is twice the character's reach from the up axis (its clip
    extents, read here with pxr) times the largest scale: 1,000 Foxes at spacing 1 were a blob."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(character))
    (extents,) = [np.asarray(p.GetAttribute("vb:clipExtents").Get(), dtype=np.float64) for p in stage.Traverse()
                  if p.GetTypeName() == "VirtualBonesAnimation"]
    corners = extents.reshape(-1, 2, 3)[:, :, [0, 2]]  # Y up: the ground plane is x, z
    reach = max(np.hypot(np.abs(c[:, 0]).max(), np.abs(c[:, 1]).max()) for c in corners)
    out = tmp_path / "grid.usda"
    report = build_crowd([character], out, CrowdOptions(layout="grid", count=4, yaw=(0, 0), scale=(1.0, 1.5)))
    expected = 2 * reach * 1.5
    assert report.spacing == pytest.approx(expected, rel=1e-6)
    (only,) = _instancers(out).values()
    xs = sorted({round(float(x), 5) for x in only["positions"][:, 0]})
    assert len(xs) == 2 and xs[1] - xs[0] == pytest.approx(expected, rel=1e-5)
    # --spacing still wins.
    assert build_crowd([character], tmp_path / "one.usda", CrowdOptions(count=4, spacing=1.0)).spacing == 1.0


@pytest.mark.parametrize("source, animations", [
    ("usdskel/usdwg_ElephantWithMonochord/SoC-ElephantWithMonochord.usdc", 2),
    pytest.param("gltf/RecursiveSkeletons/RecursiveSkeletons.glb", 84, marks=pytest.mark.slow),
])
def test_khronos_characters_of_several_skeletons_stay_whole(shared_assets, tmp_path, capsys, source, animations):
    """The Elephant's instrument played once at the origin instead of with each elephant, and
    RecursiveSkeletons instanced 1 of its 84 skins: each instance now carries every animation,
    in USD (pxr's view) and in the runtime package (no node outside the crowd)."""
    from pxr import Usd

    character = tmp_path / "character.usda"
    assert main(["convert", str(shared_assets / source), "-o", str(character), "--check-rows", "0", "-q"]) == 0
    stage = Usd.Stage.Open(str(character))
    bound = {str(p.GetRelationship("vb:animation").GetTargets()[0]) for p in stage.Traverse()
             if p.HasRelationship("vb:animation")}
    assert len(bound) == animations
    crowd = tmp_path / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "3"]) == 0
    found = _instancers(crowd)
    assert {f["animation"].replace("/Crowd/Characters/character", "/" + stage.GetDefaultPrim().GetName())
            for f in found.values()} == bound
    first = next(iter(found.values()))
    assert all(np.array_equal(f["positions"], first["positions"]) for f in found.values())
    package = tmp_path / "crowd.glb"
    capsys.readouterr()
    assert main(["export", str(crowd), "-o", str(package)]) == 0, capsys.readouterr().err
    data = package.read_bytes()
    gltf = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
    drawn = [n for n in gltf["nodes"] if "mesh" in n]
    assert len(drawn) == animations and all("extensions" in n for n in drawn)


# ----------------------------------------------------------------------------------------------
# Crossfades and layers: vbusd crowd --fade-* and --layer (spec "Crossfade", "Layers and bone masks")
# ----------------------------------------------------------------------------------------------


def test_crowd_options_make_a_crossfading_layered_crowd_that_plays_as_givenby_hand(tmp_path, capsys):
    """`vbusd crowd --fade-clips ... --fade-window ... --layer MASK CLIPS ...`: the primvars USD reads
    hold what the options ask (clips among those named, weights in their ranges, the fade weight
    sampled 0 at START and 1 at END), every instance read back through vbusd plays exactly what
    vbusd.skin gives for its parameters by hand (before, inside and after the window), and the
    crowd validates clean."""
    from vbusd.decoders.reference import skin_crowd

    character = chain_character(tmp_path)
    out = tmp_path / "crowd.usda"
    status = main(["crowd", str(character), "-o", str(out), "--count", "12", "--yaw", "0", "0", "--seed", "5",
                   "--clips", "walk", "--rate", "0.8", "1.2",
                   "--fade-clips", "run:2,wave", "--fade-window", "0.5", "1.5", "--fade-time-offset", "-0.5", "-0.5",
                   "--fade-rate", "0.9", "1.1",
                   "--layer", "upper", "wave", "--layer-weight", "0.25", "0.75", "--layer-rate", "1", "1.5",
                   "--format", "json"])
    assert status == 0, capsys.readouterr().err
    report = json.loads(capsys.readouterr().out)
    assert report["layers"] == 1 and sum(report["fadeClips"][0].values()) == 12 and report["fadeClips"][0]["walk"] == 0
    assert vbusd.validate(out).valid
    values = primvars(out)
    clips = ["walk", "run", "wave"]
    assert set(values["clip"]) == {0} and set(values["fadeClip"]) <= {1, 2}
    assert np.all((values["fadePlaybackRate"] >= 0.9 - 1e-6) & (values["fadePlaybackRate"] <= 1.1 + 1e-6))
    np.testing.assert_allclose(values["fadeTimeOffset"], -0.5)
    # The window: sampled at 0.5 s (all 0) and 1.5 s (all 1), USD interpolating between.
    samples = values["fadeWeight.samples"]
    assert sorted(samples) == pytest.approx([0.5, 1.5])
    np.testing.assert_array_equal(samples[min(samples)], 0.0)
    np.testing.assert_array_equal(samples[max(samples)], 1.0)
    assert values["layerClip"].shape == (12, 1) and set(values["layerClip"][:, 0]) == {clips.index("wave")}
    assert values["maskNames"][int(values["layerMask"][0, 0])] == "upper" and len(set(values["layerMask"][:, 0])) == 1
    assert np.all((values["layerWeight"] >= 0.25) & (values["layerWeight"] <= 0.75))
    assert np.all((values["layerPlaybackRate"] >= 1.0) & (values["layerPlaybackRate"] <= 1.5))

    def weight_at(i, t):  # the spec's ramp, by hand: 0 before START, 1 after END, linear between
        return float(np.clip((t - 0.5) / (1.5 - 0.5), 0.0, 1.0))

    back = vbusd.read_asset(out)
    (crowd,) = back.crowds
    animation = back.animations[back.crowd_animation[0]]
    for t in (0.2, 0.9, 1.25, 1.8):
        points, _ = skin_crowd(animation, animation.meshes[0], crowd, t)
        for i in range(12):
            np.testing.assert_allclose(points[i], by_hand(character, values, i, t, weight_at), atol=1e-9,
                                       err_msg=f"instance {i} at {t} s")
    # The crossfade and the layer change the pose (the comparison is not of two unblended poses).
    plain = vbusd.skin(character, 0, values["timeOffset"][0] + values["playbackRate"][0] * 1.25)[0].points
    assert np.abs(points[0] - values["positions"][0] - plain).max() > 1e-2


def test_crowd_api_constant_fade_weights_and_two_layers(tmp_path):
    """The Python API: CrowdOptions(fade_clips=..., fade_weight=..., layers=[CrowdLayer or dict, ...]);
    per-layer ranges; element i * L + j of the layer primvars is layer j of instance i, each
    instance equal to vbusd.skin by hand; the base placement and clips are those of the same
    crowd without crossfade and layers (the extra choices come after them)."""
    from vbusd.decoders.reference import skin_crowd
    from vbusd.jobs.crowd import CrowdLayer

    character = chain_character(tmp_path, masks=(("upper", "b1"), ("tip", "b2")))
    base = CrowdOptions(layout="disc", count=20, yaw=(0, 0), seed=9, clips={"walk": 1, "run": 1})
    build_crowd([character], tmp_path / "plain.usda", base)
    layered = dataclasses.replace(base, fade_clips={"wave": 1}, fade_weight=(0.1, 0.4), fade_playback_rate=(1.0, 1.0),
                                  layers=[CrowdLayer(mask="tip", clips={"run": 1}, weight=(1.0, 1.0), time_offset=(0.0, 0.3)),
                                          {"mask": "upper", "clips": {}, "weight": (0.5, 0.5)}])
    report = build_crowd([character], tmp_path / "layered.usda", layered)
    assert report.layers == 2 and report.fade_clips == [{"walk": 0, "run": 0, "wave": 20}]
    plain, values = primvars(tmp_path / "plain.usda"), primvars(tmp_path / "layered.usda")
    for name in ("positions", "clip", "timeOffset", "playbackRate"):
        np.testing.assert_array_equal(values[name], plain[name])
    assert "fadeClip" not in plain and "layerClip" not in plain
    assert np.all((values["fadeWeight"] >= 0.1) & (values["fadeWeight"] <= 0.4)) and "fadeWeight.samples" not in values
    assert values["layerClip"].shape == (20, 2)
    assert [values["maskNames"][int(m)] for m in values["layerMask"][0]] == ["tip", "upper"]
    np.testing.assert_array_equal(values["layerClip"][:, 0], 1)
    np.testing.assert_array_equal(values["layerWeight"][:, 1], 0.5)
    assert np.all((values["layerTimeOffset"][:, 0] >= 0) & (values["layerTimeOffset"][:, 0] <= 0.3 + 1e-6))
    assert vbusd.validate(tmp_path / "layered.usda").valid
    back = vbusd.read_asset(tmp_path / "layered.usda")
    animation = back.animations[back.crowd_animation[0]]
    points, _ = skin_crowd(animation, animation.meshes[0], back.crowds[0], 0.7)
    for i in range(20):
        np.testing.assert_allclose(points[i], by_hand(character, values, i, 0.7, lambda i, t: values["fadeWeight"][i]),
                                   atol=1e-9, err_msg=f"instance {i}")
    # Same seed, same bytes, with the new options too.
    build_crowd([character], tmp_path / "again.usda", layered)
    assert (tmp_path / "again.usda").read_bytes() == (tmp_path / "layered.usda").read_bytes()


@pytest.mark.parametrize("args, code, words", [
    (["--fade-weight", "0", "1"], "options.invalid", "--fade-clips"),
    (["--fade-clips", "run", "--fade-weight", "0.5", "1.5"], "options.invalid", "within 0..1"),
    (["--fade-clips", "run", "--fade-weight", "0", "1", "--fade-window", "0", "1"], "options.invalid", "not both"),
    (["--fade-clips", "run", "--fade-window", "1", "1"], "options.invalid", "START < END"),
    (["--fade-clips", "sprint"], "options.invalid", "sprint"),
    (["--layer", "legs", "wave"], "layers.noMask", "legs"),
    (["--layer", "upper", "wave", "--layer", "upper", "run", "--layer", "upper", "walk",
      "--layer-weight", "0", "1", "--layer-weight", "0", "1"], "options.invalid", "once per --layer"),
    (["--layer-rate", "1", "2"], "options.invalid", "--layer MASK CLIPS"),
    (["--layer", "upper", "wave:x"], "options.invalid", "--layer upper"),
])
def test_bad_crossfade_and_layer_options_are_one_line(tmp_path, capsys, args, code, words):
    character = chain_character(tmp_path)
    out = tmp_path / "bad.usda"
    assert main(["crowd", str(character), "-o", str(out), "--count", "4", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and code in err[0] and words in err[0], err
    assert not out.exists()


def test_a_format_1_0_character_cannot_crossfade(character, tmp_path, capsys):
    """The committed sample is format 1.0: a crossfading instancer must bind 1.1 (spec
    "Instancing"), and the crowd layer cannot raise the referenced animation's version."""
    out = tmp_path / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(out), "--fade-clips", _first_clip(character)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "crowd.character" in err[0] and "format 1.0" in err[0] and "vbusd convert" in err[0], err
    assert not out.exists()
