"""Core model tests: layout sizes, encodings, quantization, baking and reference skinning.

Expected values are worked out by hand (noted beside each) or come from independent float64
matrices of a synthetic animation, never from the code under test.
"""

import math

import numpy as np
import pytest

from vbusd.baking.baker import BakeOptions, bake, reduce_influences
from vbusd.format.encoding import (decode_bones, dequantize, encode_bones, make_hemispheres_continuous,
                            quantize)
from vbusd.format.errors import OptionsError, UnsupportedError
from vbusd.format.layout import Layout, next_power_of_two
from vbusd.format.model import AnimationClip, Clip, SkinnedAnimation, SkinnedMesh
from vbusd.decoders.reference import row_position, skin, skin_mesh

ENCODINGS = ["crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"]
FORMATS = ["float16", "float32", "unorm16"]
H = math.sqrt(0.5)


def rot_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def matrix(rotation=np.eye(3), translation=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


# ------------------------------------------------------------------------------------- layout


def test_talk_layout_is_64_by_512_and_256_kib():
    layout = Layout("crossMatrix", "float16", 18, 512, vertical_padding="powerOfTwo")
    assert (layout.used_width, layout.width, layout.height) == (54, 64, 512)
    assert layout.texel_bytes == 64 * 512 * 4 * 2 == 262144
    assert layout.padding_fraction == pytest.approx(10 / 64)


def test_power_of_two_rounds_up_never_down():
    # The talk's "closest power of two": 40 texels would not fit in 32 columns.
    assert next_power_of_two(40) == 64
    assert next_power_of_two(64) == 64
    assert next_power_of_two(65) == 128
    assert Layout("quatTranslation", "float32", 18, 300, "none").width == 36
    assert Layout("quatTranslation", "float32", 18, 300).height == 300


def test_layout_rejects_bad_sizes_and_names():
    with pytest.raises(OptionsError):
        Layout("crossMatrix", "float16", 0, 10)
    with pytest.raises(OptionsError):
        Layout("eulerAngles", "float16", 2, 10)
    with pytest.raises(OptionsError):
        Layout("crossMatrix", "float16", 10000, 10)  # 30000 columns exceed the 16384 limit


# ------------------------------------------------------------------------------------- encodings


def test_encodings_of_a_90_degree_z_rotation_match_hand_values():
    m = matrix(rot_z(math.pi / 2), (1, 2, 3))
    np.testing.assert_allclose(encode_bones(m, "crossMatrix"),
                               [[0, 1, 0, 1], [-1, 0, 0, 1], [1, 2, 3, 1]], atol=1e-15)
    np.testing.assert_allclose(encode_bones(m, "affineMatrix"),
                               [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3]], atol=1e-15)
    np.testing.assert_allclose(encode_bones(m, "quatTranslation"), [[0, 0, H, H], [1, 2, 3, 1]], atol=1e-15)
    # dual part 0.5 * (1,2,3,0) (x) (0,0,H,H), multiplied out by hand
    np.testing.assert_allclose(encode_bones(m, "dualQuat"),
                               [[0, 0, H, H], [3 * H / 2, H / 2, 3 * H / 2, -3 * H / 2]], atol=1e-15)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_decode_inverts_encode_for_random_rigid_transforms(encoding):
    rng = np.random.default_rng(1)
    q = rng.normal(size=(40, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T  # rotation matrix of a unit quaternion, written out independently
    rotation = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
    m = np.tile(np.eye(4), (40, 1, 1))
    m[:, :3, :3] = rotation
    m[:, :3, 3] = rng.normal(size=(40, 3)) * 10
    decoded = decode_bones(encode_bones(m, encoding), encoding)
    np.testing.assert_allclose(decoded.linear, rotation, atol=1e-12)
    np.testing.assert_allclose(decoded.translation, m[:, :3, 3], atol=1e-12)


def test_quat_translation_holds_uniform_scale_but_cross_matrix_refuses_it():
    m = matrix(2.0 * rot_z(0.3), (0, 1, 0))
    decoded = decode_bones(encode_bones(m, "quatTranslation"), "quatTranslation")
    np.testing.assert_allclose(decoded.linear, 2.0 * rot_z(0.3), atol=1e-12)
    np.testing.assert_allclose(decoded.normal, rot_z(0.3) / 2.0, atol=1e-12)  # inverse transpose
    with pytest.raises(UnsupportedError, match="scale"):
        encode_bones(m[None], "crossMatrix")
    shear = matrix(np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1.0]]))
    with pytest.raises(UnsupportedError, match="non-uniform"):
        encode_bones(shear, "quatTranslation")
    np.testing.assert_allclose(decode_bones(encode_bones(shear, "affineMatrix"), "affineMatrix").linear,
                               shear[:3, :3])


def test_hemispheres_are_made_continuous_along_rows():
    values = np.zeros((3, 1, 2, 4))
    values[:, 0, 0] = [[0, 0, 0, 1], [0, 0, 0.1, -0.99], [0, 0, 0.2, -0.98]]
    values[:, 0, 1] = [[1, 0, 0, 0], [2, 0, 0, 0], [3, 0, 0, 0]]
    fixed = make_hemispheres_continuous(values, "dualQuat")
    assert fixed[1, 0, 0, 3] > 0 and fixed[2, 0, 0, 3] > 0  # rows 1 and 2 flipped
    np.testing.assert_array_equal(fixed[1, 0, 1], [-2, 0, 0, 0])  # dual part flips with them
    assert make_hemispheres_continuous(values, "quatTranslation")[1, 0, 1, 0] == 2  # T=1 part only


# ------------------------------------------------------------------------------------- texel formats


def test_unorm16_quantization_matches_hand_values():
    values = np.zeros((2, 1, 2, 4))
    values[0, 0, 0, 0], values[1, 0, 0, 0] = -1.0, 3.0
    values[:, 0, 1, 0] = [0.25, 0.75]
    values[:, 0, 1, 3] = 5.0  # constant channel: range of zero width stores 0
    stored, ranges = quantize(values, "unorm16")
    assert stored.dtype == np.dtype("<u2")
    assert list(stored[:, 0, 0, 0]) == [0, 65535]
    assert list(stored[:, 0, 1, 0]) == [0, 65535]
    assert list(stored[:, 0, 1, 3]) == [0, 0]
    np.testing.assert_array_equal(ranges[0, 0], [-1.0, 3.0])
    mid = np.full_like(values, 1.0)
    mid_stored, _ = quantize(mid, "unorm16", ranges)
    assert mid_stored[0, 0, 0, 0] == 32768  # (1 - -1) / 4 * 65535 = 32767.5, rounded half to even
    np.testing.assert_allclose(dequantize(mid_stored, "unorm16", ranges)[0, 0, 0, 0], -1 + 4 * 32768 / 65535)


def test_float16_overflow_and_nan_are_refused():
    with pytest.raises(UnsupportedError, match="float16"):
        quantize(np.full((1, 1, 3, 4), 70000.0), "float16")
    with pytest.raises(UnsupportedError, match="NaN"):
        quantize(np.full((1, 1, 3, 4), np.nan), "float32")


# ------------------------------------------------------------------------------------- clips and rows


def test_row_position_loops_and_clamps():
    loop = Clip("a", 0, 4, 2.0, True)
    i0, i1, f = row_position(loop, np.array([0.0, 1.75, 2.25]))
    assert list(i0) == [0, 3, 0] and list(i1) == [1, 0, 1]
    np.testing.assert_allclose(f, [0, 0.5, 0.5])
    clamp = Clip("b", 0, 4, 2.0, False)
    i0, i1, f = row_position(clamp, np.array([-1.0, 1.25, 5.0]))
    assert list(i0) == [0, 2, 3] and list(i1) == [1, 3, 3]
    np.testing.assert_allclose(f, [0, 0.5, 0])


# ------------------------------------------------------------------------------------- skinning


def test_lbs_and_dqs_of_two_bones_match_hand_values():
    transforms_m = np.stack([np.eye(4), matrix(rot_z(math.pi / 2))])[None]
    point = np.array([[1.0, 0, 0]])
    idx, w = np.array([[0, 1]]), np.array([[0.5, 0.5]])
    for encoding in ("crossMatrix", "affineMatrix", "quatTranslation"):
        decoded = decode_bones(encode_bones(transforms_m, encoding), encoding)
        p, n = skin(decoded, encoding, point, idx, w, normals=point)
        np.testing.assert_allclose(p[0, 0], [0.5, 0.5, 0], atol=1e-12)  # average of (1,0,0) and (0,1,0)
        np.testing.assert_allclose(n[0, 0], [H, H, 0], atol=1e-12)
    decoded = decode_bones(encode_bones(transforms_m, "dualQuat"), "dualQuat")
    p, n = skin(decoded, "dualQuat", point, idx, w, normals=point)
    np.testing.assert_allclose(p[0, 0], [H, H, 0], atol=1e-12)  # DQS: a 45 degree rotation, no shrink
    np.testing.assert_allclose(n[0, 0], [H, H, 0], atol=1e-12)


def test_reduce_influences_keeps_largest_and_renormalizes():
    idx = np.array([[0, 1, 2, 3, 4]])
    w = np.array([[0.1, 0.5, 0.3, 0.05, 0.05]])
    kept_i, kept_w, dropped = reduce_influences(idx, w, 2)
    assert kept_i.tolist() == [[1, 2]]
    np.testing.assert_allclose(kept_w, [[0.625, 0.375]], rtol=1e-6)
    assert dropped == pytest.approx(0.2)


# ------------------------------------------------------------------------------------- bake


def swing_animation(duration=10.0, rate=30.0, loop=None, scale=1.0):
    """Two bones: a root fixed at the origin and a child swinging about Z once per clip."""
    def sample(times):
        times = np.atleast_1d(np.clip(times, 0.0, duration))
        out = np.tile(np.eye(4), (len(times), 2, 1, 1))
        for k, time in enumerate(times):
            angle = 0.8 * math.sin(2 * math.pi * time / duration)
            out[k, 1] = matrix(scale * rot_z(angle), (0, 1 + 0.1 * math.sin(angle), 0)) @ matrix(translation=(0, -1, 0))
        return out

    points = np.array([[0.1, 0.2, 0], [0.0, 1.0, 0.1], [-0.1, 1.5, 0], [0.1, 2.0, -0.1]])
    mesh = SkinnedMesh("/Rig/Mesh", points, np.array([3, 3]), np.array([0, 1, 2, 1, 2, 3]),
                       np.array([[0, 1], [0, 1], [1, 0], [1, 0]]),
                       np.array([[1.0, 0.0], [0.5, 0.5], [0.8, 0.2], [1.0, 0.0]]),
                       normals=np.array([[1.0, 0, 0]] * 4))
    clip = AnimationClip("swing", 0.0, duration, sample, native_rate=rate, loop=loop)
    return SkinnedAnimation("Anim", "/Rig/Anim", ("root", "root/arm"), (clip,), (mesh,)), sample, mesh


def test_bake_resamples_a_10_s_loop_into_512_rows_with_power_of_two_padding():
    animation, _, _ = swing_animation()
    vb = bake(animation, BakeOptions(vertical_padding="powerOfTwo"))
    clip = vb.clips[0]
    assert clip.loop  # first and last poses agree, so it loops
    assert (clip.row_count, clip.rows_per_second) == (512, 51.2)
    assert vb.layout.shape == (512, 8, 4)
    unpadded = bake(animation, BakeOptions())
    assert unpadded.clips[0].row_count == 300
    clamped = bake(animation, BakeOptions(loop=False, rows_per_second=10))
    assert (clamped.clips[0].row_count, clamped.clips[0].rows_per_second) == (101, 10.0)


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("texel_format", FORMATS)
def test_baked_rows_reproduce_the_source_pose(encoding, texel_format):
    animation, sample, mesh = swing_animation()
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format))
    clip = vb.clips[0]
    rows = np.arange(0, clip.row_count, 7)
    tau = rows / clip.rows_per_second
    points, normals = skin_mesh(vb, vb.meshes[0], 0, tau)
    # Independent expectation: LBS with the source's float64 matrices.
    m = sample(tau)
    w = vb.meshes[0].bone_weights.astype(np.float64)
    idx = vb.meshes[0].bone_indices
    per_influence = m[:, idx]  # (n, V, K, 4, 4)
    expected = np.einsum("nvkij,vj,vk->nvi", per_influence[..., :3, :3], mesh.points, w) + \
        np.einsum("nvki,vk->nvi", per_influence[..., :3, 3], w)
    tolerance = {"float32": 1e-6, "float16": 2e-3, "unorm16": 2e-4}[texel_format]
    if encoding == "dualQuat":  # DQS differs from LBS where influences blend
        blended = (w.max(axis=1) < 1)
        expected, points = expected[:, ~blended], points[:, ~blended]
    np.testing.assert_allclose(points, expected, atol=tolerance * 2.0)
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0)


def test_bake_names_bone_and_time_when_cross_matrix_meets_scale():
    animation, _, _ = swing_animation(scale=1.5)
    with pytest.raises(UnsupportedError) as error:
        bake(animation, BakeOptions(encoding="crossMatrix"))
    assert "root/arm" in str(error.value) and "affineMatrix" in str(error.value)
    assert bake(animation, BakeOptions(encoding="affineMatrix")).layout.bone_count == 2


def test_bake_options_are_checked_before_work():
    for bad in ({"encoding": "euler"}, {"rows_per_second": 0}, {"max_influences": 0},
                {"texel_format": "float8"}, {"vertical_padding": "square"}):
        with pytest.raises(OptionsError):
            BakeOptions(**bad)


def test_clip_extents_contain_every_skinned_point():
    animation, _, _ = swing_animation()
    vb = bake(animation, BakeOptions(encoding="affineMatrix", texel_format="float32"))
    clip = vb.clips[0]
    points, _ = skin_mesh(vb, vb.meshes[0], 0, np.linspace(0, clip.duration, 97))
    lo, hi = vb.clip_extents[0]
    assert np.all(points >= lo - 1e-6) and np.all(points <= hi + 1e-6)


def test_affine_matrix_refuses_a_zero_scaled_bone_and_inverts_others_by_cofactors():
    zero = matrix(np.zeros((3, 3)))
    with pytest.raises(UnsupportedError, match="singular"):
        encode_bones(zero[None], "affineMatrix")
    a = np.array([[2.0, 0, 0], [0, 1, 1], [0, 0, 4]])  # inverse transpose worked out by hand
    decoded = decode_bones(encode_bones(matrix(a), "affineMatrix"), "affineMatrix")
    np.testing.assert_allclose(decoded.normal, [[0.5, 0, 0], [0, 1, 0], [0, -0.25, 0.25]], atol=1e-15)


def test_unorm16_ranges_are_float32_numbers_that_contain_every_value():
    values = np.array([0.1, 0.7, -0.3]).reshape(3, 1, 1, 1) * np.ones((3, 1, 1, 4))
    stored, ranges = quantize(values, "unorm16")
    np.testing.assert_array_equal(ranges, ranges.astype(np.float32).astype(np.float64))
    assert np.all(ranges[..., 0] <= -0.3) and np.all(ranges[..., 1] >= 0.7)
    # 0.1 is not a float32, so its bound is the float32 just below/above it, within 1 ulp.
    assert np.all(np.abs(ranges[..., 1] - 0.7) < 1e-7)


def test_power_of_two_fill_never_overshoots_with_tiny_clips():
    from vbusd.baking.baker import plan_rows

    def clip(duration):
        return AnimationClip(f"c{duration}", 0.0, duration, lambda t: None, native_rate=1.0)

    clips = tuple(clip(d) for d in (1.0, 1.0, 0.01, 0.01, 0.01))
    plans = plan_rows(clips, [True] * 5, BakeOptions(vertical_padding="powerOfTwo"))
    # Natural rows: 1 + 1 + three clips of one row = 5 -> target 8; tiny clips keep one row each.
    assert sum(p.row_count for p in plans) == 8
    assert [p.row_count for p in plans[2:]] == [1, 1, 1]


def test_float16_overflow_names_the_bone_clip_and_time():
    def far(times):
        out = np.tile(np.eye(4), (len(np.atleast_1d(times)), 2, 1, 1))
        out[:, 1, 0, 3] = 1e5 * np.atleast_1d(times)  # bone 1 runs away; beyond 65504 after 0.65 s
        return out

    animation = SkinnedAnimation("A", "/A", ("root", "runner"),
                                 (AnimationClip("run", 0.0, 1.0, far, native_rate=10, loop=False),))
    with pytest.raises(UnsupportedError) as error:
        bake(animation, BakeOptions(texel_format="float16"))
    assert "'runner' at time 0.7 s of clip 'run'" in str(error.value)
    assert bake(animation, BakeOptions(texel_format="float32")).layout.row_count == 11


def test_scale_error_names_the_scaled_parent_not_the_child_that_inherits_it():
    def sample(times):
        out = np.tile(np.eye(4), (len(np.atleast_1d(times)), 3, 1, 1))
        out[:, 1, :3, :3] *= 1.5  # bone 1 scaled; bone 2 inherits exactly the same scale
        out[:, 2, :3, :3] *= 1.5
        return out

    animation = SkinnedAnimation("A", "/A", ("root", "root/arm", "root/arm/hand"),
                                 (AnimationClip("c", 0.0, 1.0, sample, native_rate=4),))
    with pytest.raises(UnsupportedError) as error:
        bake(animation, BakeOptions(encoding="crossMatrix"))
    assert "bone 'root/arm' at time 0 s" in str(error.value)


def test_absurd_row_rates_are_refused_before_sampling():
    def sample(times):
        if len(times) > 2:  # the loop decision may look at the two end poses, nothing more
            raise AssertionError("sampled before the size check")
        return np.tile(np.eye(4), (len(times), 1, 1, 1))

    animation = SkinnedAnimation("A", "/A", ("root",), (AnimationClip("c", 0.0, 10.0, sample),))
    with pytest.raises(UnsupportedError, match=r"exceeds the limit .*'c' 10000000 rows at 1e\+06/s"):
        bake(animation, BakeOptions(rows_per_second=1e6))


def _flattened(scales):
    """Bones whose z scale is given: A = diag(1, 1, scale), constant over a 1 s clip."""
    def sample(times):
        out = np.tile(np.eye(4), (len(np.atleast_1d(times)), len(scales), 1, 1))
        out[:, :, 2, 2] = scales
        return out
    names = tuple(f"b{i}" for i in range(len(scales)))
    return SkinnedAnimation("A", "/A", names, (AnimationClip("c", 0.0, 1.0, sample, native_rate=2, loop=False),))


def test_near_singular_affine_bones_are_refused_before_and_after_rounding():
    # |det| = 1e-7 <= 1e-6 x (largest column norm 1)^3: singular by the spec's rule.
    with pytest.raises(UnsupportedError, match="'b1'.*singular"):
        bake(_flattened([1.0, 1e-7]), BakeOptions(encoding="affineMatrix", texel_format="float32"))
    assert bake(_flattened([1.0, 5e-6]), BakeOptions(encoding="affineMatrix", texel_format="float32"))
    # unorm16 over the channel range [-0.5, 1] has an exact zero at u = 21845 (hand-computed:
    # -0.5 + 1.5 * 21845 / 65535 = 0), and 5e-6 rounds to it: the stored bone is singular.
    with pytest.raises(UnsupportedError, match="'b1'.*once rounded to unorm16"):
        bake(_flattened([-0.5, 5e-6, 1.0]), BakeOptions(encoding="affineMatrix", texel_format="unorm16"))


@pytest.mark.parametrize("bones", [12, 90])  # dense weight-matrix path and per-slot path
def test_reference_lbs_matches_a_per_vertex_loop(bones):
    """reference.skin against LBS written out vertex by vertex (repeated indices, faceVarying normals)."""
    from vbusd.format.encoding import BoneTransforms

    rng = np.random.default_rng(7)
    n, vertices, k = 3, 40, 4
    linear = rng.normal(size=(n, bones, 3, 3))
    normal = np.swapaxes(np.linalg.inv(linear), -1, -2)
    transforms = BoneTransforms(linear, rng.normal(size=(n, bones, 3)), normal)
    indices = rng.integers(0, bones, size=(vertices, k))
    indices[0] = [3, 3, 5, 5]
    weights = rng.random((vertices, k))
    weights /= weights.sum(axis=1, keepdims=True)
    points = rng.normal(size=(vertices, 3))
    face_points = rng.integers(0, vertices, size=70)
    rest_normals = rng.normal(size=(70, 3))
    got_points, got_normals = skin(transforms, "affineMatrix", points, indices, weights, rest_normals, face_points)
    for t in range(n):
        for v in range(vertices):
            expected = sum(weights[v, i] * (linear[t, indices[v, i]] @ points[v] + transforms.translation[t, indices[v, i]])
                           for i in range(k))
            np.testing.assert_allclose(got_points[t, v], expected, atol=1e-12)
        for j, v in enumerate(face_points):
            blended = sum(weights[v, i] * (normal[t, indices[v, i]] @ rest_normals[j]) for i in range(k))
            np.testing.assert_allclose(got_normals[t, j], blended / np.linalg.norm(blended), atol=1e-12)


def test_all_finite_in_one_pass_and_exactly_when_a_sum_overflows():
    from vbusd.format.encoding import all_finite

    values = np.ones((5000, 3))
    assert all_finite(values)
    values[4321, 2] = np.nan
    assert not all_finite(values)
    values[4321, 2] = -np.inf
    assert not all_finite(values)
    huge = np.full((5000, 3), 1e308)  # finite values whose sum overflows: checked one by one
    assert all_finite(huge)
    assert all_finite(np.full((10, 3), np.float16(65504)))
    assert all_finite(np.zeros(0)) and all_finite(np.float64(2.0)) and not all_finite(np.float64(np.nan))
