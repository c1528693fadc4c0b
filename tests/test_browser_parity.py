"""One feature, every WebGL engine: the three.js and Babylon.js runtimes probed on the same assets.

Each test is parametrized over the engines of ``vbusd view`` that draw with WebGL 2 in headless
Chromium (SwiftShader): ``three`` (WebGLRenderer, web/src) and ``babylon`` (web/babylon). Both build
their shaders from @vbusd/core (web/core: the module of ``vbusd shader``, skin records, playback
parameters, the transform-feedback probe), so a feature the core carries runs in both. Every probe
is checked against vbusd's numpy decoder (``vbusd.skin``, ``vbusd.decoders.reference``), which
shares no code with the browser path beyond the stored texels: positions within 1e-6 of the
instance's bounding-box diagonal, unit normals within 1e-5.

* the compact encoding (format 1.2, uint32 words in an RGBA32UI texture, per-bone ranges);
* the pulled skin binding (skin records in an RGBA32UI texture read by ``gl_VertexID``);
* layers with bone masks (format 1.2) on top of crossfades;
* a crowd of ``vbusd crowd --fade-window ... --layer ...``: its fade weight is time-sampled, and
  the probe at each time equals ``vbusd.skin`` given that instance's clip, fade and layer by hand
  (before, inside and after the window);
* a ``vbusd export`` package of a mesh without normals (the Fox) through each engine's glTF loader;
* unorm16 where the browser lacks EXT_texture_norm16: one clear line naming the alternative;
* blend spaces per instance (format 1.3), played as layers under the rig's every-bone mask, and their clip events;
* additive layers (format 1.3, primvars:vb:layerMode) beside override ones;
* root motion (``crowd.rootMotionMatrix``) against ``vbusd.root_motion``, and sockets
  (``crowd.socketMatrix``) of a crossfading stadium crowd against ``crowd_joint_transforms``;
* the Khronos Fox and CesiumMan (shared assets) with the compact encoding, in a crossfading crowd of
  ``vbusd crowd --fade-clips``, drawn in the pulled binding;
* the previous-frame pose (motion vectors, spec 21): the probe's ``previousPositions`` for the
  page's ``?dt=`` equal the decoder at t - dt, across a loop boundary and a clamped clip's end;
* crowd variety (format 1.3): tints, material variants and parts masks, read back from the page and
  seen in a screenshot, and a prop at a socket (the flag) where the socket puts it (the section at the end).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers.browser import layered_stadium as layered_stadium_file
from tests.helpers.browser import (CHARACTER_CAMERA, NORMAL_TOLERANCE, PAGE, POSITION_TOLERANCE, SAMPLE, STADIUM_PROBES,
                                   across_clip_time, assert_within, check_previous, check_probe, engine_probe_errors,
                                   evaluate_arrays, open_engine_page, package_probe_errors, rasterize_nearest,
                                   reference_instance)
from tests.helpers import lod_row as lod_row_helpers
from tests.helpers.animations import loop_walk
from tests.helpers.crowds import additive_chain, by_hand as crowd_by_hand, chain_character, primvars
from tests.helpers import scripts
from tests.helpers.browser import NO_ADAPTER
from tests.helpers.capabilities import require, unavailable
from tests.helpers.variety import modular_character

ENGINES = ("three", "babylon", "three-webgpu")


@pytest.fixture
def webgl_browser(browser):
    """The session's Chromium with plain WebGL 2 (tests/helpers/fixtures.py)."""
    return browser


@pytest.fixture
def browser(browser, request):
    """The browser that runs the test's ``engine``: the session's WebGPU Chromium for three-webgpu,
    else its plain WebGL 2 one (one playwright driver per process: tests/helpers/fixtures.py)."""
    engine = getattr(getattr(request.node, "callspec", None), "params", {}).get("engine")
    return request.getfixturevalue("webgpu_browser") if engine == "three-webgpu" else browser


def open_page(browser, server: ViewerServer, query: str = "") -> ViewerPage:
    return open_engine_page(browser, server, PAGE + query)


def probe_errors(browser, path: Path, engine: str, probes, query: str = "", asset=None, check=None, then=None) -> list:
    """(position error / diagonal, normal error) of each (instance, time) probe of ``path`` drawn by
    ``engine``; ``check(page)`` looks at the same page first, ``then(page)`` after the probes
    returns more (error, error) pairs."""

    def checks(page):
        if "skin=pulled" in query:  # every crowd draws with the records, no bone streams
            assert set(page.page.evaluate("window.vbusd.crowds.map((crowd) => crowd.skin)")) == {"pulled"}
        if check is not None:
            check(page)

    return engine_probe_errors(browser, path, engine, probes, query=query, asset=asset, check=checks, then=then)


def layers_matter(asset, instance: int, t: float, found: list):
    """A page check: the probe of ``instance`` at ``t`` is more than 1e-3 of the diagonal away from
    the decoder of ``asset`` without its layers (appended to ``found``), so the probes saw them (on
    the page the probes use: a second page would compile the engine's shaders again)."""
    plain = dataclasses.replace(asset, crowds=(dataclasses.replace(asset.crowds[0], layer_weight=None),))
    return lambda page: found.append(check_probe(page, plain, instance, t)[0])


@pytest.mark.parity('compact encoding (uint32)')
@pytest.mark.parametrize("engine", ENGINES)
def test_compact_encoding(browser, compact_stadium, engine):
    errors = probe_errors(browser, compact_stadium, engine, STADIUM_PROBES)
    print(engine, "compactQuatTranslation", errors)
    assert_within(errors, engine)


@pytest.mark.parity('pulled skin binding')
@pytest.mark.parametrize("engine", ENGINES)
def test_pulled_skin_binding(browser, bar_crowd, engine):
    """The skin records read by gl_VertexID; the page's geometries keep no bone attributes."""
    errors = probe_errors(browser, bar_crowd, engine, [(i, t) for i in range(0, 10, 3) for t in (0.0, 0.61)], "&skin=pulled")
    print(engine, "pulled", errors)
    assert_within(errors, engine)


@pytest.fixture(scope="module")
def layered_stadium(tmp_path_factory):
    """The stadium with masks upper=spine and arm=R_upperArm, two layers per instance on top of a
    crossfade (as tests/test_browser.py's layer test), quatTranslation float16."""
    return layered_stadium_file(tmp_path_factory.mktemp("layered"))


@pytest.mark.parity('layers with masks')
@pytest.mark.parametrize("engine", ENGINES)
def test_layers_with_masks(browser, layered_stadium, engine):
    asset = vbusd.read_asset(layered_stadium)
    assert asset.crowds[0].layered
    plain = []
    errors = probe_errors(browser, layered_stadium, engine, [(i, 0.83) for i in range(6)], asset=asset,
                          check=layers_matter(asset, 4, 0.83, plain))
    print(engine, "layers", errors)
    assert_within(errors, engine)
    # The layers matter: without them instance 4 is elsewhere.
    assert plain[0] > 1e-3


@pytest.fixture(scope="module")
def fade_window_crowd(tmp_path_factory):
    """`vbusd crowd --fade-clips run:2,wave --fade-window 0.5 1.5 --layer upper wave` of the chain
    character (tests/test_crowd.py): 12 instances, fade weight time-sampled 0 at 0.5 s, 1 at 1.5 s."""
    from vbusd.cli import main

    folder = tmp_path_factory.mktemp("fade_window")
    character = chain_character(folder)
    out = folder / "crowd.usda"
    status = main(["crowd", str(character), "-o", str(out), "--count", "12", "--yaw", "0", "0", "--seed", "5",
                   "--clips", "walk", "--rate", "0.8", "1.2",
                   "--fade-clips", "run:2,wave", "--fade-window", "0.5", "1.5", "--fade-time-offset", "-0.5", "-0.5",
                   "--fade-rate", "0.9", "1.1", "--layer", "upper", "wave", "--layer-weight", "0.25", "0.75",
                   "--layer-rate", "1", "1.5", "--format", "json"])
    assert status == 0
    return character, out


@pytest.mark.parity('crossfade, time-sampled fade (`--fade-window`)')
@pytest.mark.parametrize("engine", ENGINES)
def test_fade_window_and_layers_of_vbusd_crowd(browser, fade_window_crowd, engine):
    """The viewer follows the time-sampled fade weight: each probe equals vbusd.skin of the
    character with the instance's clip, crossfade (the weight ramp 0 before 0.5 s, 1 after 1.5 s,
    linear between) and layer given by hand."""
    character, path = fade_window_crowd
    check_fade_window(browser, path, engine, character, primvars(path))


def check_fade_window(browser, served: Path, engine: str, character: Path, values: dict) -> None:
    """Probes of the `--fade-window 0.5 1.5` crowd served from ``served`` (its USD file or a package
    of it) before, inside and after the window, each within the tolerance of vbusd.skin given the
    instance's clip, crossfade (weight 0 before 0.5 s, 1 after 1.5 s, linear between) and layer by hand."""

    def weight_at(i, t):
        return float(np.clip((t - 0.5) / (1.5 - 0.5), 0.0, 1.0))

    with ViewerServer(served, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            for t in (0.2, 0.9, 1.25, 1.8):
                for i in (0, 5, 11):
                    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [i, t])
                    got = np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3)
                    expected = crowd_by_hand(character, values, i, t, weight_at)
                    diagonal = float(np.linalg.norm(np.ptp(expected, axis=0)))
                    error = float(np.abs(got - expected).max()) / diagonal
                    print(engine, served.suffix, t, i, error)
                    assert error <= POSITION_TOLERANCE, (t, i, error)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.mark.parity("glTF package through the engine's loader, mesh without normals")
@pytest.mark.parametrize("engine", ENGINES)
def test_gltf_package_of_a_mesh_without_normals(browser, shared_assets, tmp_path, engine):
    """The Fox (no normals) as a `vbusd export` glb through each engine's glTF loader: the probe
    gives its positions (as the numpy decoder on the USD asset) and no normals."""
    from vbusd.io.gltf_package import export_gltf

    usd = tmp_path / "fox" / "Fox.usda"
    vbusd.convert(shared_assets / "gltf" / "Fox" / "Fox.glb", usd,
                  vbusd.ConvertOptions(encoding="quatTranslation", texel_format="float16", check_rows=0))
    asset = vbusd.read_asset(usd)
    assert all(mesh.normals is None for vb in asset.animations for mesh in vb.meshes)
    package = tmp_path / "fox.glb"
    export_gltf(asset, package)
    errors = package_probe_errors(browser, package, engine, asset, ((0, 0.0), (0, 0.8137), (0, 2.9)))
    assert max(errors) <= POSITION_TOLERANCE  # and no normals: the asset has none


@pytest.fixture(scope="module")
def unorm16_stadium(tmp_path_factory):
    path = tmp_path_factory.mktemp("unorm16") / "u" / "stadium.usda"
    vbusd.convert(SAMPLE / "stadium_crowd.usda", path,
                  vbusd.ConvertOptions(encoding="quatTranslation", texel_format="unorm16", check_rows=0))
    return path


# What each engine needs for 16-bit normalized textures, and how the page asks for it.
NORM16 = {
    "three": ("EXT_texture_norm16", "!!document.createElement('canvas').getContext('webgl2').getExtension('EXT_texture_norm16')"),
    "babylon": ("EXT_texture_norm16", "!!document.createElement('canvas').getContext('webgl2').getExtension('EXT_texture_norm16')"),
    "three-webgpu": ("texture-formats-tier1", "navigator.gpu.requestAdapter().then((a) => a.features.has('texture-formats-tier1'))"),
}


@pytest.mark.parity('unorm16')
@pytest.mark.parametrize("engine", ENGINES)
def test_unorm16(browser, unorm16_stadium, engine, record_property):
    """unorm16 needs 16-bit normalized textures: EXT_texture_norm16 on WebGL 2, the adapter feature
    texture-formats-tier1 (rgba16unorm) on WebGPU. Where the browser has it the probe matches the
    decoder; where it lacks it (SwiftShader's WebGL 2) the page says so in one line naming what is
    missing and the alternative."""
    feature, available = NORM16[engine]
    with ViewerServer(unorm16_stadium, engine=engine) as server:
        page = open_page(browser, server)
        try:
            has = page.page.evaluate(available)
            print(engine, feature, has)
            if not has:
                record_property("parity_note", f"one line naming float16/float32 without {feature} (absent here); with it not run here")
                assert feature in page.error and "--texel-format float16 or float32" in page.error, page.error
                assert "\n" not in page.error.strip()
                return
            assert page.error == "", page.error
            asset = vbusd.read_asset(unorm16_stadium)
            errors = [check_probe(page, asset, instance, t) for instance, t in STADIUM_PROBES]
            print(engine, "unorm16", errors)
            assert_within(errors, engine)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.fixture(scope="module")
def lod_row(tmp_path_factory):
    """tests/test_browser_lod.py's row of the modular spectator (body, hat and flag parts) with 3 levels,
    instances at chosen distances in front of the page's camera (one behind it) with parts masks, as a
    .glb (MSFT_lod)."""
    require("lod")
    folder = tmp_path_factory.mktemp("lod_row")
    asset, package = lod_row_helpers.make_row_package(folder, modular=True)
    usd = folder / "usd" / "row.usda"  # the same crowd as USD: vbusd view serves it as the plain files
    usd.parent.mkdir()
    vbusd.write_asset(asset, usd)
    return asset, package, usd


# Where each engine's levels of detail come from in test_levels_of_detail: the runtime package's
# MSFT_lod through the engine's glTF loader (Babylon's: VBUSD_virtual_bones adopts the levels' nodes
# and turns Babylon's progressive MSFT_lod loading off), or the plain files of the USD crowd.
LOD_SOURCE = {"three": "glb", "three-webgpu": "glb", "babylon": "glb"}


@pytest.mark.parity('levels of detail')
@pytest.mark.parametrize("engine", ENGINES)
def test_levels_of_detail(browser, lod_row, engine, record_property):
    """The level each instance draws equals OpenUSD's UsdLodScreenSizeHeuristic.ComputeLOD for the
    page's camera (-1: outside the view, culled), and the probe skins that level's meshes as vbusd's
    decoder does (1e-6 of the diagonal plus one float32 rounding of the world coordinate). Parts on
    levels (spec 22.3): each level's part meshes draw the instances at that level with their
    placement where the mask shows the part and collapsed (linear part zero: nothing drawn, as
    test_crowd_variety's screenshot shows) where it hides it."""
    from vbusd.decoders.reference import skin_crowd

    asset, package, usd = lod_row
    vb = asset.animations[0]
    expected_levels = lod_row_helpers.usdlod_levels(asset)
    assert sorted(set(expected_levels)) == [-1, 0, 1, 2], expected_levels
    meshes = {level: [m for m in vb.meshes if m.lod == level] for level in range(3)}
    crowd = asset.crowds[0]
    t = 1.37
    if LOD_SOURCE[engine] == "usd":
        record_property("parity_note", "from the plain files of a USD crowd (its glTF loader does not read MSFT_lod yet)")
    with ViewerServer(package if LOD_SOURCE[engine] == "glb" else usd, engine=engine) as server:
        page = ViewerPage(browser, server.url + lod_row_helpers.PAGE)
        try:
            assert page.error == "", page.error
            page.page.evaluate("() => window.vbusd.render()")
            levels = page.page.evaluate("() => window.vbusd.levels()")
            assert levels["lod"] == expected_levels
            triangles = [sum(len(m.face_vertex_counts) for m in meshes[level]) for level in expected_levels if level >= 0]
            assert levels["triangles"] == sum(triangles)
            check_level_parts(page, engine, asset, expected_levels)
            for instance, level in enumerate(expected_levels):
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, t])
                assert result["lod"] == level
                if level < 0:
                    continue
                one = dataclasses.replace(crowd, **{f: getattr(crowd, f)[instance:instance + 1] for f in
                                                    ("positions", "orientations", "clip", "time_offset", "playback_rate")})
                expected = np.concatenate([skin_crowd(vb, mesh, one, t)[0][0] for mesh in meshes[level]])
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                assert positions.shape == expected.shape
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                tolerance = 1e-6 * diagonal + np.finfo(np.float32).eps * float(np.abs(expected).max())
                error = float(np.abs(positions - expected).max())
                print(engine, instance, level, error / diagonal)
                assert error <= tolerance
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def drawn_matrices(page, engine: str, level=None) -> list:
    """What each mesh of the page's first crowd draws with: ``[{name, part (the part bit the engine gave
    it, -1: no part), count, matrices (count, 4, 4) column-vector}]`` of level ``level`` (None: a crowd without levels), read from the instance buffers
    the engine uploads (three: the InstancedMesh's instanceMatrix; Babylon: the thin-instance matrices)."""
    meshes = "crowd.levels[level]" if level is not None else "crowd.meshes"
    read = ("{name: mesh.name, part: mesh.userData.virtualBones.part, count: mesh.count,"
            " m: Array.from(mesh.instanceMatrix.array.subarray(0, 16 * mesh.count))}"
            if engine.startswith("three") else
            "{name: mesh.name, part: mesh.metadata.virtualBones.part, count: mesh.thinInstanceCount,"
            " m: mesh.thinInstanceGetWorldMatrices().slice(0, mesh.thinInstanceCount).flatMap((x) => Array.from(x.m))}")
    got = page.page.evaluate(f"(level) => {{ const crowd = window.vbusd.crowds[0]; return {meshes}.map((mesh) => ({read})); }}", level)
    return [dict(item, matrices=np.asarray(item["m"], np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)) for item in got]


def placements(crowd) -> np.ndarray:
    """(N, 4, 4) placement of each instance (scale, then orientation, then position: spec 15), by hand from the quaternions."""
    x, y, z, w = np.asarray(crowd.orientations, np.float64).T
    rotation = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                         np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                         np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)
    scale = np.ones((len(x), 3)) if crowd.scales is None else np.asarray(crowd.scales, np.float64)
    out = np.tile(np.eye(4), (len(x), 1, 1))
    out[:, :3, :3] = rotation * scale[:, None, :]
    out[:, :3, 3] = np.asarray(crowd.positions, np.float64)
    return out


def expected_part_matrix(placement: np.ndarray, shown: bool) -> np.ndarray:
    """A part's matrix for one instance (spec 22.3): the placement, or with its linear part zero where hidden."""
    out = placement.copy()
    if not shown:
        out[:3, :3] = 0.0
    return out


def check_level_parts(page, engine: str, asset, levels) -> None:
    """Each level's meshes draw the instances at that level, in instance order; a part mesh's slot is
    the instance's placement where its mask shows the part and collapsed where it hides it (spec 22.3,
    parts and levels of detail), for the part names the crowd gives (Hat bit 0, Flag bit 1)."""
    crowd = asset.crowds[0]
    place = placements(crowd)
    seen = {}
    for level in sorted({level for level in levels if level >= 0}):
        at_level = [i for i, chosen in enumerate(levels) if chosen == level]
        drawn = drawn_matrices(page, engine, level)
        assert sorted(mesh["part"] for mesh in drawn) == [-1, 0, 1], (engine, level)  # the body, the hat, the flag
        for mesh in drawn:
            bit = mesh["part"]
            name = crowd.part_names[bit] if bit >= 0 else "body"
            assert mesh["count"] == len(at_level), (engine, level, name)
            for slot, i in enumerate(at_level):
                shown = bit < 0 or bool(crowd.parts[i] >> bit & 1)
                seen.setdefault((name, shown), set()).add(level)
                np.testing.assert_allclose(mesh["matrices"][slot], expected_part_matrix(place[i], shown), atol=1e-5,
                                           err_msg=f"{engine} level {level} {name} instance {i}")
    # Both parts were seen shown and hidden at levels 0 and 1 (tests/helpers/lod_row.py's PARTS).
    for name in ("Hat", "Flag"):
        assert {0, 1} <= seen[(name, True)] and {0, 1} <= seen[(name, False)], seen


@pytest.mark.parity("root motion")
@pytest.mark.parametrize("engine", ENGINES)
def test_root_motion_on_the_page(browser, tmp_path, engine):
    """Root motion (format 1.1, spec 8.5) on each engine's page: ``crowd.rootMotionMatrix(i, t0, t1)``
    of a walk baked in place (extractYaw: it turns while it walks) equals ``vbusd.root_motion`` for
    pairs of times forward, backward and across loops; its step over a frame ``(t - dt, t)`` is the
    one between ``reference.root_motion_crowd`` at ``t - dt`` and at ``t`` (spec 21.1: the previous pose's
    placement). The root tracks have no layout-metadata key,
    so the page is given them as an application gives them (``crowd.rootMotion``)."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.decoders import reference
    from vbusd.format.model import Crowd, SkinnedMesh, VirtualBonesAsset
    from vbusd.format.quaternion import quat_to_matrix

    walk = loop_walk(0.4)
    triangle = SkinnedMesh("/Walk/Mesh", np.array([[0.0, 1.0, 0.0], [0.2, 0.0, 0.1], [-0.2, 0.0, 0.1]]), np.array([3]),
                           np.array([0, 1, 2]), np.zeros((3, 1), np.int64), np.ones((3, 1)))
    walk = dataclasses.replace(walk, meshes=(triangle,))  # a drawable mesh (the walk's own is one edge)
    vb = bake(walk, BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extractYaw"))
    path = tmp_path / "walk" / "walk.usda"
    vbusd.write_asset(VirtualBonesAsset(animations=(vb,), default_prim="Walk"), path)
    vb = vbusd.read_asset(path).animations[0]
    pairs = [(0.0, 0.5), (0.25, 2.75), (2.75, 0.25), (-1.3, 0.1), (0.0, 1.0), (2.0 - 1 / 60, 2.0)]
    root = {"upAxis": vb.root_motion.up_axis, "tracks": [track.tolist() for track in vb.root_motion.tracks]}
    # three's column-major elements and Babylon's row-vector m: the same 16 numbers.
    elements = "m.toArray()" if engine.startswith("three") else "Array.from(m.m)"
    with ViewerServer(path, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            got = page.page.evaluate(f"""([root, pairs]) => {{ const crowd = window.vbusd.crowds[0]; crowd.rootMotion = root;
                return pairs.map(([t0, t1]) => {{ const m = crowd.rootMotionMatrix(0, t0, t1); return {elements}; }}); }}""",
                                     [root, pairs])
            for (t0, t1), matrix in zip(pairs, got):
                expected = vbusd.root_motion(vb, 0, t0, t1)
                assert not np.allclose(expected, np.eye(4))  # the walk moves between every pair
                np.testing.assert_allclose(np.array(matrix).reshape(4, 4).T, expected, atol=1e-5)
            # The previous frame's step (spec 21.1): M(t) M(t - dt)^-1 of the crowd moved at t - dt and at t.
            moved = [reference.root_motion_crowd(vb, Crowd("/c", np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]),
                                                           np.zeros(1, np.int32), np.zeros(1), np.ones(1)), time)
                     for time in pairs[-1]]
            placed = [np.block([[quat_to_matrix(c.orientations[0]), c.positions[0][:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
                      for c in moved]
            np.testing.assert_allclose(np.array(got[-1]).reshape(4, 4).T, placed[1] @ np.linalg.inv(placed[0]), atol=1e-5)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.fixture(scope="module")
def blending_chain(tmp_path_factory):
    """The chain character (walk, run, wave) with a 1D and a 2D blend space and a crowd of six
    instances playing them at their own parameters, phases and rates (format 1.3, spec 23.7)."""
    from vbusd.format.model import Crowd
    from vbusd.format.motion import parse_blend_space, parse_marker

    folder = tmp_path_factory.mktemp("blend")
    asset = vbusd.read_asset(chain_character(folder))
    vb = dataclasses.replace(asset.animations[0], blend_spaces=(
        parse_blend_space("speed=walk@0,run@1"), parse_blend_space("mix=walk@0:0,run@1:0,wave@0:1")),
        markers=tuple(parse_marker(m) for m in ("walk:step@0.5", "walk:step@1.5", "run:step@0.25", "wave:hi@1")))
    n = 6
    crowd = Crowd("/Chain/Crowd", np.column_stack([np.arange(n) * 1.5, np.zeros(n), np.zeros(n)]).astype(np.float32),
                  np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), np.zeros(n, np.int32), np.zeros(n, np.float32),
                  np.array([1.0, 0.75, 1.25, 1.0, 0.5, 1.0], np.float32),
                  blend_space=np.array([0, 0, 1, 1, 1, -1], np.int32),
                  blend_x=np.array([0.25, 0.8, 0.2, 0.5, 0.1, 0.0], np.float32),
                  blend_y=np.array([0.0, 0.0, 0.3, 0.25, 0.7, 0.0], np.float32),
                  blend_phase=np.array([0.0, 0.125, 0.25, 0.0, 0.375, 0.0], np.float32))
    path = folder / "blend" / "blend.usda"
    vbusd.write_asset(dataclasses.replace(asset, animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), path)
    return path


@pytest.mark.parity("blend spaces")
@pytest.mark.parametrize("engine", ENGINES)
def test_blend_spaces(browser, blending_chain, engine):
    """A crowd playing 1D and 2D blend spaces (spec 23.7) as the runtimes' layers under the rig's
    every-bone mask (23.1; vbusd view converts with reference.blends_as_layers): each instance's
    probe against the numpy decoder's blend."""
    asset = vbusd.read_asset(blending_chain)
    assert asset.crowds[0].blended
    for i in range(5):  # the blended instances are not their clip (walk) played plainly
        blended, _ = reference_instance(asset, i, 0.37)
        plain = vbusd.skin(asset.animations[0], "walk", 0.37)[0].points + asset.crowds[0].positions[i]
        assert float(np.abs(blended - plain).max()) > 1e-3 * float(np.linalg.norm(plain.max(0) - plain.min(0)))
    # On the same page load: the runtime API's crowd.setBlend (the same signature in every engine)
    # turns instance 5, which plays its clip, into a 2D blend; its probe against the decoder of the
    # crowd with that blend stored (spec 23.7).
    blend = {"space": "mix", "x": 0.3, "y": 0.4, "phase": 0.2, "playbackRate": 1.1}
    crowd = asset.crowds[0]
    changed = dataclasses.replace(asset, crowds=(dataclasses.replace(
        crowd, blend_space=np.array([*crowd.blend_space[:5], 1], np.int32),
        blend_x=np.array([*crowd.blend_x[:5], 0.3], np.float32), blend_y=np.array([*crowd.blend_y[:5], 0.4], np.float32),
        blend_phase=np.array([*crowd.blend_phase[:5], 0.2], np.float32),
        playback_rate=np.array([*crowd.playback_rate[:5], 1.1], np.float32)),))

    def set_blend(page):
        plan = page.page.evaluate("(blend) => window.vbusd.crowds[0].setBlend(5, blend)", blend)
        assert len(plan["layers"]) == 2  # three points weighted: the base and both layer slots
        return [check_probe(page, changed, 5, t) for t in (0.0, 0.37)]

    errors = probe_errors(browser, blending_chain, engine, [(i, t) for i in range(6) for t in (0.0, 0.37)], asset=asset,
                          then=set_blend)
    print(engine, "blend spaces (the last two: setBlend)", errors)
    assert_within(errors, engine)
    blended, _ = reference_instance(changed, 5, 0.37)
    plain, _ = reference_instance(asset, 5, 0.37)
    assert float(np.abs(blended - plain).max()) > 1e-3 * float(np.linalg.norm(plain.max(0) - plain.min(0)))


@pytest.fixture(scope="module")
def additive_crowd(tmp_path_factory):
    """The chain character's crowd of additive and override layers (tests/helpers/crowds.py's
    ADDITIVE_ROWS: format 1.3 primvars:vb:layerMode, layerReferenceClip, layerReferenceTime), its last
    instance playing a synced 1D blend space, and its `vbusd export` package (the same as
    ``_VB_LAYER_MODE_j``, ``_VB_LAYER_REFERENCE_*_j`` and ``_VB_BLEND_*`` instance attributes)."""
    from vbusd.io.gltf_package import export_gltf

    path = additive_chain(tmp_path_factory.mktemp("additive"), blends=True)
    package = path.with_suffix(".glb")
    export_gltf(vbusd.read_asset(path), package)
    return path, package


@pytest.mark.parity("additive layers")
@pytest.mark.parametrize("engine", ENGINES)
def test_additive_layers(browser, additive_crowd, engine):
    """Additive layers (spec 23.4) on top of override ones in every engine, beside a blending instance
    (23.7): each instance's probe against the numpy decoder, which equals vbusd.skin(..., layers=[{...,
    "mode": "additive", "reference": ...}]) for these instances (tests/test_additive_layers.py);
    without the additive layers' modes the instances are elsewhere. Twice: the USD crowd through
    vbusd view's plain files, and its glTF package through the engine's glTF loader
    (spec/runtime-package.md 5.1)."""
    path, package = additive_crowd
    asset = vbusd.read_asset(path)
    crowd = asset.crowds[0]
    assert np.any((crowd.layer_mode == 1) & (crowd.layer_weight > 0)) and crowd.blended
    override = dataclasses.replace(asset, crowds=(dataclasses.replace(crowd, layer_mode=None, blend_space=None),))
    for i in range(4):  # the additive layers (and the blend of the last instance) matter
        additive, _ = reference_instance(asset, i, 0.45)
        plain, _ = reference_instance(override, i, 0.45)
        assert float(np.abs(additive - plain).max()) > 1e-3 * float(np.linalg.norm(plain.max(0) - plain.min(0)))
    probes = [(i, t) for i in range(4) for t in (0.0, 0.45)]
    errors = probe_errors(browser, path, engine, probes, asset=asset)
    print(engine, "additive layers (USD)", errors)
    assert_within(errors, engine)
    errors = package_probe_errors(browser, package, engine, asset, probes)
    assert max(errors) <= POSITION_TOLERANCE, (engine, errors)


@pytest.mark.parity("clip events")
@pytest.mark.parametrize("engine", ENGINES)
def test_clip_events(browser, blending_chain, engine):
    """``crowd.events(t0, t1)`` on the page (format 1.3, spec 23.5, 23.7: a blending instance reports
    its first weighted point's clip) equals the reference's crowd_events, forward and backward."""
    from vbusd.decoders.reference import crowd_events

    asset = vbusd.read_asset(blending_chain)
    vb, crowd = asset.animations[0], asset.crowds[0]
    intervals = [(0.0, 1.7), (0.3, 0.9), (1.9, 0.2), (-0.5, 3.0)]
    with ViewerServer(blending_chain, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            got = page.page.evaluate("(pairs) => pairs.map(([a, b]) => window.vbusd.crowds[0].events(a, b))", intervals)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    total = 0
    for (t0, t1), theirs in zip(intervals, got):
        ours = crowd_events(vb, crowd, t0, t1)
        assert [(e["instance"], e["name"]) for e in theirs] == [(i, e["name"]) for i, e in ours], (t0, t1)
        np.testing.assert_allclose([e["time"] for e in theirs], [e["time"] for _, e in ours], rtol=0, atol=1e-5)
        total += len(ours)
    assert total > 10


@pytest.fixture(scope="module")
def socket_stadium(compact_stadium, tmp_path_factory):
    """The compact stadium (converted, so with vb:bindTransforms) with a crossfade per instance: the
    next clip, its own offset and rate, weights ramping 0 to 1 over the crowd."""
    asset = vbusd.read_asset(compact_stadium)
    crowd = asset.crowds[0]
    count, clips = crowd.instance_count, len(asset.animations[0].clips)
    fade = dict(fade_clip=((np.asarray(crowd.clip) + 1) % clips).astype(np.int32),
                fade_time_offset=np.linspace(-0.3, 0.9, count).astype(np.float32),
                fade_playback_rate=np.linspace(0.6, 1.4, count).astype(np.float32),
                fade_weight=np.linspace(0.0, 1.0, count).astype(np.float32))
    path = tmp_path_factory.mktemp("sockets") / "stadium.usda"
    vbusd.write_asset(dataclasses.replace(asset, crowds=(dataclasses.replace(crowd, **fade),)), path)
    return path


SOCKET_PROBES = [(0, 0.0), (777, 3.71), (1000, 1.2345), (1199, 12.05)]
"""(instance, scene time): fade weights 0, about 0.65, 0.83 and 1; a row time, between rows, past the loop."""


@pytest.mark.parity("sockets")
@pytest.mark.parametrize("engine", ENGINES)
def test_sockets(browser, socket_stadium, engine, record_property):
    """Sockets (format 1.1, spec 8.4) on each engine's page: ``crowd.socketMatrix(i, bone, t)`` (the
    runtime's CPU decoder, @vbusd/core's jointElements on the stored compact words) of a crossfading
    stadium crowd equals the numpy decoder's ``crowd_joint_transforms`` (placement times the
    crossfaded joint transform) within 1e-6 of the instance's bounding-box diagonal. (three's
    Matrix4 holds float64; Babylon's Matrix float32 unless the engine asks for high precision, so
    its error is the float32 rounding of a stadium seat's world coordinates, near 1e-6.)"""
    asset = vbusd.read_asset(socket_stadium)
    with ViewerServer(socket_stadium, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            errors = socket_errors(page, asset, engine, SOCKET_PROBES)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    print(engine, "sockets", errors)
    record_property("parity_note", f"largest error {max(errors):.1e} of the diagonal")
    assert max(errors) <= POSITION_TOLERANCE, errors


CHARACTER_PROBES = [(0, 0.0), (3, 0.8137), (4, 0.0), (5, 2.9)]
"""(instance, scene time) of the character crowd: Fox instances 0 to 3, CesiumMan 4 and 5."""

LAYER_PROBES = [(3, 0.8137), (8, 0.3)]
"""(instance, scene time) of the layered character crowd: a Fox (instances 0 to 5) and CesiumMan at
its level 1 (instance 8; 6 and 7 draw level 0, checked by the page's levels only: each (mesh,
influences) a probe draws costs its own layered shader compile, tens of seconds in software under
load), at a time where CesiumMan's clip and its layer's are both inside the clip (it does not loop:
past its 2 s both hold the last pose, and the layer would change nothing)."""

SOCKET_PROBES = [(i, 0.8137) for i in range(9)] + [(8, 0.3)]
"""(instance, scene time) of the layered character crowd's sockets: every instance (sockets cost no
shader compile), each layered and crossfading."""
LAYER_PAGE = ("&skin=attributes&pixelRatio=1&fov={fov}&camera=" + ",".join(map(str, CHARACTER_CAMERA[0] + CHARACTER_CAMERA[1]))
              ).format(fov=lod_row_helpers.FOV)
"""The layered character crowd's page: the camera of :data:`tests.helpers.browser.CHARACTER_CAMERA`, the
attributes skin binding (layers need it: the pulled binding's shader has no layers yet)."""


def socket_errors(page, asset, engine: str, probes, bones_of=lambda count: sorted({0, count // 2, count - 1})) -> list:
    """Largest error / instance diagonal of ``crowd.socketMatrix(i, bone, t)`` on ``page`` against
    the numpy decoder's ``crowd_joint_transforms``, per (instance, time) probe (instances numbered
    over the crowds in order, as the probe numbers them), for a few bones of each character."""
    from vbusd.decoders.reference import crowd_joint_transforms

    from tests.helpers.browser import reference_instance

    elements = "m.toArray()" if engine.startswith("three") else "Array.from(m.m)"
    errors = []
    for instance, t in probes:
        index, local = 0, instance
        while local >= asset.crowds[index].instance_count:
            local -= asset.crowds[index].instance_count
            index += 1
        crowd, vb = asset.crowds[index], asset.animations[asset.crowd_animation[index]]
        bones = bones_of(vb.layout.bone_count)
        got = np.asarray(page.page.evaluate(
            f"""([c, i, bones, t]) => bones.map((bone) => {{
                const m = window.vbusd.crowds[c].socketMatrix(i, bone, t); return {elements}; }})""",
            [index, local, bones, t])).reshape(len(bones), 4, 4).transpose(0, 2, 1)
        expected = np.stack([crowd_joint_transforms(vb, crowd, bone, t)[local] for bone in bones])
        positions, _ = reference_instance(asset, instance, t)
        diagonal = float(np.linalg.norm(positions.max(0) - positions.min(0)))
        errors.append(float(np.abs(got - expected).max()) / diagonal)
    return errors


@pytest.mark.parity("Fox and CesiumMan: compact encoding, pulled binding, crossfade, sockets")
@pytest.mark.parametrize("engine", ENGINES)
def test_fox_and_cesium_man(browser, character_crowd, engine, record_property):
    """The Khronos Fox (no normals) and CesiumMan converted with the compact encoding, in one
    ``vbusd crowd --fade-clips`` crowd (every instance crossfading, weights 0.2 to 0.8), drawn in
    the pulled binding: each probe equals the numpy decoder within 1e-6 of the instance's diagonal,
    and so do the crowds' sockets (``crowd.socketMatrix``, the first, middle and last joint) on the
    same page."""
    asset = vbusd.read_asset(character_crowd)
    sockets = []

    def pulled_and_sockets(page):
        assert set(page.page.evaluate("window.vbusd.crowds.map((crowd) => crowd.skin)")) == {"pulled"}
        sockets.extend(socket_errors(page, asset, engine, CHARACTER_PROBES))

    errors = engine_probe_errors(browser, character_crowd, engine, CHARACTER_PROBES, query="&skin=pulled", asset=asset,
                                 check=pulled_and_sockets)
    print(engine, "Fox and CesiumMan", errors, "sockets", sockets)
    record_property("parity_note", f"largest error {max(e for e, _ in errors):.1e} of the diagonal, "
                                   f"sockets {max(sockets):.1e}")
    assert_within(errors, engine)
    assert len(sockets) == len(CHARACTER_PROBES) and max(sockets) <= POSITION_TOLERANCE, sockets


def root_motion_errors(page, asset, engine: str, pairs) -> tuple:
    """Largest difference of ``crowd.rootMotionMatrix(i, t0, t1)`` on ``page`` from
    ``vbusd.root_motion`` of the instance's clip between its clip-local times offset + rate x t0
    and offset + rate x t1, per crowd, for every instance and (t0, t1) pair, and the largest
    displacement the reference moves them. The root tracks have no layout-metadata key, so the
    page is given each crowd's as an application gives them (``crowd.rootMotion``)."""
    elements = "m.toArray()" if engine.startswith("three") else "Array.from(m.m)"
    errors, moved = [], []
    for index, (crowd, animation) in enumerate(zip(asset.crowds, asset.crowd_animation)):
        vb = asset.animations[animation]
        root = {"upAxis": vb.root_motion.up_axis, "tracks": [track.tolist() for track in vb.root_motion.tracks]}
        got = np.asarray(page.page.evaluate(
            f"""([c, root, n, pairs]) => {{ const crowd = window.vbusd.crowds[c]; crowd.rootMotion = root;
                return Array.from({{length: n}}, (_, i) => pairs.map(([t0, t1]) => {{
                    const m = crowd.rootMotionMatrix(i, t0, t1); return {elements}; }})); }}""",
            [index, root, crowd.instance_count, pairs])).reshape(crowd.instance_count, len(pairs), 4, 4).transpose(0, 1, 3, 2)
        for i in range(crowd.instance_count):
            offset, rate = float(crowd.time_offset[i]), float(crowd.playback_rate[i])
            expected = np.stack([vbusd.root_motion(vb, int(crowd.clip[i]), offset + rate * t0, offset + rate * t1)
                                 for t0, t1 in pairs])
            errors.append(float(np.abs(got[i] - expected).max()))
            moved.append(float(np.abs(expected[:, :3, 3]).max()))
    return errors, moved


@pytest.mark.parity("Fox and CesiumMan: layers with masks, levels of detail, root motion")
@pytest.mark.parametrize("engine", ENGINES)
def test_fox_and_cesium_man_layers_lod_root_motion(browser, character_layers_crowd, engine, record_property):
    """The Khronos Fox (no normals) and CesiumMan converted with the compact encoding, a bone mask
    ``upper``, root motion extracted and (CesiumMan) a generated level of detail, in one ``vbusd crowd
    --layout points --fade-clips ... --layer upper ...`` crowd (every instance crossfading, weights
    0.2 to 0.8, and playing a layer over its upper body, weights 0.3 to 0.9), all checked on one
    page per engine:

    * the level each instance draws equals OpenUSD's UsdLodScreenSizeHeuristic.ComputeLOD for the
      page's camera (CesiumMan's three instances levels 0, 0 and 1; the Fox has no levels), as the
      stadium's row;
    * each probe equals the numpy decoder (``vbusd.skin``'s, with the instance's fade and layers)
      at the level the page drew, within 1e-6 of the instance's diagonal;
    * ``crowd.rootMotionMatrix`` equals ``vbusd.root_motion`` of each instance's clip at its
      clip-local times (CesiumMan's walk drifts; the Fox's root joint stands still);
    * ``crowd.socketMatrix`` (the first, middle and last joint of every instance: layered on the CPU
      by @vbusd/core's layeredJointElements) equals ``crowd_joint_transforms`` within 1e-6 of the
      diagonal, on the same page; without the layers it would be off by 0.06 to 0.39."""
    asset = vbusd.read_asset(character_layers_crowd)
    assert all(crowd.layered and crowd.crossfades for crowd in asset.crowds)
    expected_levels = lod_row_helpers.usdlod_levels_seen(asset, CHARACTER_CAMERA[0])
    assert expected_levels == [0] * 6 + [0, 0, 1], expected_levels  # CesiumMan: both levels
    # The layers matter: without them every probed instance is elsewhere.
    plain = dataclasses.replace(asset, crowds=tuple(dataclasses.replace(crowd, layer_weight=crowd.layer_weight * 0)
                                                    for crowd in asset.crowds))
    for instance, t in LAYER_PROBES:
        level = expected_levels[instance]
        with_layers, without = reference_instance(asset, instance, t, level)[0], reference_instance(plain, instance, t, level)[0]
        assert np.abs(with_layers - without).max() > 1e-3 * np.linalg.norm(with_layers.max(0) - with_layers.min(0))
    roots = {}

    def check_page(page):
        assert set(page.page.evaluate("window.vbusd.crowds.map((crowd) => crowd.skin)")) == {"attributes"}
        page.page.evaluate("() => window.vbusd.render()")
        assert page.page.evaluate("() => window.vbusd.levels()")["lod"] == expected_levels
        pairs = [(0.0, 0.5), (0.25, 2.75), (2.75, 0.25), (-1.3, 0.1)]
        roots["errors"], roots["moved"] = root_motion_errors(page, asset, engine, pairs)
        roots["sockets"] = socket_errors(page, asset, engine, SOCKET_PROBES)

    # Software WebGPU compiles the layered shaders of three meshes (the Fox, CesiumMan's two levels) slowly.
    errors = engine_probe_errors(browser, character_layers_crowd, engine, LAYER_PROBES, query=LAYER_PAGE, asset=asset,
                                 check=check_page, timeout_s=240.0)
    print(engine, "Fox and CesiumMan layers, levels, root motion", errors, "root motion", max(roots["errors"]),
          "moved", max(roots["moved"]), "sockets", roots["sockets"])
    record_property("parity_note", f"largest error {max(e for e, _ in errors):.1e} of the diagonal, root motion "
                                   f"{max(roots['errors']):.1e}, sockets {max(roots['sockets']):.1e}; levels {expected_levels}")
    assert_within(errors, engine)
    assert max(roots["moved"]) > 1e-3  # CesiumMan's root moves between the pairs
    assert max(roots["errors"]) <= 1e-6, roots["errors"]  # scene units (Babylon's matrices are float32)
    assert len(roots["sockets"]) == len(SOCKET_PROBES) and max(roots["sockets"]) <= POSITION_TOLERANCE, roots["sockets"]


def previous_errors(browser, path: Path, engine: str, probes, dt: float | None = None) -> list:
    """(previous-position error / diagonal, motion / diagonal) of each (instance, time) probe of
    ``path`` drawn by ``engine`` with the page's frame interval ``dt`` (None: the default 1/60)."""
    asset = vbusd.read_asset(path)
    with ViewerServer(path, engine=engine) as server:
        page = open_page(browser, server, "" if dt is None else f"&dt={dt!r}")
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("window.vbusd.engine") == engine
            results = [check_previous(page, asset, instance, t, 1 / 60 if dt is None else dt) for instance, t in probes]
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    return results


@pytest.mark.parity("previous pose (motion vectors)")
@pytest.mark.parametrize("engine", ENGINES)
def test_previous_pose(browser, layered_stadium, bar_crowd, engine):
    """The probe's ``previousPositions`` (the pose the engine's velocity output is computed from,
    spec virtual-bones.md 21) equal the numpy decoder at t - dt, within 1e-6 of the diagonal: on
    the stadium crowd (default dt 1/60, across its 10 s loop: t after the wrap, t - dt before it),
    on the layered stadium crossfading with per-instance rates (dt 0.05, across the loop too) and on
    the bar crowd's clamped clips across their ends (dt 0.05). Each case moves: a previous pose
    equal to the current one would fail."""
    stadium_path = SAMPLE / "stadium_crowd_vb.usda"
    stadium = vbusd.read_asset(stadium_path).crowds[0]
    loop = 10.0  # the cheer loops every 10 s of clip-local time
    stadium_probes = [(0, 1.2345), (0, across_clip_time(stadium, 0, loop, 1 / 60)),
                      (777, across_clip_time(stadium, 777, 2 * loop, 1 / 60))]
    layered = vbusd.read_asset(layered_stadium).crowds[0]
    layered_probes = [(3, 0.83), (5, 0.83), (4, across_clip_time(layered, 4, loop, 0.05)),
                      (5, across_clip_time(layered, 5, loop, 0.05))]
    bar = vbusd.read_asset(bar_crowd)
    clips = bar.animations[0].clips
    bar_probes = []
    for i in (0, 3):  # clamped clips: past the end, t - dt before it
        clip = clips[int(bar.crowds[0].clip[i])]
        assert not clip.loop
        bar_probes.append((i, across_clip_time(bar.crowds[0], i, (clip.row_count - 1) / clip.rows_per_second, 0.05)))
    cases = [("stadium", previous_errors(browser, stadium_path, engine, stadium_probes)),
             ("layered", previous_errors(browser, layered_stadium, engine, layered_probes, dt=0.05)),
             ("bar", previous_errors(browser, bar_crowd, engine, bar_probes, dt=0.05))]
    print(engine, cases)
    for name, results in cases:
        for error, moved in results:
            assert error <= POSITION_TOLERANCE, (name, results)
        assert max(moved for _, moved in results) > 100 * POSITION_TOLERANCE, (name, results)


VELOCITY_ENGINES = ("three", "three-webgpu", "babylon")
#: The velocity textures the Babylon page reads (window.vbusd.velocity({texture})): TAA's half floats
#: and MotionBlurPostProcess' 8-bit cube-root code.
BABYLON_VELOCITY_TEXTURES = ("taa", "motionBlur")
BABYLON_VELOCITY_CODE = 0.6 / 255  # half an 8-bit step, plus 0.1 of one for the GPU's float -> unorm8 rounding


def babylon_velocity_bound(expected: np.ndarray) -> np.ndarray:
    """Per component, how far Babylon's 8-bit velocity texture (MotionBlurPostProcess') may put NDC
    motion ``expected``: its shader stores v = sign(d) |d|^(1/3) / 2 + 1/2 with d = expected / 2
    (the 0..1 screen coordinates' difference), so a code off by ``BABYLON_VELOCITY_CODE`` decodes
    (NDC = 2 sign(c) |c|^3, c = 2 v - 1) to the farther of the two neighbours: about
    6 |d|^(2/3) / 255 NDC."""
    code = np.cbrt(expected / 2) * 0.5 + 0.5

    def decode(v):
        c = 2 * v - 1
        return 2 * np.sign(c) * np.abs(c) ** 3

    return np.maximum(np.abs(decode(code + BABYLON_VELOCITY_CODE) - expected),
                      np.abs(decode(code - BABYLON_VELOCITY_CODE) - expected))


@pytest.mark.parity("velocity output (motion vectors)")
@pytest.mark.parametrize("engine", VELOCITY_ENGINES)
def test_velocity_output(webgl_browser, engine):
    """The velocity an engine's motion-blur / TAA input gets from the crowd: three's
    WebGLRenderer through vbusd's velocity materials (web/src/velocity.js, renderVelocity), three's
    WebGPURenderer (on SwiftShader's WebGPU) through its own VelocityNode in an MRT ``velocity``
    output fed by the crowd's previous skinned pose (web/src/webgpu/material.js), and Babylon.js
    through both velocity textures its PrePassRenderer writes from the material plugin's previous
    skinned pose (placed by the crowd's 'previousMatrix' thin-instance buffer): TAA reprojection's
    (half floats) and MotionBlurPostProcess' (8 bits), read back by the page's
    ``window.vbusd.velocity()``. On the stadium, against the decoder's poses at t and t - dt
    rasterized with the page's own camera (depth-tested, perspective-correct barycentrics:
    tests/helpers/browser.py rasterize_nearest): at each pixel both cover, the velocity written
    (ndcCurrent - ndcPrevious) is the pixel's NDC minus the previous clip position interpolated as a
    varying is, within 0.02 pixel for 98 % of them (the rest: silhouette edges and touching
    figures, where the two rasterizers may pick different triangles); in Babylon's 8-bit texture (a
    cube-root code) each component may be off by what half an 8-bit code (plus 0.1 of one for the
    GPU's rounding) decodes to as well (babylon_velocity_bound: 0.07 px at 1 px of motion, 0.3 px
    at 10). With every instance reset (spec 21: switched clip) the velocity is 0 everywhere (within
    1/1000 pixel: the same products rounded in float32; the 8-bit zero code decodes to 1e-5 of a
    pixel)."""
    from vbusd.decoders.reference import skin_crowd

    path = SAMPLE / "stadium_crowd_vb.usda"
    asset = vbusd.read_asset(path)
    width, height, t, dt = 320, 180, 2.5, 0.25
    query = (f"?time={t}&dt={dt}&paused=1&ui=0&antialias=0&pixelRatio=1&width={width}&height={height}"
             f"&camera=0,11,38,0,2.5,44&fov=30")
    textures = BABYLON_VELOCITY_TEXTURES if engine == "babylon" else (None,)
    read = "(texture) => window.vbusd.velocity(texture ? {texture} : undefined)"
    with ViewerServer(path, engine=engine) as server:
        page = ViewerPage(webgl_browser, server.url + query, width=width, height=height)
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("window.vbusd.engine") == engine
            if engine == "three-webgpu":  # WebGPU itself, not three's WebGL 2 fallback
                assert page.page.evaluate("window.vbusd.renderer.backend.isWebGPUBackend") is True
            images = {texture: evaluate_arrays(page.page, read, texture, ["rg"]) for texture in textures}
            camera = page.page.evaluate(
                "({p: window.vbusd.camera.projectionMatrix.elements, v: window.vbusd.camera.matrixWorldInverse.elements})")
            page.page.evaluate("""() => { for (const crowd of window.vbusd.crowds) {
                for (let i = 0; i < crowd.capacity; ++i) crowd.resetPrevious(i); crowd.updatePrevious(crowd.animation.time, %r); } }""" % dt)
            # Last texture first: Babylon's page sets its pre-pass up again (shaders) at each change of texture.
            resets = {texture: evaluate_arrays(page.page, read, texture, ["rg"]) for texture in reversed(textures)}
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    pixel = 2.0 / height  # one pixel in NDC

    vb, crowd = asset.animations[0], asset.crowds[0]
    mesh = vb.meshes[0]
    view_projection = np.asarray(camera["p"]).reshape(4, 4).T @ np.asarray(camera["v"]).reshape(4, 4).T

    def clip_space(points):
        return np.concatenate([points.reshape(-1, 3), np.ones((points[..., 0].size, 1))], axis=1) @ view_projection.T

    now = clip_space(skin_crowd(vb, mesh, crowd, t)[0])
    before = clip_space(skin_crowd(vb, mesh, crowd, t - dt)[0])
    assert (now[:, 3] > 0).all()
    triangles = np.asarray(mesh.face_vertex_indices).reshape(-1, 3)
    offsets = (np.arange(crowd.instance_count) * mesh.points.shape[0])[:, None, None]
    all_triangles = (triangles[None] + offsets).reshape(-1, 3)
    nearest, weights = rasterize_nearest(now, all_triangles, width, height)
    covered = nearest >= 0
    ys, xs = np.nonzero(covered)
    corners = all_triangles[nearest[covered]]
    previous = np.einsum("nk,nkc->nc", weights[covered], before[corners])
    centre = np.stack([(xs + 0.5) / width * 2 - 1, 1 - (ys + 0.5) / height * 2], axis=1)
    expected = centre - previous[:, :2] / previous[:, 3:]
    motion = np.linalg.norm(expected, axis=1) / pixel
    assert 0.2 < covered.mean() < 0.8 and np.percentile(motion, 90) > 0.5  # the check can fail: figures move pixels
    for texture in textures:
        image = images[texture]
        assert (image["width"], image["height"]) == (width, height)
        velocity = np.asarray(image["rg"], dtype=np.float64).reshape(height, width, 2)[covered]
        drawn = np.abs(velocity).sum(axis=1) > 0  # the page covers the pixel too
        error = np.linalg.norm(velocity - expected, axis=1) / pixel
        if texture == "motionBlur":
            bound = babylon_velocity_bound(expected) + 0.02 * pixel / np.sqrt(2)
            good = (np.abs(velocity - expected) <= bound).all(axis=1)
        else:
            good = error <= 0.02
        print(f"{texture or engine}: pixels covered {covered.sum()}, drawn there {drawn.mean():.4f}, motion (px) median "
              f"{np.median(motion):.3f} max {motion.max():.2f}, within bounds {good.mean():.4f}, error median {np.median(error):.5f}")
        assert good.mean() >= 0.98, texture
        assert np.abs(np.asarray(resets[texture]["rg"])).max() <= 1e-3 * pixel, texture


@pytest.mark.parity('glTF package carrying layers and crossfades')
@pytest.mark.parametrize("engine", ENGINES)
def test_gltf_package_of_a_layered_crossfading_crowd(browser, layered_stadium, fade_window_crowd, tmp_path, engine):
    """`vbusd export` of two crowds, drawn through each engine's glTF loader (spec/runtime-package.md
    5.1): the layered stadium (two layers with bone masks on top of a crossfade) probed against the
    numpy decoder of its USD asset, and the `vbusd crowd --fade-window --layer` crowd, whose fade
    weight is time-sampled in the package, against vbusd.skin given each instance's clip, fade and
    layer by hand (before, inside and after the window)."""
    from vbusd.io.gltf_package import export_gltf

    asset = vbusd.read_asset(layered_stadium)
    package = tmp_path / "layered.glb"
    export_gltf(asset, package)
    plain = []
    errors = probe_errors(browser, package, engine, [(i, 0.83) for i in range(6)], asset=asset,
                          check=layers_matter(asset, 4, 0.83, plain))
    print(engine, "layered glb", errors)
    assert_within(errors, engine)
    # The layers matter: without them instance 4 is elsewhere, so the probes above saw them.
    assert plain[0] > 1e-3

    character, path = fade_window_crowd
    package = tmp_path / "fade_window.glb"
    export_gltf(vbusd.read_asset(path), package)
    check_fade_window(browser, package, engine, character, primvars(path))


# --------------------------------------------------------------------------------------------
# Crowd variety (format 1.3, spec virtual-bones.md 22): a row of modular spectators (body and an
# optional hat, samples/stadium_crowd.py's write_modular) tinted pure red, green and blue, two
# material variants, the hat on some. Each probe's positions are the numpy decoder's (variety never
# moves a vertex); the tint, variant and parts mask the page reports are the crowd's (pxr); in a
# screenshot, each body's pixel (its skinned vertices projected with the page's camera) is dominated
# by its tint's channel, a brighter variant material gives a brighter body, and the pixel inside the
# hat shows the tint when the mask shows the hat and the background when it hides it. The flag is a
# prop at the right hand's socket (spec 22.3, "Props at sockets"): its probed points are the numpy
# decoder's socket (crowd_joint_transforms) applied to its joint-space points, the page's own
# socketMatrix agrees, and the pixel at its cloth is the background where the mask hides it.
# --------------------------------------------------------------------------------------------

VARIETY_SIZE = (960, 540)
VARIETY_CAMERA = "0,1.5,8,0,1.1,0"
VARIETY_TIME = 9.0  # the cheer with the hands away from the head: nothing in front of the hat
VARIETY_XS = (-4.0, -2.0, 0.0, 2.0, 4.0)
VARIETY_BODY_POINTS = 202
VARIETY_HAT_POINTS = 8  # then the flag's 16 (samples/stadium_crowd.py: hat_mesh, flag_mesh)


@pytest.fixture(scope="module")
def variety_row(tmp_path_factory):
    """Five spectators in a row facing the camera, tinted red / green / blue, variants home and away,
    the hat on some and the flag on others: ``vbusd crowd --layout points ... --tints --variants --parts``."""
    from vbusd.cli import main

    folder = tmp_path_factory.mktemp("variety_row")
    character = modular_character(folder)
    points = folder / "row.csv"
    points.write_text("".join(f"{x},0,0\n" for x in VARIETY_XS))
    out = folder / "crowd.usda"
    status = main(["crowd", str(character), "-o", str(out), "--layout", "points", str(points), "--yaw", "0", "0",
                   "--time-offset", "0", "0", "--tints", "#ff0000,#00ff00,#0000ff", "--variants", "home=1,away=1",
                   "--parts", "Hat=0.5,Flag=0.5", "--seed", "11", "-q"])
    assert status == 0
    return out


def _variety_primvars(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    primvars = UsdGeom.PrimvarsAPI(prim)
    return (np.asarray(primvars.GetPrimvar("vb:tint").Get(), dtype=np.float64),
            np.asarray(primvars.GetPrimvar("vb:variant").Get()), np.asarray(primvars.GetPrimvar("vb:parts").Get()),
            list(prim.GetAttribute("vb:variantNames").Get()), list(prim.GetAttribute("vb:partNames").Get()))


def _rgb_pixels(png_bytes: bytes) -> np.ndarray:
    """The screenshot as (height, width, 3) 8-bit RGB values (pypng, as tests/helpers/browser.py reads them)."""
    import png

    width, height, rows, _ = png.Reader(bytes=png_bytes).asRGBA8()
    rgba = np.vstack([np.frombuffer(bytes(row), dtype=np.uint8) for row in rows]).reshape(height, width, 4)
    return rgba[:, :, :3].astype(np.float64)


def _project_to_pixels(points, camera) -> np.ndarray:
    view_projection = np.asarray(camera["p"]).reshape(4, 4).T @ np.asarray(camera["v"]).reshape(4, 4).T
    clip = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ view_projection.T
    ndc = clip[:, :2] / clip[:, 3:]
    return np.stack([(ndc[:, 0] + 1) / 2 * VARIETY_SIZE[0], (1 - ndc[:, 1]) / 2 * VARIETY_SIZE[1]], axis=1)


def _pixel_at(image, xy) -> np.ndarray:
    x, y = int(round(xy[0])), int(round(xy[1]))
    return np.median(image[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3), axis=0)


@pytest.mark.parity("crowd variety")
@pytest.mark.parametrize("engine", ENGINES)
def test_crowd_variety(browser, variety_row, engine, tmp_path):
    """The USD crowd (``vbusd view`` of the .usda: the plain files) and its ``vbusd export`` package
    (through each engine's glTF loader) show the same variety."""
    from vbusd.io.gltf_package import export_gltf

    asset = vbusd.read_asset(variety_row)
    package = tmp_path / "variety.glb"
    export_gltf(asset, package)
    for source in (variety_row, package):
        _check_variety_page(browser, engine, source, variety_row, asset)


VARIETY_MOVED = 3  # the instance probed again after root motion (it shows the hat and the flag)


def check_root_motion_moves_parts(page, engine: str, asset, before: np.ndarray) -> None:
    """Root motion moves the parts with their instance (spec 8.5 and 22.3): given a root track (a walk
    along +Z that turns, as an application gives one: ``crowd.rootMotion``), ``crowd.applyRootMotion(t0,
    t1)`` makes every mesh's drawn matrices, the part meshes' included, the placement ``P`` times the
    numpy decoder's ``root_motion`` at the instance's clip times (collapsed where the mask hides the part),
    and the probe of instance VARIETY_MOVED the points it had before moved by ``P D P^-1``."""
    from vbusd.decoders.reference import root_motion
    from vbusd.format.rootmotion import RootMotion

    vb, crowd = asset.animations[0], asset.crowds[0]
    rows = vb.clips[0].row_count
    steps = np.arange(rows + 1) / rows  # looping: one entry per row and the loop's displacement
    track = np.stack([0.3 * np.sin(2 * np.pi * steps), np.zeros_like(steps), 1.5 * steps, 0.6 * steps], axis=1)
    walking = dataclasses.replace(vb, root_motion=RootMotion("Y", (track,)))
    t0, t1 = 2.25, 7.5
    page.page.evaluate("([track, t0, t1]) => { const crowd = window.vbusd.crowds[0]; crowd.rootMotion = {upAxis: 'Y', tracks: [track]};"
                       " crowd.applyRootMotion(t0, t1); window.vbusd.render(); }", [track.tolist(), t0, t1])
    place = placements(crowd)
    offsets, rates = np.asarray(crowd.time_offset, np.float64), np.asarray(crowd.playback_rate, np.float64)
    moved = np.stack([place[i] @ root_motion(walking, 0, offsets[i] + rates[i] * t0, offsets[i] + rates[i] * t1)
                      for i in range(crowd.instance_count)])
    assert np.linalg.norm(moved[:, :3, 3] - place[:, :3, 3], axis=1).min() > 0.5  # every instance walked
    drawn = drawn_matrices(page, engine)
    assert sorted(mesh["part"] for mesh in drawn) == [-1, 0, 1], engine  # the body, the hat, the flag
    for mesh in drawn:
        bit = mesh["part"]
        name = crowd.part_names[bit] if bit >= 0 else "body"
        for i in range(crowd.instance_count):
            shown = bit < 0 or bool(crowd.parts[i] >> bit & 1)
            np.testing.assert_allclose(mesh["matrices"][i], expected_part_matrix(moved[i], shown), atol=1e-5,
                                       err_msg=f"{engine} {name} instance {i} after root motion")
    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [VARIETY_MOVED, VARIETY_TIME])
    after = np.asarray(result["positions"], np.float64).reshape(-1, 3)
    change = moved[VARIETY_MOVED] @ np.linalg.inv(place[VARIETY_MOVED])
    expected = before @ change[:3, :3].T + change[:3, 3]
    diagonal = float(np.linalg.norm(before.max(0) - before.min(0)))
    assert float(np.abs(after - expected).max()) <= 1e-6 * diagonal + 4 * np.finfo(np.float32).eps * float(np.abs(expected).max())


def check_prop_at_socket(drawn, local, asset, instance, bone, body) -> None:
    """The prop's probed points ``drawn`` equal the numpy decoder's socket of ``bone`` at ``instance``
    (placement times J = M B, crowd_joint_transforms) applied to its joint-space points ``local``,
    within 1e-6 of the instance's bounding-box diagonal (spec 22.3, "Props at sockets")."""
    from vbusd.decoders.reference import crowd_joint_transforms

    socket = crowd_joint_transforms(asset.animations[0], asset.crowds[0], bone, VARIETY_TIME)[instance]
    expected = local @ socket[:3, :3].T + socket[:3, 3]
    diagonal = float(np.linalg.norm(body.max(0) - body.min(0)))
    assert drawn.shape == expected.shape
    error = float(np.abs(drawn - expected).max()) / diagonal
    assert error <= POSITION_TOLERANCE, (instance, error)


def _check_variety_page(browser, engine, source, usd_crowd, asset):
    tints, variants, parts, variant_names, part_names = _variety_primvars(usd_crowd)
    assert len({tuple(t) for t in tints}) >= 2 and set(variants) == {0, 1}
    assert set(parts & 1) == {0, 1} and set(parts >> 1 & 1) == {0, 1}, parts  # hat and flag, each shown and hidden
    sample = scripts.load("samples/stadium_crowd.py")
    flag_bone = sample.JOINT_NAMES.index(sample.FLAG_BONE)
    flag_local, _, _ = sample.flag_local()
    socket_errors_of_page = []
    width, height = VARIETY_SIZE
    query = (f"?time={VARIETY_TIME}&paused=1&ui=0&antialias=0&pixelRatio=1&width={width}&height={height}"
             f"&camera={VARIETY_CAMERA}&fov=40")
    with ViewerServer(source, engine=engine) as server:
        page = ViewerPage(browser, server.url + query, width=width, height=height)
        try:
            if "WebGPU is not available" in " ".join(page.messages):
                unavailable("browser", NO_ADAPTER)  # fails where the browser is required (CI)
            assert page.error == "", page.error
            results = []
            for i in range(len(VARIETY_XS)):
                position_error, normal_error = check_probe(page, asset, i, VARIETY_TIME)
                assert position_error <= POSITION_TOLERANCE and normal_error <= NORMAL_TOLERANCE, (i, position_error)
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [i, VARIETY_TIME])
                np.testing.assert_allclose(result["tint"], tints[i], rtol=1e-6)
                assert result["variant"] == variants[i] and result["variantName"] == variant_names[variants[i]]
                assert result["parts"] == parts[i] and result["partNames"] == part_names
                results.append(np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3))
                if parts[i] >> 1 & 1:
                    check_prop_at_socket(results[-1][VARIETY_BODY_POINTS + VARIETY_HAT_POINTS:], flag_local, asset, i,
                                         flag_bone, results[-1][:VARIETY_BODY_POINTS])
                    socket_errors_of_page += socket_errors(page, asset, engine, [(i, VARIETY_TIME)], lambda _: [flag_bone])
            page.page.evaluate("window.vbusd.render()")
            image = _rgb_pixels(page.page.locator("#view").screenshot())
            camera = page.page.evaluate(
                "({p: Array.from(window.vbusd.camera.projectionMatrix.elements),"
                " v: Array.from(window.vbusd.camera.matrixWorldInverse.elements)})")
            check_root_motion_moves_parts(page, engine, asset, results[VARIETY_MOVED])
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    assert max(socket_errors_of_page) <= POSITION_TOLERANCE, socket_errors_of_page
    assert image.shape == (height, width, 3)
    background = _pixel_at(image, (3, 3))
    variant_colours = [np.asarray(c) for c in asset.crowds[0].variant_colors]  # the materials' diffuseColor
    bodies = {}
    for i, positions in enumerate(results):
        body, hat = positions[:VARIETY_BODY_POINTS], positions[VARIETY_BODY_POINTS:VARIETY_BODY_POINTS + VARIETY_HAT_POINTS]
        flag = positions[VARIETY_BODY_POINTS + VARIETY_HAT_POINTS:]
        channel = int(np.argmax(tints[i]))
        others = [c for c in range(3) if c != channel]
        # The middle of the flag's cloth (its last 8 points): drawn where the mask shows it, the background where not.
        seen = _pixel_at(image, _project_to_pixels(flag[8:].mean(axis=0, keepdims=True), camera)[0])
        print(engine, source.suffix, i, "flag", bool(parts[i] >> 1 & 1), seen, "background", background)
        if parts[i] >> 1 & 1:  # the flag takes the instance's colour, as every mesh of it does
            assert seen[channel] > 2 * seen[others].max() and np.abs(seen - background).max() > 10, (engine, i, seen, background)
        else:
            assert np.abs(seen - background).max() <= 12, (engine, i, seen, background)
        colour = _pixel_at(image, _project_to_pixels(body.mean(axis=0, keepdims=True), camera)[0])
        print(engine, source.suffix, i, "body", colour, "tint", tints[i], "variant", variants[i])
        assert colour[channel] > 10 and colour[channel] > 2 * colour[others].max(), (engine, i, colour, tints[i])
        bodies.setdefault(channel, []).append((variant_colours[variants[i]][channel], colour[channel]))
        # Inside the hat, above the head (the body's highest point under the hat; hands may be higher
        # elsewhere): the tint with the hat, the background without.
        point = hat.mean(axis=0)
        up = np.asarray(camera["v"]).reshape(4, 4).T[1, :3]  # the camera's up axis in world space
        under = np.linalg.norm((body - point) - np.outer((body - point) @ up, up), axis=1) < 0.15
        head_top, hat_top = float((body[under] @ up).max()), float((hat @ up).max())
        assert hat_top - head_top > 0.03, (head_top, hat_top)
        point = point + (0.5 * (head_top + hat_top) - point @ up) * up
        seen = _pixel_at(image, _project_to_pixels(point[None], camera)[0])
        print(engine, source.suffix, i, "hat", bool(parts[i] & 1), seen, "background", background)
        if parts[i] & 1:
            assert seen[channel] > 2 * seen[others].max() and np.abs(seen - background).max() > 20, (engine, i, seen)
        else:
            assert np.abs(seen - background).max() <= 12, (engine, i, seen, background)
    # The variant selects the material: of two bodies with the same tint, the one whose variant material
    # is brighter in that channel is the brighter one on screen.
    for channel, pairs in bodies.items():
        for (base_a, seen_a), (base_b, seen_b) in zip(pairs, pairs[1:]):
            if abs(base_a - base_b) > 0.3:
                assert (seen_a > seen_b) == (base_a > base_b), (engine, channel, pairs)
