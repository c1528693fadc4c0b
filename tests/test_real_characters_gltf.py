"""Real characters convert whole (issue 12), glTF side: hand-built glTF characters against three.js.

Each fixture is written by :class:`GltfBuilder` (glTF JSON with an embedded base64 buffer) into
the test's temporary folder. The independent result is three.js r187 under Node
(tests/node/skin_pose.mjs: GLTFLoader, AnimationMixer, SkinnedMesh CPU skinning, scene-graph world
matrices): it renormalizes weights (``SkinnedMesh.normalizeSkinWeights``, weight 1 on the first
JOINTS_0 component for an all-zero vertex) and moves meshes under joints with them. The converted
asset is baked in affineMatrix/float32 and decoded by the reference decoder at every row; the
largest distance must stay within 1e-6 of the diagonal of the three.js bounding box.

Bad input (negative or NaN weight, joint index out of range with non-zero weight, a ``--clips``
name the file lacks, ``--strict-weights`` on unnormalized weights, a bad clip under
``--on-bad-clip error``) gives one line, exit status 2 and no output.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest

from vbusd.baking.baker import BakeOptions, bake
from vbusd.converters import gltf
from vbusd.decoders.reference import skin_mesh_at_rows
from vbusd.format.model import ReadOptions
from tests.helpers import cli
from tests.helpers import node as node_tools


TOLERANCE = 1e-6
"""Largest decoded-vs-three.js distance, as a fraction of the bounding box diagonal."""


# ------------------------------------------------------------------------------------------------
# Building glTF by hand
# ------------------------------------------------------------------------------------------------


class GltfBuilder:
    """A glTF 2.0 document built from numpy arrays, saved with one base64 buffer."""

    _DTYPES = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}

    def __init__(self) -> None:
        self.bin = bytearray()
        self.doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"name": "Scene", "nodes": []}],
                    "nodes": [], "meshes": [], "skins": [], "animations": [], "accessors": [],
                    "bufferViews": [], "buffers": []}

    def accessor(self, values, kind: str, component: int = 5126, normalized: bool = False) -> int:
        array = np.ascontiguousarray(values, dtype=self._DTYPES[component])
        while len(self.bin) % 4:
            self.bin.append(0)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.bin), "byteLength": array.nbytes})
        self.bin += array.tobytes()
        rows = array.reshape(len(array), -1)
        accessor = {"bufferView": len(self.doc["bufferViews"]) - 1, "componentType": component,
                    "count": len(array), "type": kind}
        if normalized:
            accessor["normalized"] = True
        if component == 5126 and kind in ("SCALAR", "VEC3"):
            accessor["min"] = rows.min(axis=0).tolist()
            accessor["max"] = rows.max(axis=0).tolist()
        self.doc["accessors"].append(accessor)
        return len(self.doc["accessors"]) - 1

    def node(self, name: str, parent: int | None = None, in_scene: bool = True, **fields) -> int:
        self.doc["nodes"].append({"name": name, **fields})
        index = len(self.doc["nodes"]) - 1
        if parent is None:
            if in_scene:
                self.doc["scenes"][0]["nodes"].append(index)
        else:
            self.doc["nodes"][parent].setdefault("children", []).append(index)
        return index

    def mesh(self, name: str, points, triangles, joints=None, weights=None, targets=(), weights_default=None) -> int:
        attributes = {"POSITION": self.accessor(points, "VEC3")}
        if joints is not None:
            attributes["JOINTS_0"] = self.accessor(joints, "VEC4", 5123)
            attributes["WEIGHTS_0"] = self.accessor(weights, "VEC4")
        primitive = {"attributes": attributes, "indices": self.accessor(np.asarray(triangles).reshape(-1), "SCALAR", 5123)}
        if targets:
            primitive["targets"] = [{"POSITION": self.accessor(t, "VEC3")} for t in targets]
        mesh = {"name": name, "primitives": [primitive]}
        if weights_default is not None:
            mesh["weights"] = list(weights_default)
        self.doc["meshes"].append(mesh)
        return len(self.doc["meshes"]) - 1

    def skin(self, joints: list, inverse_binds) -> int:
        ibm = np.asarray(inverse_binds, dtype=np.float64).transpose(0, 2, 1).reshape(-1, 16)  # column-major
        self.doc["skins"].append({"joints": joints, "inverseBindMatrices": self.accessor(ibm, "MAT4")})
        return len(self.doc["skins"]) - 1

    def animation(self, name: str, channels: list) -> None:
        """``channels``: (node, path, times, values, interpolation)."""
        samplers, targets = [], []
        for node, path, times, values, interpolation in channels:
            kind = {"translation": "VEC3", "scale": "VEC3", "rotation": "VEC4", "weights": "SCALAR"}[path]
            samplers.append({"input": self.accessor(times, "SCALAR"), "interpolation": interpolation,
                             "output": self.accessor(values, kind)})
            targets.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})
        self.doc["animations"].append({"name": name, "samplers": samplers, "channels": targets})

    def save(self, path: Path) -> Path:
        doc = json.loads(json.dumps(self.doc))
        for key in ("skins", "animations"):
            if not doc[key]:
                del doc[key]
        doc["buffers"] = [{"byteLength": len(self.bin),
                           "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(self.bin)).decode()}]
        path.write_text(json.dumps(doc))
        return path


def box(center, size) -> tuple[np.ndarray, np.ndarray]:
    """8 corners and 12 triangles of an axis-aligned box."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    points = np.asarray(center, dtype=np.float64) + 0.5 * np.asarray(size, dtype=np.float64) * corners
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return points, np.array(faces)


def quat(axis, degrees) -> list:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return [*(np.sin(half) * axis), np.cos(half)]


def translation(x, y, z) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def soldier(weights_off: bool = True, zero_vertex: bool = True, spawn: bool = False, morph: bool = False) -> GltfBuilder:
    """A small character of the kinds the issue names.

    Joints Hips (y=1) -> Spine (+0.5) -> Head (+0.5). Body: a skinned box spanning the three joints;
    vertex 2 has weights summing to 0.996 (three.js's soldier vertex 25), vertex 5 only zero weights
    (JOINTS_0 = (2, ...): three.js binds it to Head). Helmet: a mesh node (no skin) under Head with
    its own offset and rotation. Weapon: a mesh node under WeaponMount, an animated node (not a
    joint) under Spine. CrateLid: a mesh node under the static, non-joint Crate (a prop beside the
    character). Orphan: a mesh node in no scene. Animation Walk moves Hips, Spine, Head and WeaponMount;
    Spawn (optional) scales Hips to zero on its first key.
    """
    b = GltfBuilder()
    hips = b.node("Hips", translation=[0, 1, 0])
    spine = b.node("Spine", hips, translation=[0, 0.5, 0])
    head = b.node("Head", spine, translation=[0, 0.5, 0])
    points, faces = box((0, 1.5, 0), (0.6, 1.2, 0.4))
    joints = np.zeros((8, 4), dtype=np.int64)
    weights = np.zeros((8, 4))
    for v, p in enumerate(points):
        if p[1] < 1.5:
            joints[v], weights[v] = (0, 1, 0, 0), (0.7, 0.3, 0, 0)
        else:
            joints[v], weights[v] = (1, 2, 0, 0), (0.4, 0.6, 0, 0)
    if weights_off:
        weights[2] = (0.4, 0.596, 0, 0)
    if zero_vertex:
        joints[5], weights[5] = (2, 1, 0, 0), (0, 0, 0, 0)
    targets = ()
    if morph:
        offset = np.zeros((8, 3))
        offset[7] = (0.0, 0.3, 0.4)     # |offset| = 0.5
        offset[1] = (0.1, 0.0, 0.0)
        targets = (offset,)
    body_mesh = b.mesh("BodyMesh", points, faces, joints, weights, targets=targets,
                       weights_default=[0.0] if morph else None)
    body = b.node("Body", mesh=body_mesh, skin=0)
    helmet_points, helmet_faces = box((0, 0.15, 0), (0.3, 0.3, 0.3))
    b.node("Helmet", head, mesh=b.mesh("HelmetMesh", helmet_points, helmet_faces),
           translation=[0, 0.2, 0.05], rotation=quat((0, 1, 0), 30), scale=[1.1, 1.1, 1.1])
    mount = b.node("WeaponMount", spine, translation=[0.4, 0, 0])
    weapon_points, weapon_faces = box((0, -0.3, 0), (0.05, 0.8, 0.05))
    b.node("Weapon", mount, mesh=b.mesh("WeaponMesh", weapon_points, weapon_faces), translation=[0.05, 0, 0])
    crate_points, crate_faces = box((0, 0.25, 0), (0.5, 0.5, 0.5))
    crate = b.node("Crate", translation=[1.5, 0, 0], rotation=quat((0, 1, 0), 20))
    b.node("CrateLid", crate, mesh=b.mesh("CrateMesh", crate_points, crate_faces), translation=[0, 0.1, 0])
    b.node("Orphan", in_scene=False, mesh=b.mesh("OrphanMesh", crate_points, crate_faces))
    worlds = [translation(0, 1, 0), translation(0, 1.5, 0), translation(0, 2, 0)]
    b.skin([hips, spine, head], [np.linalg.inv(w) for w in worlds])
    times = np.array([0.0, 0.5, 1.0])
    b.animation("Walk", [
        (hips, "translation", times, [[0, 1, 0], [0.2, 1.05, 0.1], [0.4, 1, 0.2]], "LINEAR"),
        (spine, "rotation", times, [quat((0, 0, 1), 0), quat((0, 0, 1), 25), quat((1, 0, 0), 10)], "LINEAR"),
        (head, "rotation", times, [quat((0, 1, 0), 0), quat((0, 1, 0), -40), quat((0, 1, 0), 15)], "LINEAR"),
        (mount, "rotation", times, [quat((1, 0, 0), 0), quat((1, 0, 0), 60), quat((1, 0, 0), 90)], "LINEAR"),
    ] + ([(body, "weights", times, [0.0, 1.0, 0.25], "LINEAR")] if morph else []))
    if spawn:
        b.animation("Spawn", [(hips, "scale", np.array([0.0, 0.5]), [[0, 0, 0], [1, 1, 1]], "LINEAR")])
    return b


# ------------------------------------------------------------------------------------------------
# The two sides
# ------------------------------------------------------------------------------------------------


def three_poses(path: Path, clip: str, times) -> list:
    result = node_tools.run_json("skin_pose.mjs", path, clip, *[f"{t:.17g}" for t in times], packages=("three",))
    return result["poses"]


def decoded(path: Path, options: ReadOptions = ReadOptions()):
    """(scene, baked animations): affineMatrix, float32, every clip."""
    scene = gltf.read(path, options)
    baked = [bake(a, BakeOptions(encoding="affineMatrix", texel_format="float32")) for a in scene.animations]
    return scene, baked


def compare_with_three(path: Path, options: ReadOptions = ReadOptions()) -> dict:
    """Largest decoded-vs-three.js distance over the bbox diagonal, per clip and mesh name."""
    scene, baked = decoded(path, options)
    worst = {}
    for vb in baked:
        for c, clip in enumerate(vb.clips):
            times = clip.start_time + np.arange(clip.row_count) / clip.rows_per_second
            poses = three_poses(path, clip.name, times)
            for mesh in vb.meshes:
                name = mesh.path.rsplit("/", 1)[-1]
                ours, _ = skin_mesh_at_rows(vb, mesh, c)
                theirs = np.array([np.reshape(pose["meshes"][name], (-1, 3)) for pose in poses])
                diagonal = np.linalg.norm(theirs.reshape(-1, 3).max(axis=0) - theirs.reshape(-1, 3).min(axis=0))
                worst[(clip.name, name)] = float(np.linalg.norm(ours - theirs, axis=-1).max() / diagonal)
    return worst


# ------------------------------------------------------------------------------------------------
# Weights (item 1) and rigid attachments (item 2) against three.js
# ------------------------------------------------------------------------------------------------


@pytest.mark.node
def test_renormalized_weights_and_attachments_match_three(tmp_path):
    path = soldier().save(tmp_path / "soldier.gltf")
    worst = compare_with_three(path)
    assert set(worst) == {("Walk", "Body"), ("Walk", "Helmet"), ("Walk", "Weapon"), ("Walk", "CrateLid")}
    assert max(worst.values()) <= TOLERANCE, worst


def test_attachment_bones_and_rest_points(tmp_path):
    path = soldier().save(tmp_path / "soldier.gltf")
    scene = gltf.read(path)
    (animation,) = scene.animations
    # Helmet follows the joint Head; Weapon the animated non-joint WeaponMount (an extra bone);
    # CrateLid the static root of its tree, Crate (another extra bone); Orphan, in no scene, is left out.
    assert animation.bones == ("Hips", "Spine", "Head", "WeaponMount", "Crate")
    assert [m.path.rsplit("/", 1)[-1] for m in animation.meshes] == ["Body", "Helmet", "Weapon", "CrateLid"]
    assert any("'Orphan'" in w and "not in the default scene; left out" in w for w in scene.warnings)
    meshes = {m.path.rsplit("/", 1)[-1]: m for m in animation.meshes}
    assert np.all(meshes["Helmet"].bone_indices == 2) and np.all(meshes["Helmet"].bone_weights == 1)
    assert np.all(meshes["Weapon"].bone_indices == 3)
    # By hand: Head's inverse bind is T(0,-2,0), so Helmet's rest points are its world rest points.
    local, _ = box((0, 0.15, 0), (0.3, 0.3, 0.3))
    x, y, z, w = quat((0, 1, 0), 30)
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    world = local @ (1.1 * rotation).T + np.array([0, 2.2, 0.05])
    np.testing.assert_allclose(meshes["Helmet"].points, world, atol=1e-6)
    # Weapon is in WeaponMount's own space: its node offset only.
    local, _ = box((0, -0.3, 0), (0.05, 0.8, 0.05))
    np.testing.assert_allclose(meshes["Weapon"].points, local + (0.05, 0, 0), atol=1e-6)


def rigid_robot(with_skin: bool) -> GltfBuilder:
    """A robot made of rigid parts, as three.js's example robot is apart from its hands: a torso under
    the joint Body, a head under the joint Neck. ``with_skin``: the skin exists but no mesh is skinned
    (so no skin is "used"); without it the parts hang under plain animated nodes and the file has no
    skin at all. A Pedestal stands beside it, moved by nothing."""
    b = GltfBuilder()
    body = b.node("Body", translation=[0, 1, 0])
    neck = b.node("Neck", body, translation=[0, 0.6, 0])
    torso_points, faces = box((0, 0.3, 0), (0.6, 0.6, 0.3))
    b.node("Torso", body, mesh=b.mesh("TorsoMesh", torso_points, faces))
    head_points, _ = box((0, 0.2, 0), (0.3, 0.3, 0.3))
    b.node("HeadPart", neck, mesh=b.mesh("HeadMesh", head_points, faces), translation=[0, 0.05, 0],
           rotation=quat((0, 0, 1), 10))
    pedestal_points, _ = box((0, 0.1, 0), (1.0, 0.2, 1.0))
    b.node("Pedestal", mesh=b.mesh("PedestalMesh", pedestal_points, faces), translation=[0, -0.2, 0])
    if with_skin:
        b.skin([body, neck], [np.linalg.inv(translation(0, 1, 0)), np.linalg.inv(translation(0, 1.6, 0))])
    times = np.array([0.0, 0.5, 1.0])
    b.animation("Wave", [
        (body, "rotation", times, [quat((0, 1, 0), 0), quat((0, 1, 0), 45), quat((0, 1, 0), 90)], "LINEAR"),
        (neck, "rotation", times, [quat((1, 0, 0), 0), quat((1, 0, 0), -30), quat((1, 0, 0), 20)], "LINEAR"),
        (neck, "scale", times, [[1, 1, 1], [1.2, 1.2, 1.2], [1, 1, 1]], "LINEAR"),
    ])
    return b


@pytest.mark.node
@pytest.mark.parametrize("with_skin", [True, False], ids=["unused-skin", "no-skin"])
def test_rigid_parts_without_skinned_mesh_match_three(tmp_path, with_skin):
    path = rigid_robot(with_skin).save(tmp_path / "robot.gltf")
    scene = gltf.read(path)
    (animation,) = scene.animations
    if with_skin:   # the skin's joints are the bones; the pedestal a fixed extra bone
        assert animation.path == "/Scene/skin0_Anim" and animation.bones == ("Body", "Neck", "Pedestal")
    else:           # no skin: an animation of the animated nodes' own
        assert animation.path == "/Scene/Nodes_Anim" and animation.bones == ("Body", "Neck", "Pedestal")
    assert [m.path for m in animation.meshes] == ["/Scene/Torso", "/Scene/HeadPart", "/Scene/Pedestal"]
    worst = compare_with_three(path)
    assert set(worst) == {("Wave", "Torso"), ("Wave", "HeadPart"), ("Wave", "Pedestal")}
    assert max(worst.values()) <= TOLERANCE, worst


def test_attached_lines_are_left_out_with_a_warning(tmp_path):
    b = rigid_robot(with_skin=True)
    strand = b.mesh("StrandMesh", [[0, 0, 0], [0, 0.5, 0]], [[0, 1, 0]])
    b.doc["meshes"][strand]["primitives"][0]["mode"] = 1            # LINES
    b.node("Antenna", 1, mesh=strand)                               # under the joint Neck
    scene = gltf.read(b.save(tmp_path / "robot.gltf"))
    assert [m.path for m in scene.animations[0].meshes] == ["/Scene/Torso", "/Scene/HeadPart", "/Scene/Pedestal"]
    assert any(w.startswith("node 5 'Antenna' primitive 0: primitive mode LINES") and w.endswith("; left out")
               for w in scene.warnings), scene.warnings


def test_morph_only_animation_is_refused_by_name(tmp_path, capsys):
    """Three.js's Horse or Parrot: one mesh, no skin, only morph weights animated: nothing a bone can
    hold; one line that says why, nothing written."""
    from vbusd import cli

    b = GltfBuilder()
    points, faces = box((0, 0, 0), (1, 1, 1))
    mesh = b.mesh("HorseMesh", points, faces, targets=(np.ones((8, 3)),), weights_default=[0.0])
    horse = b.node("Horse", mesh=mesh)
    b.animation("Gallop", [(horse, "weights", np.array([0.0, 1.0]), [0.0, 1.0], "LINEAR")])
    path = b.save(tmp_path / "horse.gltf")
    status = cli.main(["convert", str(path), "-o", str(tmp_path / "out" / "horse.usda")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1, err
    assert "gltf.noSkin" in err[0] and "only morph target weights" in err[0]
    assert not (tmp_path / "out").exists()


def test_weight_warnings_state_count_and_deviation(tmp_path):
    path = soldier().save(tmp_path / "soldier.gltf")
    scene = gltf.read(path)
    text = "\n".join(scene.warnings)
    assert "weights of 1 vertices do not sum to 1 (largest deviation 0.004: vertex 2 sums to 0.996" in text
    assert "1 vertices have only zero weights (first: vertex 5)" in text and "joint 2" in text
    (animation,) = scene.animations
    body = next(m for m in animation.meshes if m.path.endswith("/Body"))
    np.testing.assert_allclose(body.bone_weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(body.bone_weights[2, :2], np.array([0.4, 0.596]) / 0.996, atol=1e-7)
    assert body.bone_indices[5, 0] == 2 and body.bone_weights[5, 0] == 1.0


def test_renormalization_error_in_report(tmp_path):
    from vbusd.jobs.conversion import ConvertOptions, convert

    path = soldier(zero_vertex=False).save(tmp_path / "soldier.gltf")
    report = convert(path, tmp_path / "out" / "soldier.usda",
                     ConvertOptions(encoding="affineMatrix", texel_format="float32", check_rows=None))
    body = next(m for m in report.animations[0].meshes if m.path.endswith("/Body"))
    # By hand: at every row vertex 2 skins to s * q with the stored weights and to q renormalized, s = 0.996,
    # so the distance is 0.004 * |q|, largest where |q| is.
    scene, baked = decoded(path)
    ours, _ = skin_mesh_at_rows(baked[0], baked[0].meshes[0], 0)
    expected = 0.004 * np.linalg.norm(ours[:, 2], axis=-1).max()
    assert body.renormalization_error == pytest.approx(expected, rel=1e-4)
    assert body.max_error_fraction <= TOLERANCE
    others = [m for m in report.animations[0].meshes if not m.path.endswith("/Body")]
    assert others and all(m.renormalization_error is None for m in others)


def test_strict_weights_refuses(tmp_path, capsys):
    from vbusd import cli

    path = soldier(zero_vertex=False).save(tmp_path / "soldier.gltf")
    out = tmp_path / "out"
    status = cli.main(["convert", str(path), "-o", str(out / "a.usda"), "--strict-weights"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1, err
    assert "/meshes/0/primitives/0/attributes/WEIGHTS_0: gltf.skin.weights: vertex 2: weights sum to 0.99" in err[0]
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# Clips (item 3)
# ------------------------------------------------------------------------------------------------


def _convert(capfd, tmp_path, path, *extra):
    """``vbusd convert`` in this process (tests.helpers.cli), its output captured like a child's."""
    out = tmp_path / "out" / "soldier.usda"
    return cli.run(capfd, "convert", path, "-o", out, "--format", "json", *extra), out


@pytest.mark.slow
def test_bad_clip_error_names_it_and_suggests_options(tmp_path, capfd):
    path = soldier(spawn=True).save(tmp_path / "soldier.gltf")
    result, out = _convert(capfd, tmp_path, path)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "clip 'Spawn'" in lines[0] and "--on-bad-clip skip" in lines[0] and "--clips" in lines[0]
    assert "Traceback" not in result.stderr and not out.parent.exists()


@pytest.mark.node
def test_bad_clip_skip_converts_the_others(tmp_path, capfd):
    path = soldier(spawn=True).save(tmp_path / "soldier.gltf")
    result, out = _convert(capfd, tmp_path, path, "--on-bad-clip", "skip")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [c["name"] for c in report["animations"][0]["clips"]] == ["Walk"]
    (skipped,) = report["skippedClips"]
    assert skipped["clip"] == "Spawn" and skipped["animation"] == "/Scene/skin0_Anim"
    assert "singular" in skipped["reason"] or "nonRigid" in skipped["reason"]
    assert out.exists()
    # What was kept still matches three.js.
    worst = compare_with_three(path, ReadOptions(clips=("Walk",)))
    assert max(worst.values()) <= TOLERANCE, worst


@pytest.mark.slow
def test_clips_selects(tmp_path, capfd):
    path = soldier(spawn=True).save(tmp_path / "soldier.gltf")
    result, out = _convert(capfd, tmp_path, path, "--clips", "Walk")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [c["name"] for c in report["animations"][0]["clips"]] == ["Walk"] and report["skippedClips"] == []


@pytest.mark.slow
def test_only_bad_clips_exit_2(tmp_path, capfd):
    path = soldier(spawn=True).save(tmp_path / "soldier.gltf")
    result, out = _convert(capfd, tmp_path, path, "--clips", "Spawn", "--on-bad-clip", "skip")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and "convert.nothingConverted" in lines[-1], result.stderr
    assert not out.parent.exists()


# ------------------------------------------------------------------------------------------------
# Morph targets (item 4)
# ------------------------------------------------------------------------------------------------


@pytest.mark.node
def test_morph_warning_states_largest_displacement(tmp_path):
    path = soldier(morph=True).save(tmp_path / "soldier.gltf")
    scene = gltf.read(path)
    (warning,) = [w for w in scene.warnings if "morph" in w]
    # By hand: the Walk weight peaks at 1.0 (t = 0.5 s); vertex 7's offset is (0, 0.3, 0.4), length 0.5.
    assert "move a vertex by up to 0.5 scene units (vertex 7, clip 'Walk' at 0.5 s)" in warning
    assert "rest shape used is POSITION as stored" in warning
    # three.js shows the morph: at 0.5 s its Body differs from the converted one by the offset
    # carried through the blended joint matrices, sum_i w_i L_i d (L_i: linear parts), vertex by vertex.
    scene, baked = decoded(path)
    vb = baked[0]
    clip = vb.clips[0]
    row = int(round(0.5 * clip.rows_per_second))
    poses = three_poses(path, "Walk", [clip.start_time + row / clip.rows_per_second])
    ours, _ = skin_mesh_at_rows(vb, vb.meshes[0], 0)
    theirs = np.reshape(poses[0]["meshes"]["Body"], (-1, 3))
    time = clip.start_time + row / clip.rows_per_second
    matrices = scene.animations[0].clips[0].sample(np.array([time]))[0]
    body = scene.animations[0].meshes[0]
    offsets = np.zeros((8, 3))
    offsets[7], offsets[1] = (0.0, 0.3, 0.4), (0.1, 0.0, 0.0)
    carried = np.einsum("vk,vkij,vj->vi", body.bone_weights, matrices[body.bone_indices][..., :3, :3], offsets)
    np.testing.assert_allclose(theirs - ours[row], carried, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# Bad input: one line, exit 2, nothing written
# ------------------------------------------------------------------------------------------------


def _mutated(tmp_path, mutate) -> Path:
    b = soldier(weights_off=False, zero_vertex=False)
    mutate(b)
    return b.save(tmp_path / "bad.gltf")


def _weights_accessor(b: GltfBuilder) -> tuple[int, int]:
    index = b.doc["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"]
    return index, b.doc["bufferViews"][b.doc["accessors"][index]["bufferView"]]["byteOffset"]


def _set_weight(b: GltfBuilder, vertex: int, component: int, value: float) -> None:
    _, offset = _weights_accessor(b)
    b.bin[offset + 16 * vertex + 4 * component:offset + 16 * vertex + 4 * component + 4] = \
        np.float32(value).tobytes()


def _set_joint(b: GltfBuilder, vertex: int, component: int, value: int) -> None:
    index = b.doc["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"]
    offset = b.doc["bufferViews"][b.doc["accessors"][index]["bufferView"]]["byteOffset"]
    b.bin[offset + 8 * vertex + 2 * component:offset + 8 * vertex + 2 * component + 2] = np.uint16(value).tobytes()


@pytest.mark.parametrize("case, code, words", [
    ("negative", "gltf.skin.weights", "vertex 3 component 1: weight -0.25 is negative"),
    ("nan", "gltf.accessor.nonFinite", "NaN"),
    ("joint", "gltf.skin.jointIndex", "vertex 4 component 0: joint 7 is out of range (skin 0 has 3 joints)"),
    ("clips", "gltf.option", "no animation named 'Run' (known: 'Walk')"),
])
def test_bad_input_one_line_no_output(tmp_path, capsys, case, code, words):
    from vbusd import cli

    mutations = {"negative": lambda b: _set_weight(b, 3, 1, -0.25), "nan": lambda b: _set_weight(b, 3, 1, float("nan")),
                 "joint": lambda b: _set_joint(b, 4, 0, 7), "clips": lambda b: None}
    path = _mutated(tmp_path, mutations[case])
    out = tmp_path / "out"
    extra = ["--clips", "Run"] if case == "clips" else []
    status = cli.main(["convert", str(path), "-o", str(out / "a.usda"), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1, err
    assert f": {code}: " in err[0] and words in err[0] and str(path) in err[0], err[0]
    assert "Traceback" not in err[0] and not out.exists()
