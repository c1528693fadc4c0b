"""The draw-cost benchmark's own correctness logic (benchmarks/draw_cost.py, issue 18).

Its figures are only worth something if every method draws the right frames, so this checks, at a
tiny crowd, what the GPU run relies on: the dense character is a crack-free refinement of the body;
the keyed animation that palette skinning evaluates matches the generator's exact matrices at its
keys; the vertex animation texture holds the exact skinned mesh at its rows; and, in a real OpenGL
pipeline (any EGL driver, Mesa's llvmpipe without a GPU), the read-back of each method's draw shader
agrees with its numpy reference, which in turn disagrees when the time is off.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "draw_cost.py"


@pytest.fixture(scope="module")
def dc():
    spec = importlib.util.spec_from_file_location("vbusd_bench_draw_cost", BENCHMARK)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def baked(dc):
    return dc.SAMPLE.bake_reference()


def _edge_uses(triangles):
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


def _area(points, triangles):
    p = np.asarray(points, np.float64)[triangles]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


@pytest.mark.parametrize("splits", [2, 3, 5])
def test_subdivision_is_a_closed_flat_refinement(dc, baked, splits):
    body = dc.stadium_character(baked)
    dense = dc.subdivide(body, splits, baked.layout.bone_count)
    v, f = body.vertex_count, len(body.triangles)
    edges = len(np.unique(np.sort(np.concatenate([body.triangles[:, [0, 1]], body.triangles[:, [1, 2]],
                                                  body.triangles[:, [2, 0]]]), axis=1), axis=0))
    assert dense.vertex_count == v + edges * (splits - 1) + f * (splits - 1) * (splits - 2) // 2
    assert len(dense.triangles) == f * splits * splits
    assert (_edge_uses(body.triangles) == 2).all()  # the body is closed ...
    assert (_edge_uses(dense.triangles.astype(np.int64)) == 2).all()  # ... and so is its refinement
    assert np.isclose(_area(dense.mesh.points, dense.triangles), _area(body.mesh.points, body.triangles), rtol=1e-5)
    np.testing.assert_array_equal(dense.mesh.points[:v], body.mesh.points)
    np.testing.assert_allclose(dense.mesh.bone_weights.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(dense.mesh.normals, axis=1), 1.0, atol=1e-5)


def test_the_issue_size_of_the_dense_character(dc, baked):
    dense = dc.subdivide(dc.stadium_character(baked), dc.DENSE_SPLITS, baked.layout.bone_count)
    assert (dense.vertex_count, len(dense.triangles)) == (50_890, 101_728)


def test_keyed_animation_matches_the_generator(dc):
    keys = dc.KeyedAnimation()
    at_keys = np.array([0.0, 1 / 30, 4.5, 299 / 30, 10.0 + 7 / 30, -2 / 30])
    exact = dc.SAMPLE.skinning_matrices(at_keys)[:, :, :3, :]
    assert np.abs(keys.evaluate(at_keys) - exact).max() < 2e-6
    between = np.array([0.5 / 30, 3.0 + 0.5 / 30, 9.99])
    error = np.abs(keys.evaluate(between) - dc.SAMPLE.skinning_matrices(between)[:, :, :3, :]).max()
    assert 1e-5 < error < 1e-2  # interpolating 30 fps keys: close, but not the exact curve


def test_vertex_animation_texture_holds_the_exact_pose_at_rows(dc, baked):
    body = dc.stadium_character(baked)
    clip = baked.clips[0]
    vat = dc.bake_vat(body.mesh, clip)
    assert vat.nbytes == 2 * body.vertex_count * clip.row_count * 8
    crowd = dc.crowd_rows(dc.crowd_grid(5), np.arange(5))
    rows = np.array([0, 17, 255, 511, 3])
    t = 0.0
    crowd = dc.vbusd.Crowd(path=crowd.path, positions=crowd.positions, orientations=crowd.orientations,
                           clip=crowd.clip, time_offset=(rows / clip.rows_per_second).astype(np.float32),
                           playback_rate=np.ones(5, np.float32))
    points, normals = dc.vat_pose(vat, crowd, body.vertex_count, t)
    exact_points, exact_normals = dc.exact_pose(crowd, body.mesh, t)
    assert np.abs(points - exact_points).max() < 2e-3  # float16 storage of metre-scale positions
    assert np.abs(normals - exact_normals).max() < 2e-3


@pytest.fixture(scope="module")
def gl(dc):
    pytest.importorskip("moderngl", reason="install moderngl (pip install moderngl)")
    try:
        ctx, framebuffer = dc.create_context()
    except Exception as error:  # no EGL driver, or no OpenGL 4.3
        pytest.skip(f"no EGL OpenGL 4.3 context (install Mesa's libegl1 and libgl1-mesa-dri): {error}")
    yield ctx, framebuffer
    ctx.release()


def _scene(dc, gl, character, count=3):
    ctx, framebuffer = gl
    crowd = dc.crowd_grid(count)
    return dc.Scene(ctx, framebuffer, character, crowd, np.arange(count))


@pytest.mark.parametrize("method_name", ["static", "vb", "vat", "palette", "warp"])
def test_each_method_draws_what_numpy_computes(dc, baked, gl, method_name):
    body = dc.stadium_character(baked)
    scene = _scene(dc, gl, body)
    if method_name == "static":
        method = dc.setup_static(scene)
    elif method_name == "vb":
        method = dc.setup_vb(scene, baked, "crossMatrix", "float16")
    elif method_name == "vat":
        method = dc.setup_vat(scene, dc.bake_vat(body.mesh, baked.clips[0]))
    elif method_name == "palette":
        method = dc.setup_palette(scene, dc.KeyedAnimation())
    else:
        pytest.importorskip("warp", reason="install warp-lang")
        from vbusd.decode.warp import available_devices

        devices = available_devices()  # CUDA (GL interop) where there is a GPU, else warp's CPU backend
        if not devices:
            pytest.skip("warp has neither a CUDA device nor its CPU backend here")
        method = dc.setup_warp(scene, baked, "cuda" if "cuda" in devices else "cpu")
    vat = dc.bake_vat(body.mesh, baked.clips[0]) if method_name == "vat" else None
    result = dc.check(method, scene, baked, vat)
    assert result["agrees"], result
    assert result["position_error_m"] < 1e-5
    if method_name != "static":
        # Each method follows the animation (the generator's exact pose) to within its storage's error.
        assert result["exact_position_error_m"] < 1e-2
        # The comparison can fail: the same read-back against numpy 0.1 s later does not agree.
        points, _, extra = dc.read_back(method, scene, dc.CHECK_TIME)
        later, _ = dc.expected(method, scene, dc.CHECK_TIME + 0.1, baked, vat, extra if extra is None else
                               dc.KeyedAnimation().evaluate(dc.reference.instance_time(scene.check_crowd,
                                                                                       dc.CHECK_TIME + 0.1)))
        assert np.abs(points - later).max() > 100 * dc.tolerance(later)
    frame = dc.render_frame(method, scene, 2.0, scene.ctx.query(time=True))
    assert frame.wall >= frame.cpu > 0
    scene.release()


@pytest.mark.parametrize("variant", ["skin_buffers", "packed_vb", "packed_static", "k2"])
def test_factor_study_variants_draw_what_numpy_computes(dc, baked, gl, variant):
    # The one-factor study (draw_cost.py factors) changes how the skin reaches the vertex shader; each
    # variant must still draw the pose numpy computes, and the packed weights must be exact unorm8.
    body = dc.stadium_character(baked)
    character = {"packed_vb": dc.packed_weights(body), "packed_static": dc.packed_weights(body),
                 "k2": dc.fewer_influences(body, 2, baked.layout.bone_count)}.get(variant, body)
    if variant.startswith("packed"):
        q = character.mesh.bone_weights.astype(np.float64) * 255
        np.testing.assert_allclose(q, np.round(q), atol=1e-4)
        np.testing.assert_allclose(character.mesh.bone_weights.sum(axis=1), 1.0, atol=1e-6)
    ctx, framebuffer = gl
    scene = dc.Scene(ctx, framebuffer, character, dc.crowd_grid(3), np.arange(3),
                     packed_skin=variant.startswith("packed"))
    if variant == "packed_static":
        method = dc.setup_static(scene, dc.STATIC_SKIN_ATTRIBUTES_VS, "packed")
    else:
        method = dc.setup_vb(scene, baked, "crossMatrix", "float16", skin_buffers=variant == "skin_buffers")
    result = dc.check(method, scene, baked, None)
    assert result["agrees"], result
    if variant != "packed_static":
        # The check can fail: against the wrong pose (0.1 s later; or the original float weights, which
        # unorm8 moves by up to 1/510 and K=2 by much more) the read-back does not agree.
        points, _, _ = dc.read_back(method, scene, dc.CHECK_TIME)
        if variant == "skin_buffers":
            other, _ = dc.reference.skin_crowd(baked, body.mesh, scene.check_crowd, dc.CHECK_TIME + 0.1)
        else:
            other, _ = dc.reference.skin_crowd(baked, body.mesh, scene.check_crowd, dc.CHECK_TIME)
        assert np.abs(points - other).max() > (5 if variant == "packed_vb" else 100) * dc.tolerance(other)
    scene.release()
