"""The draw-cost benchmark's own correctness logic (benchmarks/draw_cost.py, issue 18).

Its figures are only worth something if every method draws the right frames, so this checks, at a
tiny crowd, what the GPU run relies on: the dense character is a crack-free refinement of the body;
the keyed animation that palette skinning evaluates matches the generator's exact matrices at its
keys; the vertex animation texture holds the exact skinned mesh at its rows; and, in a real OpenGL
pipeline (any EGL driver, Mesa's llvmpipe without a GPU), the read-back of each method's draw shader
agrees with its numpy reference, which in turn disagrees when the time is off. Issue 25: the
``vb_pulled`` method draws the shipped pulled module with the skin records read by ``gl_VertexID``
(every encoding and texel format, K = 1..4, a larger mesh), ``run --plan issue25`` is exactly the
issue's set of configurations, and the report's table states each time as a factor of static.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import draw_cost
from tests.helpers.capabilities import require, unavailable



@pytest.fixture(scope="module")
def dc():
    return draw_cost  # the harness of benchmarks/draw_cost.py


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
    require("gl")
    try:
        ctx, framebuffer = dc.create_context()
    except Exception as error:  # an EGL driver without OpenGL 4.3
        unavailable("gl", f"no EGL OpenGL 4.3 context (Mesa's libegl1 and libgl1-mesa-dri give one): {error}")
    yield ctx, framebuffer
    ctx.release()


def _scene(dc, gl, character, count=3):
    ctx, framebuffer = gl
    crowd = dc.crowd_grid(count)
    return dc.Scene(ctx, framebuffer, character, crowd, np.arange(count))


@pytest.mark.gl
@pytest.mark.parametrize("method_name", ["static", "vb", "vb_pulled", "vat", "palette", "warp"])
def test_each_method_draws_what_numpy_computes(dc, baked, gl, method_name):
    body = dc.stadium_character(baked)
    scene = _scene(dc, gl, body)
    if method_name == "static":
        method = dc.setup_static(scene)
    elif method_name == "vb":
        method = dc.setup_vb(scene, baked, "crossMatrix", "float16")
    elif method_name == "vb_pulled":
        method = dc.setup_vb(scene, baked, "crossMatrix", "float16", skin="pulled")
    elif method_name == "vat":
        method = dc.setup_vat(scene, dc.bake_vat(body.mesh, baked.clips[0]))
    elif method_name == "palette":
        method = dc.setup_palette(scene, dc.KeyedAnimation())
    else:
        from vbusd.decoders.warp import available_devices

        devices = available_devices()  # CUDA (GL interop) where there is a GPU, else warp's CPU backend
        if "cuda" not in devices:
            require("warp")
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


@pytest.mark.gl
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


def _words(indices, weights):
    """The skin record words of one K <= 4 vertex, by hand from spec/shaders.md (Skin records)."""
    k = len(indices)
    padded = list(indices) + [0] * (k % 2)
    pairs = [int(padded[2 * i]) | int(padded[2 * i + 1]) << 16 for i in range(len(padded) // 2)]
    bits = list(np.asarray(weights, "<f4").view("<u4"))
    words = pairs + bits
    return words + [0] * (-len(words) % 4)


@pytest.mark.gl
@pytest.mark.parametrize("encoding,texel_format,variant", [
    ("crossMatrix", "float16", "dense"), ("crossMatrix", "float32", "k1"), ("crossMatrix", "unorm16", "k3"),
    ("affineMatrix", "float16", "k2"), ("affineMatrix", "float32", "body"), ("affineMatrix", "unorm16", "body"),
    ("quatTranslation", "float16", "body"), ("quatTranslation", "float32", "k3"),
    ("quatTranslation", "unorm16", "body"), ("dualQuat", "float16", "k2"), ("dualQuat", "float32", "body"),
    ("dualQuat", "unorm16", "dense")])
def test_pulled_method_reads_the_skin_records_by_vertex_id(dc, gl, encoding, texel_format, variant):
    # vb_pulled (issue 25) must draw the shipped pulled module: the mesh has no skin attributes, the
    # skin comes from the records in the module's storage buffer at gl_VertexID, and the read-back
    # agrees with numpy (and with the attribute binding) for every encoding, texel format and K.
    vb = dc.SAMPLE.bake_reference(encoding=encoding, texel_format=texel_format)
    body = dc.stadium_character(vb)
    character = {"dense": lambda: dc.subdivide(body, 3, vb.layout.bone_count),
                 "k1": lambda: dc.fewer_influences(body, 1, vb.layout.bone_count),
                 "k2": lambda: dc.fewer_influences(body, 2, vb.layout.bone_count),
                 "k3": lambda: dc.fewer_influences(body, 3, vb.layout.bone_count)}.get(variant, lambda: body)()
    k = character.mesh.bone_indices.shape[1]
    scene = _scene(dc, gl, character, count=5)
    method = dc.setup_vb(scene, vb, encoding, texel_format, skin="pulled")
    assert method.name == "vb_pulled"
    # The module is what `vbusd shader --skin pulled --no-main` prints, unchanged (the GPU image of
    # benchmarks/draw_run.sh has no click: there, what the CLI calls).
    source = dc.vb_vertex_shader(encoding, texel_format, k, dc.VB_MAIN_PULLED, skin="pulled")
    try:
        from vbusd.cli import main as vbusd_main
    except ImportError:
        module = dc.vbusd.shader("glsl", encoding, texel_format, max_influences=k, main=False, skin="pulled")
    else:
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            assert vbusd_main(["shader", "--lang", "glsl", "--encoding", encoding, "--texel-format", texel_format,
                               "--max-influences", str(k), "--skin", "pulled", "--no-main"]) == 0
        module = printed.getvalue()
    assert "#define VB_SKIN_PULLED 1" in module and module.strip() in source
    assert "bone_indices" not in source and "bone_weights" not in source
    assert {"bone_indices", "bone_weights"}.isdisjoint(name for name in method.program)
    # The storage buffer holds each vertex's record as the spec lays it out (words by hand).
    texels = -(-(-(-k // 2) + k) // 4)
    stored = np.frombuffer(method.skin_records.read(), "<u4").reshape(character.vertex_count, 4 * texels)
    for vertex in (0, 1, character.vertex_count // 2, character.vertex_count - 1):
        assert list(stored[vertex]) == _words(character.mesh.bone_indices[vertex], character.mesh.bone_weights[vertex])

    result = dc.check(method, scene, vb, None)
    assert result["agrees"], result
    assert result["exact_position_error_m"] < 2e-2
    pulled, pulled_normals, _ = dc.read_back(method, scene, dc.CHECK_TIME)
    attributes = dc.setup_vb(scene, vb, encoding, texel_format)
    points, normals, _ = dc.read_back(attributes, scene, dc.CHECK_TIME)
    assert np.abs(pulled - points).max() <= dc.tolerance(points)
    assert np.abs(pulled_normals - normals).max() <= 1e-5
    # The records are what the shader reads: each vertex given its neighbour's skin draws another pose.
    method.skin_records.write(np.roll(stored, 1, axis=0).tobytes())
    moved, _, _ = dc.read_back(method, scene, dc.CHECK_TIME)
    want, _ = dc.expected(method, scene, dc.CHECK_TIME, vb, None, None)
    assert np.abs(moved - want).max() > 100 * dc.tolerance(want)
    scene.release()


@pytest.mark.gl
@pytest.mark.parametrize("encoding,texel_format,variant", [
    ("crossMatrix", "float16", "body"), ("quatTranslation", "unorm16", "k3"), ("dualQuat", "float32", "dense")])
def test_pulled_texture_method_reads_the_records_as_webgl_must(dc, gl, encoding, texel_format, variant):
    # vb_pulled_texture: the same shipped module with VB_SKIN_STORAGE 0, the records in an RGBA32UI
    # texture (what WebGL 2 and the three.js runtime read); it must agree with numpy, and the texture
    # must be what the shader reads (each vertex given its neighbour's record draws another pose).
    vb = dc.SAMPLE.bake_reference(encoding=encoding, texel_format=texel_format)
    body = dc.stadium_character(vb)
    character = {"dense": lambda: dc.subdivide(body, 3, vb.layout.bone_count),
                 "k3": lambda: dc.fewer_influences(body, 3, vb.layout.bone_count)}.get(variant, lambda: body)()
    k = character.mesh.bone_indices.shape[1]
    scene = _scene(dc, gl, character, count=5)
    method = dc.setup_vb(scene, vb, encoding, texel_format, skin="pulled_texture")
    assert method.name == "vb_pulled_texture" and "RGBA32UI texture" in method.config
    assert {"bone_indices", "bone_weights", "VbSkin"}.isdisjoint(name for name in method.program)
    assert "vb_skinTexture" in {name for name in method.program}
    texels = -(-(-(-k // 2) + k) // 4)
    width, height = method.skin_records.size
    assert width == min(character.vertex_count * texels, 4096)
    stored = np.frombuffer(method.skin_records.read(), "<u4").reshape(-1, 4)[:character.vertex_count * texels]
    stored = stored.reshape(character.vertex_count, 4 * texels)
    for vertex in (0, character.vertex_count // 2, character.vertex_count - 1):
        assert list(stored[vertex]) == _words(character.mesh.bone_indices[vertex], character.mesh.bone_weights[vertex])
    result = dc.check(method, scene, vb, None)
    assert result["agrees"], result
    rolled = np.zeros((width * height, 4), np.uint32)
    rolled[:character.vertex_count * texels] = np.roll(stored, 1, axis=0).reshape(-1, 4)
    method.skin_records.write(rolled.tobytes())
    moved, _, _ = dc.read_back(method, scene, dc.CHECK_TIME)
    want, _ = dc.expected(method, scene, dc.CHECK_TIME, vb, None, None)
    assert np.abs(moved - want).max() > 100 * dc.tolerance(want)
    scene.release()


def test_issue25_texture_plan_sets_the_texture_variant_beside_the_buffer(dc):
    args = dc.parse_args(["run", "--json", "out.json", "--plan", "issue25-texture"])
    plan = dc._plan(args)
    assert len(plan) == len(set(plan)) == 20
    assert plan[:4] == [("stadium", 100_000, m, *(("crossMatrix", "float16") if m != "static" else (None, None)))
                        for m in ("static", "vb", "vb_pulled", "vb_pulled_texture")]
    assert args.budget <= 450 and not args.factors


def test_issue25_plan_is_exactly_the_issue_set(dc):
    args = dc.parse_args(["run", "--json", "out.json", "--plan", "issue25", "--sizes", "5", "--methods", "warp"])
    plan = dc._plan(args)
    assert len(plan) == len(set(plan)) == 20
    assert {(c, n) for c, n, *_ in plan} == {("stadium", 10_000), ("stadium", 100_000), ("stadium", 1_000_000),
                                             ("dense", 1_200), ("dense", 10_000)}
    for character, n in {(c, n) for c, n, *_ in plan}:
        assert sorted(m for c, size, m, *_ in plan if (c, size) == (character, n)) == \
            ["static", "vat", "vb", "vb_pulled"]
    assert all((e, f) == (("crossMatrix", "float16") if m.startswith("vb") else (None, None))
               for _, _, m, e, f in plan)
    assert [(c, n) for c, n, *_ in plan[:8]] == [("stadium", 100_000)] * 4 + [("stadium", 1_000_000)] * 4
    # One device call of 600 s: the run stops starting configurations well before it, no factor study.
    assert args.budget <= 450 and args.min_runs >= 10 and args.warmup_s > 0 and not args.factors
    assert dc.parse_args(["run", "--json", "o", "--plan", "issue25", "--budget", "100"]).budget == 100
    default = dc.parse_args(["run", "--json", "o"])
    assert (default.budget, default.per_config_s, default.min_runs, default.warmup_s, default.factors) == \
        (420.0, 1.5, 3, 0.0, True)
    assert "vb_pulled" in {m for _, _, m, *_ in dc._plan(default)}


def test_bindings_table_states_times_as_factors_of_static(dc):
    def row(character, n, method, ms, error, agrees=True, runs=10):
        vb = method.startswith("vb")
        return {"character": character, "instances": n, "method": method, "encoding": "crossMatrix" if vb else None,
                "texel_format": "float16" if vb else None, "gpu_draw_ms": {"median": ms}, "runs": runs,
                "frame_ms": {"median": ms}, "anim_bytes": 20 * n + 1000,
                "correctness": {"position_error_m": error, "agrees": agrees}}

    data = {"runs": [row("dense", 1_200, "static", 4.0, 0.0), row("dense", 1_200, "vb", 10.0, 2e-6),
                     row("stadium", 100_000, "static", 20.0, 2.5e-7), row("stadium", 100_000, "vb", 33.0, 1e-6),
                     row("stadium", 100_000, "vb_pulled", 20.5, 1.1e-6),
                     row("stadium", 100_000, "vb_pulled_texture", 21.0, 1.2e-6),
                     row("stadium", 100_000, "vat", 25.0, 3e-3, agrees=False)]}
    lines = dc.bindings_markdown(data).splitlines()
    assert len(lines) == 4
    stadium = [c.strip() for c in lines[2].strip("|").split("|")]
    assert stadium[:7] == ["stadium", "100,000", "20.000", "33.000 (1.65x)", "20.500 (1.02x)", "21.000 (1.05x)",
                           "25.000 (1.25x)"]
    assert stadium[7:12] == ["2.5e-07", "1.0e-06", "1.1e-06", "1.2e-06", "3.0e-03 (DISAGREES)"]
    dense = [c.strip() for c in lines[3].strip("|").split("|")]
    assert dense[:7] == ["dense", "1,200", "4.000", "10.000 (2.50x)", "not run", "not run", "not run"]
    goal = [line for line in dc.goals(data) if "VB pulled" in line]
    assert goal == ["VB pulled GPU time at 100,000 stadium instances = 1.025 x static (20.500 vs 20.000 ms): "
                    "goal <= 1.05x MET"]


@pytest.mark.gl
def test_lod_method_draws_each_level_and_selects_as_vbusd_lod(dc, baked, gl):
    """Issue 29's ``vb_lod``: three levels sharing the texture, chosen per instance by a compute shader.
    Each level's transform feedback agrees with numpy's skinning of that level's mesh, and the GPU's
    instances per level equal vbusd.baking.lod's choice (UsdLod's rule; tests/test_lod.py checks it against
    UsdLod itself) with frustum culling, on a crowd large enough that two levels appear."""

    body = dc.stadium_character(baked)
    ctx, framebuffer = gl
    n = 2000
    scene = dc.Scene(ctx, framebuffer, body, dc.crowd_grid(n), np.array([0, 1, 1000, n - 1]), view="stand")
    method = dc.setup_vb_lod(scene, baked, "crossMatrix", "float16")
    result = method.custom_check()
    assert result["agrees"], result
    assert result["levels_gpu"] == result["levels_numpy"]
    assert sum(1 for c in result["levels_gpu"] if c) >= 2 and result["culled_numpy"] > 0
    assert method.level_triangles[0] == 352 and method.level_triangles[0] > method.level_triangles[1] > \
        method.level_triangles[2]
    frame = dc.render_frame(method, scene, 2.0, scene.ctx.query(time=True))
    assert frame.wall >= frame.cpu > 0
    assert method.level_counts().tolist() == result["levels_gpu"]
    for item in method.release:
        item.release()
    scene.release()


def test_issue29_plan_compares_one_level_with_three_in_the_same_view(dc):
    args = dc.parse_args(["run", "--json", "out.json", "--plan", "issue29"])
    plan = dc._plan(args)
    assert [(c, n, m) for c, n, m, *_ in plan] == [("stadium", n, m) for n in (1_000_000, 100_000, 10_000)
                                                   for m in ("vb", "vb_lod")]
    assert dc.PLAN_VIEWS["issue29"] == "stand" and args.budget <= 450 and args.min_runs >= 10


MACHINE_PATH = r"(?<![\w$.])/(?:root|home|work|opt|tmp|mnt|srv|var|usr/local)/"
"""The start of an absolute path of some machine (a user's home, a work tree, a device's venv)."""


def test_committed_results_hold_no_machine_paths_and_failures_are_noted():
    """Issue 35 item 18: the committed results name no machine's paths, and every committed test
    log that shows a failing test has the failing test named in benchmarks/README.md."""
    import re

    results = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
    readme = (results.parent / "README.md").read_text()
    for path in sorted(results.iterdir()):
        if path.suffix not in (".json", ".log", ".md", ".txt", ".csv"):
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        found = re.findall(MACHINE_PATH + r"\S*", text)
        assert not found, f"{path.name} names machine paths: {found[:3]}"
        if path.suffix == ".log":
            for failed in re.findall(r"^_{3,} (test_\w+)", text, flags=re.M):
                assert failed in readme, f"{path.name}: {failed} fails there and benchmarks/README.md does not say why"


def test_a_result_records_its_command_without_machine_paths(dc, monkeypatch, tmp_path):
    import re

    out = tmp_path / "device_out"
    monkeypatch.setenv("OUT", str(out))
    root = Path(__file__).resolve().parents[1]
    line = dc.command_line([str(root / "benchmarks" / "draw_cost.py"), "run", "--json", str(out / "r.json"),
                            "--cache", "/opt/some/venv/cache.bin"])
    assert line == "benchmarks/draw_cost.py run --json $OUT/r.json --cache cache.bin"
    assert not re.search(MACHINE_PATH, line)


# ----------------------------------------------------------------------------------------------
# Issue 36: the previous-frame pose (--previous), what the lead times on the device
# ----------------------------------------------------------------------------------------------


@pytest.mark.gl
@pytest.mark.parametrize("skin", ["attributes", "pulled", "pulled_texture"])
def test_previous_pose_methods_draw_what_numpy_computes_and_write_velocity(dc, baked, gl, skin):
    """With --previous the read-back's previous positions agree with reference.skin_crowd_previous
    (the check fails when they are the current ones: the crowd moves 100 times the tolerance in a
    frame), and a drawn frame writes non-zero screen-space velocity into the RG16F target."""
    body = dc.stadium_character(baked)
    scene = _scene(dc, gl, body)
    method = dc.setup_vb(scene, baked, "crossMatrix", "float16", skin=skin, previous=True)
    result = dc.check(method, scene, baked, None)
    assert result["agrees"], result
    assert result["previous_position_error_m"] < 1e-5
    assert result["previous_motion_m"] > 100 * result["tolerance_m"]
    frame = dc.render_frame(method, scene, 2.0, scene.ctx.query(time=True))
    assert frame.wall >= frame.cpu > 0
    velocity = np.frombuffer(method.framebuffer.read(components=2, attachment=1, dtype="f2"), dtype="<f2")
    assert np.isfinite(velocity).all() and np.abs(velocity).max() > 0
    for item in method.release:
        item.release()
    scene.release()


def test_previous_axis_and_the_issue36_plan(dc, capsys):
    default = dc.parse_args(["run", "--json", "o"])
    assert default.previous == "off"
    args = dc.parse_args(["run", "--json", "o", "--plan", "issue36"])
    assert args.previous == "both" and not args.factors and args.budget <= 450
    plan = dc._plan(args)
    assert {m for _, _, m, *_ in plan} == {"static", "vb", "vb_pulled_texture"}
    assert dc.parse_args(["run", "--json", "o", "--plan", "issue36", "--previous", "on"]).previous == "on"
    with pytest.raises(SystemExit):
        dc.parse_args(["--help"])
    assert "--previous" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        dc.parse_args(["run", "--help"])
    assert "--previous {off,on,both}" in capsys.readouterr().out


def test_previous_table_states_the_cost_as_a_ratio(dc):
    def row(method, ms, previous):
        return {"character": "stadium", "instances": 1000, "method": method, "encoding": "crossMatrix",
                "texel_format": "float16", "previous": previous, "gpu_draw_ms": {"median": ms},
                "frame_ms": {"median": ms + 1}, "correctness": {"previous_position_error_m": 2e-6} if previous else {}}
    table = dc.previous_markdown({"runs": [row("vb", 2.0, False), row("vb", 3.0, True), row("static", 1.0, False)]})
    assert "| stadium | 1,000 | vb (crossMatrix float16) | 2.000 | 3.000 | 1.50 | 3.000 | 4.000 | 2.00e-06 |" in table


@pytest.mark.gl
def test_variety_method_draws_the_same_body_and_colours_by_tint_and_variant(dc, baked, gl):
    """Issue 37's ``vb_variety``: the body read back by transform feedback is the numpy decoder's (variety
    moves no vertex); in the picture an instance's pixels carry its variant colour x tint (the instance
    nearest the camera, its body's projected centre), and the hat draws only on instances whose mask has it:
    the picture with every hat hidden differs from it exactly where hats stand."""
    from vbusd.format.variety import VARIANT_COLORS

    ctx, framebuffer = gl
    body = dc.stadium_character(baked)
    scene = _scene(dc, gl, body, count=16)
    method = dc.setup_vb_variety(scene, baked, "crossMatrix", "float16", dc.SAMPLE.hat_mesh())
    correctness = dc.check(method, scene, baked, None)
    assert correctness["agrees"], correctness
    tint, variant, parts = dc.variety_arrays(16)
    assert set(parts) == {0, 1}
    t = 1.0
    ctx.enable(scene.moderngl.DEPTH_TEST)

    def picture():
        method.set_time(method.program, t)
        framebuffer.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        dc._draw(method, scene)
        width, height = dc.RESOLUTION
        return np.frombuffer(framebuffer.read(components=3), np.uint8).reshape(height, width, 3).astype(float)

    image = picture()
    from vbusd.decoders.reference import skin_crowd  # noqa: PLC0415

    points, _ = skin_crowd(baked, body.mesh, dc.crowd_rows(scene.crowd, np.arange(16)), t)
    width, height = dc.RESOLUTION
    centres = np.concatenate([points.mean(axis=1), np.ones((16, 1))], axis=1) @ scene.view_projection.T
    pixels = np.stack([(centres[:, 0] / centres[:, 3] + 1) / 2 * width,
                       (centres[:, 1] / centres[:, 3] + 1) / 2 * height], axis=1).astype(int)  # rows from the bottom
    # The row nearest the camera (lowest on the picture): no other instance stands in front of it.
    front = np.argsort(pixels[:, 1])[:4]
    for i in front:
        pixel = image[pixels[i, 1], pixels[i, 0]]
        assert pixel.any(), i
        colour = np.asarray(VARIANT_COLORS[variant[i]]) * tint[i]
        np.testing.assert_allclose(pixel / pixel.max(), colour / colour.max(), atol=0.08)
    assert len({(int(variant[i]), tuple(tint[i])) for i in front}) >= 2  # the check tells colours apart
    # The hat's draw collapses exactly the instances whose mask hides it: its vertex shader read back
    # by transform feedback over every instance puts each non-wearer's 8 hat vertices on its position.
    hat_tf = ctx.program(vertex_shader=method.vertex_shader, varyings=dc.VARYINGS)
    hat_tf["vb_texture"].value = 0
    hat_tf["vb_clips"].value = method.program["vb_clips"].value
    hat_tf["part_bit"].value = 0
    method.set_time(hat_tf, t)
    vao = ctx.vertex_array(hat_tf, [(method.hat_vertices, *dc.Scene.MESH_FORMAT),
                                    (scene.placement, *dc.PLACEMENT[1]), (scene.animation, *dc.ANIMATION_CLIP_TIME[1]),
                                    (method.variety_buffer, "16x 1i/i", "instance_parts")],  # the colour is not fed back
                           skip_errors=True)
    out = ctx.buffer(reserve=16 * 8 * 24)
    vao.transform(out, mode=scene.moderngl.POINTS, vertices=8, instances=16)
    hat_points = np.frombuffer(out.read(), "<f4").reshape(16, 8, 6)[:, :, :3]
    positions = np.asarray(scene.crowd.positions, np.float64)
    for i in range(16):
        on_position = np.allclose(hat_points[i], positions[i], atol=1e-6)
        assert on_position == (not parts[i]), i
        if parts[i]:  # worn: on the head, about 1.9 m above the feet
            assert hat_points[i][:, 1].mean() - positions[i][1] > 1.5, i
    for item in (vao, out, hat_tf):
        item.release()
    for item in method.release:
        item.release()


def test_variety_axis_plans_variety_on_and_off(dc):
    """``run --variety both`` measures each vb configuration with and without variety, ``on`` with only;
    ``--plan issue37`` is both at 100,000, 1,000,000 and 10,000 spectators."""
    both = dc._plan(dc.parse_args(["run", "--json", "x.json", "--sizes", "100000", "--characters", "stadium",
                                   "--methods", "vb", "--variety", "both"]))
    assert ("stadium", 100_000, "vb", "crossMatrix", "float16") in both
    assert ("stadium", 100_000, "vb_variety", "crossMatrix", "float16") in both
    only = dc._plan(dc.parse_args(["run", "--json", "x.json", "--sizes", "100000", "--characters", "stadium",
                                   "--methods", "vb", "--variety", "on"]))
    assert {item[2] for item in only} == {"vb_variety"}
    plan = dc._plan(dc.parse_args(["run", "--json", "x.json", "--plan", "issue37"]))
    assert [(n, m) for _, n, m, _, _ in plan][:2] == [(100_000, "vb"), (100_000, "vb_variety")]
