"""The three.js runtime and `vbusd view` in a real browser: headless Chromium, software WebGL 2.

Chromium (Debian's ``chromium``) is driven by playwright-python (:mod:`vbusd.web.browser`): one
browser for the module, one page per asset. Checked against vbusd's numpy reference decoder, which
shares no code with the browser's GLSL path beyond the stored texels:

* (a) ``window.vbusd.probe(instance, time)``: the GPU's world-space skinned positions and normals
  (transform feedback through three's WebGL 2 context) for every encoding in float16 and float32,
  on the stadium crowd (its 1,200 placed instances) and on glTF rigs converted with
  ``vbusd convert`` (the repository's bar fixture, with the encodings that hold its scale, and the
  shared Fox asset, all four, when ``$VBUSD_SHARED_ASSETS`` is there): positions within 1e-6 of the
  instance's bounding-box diagonal, unit normals within 1e-5;
* (b) a screenshot at a fixed camera and time against the silhouette rasterized from the decoder's
  vertices, projected with the page's own camera matrices: intersection over union >= 0.98;
* (c) no console error on any page; unorm16 without EXT_texture_norm16 fails with the runtime's
  one clear message instead.

The probes run in both skin bindings (spec/shaders.md, "Skin bindings"; the page's ``?skin=``):
``attributes`` and ``pulled`` (the skin records in an RGBA32UI texture read by ``gl_VertexID``,
packed by the runtime from the plain files' or the glTF package's bone attributes), with the same
tolerances; each pulled page is checked to have no bone attributes left on its geometries.

Skips with one line naming what to install when Chromium or playwright is missing.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import vbusd
from vbusd.format.model import Crowd
from vbusd.io.gltf_package import export_gltf
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers import node
from tests.helpers.browser import (CAMERA, NORMAL_TOLERANCE, PAGE, POSITION_TOLERANCE, SAMPLE, SKINS, STADIUM_PROBES,
                                   check_probe, check_silhouette, check_skin_binding, convert, crossfading_bar_crowd,
                                   encoding_format_skin_cases, layered_stadium, package_probe_errors, reference_instance,
                                   run_probes, screenshot_luminance)
from tests.helpers.capabilities import shared_asset

pytestmark = pytest.mark.browser

@pytest.mark.parametrize("skin", SKINS)
def test_probe_matches_reference_compact_encoding(browser, compact_stadium, skin):
    """The compact encoding in three.js: an RGB32UI texture read with texelFetch from a usampler2D,
    the per-bone range uniforms, the same tolerances as the other encodings."""
    errors = run_probes(browser, compact_stadium, STADIUM_PROBES, skin)
    print("compactQuatTranslation uint32", skin, errors)
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE and normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("encoding,texel_format,skin", encoding_format_skin_cases())
def test_probe_matches_reference_on_stadium_crowd(browser, stadium_assets, encoding, texel_format, skin):
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES, skin)
    print(encoding, texel_format, skin, errors)
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("encoding,texel_format,skin",
                         encoding_format_skin_cases(encodings=("affineMatrix", "quatTranslation")))
def test_probe_matches_reference_on_gltf_bar(browser, rig_assets, encoding, texel_format, skin):
    for position_error, normal_error in run_probes(browser, rig_assets[encoding, texel_format],
                                                   [(0, 0.0), (0, 0.4321), (0, 0.77), (0, 5.0)], skin):
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("skin", SKINS)
def test_probe_per_instance_clip_offset_rate(browser, bar_crowd, skin):
    """Each instance plays its own clip at its own offset and rate (VirtualBonesInstancingAPI)."""
    probes = [(instance, t) for instance in range(10) for t in (0.0, 0.61)]
    for position_error, normal_error in run_probes(browser, bar_crowd, probes, skin):
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("skin", SKINS)
def test_probe_crossfade_from_the_plain_files(browser, bar_crowd, tmp_path, skin):
    """A crossfading crowd (format 1.1 fade primvars, written and read back) through `vbusd view`'s
    plain files: each instance blended with its own fade clip, offset, rate and weight, as the
    numpy decoder does."""
    crowd = vbusd.read_asset(bar_crowd).crowds[0]
    path = crossfading_bar_crowd(bar_crowd, tmp_path / "faded" / "faded.usda")
    asset = vbusd.read_asset(path)
    assert asset.crowds[0].crossfades
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + PAGE + f"&skin={skin}")
        try:
            assert page.error == "", page.error
            check_skin_binding(page, skin)
            for instance in range(5):
                position_error, normal_error = check_probe(page, asset, instance, 0.83)
                assert position_error <= POSITION_TOLERANCE, instance
                assert normal_error <= NORMAL_TOLERANCE, instance
            # The fade matters: the same instances without it are elsewhere.
            unfaded = dataclasses.replace(asset, crowds=(crowd,))
            assert check_probe(page, unfaded, 1, 0.83)[0] > 1e-3
            assert page.errors() == [], page.errors()
        finally:
            page.close()


# quatTranslation float16 is tests/test_browser_parity.py::test_layers_with_masks[three]: the same
# asset, probes and check that the layers matter.
@pytest.mark.parametrize("encoding,texel_format", [("crossMatrix", "float32"), ("dualQuat", "float32")])
def test_probe_layers_from_the_plain_files(browser, tmp_path, encoding, texel_format):
    """Layers with bone masks (format 1.2): the stadium converted with --mask upper=spine and
    --mask arm=R_upperArm, its crowd given two layers per instance (primvars:vb:layer*, written and
    read back) on top of crossfades; the runtime's GPU skinning (vbSkinLayered) matches the numpy
    decoder within the usual tolerances, in the encodings the parity test's quatTranslation float16
    leaves."""
    path = layered_stadium(tmp_path, encoding, texel_format)
    asset = vbusd.read_asset(path)
    assert asset.crowds[0].layered and asset.animations[0].masks
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            for instance in range(6):
                position_error, normal_error = check_probe(page, asset, instance, 0.83)
                assert position_error <= POSITION_TOLERANCE, (instance, position_error)
                assert normal_error <= NORMAL_TOLERANCE, (instance, normal_error)
            # The layers matter: the same instance without them is elsewhere.
            plain = dataclasses.replace(asset, crowds=(dataclasses.replace(asset.crowds[0], layer_weight=None),))
            assert check_probe(page, plain, 4, 0.83)[0] > 1e-3
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def test_runtime_layers_match_threejs_animation_mixer_on_the_fox(browser, shared_assets, tmp_path):
    """The Fox walking with its upper body surveying, drawn by the three.js runtime (a crowd of one
    instance per pose: the walk's time as its offset, rate 0, the Survey layer under the mask upper
    = b_Spine01_02 at weights 0.35 and 1) against three.js' own AnimationMixer blend of the glTF
    (tests/node/layered_pose.mjs), float32 texels: within 1e-6 of the bounding-box diagonal."""
    source = shared_asset("gltf", "Fox", "Fox.glb")
    converted = tmp_path / "c" / "fox.usda"
    vbusd.convert(source, converted, vbusd.ConvertOptions(encoding="crossMatrix", texel_format="float32", check_rows=0,
                                                          masks=("upper=b_Spine01_02",)))
    asset = vbusd.read_asset(converted)
    vb = asset.animations[0]
    names = [c.name for c in vb.clips]
    walk, survey = names.index("Walk"), names.index("Survey")
    masked = [int(b) for b in np.flatnonzero(vb.masks[0][1])]
    pairs = [(r / vb.clips[walk].rows_per_second, q / vb.clips[survey].rows_per_second)
             for r, q in ((0, 3), (5, 40), (11, 17))]
    poses = [(a, b, w) for w in (0.35, 1.0) for a, b in pairs]
    n = len(poses)
    crowd = Crowd("/Fox/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.full(n, walk, np.int32), np.array([a for a, _, _ in poses], np.float32), np.zeros(n, np.float32),
                  layer_clip=np.full((n, 1), survey, np.int32),
                  layer_time_offset=np.array([[b] for _, b, _ in poses], np.float32),
                  layer_playback_rate=np.zeros((n, 1), np.float32),
                  layer_weight=np.array([[w] for _, _, w in poses], np.float32), layer_mask=np.zeros((n, 1), np.int32))
    path = tmp_path / "layered" / "fox.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,)), path)
    expected = []
    for weight in (0.35, 1.0):
        result = node.run_json(
            "layered_pose.mjs", source, 0, "Walk", "Survey", ",".join(map(str, masked)), weight,
            *[f"{vb.clips[walk].start_time + a:.17g}:{vb.clips[survey].start_time + b:.17g}" for a, b in pairs],
            packages=("three",))
        expected += [np.array(p["meshes"][0]["positions"]).reshape(-1, 3) for p in result["poses"]]
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            for instance, theirs in enumerate(expected):
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, 0.0])
                ours = np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3)
                diagonal = float(np.linalg.norm(theirs.max(0) - theirs.min(0)))
                error = float(np.abs(ours - theirs).max()) / diagonal
                assert error <= POSITION_TOLERANCE, (instance, error)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def test_viewer_controls(browser, bar_crowd):
    """The page's controls act on the crowd: the clip picker makes every instance play that clip,
    the instance count draws fewer instances, play advances the clock and pause stops it."""
    asset = vbusd.read_asset(bar_crowd)
    vb, crowd = asset.animations[0], asset.crowds[0]
    with ViewerServer(bar_crowd) as server:
        page = ViewerPage(browser, server.url + "?ui=1&silhouette=1&width=320&height=180")
        try:
            assert page.error == ""
            assert page.page.locator("#play").text_content() == "Pause"  # playing when opened
            started_at = page.page.locator("#time-label").text_content()
            page.page.wait_for_function(f"document.getElementById('time-label').textContent !== {started_at!r}",
                                        timeout=20_000)  # the clock runs
            page.page.click("#play")
            assert page.page.locator("#play").text_content() == "Play"
            paused_at = page.page.locator("#time-label").text_content()
            page.page.wait_for_timeout(300)
            assert page.page.locator("#time-label").text_content() == paused_at
            page.page.select_option("#clip", "Slide")
            slide = [c.name for c in vb.clips].index("Slide")
            all_slide = dataclasses.replace(asset, crowds=(dataclasses.replace(
                crowd, clip=np.full(crowd.instance_count, slide, dtype=np.int32)),))
            for instance in (0, 3):
                position_error, _ = check_probe(page, all_slide, instance, 0.7)
                assert position_error <= POSITION_TOLERANCE
            page.page.locator("#count").fill("4")
            assert page.page.evaluate("window.vbusd.crowds[0].count") == 4
            assert page.page.locator("#count-label").text_content() == "4"
            assert "frame time:" in page.page.locator("#stats").text_content()
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def test_frustum_culling_bounds_cover_every_pose(browser, bar_crowd):
    """The culling box is the union of the played clips' vb:clipExtents, placed at every instance:
    every vertex the GPU skins lies inside it, while the rest pose's box would cut some off; and a
    camera looking away draws nothing, one looking at the crowd draws it."""
    asset = vbusd.read_asset(bar_crowd)
    vb, crowd = asset.animations[0], asset.crowds[0]
    extents = np.asarray(vb.clip_extents, dtype=np.float64)
    with ViewerServer(bar_crowd) as server:
        page = ViewerPage(browser, server.url + "?paused=1&ui=0&silhouette=1&width=320&height=180")
        try:
            assert page.error == ""
            boxes = page.page.evaluate("""() => window.vbusd.crowds[0].meshes.map((mesh) => ({
                geometry: [mesh.geometry.boundingBox.min.toArray(), mesh.geometry.boundingBox.max.toArray()],
                world: [mesh.boundingBox.min.toArray(), mesh.boundingBox.max.toArray()],
                culled: mesh.frustumCulled}))""")
            assert boxes and all(box["culled"] for box in boxes)
            played = np.unique(crowd.clip)
            np.testing.assert_allclose(boxes[0]["geometry"][0], extents[played, 0].min(axis=0), rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(boxes[0]["geometry"][1], extents[played, 1].max(axis=0), rtol=1e-6, atol=1e-6)
            low, high = np.asarray(boxes[0]["world"][0]), np.asarray(boxes[0]["world"][1])
            rest = np.asarray(vb.meshes[0].points, dtype=np.float64)
            outside_rest = 0
            for instance in range(crowd.instance_count):
                for t in np.linspace(0.0, 4.0, 9):
                    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, float(t)])
                    points = np.asarray(result["positions"]).reshape(-1, 3)
                    assert (points >= low - 1e-4).all() and (points <= high + 1e-4).all(), (instance, t)
                    local = (points - crowd.positions[instance]) @ _rotation(crowd.orientations[instance]) \
                        / crowd.scales[instance]
                    outside_rest += int(((local < rest.min(0) - 1e-3) | (local > rest.max(0) + 1e-3)).any())
            assert outside_rest > 0  # the animation leaves the rest pose's box: rest bounds would cull it
            calls = page.page.evaluate("""() => {
                const v = window.vbusd, box = v.crowds[0].meshes[0].boundingBox;
                const centre = box.getCenter(box.min.clone());
                const draws = (target) => { v.camera.position.copy(centre).addScaledVector(box.max.clone().sub(box.min), 1.5);
                    v.controls.target.copy(target); v.render(); return v.renderer.info.render.calls; };
                const toward = draws(centre);
                const away = draws(v.camera.position.clone().multiplyScalar(2).sub(centre));
                return [toward, away]; }""")
            assert calls[0] >= 1 and calls[1] == 0, calls
            assert page.errors() == [], page.errors()
        finally:
            page.close()

def _rotation(quaternion) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(quaternion, dtype=np.float64) / np.linalg.norm(quaternion)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

@pytest.mark.parametrize("encoding,texel_format,skin", encoding_format_skin_cases())
def test_probe_matches_reference_on_gltf_fox(browser, shared_assets, tmp_path, encoding, texel_format, skin):
    """A real rig (Khronos sample Fox: 24 joints, 1,728 vertices), every encoding."""
    path = convert(shared_assets / "gltf" / "Fox" / "Fox.glb", tmp_path / "fox.usda", encoding, texel_format)
    for position_error, normal_error in run_probes(browser, path, [(0, 0.0), (0, 0.8137), (0, 2.9)], skin):
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("skin", SKINS)
def test_unorm16_needs_norm16_extension(browser, tmp_path, skin):
    """unorm16 runs where EXT_texture_norm16 exists; elsewhere the page says so in one clear line."""
    path = convert(SAMPLE / "stadium_crowd.usda", tmp_path / "unorm.usda", "crossMatrix", "unorm16")
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + PAGE + f"&skin={skin}")
        try:
            has_norm16 = page.page.evaluate(
                "!!document.createElement('canvas').getContext('webgl2').getExtension('EXT_texture_norm16')")
            if has_norm16:
                assert page.error == ""
                position_error, normal_error = check_probe(page, vbusd.read_asset(path), 0, 1.5)
                assert position_error <= POSITION_TOLERANCE and normal_error <= NORMAL_TOLERANCE
            else:
                assert "EXT_texture_norm16" in page.error and "--texel-format float16" in page.error
                assert "\n" not in page.error.strip()
        finally:
            page.close()


def test_unorm16_dequantization_in_the_runtime(browser, tmp_path):
    """The runtime's unorm16 path (the module's VB_UNORM16 branch, vb_rangeMin/vb_rangeMax from
    the layout's unormRanges) where EXT_texture_norm16 is missing: the stored 16-bit texels are
    handed to the shader as the floats a normalized fetch returns (u / 65535, a float32 texture),
    and the GPU's vertices match the numpy decoder's for the unorm16 asset."""
    path = convert(SAMPLE / "stadium_crowd.usda", tmp_path / "unorm.usda", "quatTranslation", "unorm16")
    asset = vbusd.read_asset(path)
    script = """async ([t]) => {
        const THREE = await import(location.origin + '/three/three.module.js');
        const V = await import(location.origin + '/vbusd-three/index.js');
        const { crowds, animations } = V.buildObjects(await V.loadPlainScene('scene/scene.json'), {});
        const animation = animations[0];
        const { width, height, data } = animation.texture.image;
        const texture = new THREE.DataTexture(Float32Array.from(data, (u) => u / 65535), width, height,
                                              THREE.RGBAFormat, THREE.FloatType);
        texture.minFilter = texture.magFilter = THREE.NearestFilter;
        texture.generateMipmaps = false;
        texture.needsUpdate = true;
        animation.texture = texture;
        animation.uniforms.vb_texture.value = texture;
        animation.checkSupport = () => {};  // the float texture needs no extension
        const renderer = new THREE.WebGLRenderer({ canvas: document.createElement('canvas') });
        const result = V.probeCrowd(renderer, crowds[0], 0, t);
        return { positions: Array.from(result.positions), normals: Array.from(result.normals),
                 ranges: !!animation.uniforms.vb_rangeMin };
    }"""
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + "?paused=1&ui=0&silhouette=1&width=320&height=180")
        try:
            for t in (0.0, 1.5, 7.77):
                result = page.page.evaluate(script, [t])
                assert result["ranges"]
                expected_positions, expected_normals = reference_instance(asset, 0, t)
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                diagonal = float(np.linalg.norm(np.ptp(expected_positions, axis=0)))
                assert np.abs(positions - expected_positions).max() / diagonal <= POSITION_TOLERANCE
                normals = np.asarray(result["normals"]).reshape(-1, 3)
                assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE
        finally:
            page.close()

@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("case", ["stadium.glb", "bar_crowd.gltf"])
def test_probe_matches_reference_through_gltf_plugin(browser, bar_crowd, tmp_path, case, skin):
    """The runtime package of ``vbusd export`` (KTX2 in a buffer view, EXT_mesh_gpu_instancing with
    _VB_CLIP, _VB_TIME_OFFSET, _VB_PLAYBACK_RATE) through three's GLTFLoader and the
    VirtualBonesGLTFPlugin: the same vertices as the numpy decoder on the USD asset."""
    source = SAMPLE / "stadium_crowd_vb.usda" if case == "stadium.glb" else bar_crowd
    asset = vbusd.read_asset(source)
    assert asset.up_axis == "Y" and asset.meters_per_unit == 1.0  # the package's root node is the identity
    package = tmp_path / case
    export_gltf(asset, package)
    probes = [(0, 0.0), (3, 0.61), (asset.crowds[0].instance_count - 1, 2.3)]
    # pulled: records packed from _VB_JOINTS_n/_VB_WEIGHTS_n
    errors = package_probe_errors(browser, package, "three", asset, probes, f"&skin={skin}",
                                  check=lambda page: check_skin_binding(page, skin))
    assert max(errors) <= POSITION_TOLERANCE


# MeshStandardMaterial: the README picture, the shadow test; MeshBasicMaterial: the probes' pages.
MATERIALS = ("MeshLambertMaterial", "MeshPhongMaterial", "MeshPhysicalMaterial", "MeshToonMaterial",
             "MeshNormalMaterial")


def test_any_three_material_skins(browser):
    """patchMaterial works on three's other mesh materials: each draws the crowd where the patched
    MeshBasicMaterial does (emissive white, so unlit materials show their coverage), while an
    unpatched material draws the rest pose elsewhere."""
    width, height = 320, 180
    query = (f"?paused=1&time=2.5&ui=0&silhouette=1&antialias=0&pixelRatio=1&width={width}&height={height}"
             f"&camera={CAMERA}&fov=30")
    script = """async (name) => {
        const THREE = await import(location.origin + '/three/three.module.js');
        const { patchMaterial } = await import(location.origin + '/vbusd-three/index.js');
        for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
            const options = name === 'MeshNormalMaterial' ? {}
                : { color: 0xffffff, emissive: 0xffffff };
            const material = name === 'unpatched' ? new THREE.MeshBasicMaterial({ color: 0xffffff })
                : patchMaterial(new THREE[name](options), crowd.animation, mesh.userData.virtualBones.maxInfluences,
                                mesh.userData.virtualBones.binding);  // the crowd's skin binding (pulled by default)
            mesh.material = material;
        }
        window.vbusd.render();
    }"""
    with ViewerServer(SAMPLE / "stadium_crowd_vb.usda") as server:
        page = ViewerPage(browser, server.url + query, width=width, height=height)
        try:
            assert page.error == ""
            page.page.evaluate("window.vbusd.render()")
            basic = screenshot_luminance(page.page.locator("#view").screenshot()) > 20
            masks = {}
            for name in MATERIALS + ("unpatched",):
                page.page.evaluate(script, name)
                masks[name] = screenshot_luminance(page.page.locator("#view").screenshot()) > 20
            assert page.errors() == [], page.errors()
        finally:
            page.close()

    def iou(a, b):
        return float((a & b).sum() / (a | b).sum())

    assert 0.1 < basic.mean() < 0.9
    for name in MATERIALS:
        assert iou(masks[name], basic) >= 0.99, (name, iou(masks[name], basic))
    assert iou(masks["unpatched"], basic) < 0.9


@pytest.mark.parametrize("skin", SKINS)
def test_shadows_follow_the_animation(browser, skin):
    """The crowd's shadow map is drawn with the patched depth material: with the figures hidden
    from the camera (no colour, no depth) the shadows on the ground still change as the crowd
    moves, and with three's own (unpatched, rest-pose) depth material instead they do not."""
    width, height = 480, 200
    query = (f"?paused=1&time=1.0&ui=0&antialias=0&pixelRatio=1&width={width}&height={height}"
             f"&camera=-16,7,27,4,2.2,46&fov=34&instances=400&skin={skin}")
    with ViewerServer(SAMPLE / "stadium_crowd_vb.usda") as server:
        page = ViewerPage(browser, server.url + query, width=width, height=height)
        try:
            assert page.error == ""
            check_skin_binding(page, skin)
            page.page.evaluate("""() => { for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
                mesh.material.colorWrite = false; mesh.material.depthWrite = false; } }""")

            def shot(t: float) -> np.ndarray:
                page.page.evaluate("(t) => { window.vbusd.setTime(t); window.vbusd.render(); }", t)
                return screenshot_luminance(page.page.locator("#view").screenshot())

            def changed(a: np.ndarray, b: np.ndarray) -> float:
                return float((np.abs(a - b) > 8).mean())

            patched = shot(1.0), shot(3.6)
            page.page.evaluate("""() => { for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
                mesh.customDepthMaterial = undefined; } }""")
            rest = shot(1.0), shot(3.6)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    print(f"shadow pixels changed: animated {changed(*patched):.4f}, rest {changed(*rest):.4f}, "
          f"animated vs rest {changed(patched[0], rest[0]):.4f}")
    assert changed(*patched) > 0.005  # the shadows move with the cheer
    assert changed(*rest) == 0.0  # three's own depth material: the rest pose, frozen
    assert changed(patched[0], rest[0]) > 0.005

def test_screenshot_matches_decoder_silhouette(browser):
    check_silhouette(browser)

