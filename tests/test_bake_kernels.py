"""The compiled twins of the bake (vbusd.kernels.bake) against their numpy twins and UsdSkel.

Each kernel is compared with the numpy code it replaces on the same inputs (random near-rotations,
random skinning, baked animations in every linear-blend encoding and texel format), and a whole
conversion of a generated 101-joint rig through the kernels is compared with the same conversion
through numpy (the same texels, the same bounds) and with UsdSkel's own skinning (the
conversion's accuracy check). The all-frames skinning transforms are checked against UsdSkel's
``ComputeSkinningTransforms`` on every shared asset in tests/test_usdskel_all_frames.py, and the
clip extents against every decoded vertex in tests/test_clip_extents.py, both on each path.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import vbusd  # noqa: F401  (registers the schema before pxr builds its registry)
from vbusd.kernels import bake as bake_kernels
from vbusd.process import parallel
from vbusd.format import encoding as enc

from tests.helpers.capabilities import require
from tests.helpers.rigs import build_rig


@pytest.fixture(autouse=True)
def _compiled_kernels():
    """Every test here compiles warp kernels on the CPU."""
    require("warp")


REPO = Path(__file__).resolve().parents[1]


def _force(monkeypatch, compiled: bool) -> None:
    monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 0 if compiled else 1 << 62)


def _near_rotations(count: int, wobble: float, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(count, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rotation = enc.quat_to_matrix(q)
    return rotation + wobble * rng.normal(size=rotation.shape)


def _matrices(linear: np.ndarray, seed: int = 6) -> np.ndarray:
    m = np.zeros(linear.shape[:-2] + (4, 4))
    m[..., :3, :3] = linear
    m[..., :3, 3] = np.random.default_rng(seed).normal(scale=3.0, size=linear.shape[:-2] + (3,))
    m[..., 3, 3] = 1.0
    return m


def test_polar_rotation_equals_the_numpy_iteration(monkeypatch):
    linear = _near_rotations(3000, 2e-5).reshape(30, 100, 3, 3)
    _force(monkeypatch, True)
    compiled = enc._near_rotation_polar(linear, 1e-3, bake_kernels)
    _force(monkeypatch, False)
    reference = enc._near_rotation_polar(linear, 1e-3, bake_kernels)
    assert compiled.rotation.shape == reference.rotation.shape == linear.shape
    assert np.abs(compiled.rotation - reference.rotation).max() <= 1e-14
    assert np.abs(compiled.det - reference.det).max() <= 1e-14
    # an orthonormal result: the iteration converged
    gram = np.einsum("...ji,...jk->...ik", compiled.rotation, compiled.rotation)
    assert np.abs(gram - np.eye(3)).max() <= 1e-13


@pytest.mark.parametrize("case", ["sheared", "mirrored"])
def test_polar_refuses_what_numpy_refuses(monkeypatch, case):
    linear = _near_rotations(500, 1e-5)
    if case == "sheared":
        linear[123, 0, 1] += 0.01
    else:
        linear[77] *= -1.0
    _force(monkeypatch, True)
    assert enc._near_rotation_polar(linear, 1e-3, bake_kernels) is None
    _force(monkeypatch, False)
    assert enc._near_rotation_polar(linear, 1e-3, bake_kernels) is None


def test_cross_matrix_encoding_equals_numpy_and_falls_back_on_bad_matrices(monkeypatch):
    matrices = _matrices(_near_rotations(4000, 2e-5))
    _force(monkeypatch, True)
    compiled = enc.encode_bones(matrices, "crossMatrix", compiled=bake_kernels)
    _force(monkeypatch, False)
    reference = enc.encode_bones(matrices, "crossMatrix", compiled=bake_kernels)
    assert compiled.shape == reference.shape == (4000, 3, 4)
    assert np.abs(compiled - reference).max() <= 1e-14
    # A non-finite translation or a non-rigid matrix: the kernel declines, numpy answers and reports
    matrices[10, 1, 3] = np.nan
    assert bake_kernels.encode_cross_matrix(matrices, 1e-3) is None
    matrices[10, 1, 3] = 0.0
    matrices[20, :3, :3] *= 1.5
    assert bake_kernels.encode_cross_matrix(matrices, 1e-3) is None
    _force(monkeypatch, True)
    with pytest.raises(enc.NonRigidError) as raised:
        enc.encode_bones(matrices, "crossMatrix", compiled=bake_kernels)
    assert raised.value.index == (20,)


@pytest.mark.parametrize("dense", [True, False], ids=["few-bones", "many-bones"])
def test_linear_blend_skinning_equals_the_reference(monkeypatch, dense):
    from vbusd.jobs.conversion import _skin_checked
    from vbusd.decoders.reference import decode_bones, skin
    from vbusd.format.layout import Encoding
    from vbusd.format.model import BoundMesh

    rng = np.random.default_rng(8)
    bones = 20 if dense else 90  # the reference blends a dense weight matrix below 64 bones
    values = enc.encode_bones(_matrices(_near_rotations(4 * bones, 1e-6)).reshape(4, bones, 4, 4), "affineMatrix")
    transforms = decode_bones(values, "affineMatrix")
    points = rng.normal(size=(3000, 3))
    indices = rng.integers(0, bones, size=(3000, 4))
    weights = rng.random((3000, 4))
    weights /= weights.sum(axis=1, keepdims=True)
    normals = rng.normal(size=(5000, 3))
    normal_points = rng.integers(0, 3000, size=5000)  # faceVarying normals
    bound = BoundMesh(path="/M", points=points, bone_indices=indices, bone_weights=weights, normals=normals,
                      normals_interpolation="faceVarying", face_vertex_counts=np.zeros(0, dtype=np.int64),
                      face_vertex_indices=normal_points)
    expected = skin(transforms, Encoding.AFFINE_MATRIX, points, indices, weights, normals, normal_points)
    _force(monkeypatch, True)
    got = _skin_checked(transforms, Encoding.AFFINE_MATRIX, bound, normal_points)
    assert np.abs(got[0] - expected[0]).max() <= 1e-12 * np.abs(expected[0]).max()
    assert np.abs(got[1] - expected[1]).max() <= 1e-12
    assert np.allclose(np.linalg.norm(got[1], axis=-1), 1.0)


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    """The benchmark's rig, smaller: 101 joints, 400 frames, 2,500 points, every joint moving; with
    vertex normals, so that a conversion checks its normals against UsdSkel's too."""
    path = tmp_path_factory.mktemp("rig") / "rig.usdc"
    build_rig(path, frames=400, points=2500, joints=101, normals=True)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("encoding,texel_format", [("crossMatrix", "float16"), ("affineMatrix", "float32"),
                                                   ("quatTranslation", "unorm16")])
def test_clip_extents_equal_the_numpy_bounds(monkeypatch, rig, encoding, texel_format):
    from vbusd.jobs.conversion import ConvertOptions, bake_animation
    from vbusd.converters import usdskel
    from vbusd.decoders import bounds
    from vbusd.decoders.reference import channel_values
    from vbusd.format.model import ReadOptions

    scene = usdskel.read(rig, ReadOptions())
    _force(monkeypatch, False)
    vb, _, _ = bake_animation(scene, 0, ConvertOptions(encoding=encoding, texel_format=texel_format))
    clip = vb.clips[0]
    times = bounds._sample_times(clip, bounds.SUBSTEPS[encoding])
    rest = bounds._bone_boxes(vb)
    boxes = {}
    for compiled in (False, True):
        _force(monkeypatch, compiled)
        boxes[compiled] = bounds._bone_box_bounds(vb, 0, clip, times, lambda: channel_values(vb), rest, 4_000_000)
    for numpy_part, compiled_part in zip(boxes[False], boxes[True]):
        scale = max(1.0, float(np.abs(numpy_part).max()))
        assert np.abs(compiled_part - numpy_part).max() <= 1e-12 * scale, (numpy_part, compiled_part)


@pytest.mark.slow
def test_a_whole_conversion_is_the_same_either_way_and_matches_usdskel(monkeypatch, rig, tmp_path):
    from vbusd.jobs.conversion import ConvertOptions, convert
    from vbusd.io.usd_reader import read_asset

    reports, assets = {}, {}
    for compiled in (False, True):
        _force(monkeypatch, compiled)
        output = tmp_path / ("compiled" if compiled else "numpy") / "rig.vb.usdc"
        reports[compiled] = convert(rig, output, ConvertOptions(check_rows=None))  # every row checked
        assets[compiled] = read_asset(output)
    numpy_vb, compiled_vb = (assets[c].animations[0] for c in (False, True))
    assert np.array_equal(numpy_vb.texels, compiled_vb.texels)
    assert np.array_equal(numpy_vb.clip_extents, compiled_vb.clip_extents)
    for compiled in (False, True):
        mesh = reports[compiled].animations[0].meshes[0]
        assert mesh.rows_checked == numpy_vb.layout.row_count
        # UsdSkel's own skinning of every row is the yardstick: float16 texels hold it to 1e-3 of the box
        assert mesh.max_error_fraction < 1e-3, mesh
    first, second = (reports[c].animations[0].meshes[0] for c in (False, True))
    assert second.max_error == pytest.approx(first.max_error, rel=1e-9)
    # The normals are checked against UsdSkel.SkinNormals (the rig authors them; a mesh without
    # normals reports None, which is no number to compare). float16 rounds each axis to 2^-11, and
    # where a vertex blends bones turned far apart its blended normal is short, so renormalizing
    # magnifies that: 4.1 degrees at worst on this rig (float32 texels: 0.0023 degrees).
    assert first.max_normal_error_degrees is not None and second.max_normal_error_degrees is not None
    assert first.max_normal_error_degrees < 5.0, first
    assert second.max_normal_error_degrees == pytest.approx(first.max_normal_error_degrees, rel=1e-9, abs=1e-9)


def test_work_is_split_into_disjoint_slices_that_cover_it(monkeypatch):
    monkeypatch.setattr(parallel, "_workers", lambda: 3)
    seen = np.zeros(10_000, dtype=np.int64)

    def mark(start, stop):
        seen[start:stop] += 1

    parallel.split_work(10_000, mark)
    assert (seen == 1).all()
    bake_kernels.split_work(0, mark)
    assert (seen == 1).all()


def test_vbusd_threads_limits_the_slices(monkeypatch):
    """A batch worker runs with VBUSD_THREADS=1: one slice, on the calling thread."""
    import threading

    calls = []
    monkeypatch.setenv("VBUSD_THREADS", "1")
    bake_kernels.split_work(50_000, lambda a, b: calls.append((a, b, threading.current_thread())))
    assert calls == [(0, 50_000, threading.current_thread())]
    monkeypatch.setenv("VBUSD_THREADS", "2")
    calls.clear()
    bake_kernels.split_work(50_000, lambda a, b: calls.append((a, b, threading.current_thread())))
    assert sorted(c[:2] for c in calls) == [(0, 25_000), (25_000, 50_000)]
