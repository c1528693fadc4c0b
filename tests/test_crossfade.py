"""Crossfade (spec virtual-bones.md 8.3, format 1.1): one clip blended into another per instance.

Checked against things the decoders do not compute themselves:

* the spec's worked example, by hand (one bone, 90 degrees about Z, w = 0.25);
* UsdSkel's own skinning (``SkinningQuery.ComputeSkinnedPoints``) at the two source times, blended
  with the same weight: the crossfade of a converted UsdSkel rig agrees with it within the accuracy
  bound of version 1 at the rows (float32 texels), for the three LBS encodings and for dualQuat
  on a dual-quaternion rig; and three.js's own skinning of a glTF (the shared Fox, Walk into Run);
* w = 0 gives the single-clip result bit for bit and w = 1 the fade clip's (the spec's promise
  that a 1.0 crowd is unchanged);
* the warp kernels (CPU) and ``vbusd.skin(..., fade_clip=, fade_time=, fade_weight=)`` agree with
  the numpy reference, which is checked by the two items above.

The GLSL, HLSL and three.js crossfades are checked on the conformance vectors
(tests/test_conformance.py).
"""

from __future__ import annotations


import numpy as np
import pytest

import vbusd
from vbusd.baking.baker import BakeOptions, bake
from vbusd.decoders.reference import skin_mesh, skin_mesh_crossfade
from vbusd.format.errors import OptionsError
from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh

from tests.helpers.animations import chain_animation
from tests.helpers import node as node_tools
from tests.helpers.capabilities import require, shared_asset

ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")


def _constant(matrix):
    def sample(times):
        return np.tile(np.asarray(matrix, dtype=np.float64), (len(np.atleast_1d(times)), 1, 1, 1))
    return sample


def _spec_example_animation() -> SkinnedAnimation:
    """One bone; clip 'rest' holds the identity, clip 'turn' the 90-degrees-about-Z example of 5.5."""
    turn = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    mesh = SkinnedMesh("/Example/Mesh", np.array([[1.0, 0, 0]]), np.array([1]), np.array([0]),
                       np.array([[0]]), np.array([[1.0]]), normals=np.array([[1.0, 0, 0]]))
    clips = (AnimationClip("rest", 0.0, 1.0, _constant(np.eye(4)[None]), native_rate=2, loop=False),
             AnimationClip("turn", 0.0, 1.0, _constant(turn[None]), native_rate=2, loop=False))
    return SkinnedAnimation("Example", "/Example/Anim", ("bone",), clips, (mesh,))


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_spec_worked_example_by_hand(encoding):
    """Spec 8.3's example: p' = (1, 0.75, 0.75), n' = normalize(0.75, 0.25, 0), for every encoding."""
    vb = bake(_spec_example_animation(), BakeOptions(encoding=encoding, texel_format="float32"))
    points, normals = skin_mesh_crossfade(vb, vb.meshes[0], 0, [0.3], 1, [0.6], 0.25)
    np.testing.assert_allclose(points[0, 0], [1.0, 0.75, 0.75], atol=1e-6)
    np.testing.assert_allclose(normals[0, 0], [0.9486833, 0.3162278, 0.0], atol=1e-6)
    # The API takes clips by name and gives the same pose.
    pose = vbusd.skin(vb, "rest", 0.3, fade_clip="turn", fade_time=0.6, fade_weight=0.25)[0]
    np.testing.assert_array_equal(pose.points, points[0])


def _chain(encoding: str):
    """test_shaders' 5-bone chain (two clips, 6 influences, twisted for dualQuat), baked in float16."""
    animation = chain_animation(scaled=encoding in ("affineMatrix", "quatTranslation"),
                                         twist=encoding == "dualQuat")
    return bake(animation, BakeOptions(encoding=encoding, texel_format="float16", max_influences=6))


@pytest.fixture(scope="module")
def chains():
    return {encoding: _chain(encoding) for encoding in ENCODINGS}


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_weight_zero_is_the_first_clip_and_one_the_fade_clip_bit_for_bit(chains, encoding):
    vb = chains[encoding]
    mesh = vb.meshes[0]
    tau, fade_tau = np.array([0.1, 0.77, 1.93]), np.array([0.4, 0.05, 0.99])
    first, fade = skin_mesh(vb, mesh, 0, tau), skin_mesh(vb, mesh, 1, fade_tau)
    for weight, expected in ((0.0, first), (1.0, fade)):
        points, normals = skin_mesh_crossfade(vb, mesh, 0, tau, 1, fade_tau, weight)
        np.testing.assert_array_equal(points, expected[0])
        np.testing.assert_array_equal(normals, expected[1])
    # Weights outside 0..1 are clamped, as the spec says decoders do.
    np.testing.assert_array_equal(skin_mesh_crossfade(vb, mesh, 0, tau, 1, fade_tau, 1.7)[0], fade[0])


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_warp_cpu_crossfade_matches_reference(chains, encoding):
    require("warp")
    from vbusd.decoders import warp

    vb = chains[encoding]
    mesh = vb.meshes[0]
    tau, fade_tau = np.array([0.1, 0.77, 1.93, 0.5]), np.array([0.4, 0.05, 0.99, 0.7])
    weight = np.array([0.0, 0.35, 1.0, 0.8])
    expected_points, expected_normals = skin_mesh_crossfade(vb, mesh, 0, tau, 1, fade_tau, weight)
    points, normals = warp.skin_mesh_crossfade(vb, mesh, 0, tau, 1, fade_tau, weight, device="cpu")
    diagonal = np.linalg.norm(np.ptp(expected_points.reshape(-1, 3), axis=0))
    assert np.abs(points - expected_points).max() / diagonal < 5e-6
    assert np.abs(normals - expected_normals).max() < 2.5e-5


def test_warp_crowd_crossfade_matches_reference(chains):
    """A crowd whose instances fade per instance (placed, non-uniform scale) through Decoder.skin_crowd."""
    require("warp")
    from vbusd.decoders import warp
    from vbusd.decoders.reference import skin_crowd
    from vbusd.format.model import Crowd

    rng = np.random.default_rng(3)
    n = 6
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    crowd = Crowd("/Crowd", positions=rng.uniform(-5, 5, (n, 3)).astype(np.float32),
                  orientations=quats.astype(np.float32), clip=np.array([0, 1, 0, 1, 0, 1], np.int32),
                  time_offset=rng.uniform(0, 2, n).astype(np.float32),
                  playback_rate=rng.uniform(0.5, 1.5, n).astype(np.float32),
                  scales=rng.uniform(0.5, 2.0, (n, 3)).astype(np.float32),
                  fade_clip=np.array([1, 0, 1, 0, 0, 1], np.int32),
                  fade_time_offset=rng.uniform(0, 2, n).astype(np.float32),
                  fade_playback_rate=rng.uniform(0.5, 1.5, n).astype(np.float32),
                  fade_weight=np.array([0.0, 0.25, 0.5, 1.0, 0.9, 0.1], np.float32))
    for encoding in ENCODINGS:
        vb = chains[encoding]
        expected_points, expected_normals = skin_crowd(vb, vb.meshes[0], crowd, 0.61)
        points, normals = warp.skin_crowd(vb, vb.meshes[0], crowd, 0.61, device="cpu")
        diagonal = np.linalg.norm(np.ptp(expected_points.reshape(-1, 3), axis=0))
        assert np.abs(points - expected_points).max() / diagonal < 5e-6, encoding
        assert np.abs(normals - expected_normals).max() < 5e-5, encoding


def test_api_refuses_bad_fade_arguments(chains):
    vb = chains["crossMatrix"]
    with pytest.raises(OptionsError, match="fade_weight must be a number in 0..1"):
        vbusd.skin(vb, 0, 0.1, fade_clip=1, fade_time=0.2, fade_weight=1.5)
    with pytest.raises(OptionsError, match="fade_clip needs fade_time"):
        vbusd.skin(vb, 0, 0.1, fade_clip=1, fade_weight=0.5)
    with pytest.raises(OptionsError, match="needs a fade_clip"):
        vbusd.skin(vb, 0, 0.1, fade_weight=0.5)
    with pytest.raises(OptionsError, match="has no clip 'run'"):
        vbusd.skin(vb, 0, 0.1, fade_clip="run", fade_time=0.0, fade_weight=0.5)
    with pytest.raises(OptionsError, match="fade_time must be a finite number"):
        vbusd.skin(vb, 0, 0.1, fade_clip=1, fade_time=float("nan"), fade_weight=0.5)


# ----------------------------------------------------------------------------------------------
# Against UsdSkel: the crossfade equals blending UsdSkel's own skinning at the two times
# ----------------------------------------------------------------------------------------------
from pxr import Usd, UsdGeom  # noqa: E402

from tests.helpers import scenes

# Version 1's bound for these rigs with float32 texels (tests/test_usdskel_semantics.py): scene units.
USDSKEL_TOLERANCE = 2e-4
DQS_TOLERANCE = 1e-3


def _raw_normals(vb, tau):
    """Skinned normals of the first mesh before normalization (their lengths), clip 0 at ``tau``."""
    from vbusd.decoders.reference import bone_transforms, normal_point_indices, skin

    mesh = vb.meshes[0]
    return skin(bone_transforms(vb, 0, [tau]), vb.layout.encoding, mesh.points, mesh.bone_indices,
                mesh.bone_weights, mesh.normals, normal_point_indices(mesh), normalize_normals=False)[1][0]


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_crossfade_equals_blend_of_usdskel_poses(tmp_path, encoding):
    method = "dualQuaternion" if encoding == "dualQuat" else None
    rig = scenes.RigSpec(meshes=[scenes.MeshSpec(normals="vertex", method=method)], bend=70.0)
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    vbusd.convert(source, tmp_path / "asset.usda", vbusd.ConvertOptions(encoding=encoding, texel_format="float32"))
    asset = vbusd.read_asset(tmp_path / "asset.usda")
    vb = asset.animations[0]
    clip = vb.clips[0]
    stage = Usd.Stage.Open(str(tmp_path / "asset.usda"))
    mesh_path = vb.meshes[0].path
    world = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(mesh_path)).ComputeLocalToWorldTransform(0))
    tcps = asset.time_codes_per_second
    rows = [(1, clip.row_count - 2, 0.3), (clip.row_count // 2, 2, 0.65), (0, clip.row_count - 1, 0.5)]
    for row_a, row_b, weight in rows:
        tau_a, tau_b = row_a / clip.rows_per_second, row_b / clip.rows_per_second
        codes = [(clip.start_time + tau) * tcps for tau in (tau_a, tau_b)]
        expected, expected_normals = scenes.usdskel_world(source, mesh_path, codes)
        blended = (1 - weight) * expected[0] + weight * expected[1]
        pose = vbusd.skin(asset, 0, tau_a, fade_clip=0, fade_time=tau_b, fade_weight=weight)[0]
        points = pose.points @ world[:3, :3] + world[3, :3]
        error = np.linalg.norm(points - blended, axis=-1).max()
        assert error < (DQS_TOLERANCE if encoding == "dualQuat" else USDSKEL_TOLERANCE), (encoding, row_a, row_b, error)
        if encoding == "dualQuat":
            continue  # the oracle's normals are UsdSkel.SkinNormalsLBS: LBS only
        # Normals: UsdSkel's two unit normals, each scaled by the length LBS gives it before
        # normalization (sum_i w_i N_i n; spec 8.3 blends the normals before normalization, which
        # is the blend of the two skinning matrices), blended and normalized: within 0.05 degrees.
        lengths = [np.linalg.norm(_raw_normals(vb, tau), axis=-1, keepdims=True) for tau in (tau_a, tau_b)]
        expected_n = (1 - weight) * lengths[0] * expected_normals[0] + weight * lengths[1] * expected_normals[1]
        expected_n /= np.linalg.norm(expected_n, axis=-1, keepdims=True)
        normals = pose.normals @ np.linalg.inv(world[:3, :3]).T
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(np.einsum("vi,vi->v", normals, expected_n), -1, 1))).max()
        assert angle < 0.05, (encoding, angle)
    # and the crossfade is a real blend here: it differs from both poses by much more than the bound
    assert np.linalg.norm(expected[0] - expected[1], axis=-1).max() > 100 * USDSKEL_TOLERANCE


@pytest.mark.node
def test_gltf_crossfade_equals_blend_of_threejs_poses(shared_assets):
    """Fox: Walk at one row blended with Run at another (w = 0.4) against three.js's own skinning
    (GLTFLoader + AnimationMixer + SkinnedMesh, tests/node/skin_pose.mjs) at the two source times,
    blended; float32 texels, within 1e-6 of the bounding-box diagonal (version 1's bound for
    glTF rigs at rows, tests/test_real_characters_gltf.py)."""

    path = shared_asset("gltf", "Fox", "Fox.glb")
    from vbusd.converters import gltf

    scene = gltf.read(path)
    vb = bake(scene.animations[0], BakeOptions(encoding="crossMatrix", texel_format="float32"))
    clips = {clip.name: clip for clip in vb.clips}
    walk, run = clips["Walk"], clips["Run"]
    tau_a, tau_b, weight = 7 / walk.rows_per_second, 11 / run.rows_per_second, 0.4
    poses = []
    for clip, tau in ((walk, tau_a), (run, tau_b)):
        result = node_tools.run_json("skin_pose.mjs", path, clip.name, f"{clip.start_time + tau:.17g}",
                                     packages=("three",))
        poses.append(np.array(result["poses"][0]["meshes"]["fox"], dtype=np.float64).reshape(-1, 3))
    expected = (1 - weight) * poses[0] + weight * poses[1]
    ours = vbusd.skin(vb, "Walk", tau_a, fade_clip="Run", fade_time=tau_b, fade_weight=weight)[0].points
    diagonal = float(np.linalg.norm(expected.max(axis=0) - expected.min(axis=0)))
    error = float(np.linalg.norm(ours - expected, axis=-1).max()) / diagonal
    assert error <= 1e-6, f"crossfade differs from three.js's blended poses by {error:.3g} of the diagonal"
    assert float(np.linalg.norm(poses[0] - poses[1], axis=-1).max()) / diagonal > 1e-2  # a real blend
