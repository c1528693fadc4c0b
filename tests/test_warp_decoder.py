"""Tests of the warp decoder (vbusd.decoders.warp) on every available device.

Two kinds of expected values, neither produced by the kernels themselves:

* hand-worked results of tiny textures (the talk's linear blend of matrices, dual-quaternion
  blending, looping and clamping rows, the point instancer transform);
* the numpy reference decoder (vbusd.decoders.reference, float64), on a synthetic animation baked in every
  encoding and texel format and on the stadium crowd sample: positions must agree within 1e-6 of
  the bounding-box diagonal (the spec's conformance tolerance), unit normals within 5e-6.

Devices: "cpu" always (when warp's CPU backend loads), "cuda" when a CUDA device is present.
"""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


from vbusd.decoders import reference  # noqa: E402
from vbusd.decoders import warp as wd  # noqa: E402
from vbusd.format.errors import InputError, OptionsError  # noqa: E402
from vbusd.format.layout import Layout  # noqa: E402
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones  # noqa: E402

from tests.helpers import scripts  # noqa: E402
from tests.helpers import warp_synthetic as synthetic  # noqa: E402
from tests.helpers.capabilities import require

ROOT = Path(__file__).resolve().parents[1]
DEVICES = wd.available_devices()
ENCODINGS = ["crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"]
FORMATS = ["float16", "float32", "unorm16"]
POSITION_TOLERANCE = 1e-6  # of the bounding-box diagonal
NORMAL_TOLERANCE = 5e-6
H = math.sqrt(0.5)




def diagonal(points):
    flat = np.asarray(points).reshape(-1, 3)
    return float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))


def assert_agrees(result, expected):
    points, normals = result
    ref_points, ref_normals = expected
    assert points.shape == ref_points.shape
    error = np.abs(points - ref_points).max() / diagonal(ref_points)
    assert error <= POSITION_TOLERANCE, f"positions differ by {error:.3g} of the diagonal"
    if ref_normals is None:
        assert normals is None
    else:
        assert normals.shape == ref_normals.shape
        assert np.abs(normals - ref_normals).max() <= NORMAL_TOLERANCE


# Clip-local times: before the start, inside, across the loop's wrap, past the end, far away.
TIMES = np.concatenate([np.linspace(-1.3, 2.7, 41), [0.0, 0.5, 0.99, 1.0, 1.01, 1e3 + 0.123]])


# ------------------------------------------------------------------------------ agreement with numpy


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_skin_agrees_with_reference_for_every_encoding_and_format(device, encoding, texel_format):
    face_varying = texel_format == "unorm16"  # cover faceVarying normals too, without doubling the matrix
    vb = synthetic.make_vb(encoding, texel_format, face_varying=face_varying)
    mesh = vb.meshes[0]
    decoder = wd.Decoder(vb, mesh, device=device)
    for clip_index in range(len(vb.clips)):
        assert_agrees(decoder.skin(clip_index, TIMES).numpy(), reference.skin_mesh(vb, mesh, clip_index, TIMES))
    crowd = synthetic.make_crowd()
    for t in (0.0, 0.77, -5.25):
        assert_agrees(decoder.skin_crowd(crowd, t).numpy(), reference.skin_crowd(vb, mesh, crowd, t))


@pytest.mark.parametrize("device", DEVICES)
def test_compact_encoding_agrees_with_reference(device):
    """Format 1.2's compactQuatTranslation (uint32 words, spec 5.6) on every device, CUDA included:
    rows, mid-rows with the per-row sign flip, the loop's wrap, clamping, crowds and bone buffers."""
    vb = synthetic.make_vb("compactQuatTranslation", "uint32")
    mesh = vb.meshes[0]
    decoder = wd.Decoder(vb, mesh, device=device)
    for clip_index in range(len(vb.clips)):
        assert_agrees(decoder.skin(clip_index, TIMES).numpy(), reference.skin_mesh(vb, mesh, clip_index, TIMES))
    crowd = synthetic.make_crowd()
    for t in (0.0, 0.77, -5.25):
        assert_agrees(decoder.skin_crowd(crowd, t).numpy(), reference.skin_crowd(vb, mesh, crowd, t))
    tau = np.linspace(-0.4, 1.6, 23)
    got, want = decoder.bone_transforms(0, tau), reference.bone_transforms(vb, 0, tau)
    np.testing.assert_allclose(got["linear"][..., :3], want.linear, atol=2e-6)
    np.testing.assert_allclose(got["linear"][..., 3], want.translation, atol=2e-6)
    with pytest.raises(OptionsError, match="texelFetch only"):
        wd.Decoder(vb, mesh, device=device, sampling="hardware")


@pytest.mark.parametrize("device", DEVICES)
def test_compact_rows_with_opposite_signs_blend_the_short_way(device):
    """Row 0 drops x of q0 = (0.8, 0, 0, 0.6); row 1 drops w of q1 = (0.7, 0, 0, -0.7) / |.|, stored
    negated so that w >= 0 (spec 5.6.1): the stored quaternions have a negative dot product. By hand:
    row 0 turns 106.26 degrees about x, row 1 270 (= -90); the short way between them (164 degrees)
    passes 188.13 halfway, which the flip of spec 5.6.4 gives; without it the blend would take the
    long way (196 degrees) through 8.13."""
    from vbusd.format.compact import encode_compact

    q = np.array([[[0.8, 0.0, 0.0, 0.6]], [[0.7, 0.0, 0.0, -0.7]]])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    words, ranges = encode_compact(q, np.zeros((2, 1, 3)), dropped=np.array([[0], [3]]))
    layout = Layout("compactQuatTranslation", "uint32", 1, 2, "none", "none")
    texels = np.zeros(layout.shape, "<u4")
    texels[:, 0, :3] = words[:, 0]
    points = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]], np.float32)
    mesh = BoundMesh("/M", points, np.array([3], np.int32), np.arange(3, dtype=np.int32),
                     np.zeros((3, 1), np.int32), np.ones((3, 1), np.float32), normals=points / np.linalg.norm(points, axis=1, keepdims=True))
    vb = VirtualBones(layout, texels, ("b",), (Clip("c", 0, 2, 1.0, False, 0.0),), ranges, (mesh,))
    halfway, _ = wd.Decoder(vb, mesh, device=device).skin(0, np.array([0.5])).numpy()
    angle = 0.5 * (2 * math.atan2(0.8, 0.6) + 2 * math.atan2(1.0, -1.0))  # mean of 106.26 and 270 degrees
    c, s = math.cos(angle), math.sin(angle)
    expected = points.astype(np.float64) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])  # rows: R p
    # nlerp halfway of two unit quaternions is the slerp midpoint: exact, not approximate
    np.testing.assert_allclose(halfway[0], expected, atol=2e-4)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_bone_buffers_agree_with_reference_transforms(device, encoding):
    vb = synthetic.make_vb(encoding, "float32")
    decoder = wd.Decoder(vb, vb.meshes[0], device=device)
    tau = np.linspace(-0.4, 1.6, 23)
    got = decoder.bone_transforms(0, tau)
    want = reference.bone_transforms(vb, 0, tau)
    if encoding == "dualQuat":
        np.testing.assert_allclose(got["dual"][:, :, 0], want.dual_real, atol=2e-6)
        np.testing.assert_allclose(got["dual"][:, :, 1], want.dual_dual, atol=2e-6)
        return
    np.testing.assert_allclose(got["linear"][..., :3], want.linear, atol=2e-6)
    np.testing.assert_allclose(got["linear"][..., 3], want.translation, atol=2e-6)
    if encoding != "crossMatrix":
        np.testing.assert_allclose(got["normal"], want.normal, atol=5e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_module_functions_have_the_reference_call_shape(device):
    vb = synthetic.make_vb("quatTranslation", "float16")
    mesh, crowd = vb.meshes[0], synthetic.make_crowd(5)
    assert_agrees(wd.skin_mesh(vb, mesh, 1, [0.1, 0.2], device=device), reference.skin_mesh(vb, mesh, 1, [0.1, 0.2]))
    assert_agrees(wd.skin_crowd(vb, mesh, crowd, 2.5, device=device), reference.skin_crowd(vb, mesh, crowd, 2.5))
    uploaded = wd._LAST_DECODER[0][-1]
    assert_agrees(wd.skin_crowd(vb, mesh, crowd, 3.5, device=device), reference.skin_crowd(vb, mesh, crowd, 3.5))
    assert wd._LAST_DECODER[0][-1] is uploaded  # the next frame reuses the uploaded texture and mesh


def _stadium():
    return scripts.load("samples/stadium_crowd.py").make_asset()


@pytest.mark.parametrize("device", DEVICES)
def test_stadium_crowd_sample_agrees_with_reference(device):
    asset = _stadium()
    vb, crowd = asset.animations[0], asset.crowds[0]
    mesh = vb.meshes[0]
    assert (crowd.instance_count, mesh.points.shape[0], vb.layout.width, vb.layout.height) == (1200, 202, 64, 512)
    decoder = wd.Decoder(vb, mesh, device=device)
    for t in (0.0, 3.7):
        assert_agrees(decoder.skin_crowd(crowd, t).numpy(), reference.skin_crowd(vb, mesh, crowd, t))


@pytest.mark.parametrize("device", DEVICES)
def test_stadium_crowd_sample_file_agrees_with_reference(device):
    # The sample as written to disk (USD + float16 EXR texture), read back by vbusd's reader.
    path = ROOT / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    assert path.exists(), f"the committed sample {path} is missing"
    # pxr and OpenEXR are dependencies; only benchmarks/gpu_run.sh's GPU run carries warp without them.
    pytest.importorskip("pxr", reason="benchmarks/gpu_run.sh's GPU run carries numpy and warp only")
    from vbusd.io import usd as usd_io

    asset = usd_io.read_asset(path)
    vb, crowd = asset.animations[0], asset.crowds[0]
    mesh = vb.meshes[0]
    decoder = wd.Decoder(vb, mesh, device=device)
    assert_agrees(decoder.skin_crowd(crowd, 5.2).numpy(), reference.skin_crowd(vb, mesh, crowd, 5.2))
    assert_agrees(decoder.skin(0, [0.0, 9.99]).numpy(), reference.skin_mesh(vb, mesh, 0, [0.0, 9.99]))


# ------------------------------------------------------------------------------ hand-worked values


def _one_bone_vb(rows, encoding="crossMatrix", loop=True, rate=1.0):
    """A float32 texture of one bone whose rows hold the given (T, 4) channel values."""
    rows = np.asarray(rows, dtype=np.float32)
    layout = Layout(encoding, "float32", 1, rows.shape[0], "none")
    mesh = BoundMesh(path="/M", points=np.array([[1.0, 0, 0], [0, 0, 1.0]], np.float32),
                     face_vertex_counts=np.zeros(0, np.int32), face_vertex_indices=np.zeros(0, np.int32),
                     bone_indices=np.zeros((2, 1), np.int32), bone_weights=np.ones((2, 1), np.float32),
                     normals=np.array([[1.0, 0, 0], [0, 0, 1.0]], np.float32))
    return VirtualBones(layout=layout, texels=rows.reshape(layout.shape), bones=("b",),
                        clips=(Clip("c", 0, rows.shape[0], rate, loop),), meshes=(mesh,))


# crossMatrix rows: identity at (0, 0, 0), then 90 degrees about +z translated by (0, 0, 2).
CROSS_ROWS = [[[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 0, 1]],
              [[0, 1, 0, 1], [-1, 0, 0, 1], [0, 0, 2, 1]]]


@pytest.mark.parametrize("device", DEVICES)
def test_cross_matrix_blends_matrices_linearly_like_the_talk(device):
    decoder = wd.Decoder(_one_bone_vb(CROSS_ROWS), device=device)
    points, normals = decoder.skin(0, [0.5, 1.5, -0.25]).numpy()
    # tau 0.5: x = (.5, .5, 0), y = (-.5, .5, 0), z = x cross y = (0, 0, .5), t = (0, 0, 1).
    np.testing.assert_allclose(points[0], [[0.5, 0.5, 1.0], [0, 0, 1.5]], atol=1e-6)
    np.testing.assert_allclose(normals[0], [[H, H, 0], [0, 0, 1]], atol=1e-6)
    # tau 1.5 on a looping clip of 2 rows: row 1 blends back into row 0 halfway: the same pose.
    np.testing.assert_allclose(points[1], points[0], atol=1e-6)
    # tau -0.25 wraps to x = 1.75: 0.25 * row 1 + 0.75 * row 0.
    np.testing.assert_allclose(points[2, 0], [0.75, 0.25, 0.5], atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_clamped_clip_holds_its_first_and_last_rows(device):
    decoder = wd.Decoder(_one_bone_vb(CROSS_ROWS, loop=False, rate=4.0), device=device)
    points, _ = decoder.skin(0, [-3.0, 0.125, 7.0]).numpy()
    np.testing.assert_allclose(points[0, 0], [1, 0, 0], atol=1e-6)  # before the start: row 0
    np.testing.assert_allclose(points[1, 0], [0.5, 0.5, 1.0], atol=1e-6)  # 0.125 s x 4 rows/s = row 0.5
    np.testing.assert_allclose(points[2, 0], [0, 1, 2], atol=1e-6)  # after the end: row 1


@pytest.mark.parametrize("device", DEVICES)
def test_dual_quaternions_blend_rotations_not_matrices(device):
    # Two bones on one vertex with weights 1/2: identity, and 90 degrees about +z stored with the
    # opposite sign (-q): DQS aligns it with the first influence and rotates the point by 45 degrees,
    # where LBS would shrink it to (0.5, 0.5, 0).
    layout = Layout("dualQuat", "float32", 2, 1, "none")
    texels = np.array([[[0, 0, 0, 1], [0, 0, 0, 0], [0, 0, -H, -H], [0, 0, 0, 0]]], np.float32)
    mesh = BoundMesh(path="/M", points=np.array([[1.0, 0, 0]], np.float32),
                     face_vertex_counts=np.zeros(0, np.int32), face_vertex_indices=np.zeros(0, np.int32),
                     bone_indices=np.array([[0, 1]], np.int32), bone_weights=np.array([[0.5, 0.5]], np.float32),
                     normals=np.array([[1.0, 0, 0]], np.float32))
    vb = VirtualBones(layout=layout, texels=texels.reshape(layout.shape), bones=("a", "b"),
                      clips=(Clip("c", 0, 1, 1.0, False),), meshes=(mesh,))
    points, normals = wd.Decoder(vb, device=device).skin(0, 0.0).numpy()
    np.testing.assert_allclose(points[0, 0], [H, H, 0], atol=1e-6)
    np.testing.assert_allclose(normals[0, 0], [H, H, 0], atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_instancer_scales_then_rotates_then_translates(device):
    vb = _one_bone_vb([CROSS_ROWS[0]])  # identity bone
    # 90 degrees about +y: (x, y, z) -> (z, y, -x). Scale (2, 1, 1), position (10, 0, 0).
    crowd = Crowd(path="/C", positions=np.array([[10.0, 0, 0]], np.float32),
                  orientations=np.array([[0, H, 0, H]], np.float32), clip=np.zeros(1, np.int32),
                  time_offset=np.zeros(1, np.float32), playback_rate=np.ones(1, np.float32),
                  scales=np.array([[2.0, 1.0, 1.0]], np.float32))
    points, normals = wd.Decoder(vb, device=device).skin_crowd(crowd, 0.0).numpy()
    np.testing.assert_allclose(points[0], [[10, 0, -2], [11, 0, 0]], atol=1e-5)
    np.testing.assert_allclose(normals[0], [[0, 0, -1], [1, 0, 0]], atol=1e-6)


# ------------------------------------------------------------------------------ hardware texture path


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("texel_format", FORMATS)
def test_hardware_texture_path_stays_within_its_filter_precision(device, texel_format):
    vb = synthetic.make_vb("crossMatrix", texel_format)
    exact = wd.Decoder(vb, device=device)
    hardware = wd.Decoder(vb, device=device, sampling="hardware")
    for clip_index in range(2):
        want = exact.skin(clip_index, TIMES).numpy()[0]
        got = hardware.skin(clip_index, TIMES).numpy()[0]
        error = np.abs(got - want).max() / diagonal(want)
        if device == "cpu":
            # warp's CPU textures filter in software with a full float32 fraction: exact path.
            assert error <= POSITION_TOLERANCE
        else:
            # CUDA filter weights have 8 fractional bits: at most the error of a fraction rounded
            # to 1/256 (modelled by the exact path's fraction_steps; 2.5x leaves room for ties and
            # float32 coordinates). float16 textures are also filtered in half precision: each
            # channel may move by half a float16 ulp, 2^-11 of its size (spec/hardware-sampling.md).
            model = exact.skin(clip_index, TIMES, fraction_steps=256).numpy()[0]
            bound = np.abs(model - want).max() / diagonal(want)
            if texel_format == "float16":
                channels = float(np.abs(vb.texels.astype(np.float64)).max())
                reach = 3.0 * float(np.abs(vb.meshes[0].points).max()) + 1.0
                bound += 2.0 ** -11 * channels * reach / diagonal(want)
            assert error <= 2.5 * bound + POSITION_TOLERANCE


# ------------------------------------------------------------------------------ library object


@pytest.mark.parametrize("device", DEVICES)
def test_decoder_reuses_outputs_and_uploaded_crowds(device):
    vb = synthetic.make_vb("crossMatrix", "float16")
    decoder = wd.Decoder(vb, device=device)
    crowd = synthetic.make_crowd(6)
    out = decoder.allocate(6)
    assert decoder.skin_crowd(crowd, 1.0, out=out) is out
    uploaded = decoder._crowd_cache[1]
    first = out.points.numpy().copy()
    decoder.skin_crowd(crowd, 1.25, out=out)
    assert decoder._crowd_cache[1] is uploaded  # same Crowd object: no second upload
    assert not np.allclose(out.points.numpy(), first)  # the frame moved on
    on_device = decoder.upload_crowd(crowd)
    again = decoder.skin_crowd(on_device, 1.0)
    np.testing.assert_array_equal(again.points.numpy(), first)
    with pytest.raises(OptionsError, match="allocate"):
        decoder.skin_crowd(crowd, 1.0, out=decoder.allocate(5))


def test_bad_inputs_raise_one_line_errors():
    device = DEVICES[0]
    vb = synthetic.make_vb("crossMatrix", "float16")
    with pytest.raises(OptionsError, match="device"):
        wd.Decoder(vb, device=None)
    if "cuda" not in DEVICES:
        with pytest.raises(OptionsError, match="no CUDA device"):
            wd.Decoder(vb, device="cuda")
    with pytest.raises(OptionsError, match="sampling"):
        wd.Decoder(vb, device=device, sampling="nearest")
    decoder = wd.Decoder(vb, device=device)
    with pytest.raises(OptionsError, match="clip index 2"):
        decoder.skin(2, 0.0)
    crowd = synthetic.make_crowd(4, clips=3)  # instance 2 plays clip 2, which does not exist
    with pytest.raises(InputError, match="clip index 2 out of range") as info:
        decoder.skin_crowd(crowd, 0.0)
    assert "/Synthetic/Crowd" in str(info.value)
    mesh = vb.meshes[0]
    broken = BoundMesh(path=mesh.path, points=mesh.points, face_vertex_counts=mesh.face_vertex_counts,
                       face_vertex_indices=mesh.face_vertex_indices, bone_indices=mesh.bone_indices + 3,
                       bone_weights=mesh.bone_weights, normals=mesh.normals)
    with pytest.raises(InputError, match="bone index 7 out of range 0..4"):
        wd.Decoder(vb, broken, device=device)


@pytest.mark.cli
def test_cpu_work_prints_nothing_on_stderr():
    require("warp")  # benchmarks/gpu_run.sh carries warp without its CPU backend
    # Without a CUDA driver, warp's native library prints a warning straight to file descriptor 2
    # on initialization; a CLI decoding on the CPU must still print only its own lines.
    script = ("from vbusd.decoders import warp as wd\n"
              "wd.available_devices()\n"
              "try:\n"
              "    wd._resolve_device('cuda')\n"
              "except Exception as error:\n"
              "    print(error)\n"
              "print(wd._resolve_device('cpu'))\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    if "cuda" not in DEVICES:  # the CUDA request's one error line carries warp's reason instead
        assert "no CUDA device is available" in run.stdout
