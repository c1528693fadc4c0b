"""What the browser tests share (tests/test_browser*.py, the conformance and side-by-side pages):
the converted assets they draw, the probe against vbusd's numpy reference decoder, the silhouette
rasterizer, and the covering matrix of encodings, texel formats and skin bindings.

The probe compares ``window.vbusd.probe(instance, time)`` (the GPU's world-space skinned positions
and normals, by transform feedback) with :func:`reference_instance`, which shares no code with the
browser's GLSL path beyond the stored texels. The session fixtures built from these helpers are in
:mod:`tests.helpers.fixtures`: each asset is converted once per test session (per xdist worker).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from pathlib import Path

import numpy as np

import vbusd
from vbusd.decoders.reference import skin_crowd, skin_mesh
from vbusd.format.model import Crowd
from vbusd.web.browser import ViewerPage
from vbusd.web.server import SHUTDOWN_POLL_S, ViewerServer

from tests.helpers.capabilities import REPO, unavailable

SAMPLE = REPO / "samples" / "stadium_crowd"
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
FORMATS = ("float16", "float32")
POSITION_TOLERANCE = 1e-6  # of the instance's bounding-box diagonal
NORMAL_TOLERANCE = 1e-5
SKINS = ("attributes", "pulled")
PAGE = "?paused=1&ui=0&silhouette=1&width=320&height=180"

STADIUM_PROBES = [(0, 0.0), (0, 1.2345), (777, 3.71), (1199, 12.05)]
"""Scene times: a row time, between rows, and past the 10 s loop (wraps)."""

# ------------------------------------------------------------------------------------------------
# The covering matrix. Each browser case is a page load and a shader compile in software (seconds),
# so by default the engines run a covering set, named here case by case: every encoding, every
# texel format and both skin bindings at least once per engine, each (encoding, texel format) pair
# once; on the real characters, every encoding once. VBUSD_FULL_MATRIX=1 runs every combination.
# ------------------------------------------------------------------------------------------------

FULL_MATRIX = os.environ.get("VBUSD_FULL_MATRIX") == "1"

COVER = {("crossMatrix", "float16"): "pulled", ("affineMatrix", "float32"): "attributes",
         ("quatTranslation", "float16"): "attributes", ("dualQuat", "float32"): "pulled"}
"""The (encoding, texel format) pairs of the default matrix, with the skin binding each runs in."""

CHARACTER_COVER = (("Fox", "crossMatrix"), ("Fox", "quatTranslation"), ("CesiumMan", "affineMatrix"),
                   ("CesiumMan", "dualQuat"))
"""The (character, encoding) pairs of the default matrix of the real characters."""


def encoding_format_skin_cases(encodings=ENCODINGS, formats=FORMATS, skins=SKINS) -> list[tuple[str, str, str]]:
    """(encoding, texel format, skin) cases: the whole product under VBUSD_FULL_MATRIX=1, else the
    pairs of :data:`COVER` among ``encodings`` x ``formats``, each in its skin binding (or, where
    ``skins`` is one binding, in that one)."""
    product = list(itertools.product(encodings, formats, skins))
    if FULL_MATRIX:
        return product
    return [(e, f, s) for e, f, s in product if (e, f) in COVER and (len(skins) == 1 or COVER[e, f] == s)]


def encoding_format_cases(encodings=ENCODINGS, formats=FORMATS) -> list[tuple[str, str]]:
    """(encoding, texel format) cases: the whole product under VBUSD_FULL_MATRIX=1, else the
    pairs of :data:`COVER`."""
    product = list(itertools.product(encodings, formats))
    return product if FULL_MATRIX else [pair for pair in product if pair in COVER]


def character_encoding_cases(characters, encodings=ENCODINGS) -> list[tuple[str, str]]:
    """(character, encoding) cases: the whole product under VBUSD_FULL_MATRIX=1, else
    :data:`CHARACTER_COVER`'s among them."""
    product = list(itertools.product(characters, encodings))
    return product if FULL_MATRIX else [pair for pair in product if pair in CHARACTER_COVER]


def convert(source: Path, output: Path, encoding: str, texel_format: str) -> Path:
    """``source`` converted to ``output`` (no accuracy check rows: the probes are the check)."""
    vbusd.convert(source, output, vbusd.ConvertOptions(encoding=encoding, texel_format=texel_format, check_rows=0))
    return output


class ConvertedOnce(dict):
    """(encoding, texel format) -> converted asset, each converted by ``make(encoding, texel_format)``
    the first time a test asks for it: a session converts only the cases its tests draw."""

    def __init__(self, make):
        super().__init__()
        self._make = make

    def __missing__(self, key):
        self[key] = self._make(*key)
        return self[key]


def build_stadium_assets(folder: Path) -> ConvertedOnce:
    """The stadium's UsdSkel source converted per encoding and format, with the sample's crowd."""
    crowd_asset = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda")

    def make(encoding: str, texel_format: str) -> Path:
        converted = convert(SAMPLE / "stadium_crowd.usda", folder / f"c_{encoding}_{texel_format}.usda",
                            encoding, texel_format)
        asset = vbusd.read_asset(converted)
        with_crowd = dataclasses.replace(asset, crowds=crowd_asset.crowds, crowd_animation=(0,))
        path = folder / f"{encoding}_{texel_format}" / "stadium.usda"
        path.parent.mkdir()
        vbusd.write_asset(with_crowd, path)
        return path

    return ConvertedOnce(make)


def build_compact_stadium(folder: Path):
    """Format 1.2: the stadium converted with compactQuatTranslation (uint32 words), with its crowd."""
    crowd_asset = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda")
    converted = convert(SAMPLE / "stadium_crowd.usda", folder / "c.usda", "compactQuatTranslation", "uint32")
    asset = dataclasses.replace(vbusd.read_asset(converted), crowds=crowd_asset.crowds, crowd_animation=(0,))
    path = folder / "compact" / "stadium.usda"
    path.parent.mkdir()
    vbusd.write_asset(asset, path)
    return path


def build_character_crowd(assets: Path, folder: Path) -> Path:
    """The Khronos Fox and CesiumMan (glTF, shared assets) converted with compactQuatTranslation
    (uint32) and made one crowd by ``vbusd crowd --fade-clips``: 4 Fox and 2 CesiumMan instances,
    each crossfading (weights 0.2 to 0.8) to a clip of its own character. Spaced 2 units apart (the
    Fox overlaps its neighbours): the default spacing, from the Fox's reach, would put CesiumMan
    hundreds of units out, where float32 world positions cannot hold 1e-6 of its 1.8-unit diagonal."""
    from vbusd.cli import main

    characters = [convert(assets / "gltf" / name / f"{name}.glb", folder / f"{name}.usda", "compactQuatTranslation",
                          "uint32") for name in ("Fox", "CesiumMan")]
    out = folder / "crowd.usda"
    status = main(["crowd", *map(str, characters), "-o", str(out), "--count", "6", "--seed", "3", "--spacing", "2",
                   "--fade-clips", "Walk,Run,animation0", "--fade-weight", "0.2", "0.8", "--quiet"])
    assert status == 0
    return out


CHARACTER_MASKS = {"Fox": "upper=b_Spine02_03", "CesiumMan": "upper=Skeleton_torso_joint_2"}
"""Each character's bone mask ``upper`` (its spine and everything above), the mask the crowd's layer plays over."""

CHARACTER_LEVELS = {"CesiumMan": ("0.2", "0.05")}
"""``--lod-ratios`` and ``--lod-screen-sizes`` of the characters given levels of detail: CesiumMan a
level 1 of a fifth of its triangles, drawn below a screen size of 0.05 (with
:data:`CHARACTER_CAMERA`, by its instance 10 units away). Not the Fox: its mesh stores three
vertices per triangle, which meshoptimizer cannot collapse (its generated levels keep all 576
triangles), and each level's layered shaders are seconds more to compile in software."""

CHARACTER_POINTS = ((0.0, 0.0, 0.0), (1.5, 0.0, -1.0), (-1.5, 0.0, 1.0), (0.0, 0.0, -3.0), (1.5, 0.0, -2.0),
                    (-1.5, 0.0, 1.5), (1.0, 0.0, 2.5), (-1.0, 0.0, -6.0), (0.5, 0.0, -6.0))
"""Where the character crowd stands (``vbusd crowd --layout points``): near the origin, where float32
world coordinates hold 1e-6 of CesiumMan's 1.8-unit diagonal. ``--seed 3`` gives points 2, 3 and 8
to CesiumMan: 3.4, 7 and 10 units from the camera, its levels 0, 0 and 1."""

CHARACTER_CAMERA = ((0.0, 1.0, 4.0), (0.0, 1.0, -100.0))
"""(eye, target) of the character crowd's page: looking down -Z, as lod_row's camera."""


def build_character_layers_crowd(assets: Path, folder: Path) -> Path:
    """Layers, levels of detail and root motion on real characters: the Khronos Fox and CesiumMan
    (glTF, shared assets) converted with compactQuatTranslation (uint32), a bone mask ``upper``
    each (``--mask``), root motion (``--root-motion extract``) and, for CesiumMan, a generated
    level of detail (:data:`CHARACTER_LEVELS`), made one crowd by ``vbusd crowd --layout points
    --fade-clips ... --layer upper ...``: 9 instances of both characters at :data:`CHARACTER_POINTS` (a few units
    apart: the Fox overlaps its neighbours; the default spacing, from the Fox's reach, would put
    CesiumMan hundreds of units out, where float32 world positions cannot hold 1e-6 of its 1.8-unit
    diagonal), each crossfading (weights 0.2 to 0.8) to a clip of its own character and playing a
    layer over its upper body (weights 0.3 to 0.9)."""
    from vbusd.cli import main

    characters = []
    for name in ("Fox", "CesiumMan"):
        out = folder / name / f"{name}.usda"
        levels = ["--lod-ratios", CHARACTER_LEVELS[name][0], "--lod-screen-sizes", CHARACTER_LEVELS[name][1]] \
            if name in CHARACTER_LEVELS else []
        status = main(["convert", str(assets / "gltf" / name / f"{name}.glb"), "-o", str(out),
                       "--encoding", "compactQuatTranslation", "--texel-format", "uint32", "--check-rows", "0",
                       "--mask", CHARACTER_MASKS[name], *levels, "--root-motion", "extract", "--quiet"])
        assert status == 0
        characters.append(out)
    points = folder / "points.csv"
    points.write_text("".join(f"{x},{y},{z}\n" for x, y, z in CHARACTER_POINTS), encoding="utf-8")
    out = folder / "crowd.usda"
    status = main(["crowd", *map(str, characters), "-o", str(out), "--layout", "points", "--points", str(points),
                   "--seed", "3", "--fade-clips", "Walk,Run,animation0", "--fade-weight", "0.2", "0.8",
                   "--layer", "upper", "Survey,animation0", "--layer-weight", "0.3", "0.9", "--quiet"])
    assert status == 0
    return out


def build_rig_assets(folder: Path):
    """The bar fixture (glTF) converted with the encodings that hold its growing scale."""
    return ConvertedOnce(lambda encoding, texel_format: convert(
        REPO / "tests" / "fixtures" / "gltf" / "bar.gltf", folder / f"{encoding}_{texel_format}" / "bar.usda",
        encoding, texel_format))


def build_bar_crowd(folder: Path):
    """A crowd of the bar rig (glTF fixture, 5 clips that bend, slide, step and grow it): every
    instance its own clip, time offset (negative too), playback rate, orientation and non-uniform
    scale."""
    asset = vbusd.read_asset(convert(REPO / "tests" / "fixtures" / "gltf" / "bar.gltf", folder / "bar.usda",
                                      "affineMatrix", "float32"))
    count = 10
    rng = np.random.default_rng(14)
    quaternions = rng.normal(size=(count, 4))
    crowd = Crowd(path="/VirtualBones/Crowd", positions=rng.uniform(-6, 6, (count, 3)).astype(np.float32),
                  orientations=(quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)).astype(np.float32),
                  scales=rng.uniform(0.5, 1.6, (count, 3)).astype(np.float32),
                  clip=(np.arange(count) % len(asset.animations[0].clips)).astype(np.int32),
                  time_offset=rng.uniform(-1.0, 2.0, count).astype(np.float32),
                  playback_rate=rng.uniform(0.3, 2.5, count).astype(np.float32))
    path = folder / "crowd" / "bar_crowd.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,)), path)
    return path


def reference_instance(asset, instance: int, t: float, level: int = 0):
    """Positions and normals the viewer's instance ``instance`` has at time ``t`` (numpy decoder),
    drawn at level of detail ``level`` (the meshes of that level; every mesh of an animation
    without levels is level 0).

    The viewer numbers the crowds' instances in the asset's order, then one instance (at the
    origin, clip 0, offset 0, rate 1) per animation that no crowd instances.
    """
    for crowd, animation in zip(asset.crowds, asset.crowd_animation):
        if instance < crowd.instance_count:
            one = dataclasses.replace(crowd, **{field: None if getattr(crowd, field) is None
                                                 else getattr(crowd, field)[instance:instance + 1]
                                                 for field in ("positions", "orientations", "scales", "clip",
                                                               "time_offset", "playback_rate", "fade_clip",
                                                               "fade_time_offset", "fade_playback_rate",
                                                               "fade_weight", "layer_clip", "layer_time_offset",
                                                               "layer_playback_rate", "layer_weight",
                                                               "layer_mask", "layer_mode", "layer_reference_clip",
                                                               "layer_reference_time", "blend_space", "blend_x",
                                                               "blend_y", "blend_phase")})
            vb = asset.animations[animation]
            results = [skin_crowd(vb, mesh, one, t) for mesh in vb.meshes if getattr(mesh, "lod", 0) == level]
            return (np.concatenate([p[0] for p, _ in results]),
                    np.concatenate([n[0] for _, n in results if n is not None] or [np.zeros((0, 3))]))
        instance -= crowd.instance_count
    singles = [vb for index, vb in enumerate(asset.animations) if index not in set(asset.crowd_animation)]
    vb = singles[instance]
    results = [skin_mesh(vb, mesh, 0, t) for mesh in vb.meshes if getattr(mesh, "lod", 0) == level]
    return (np.concatenate([p[0] for p, _ in results]),
            np.concatenate([n[0] for _, n in results if n is not None] or [np.zeros((0, 3))]))


def world_error(got: np.ndarray, expected: np.ndarray) -> float:
    """Largest coordinate difference of world positions a float32 runtime computed from the
    decoder's, less half a float32 unit in the last place of each expected coordinate: the runtime's
    output is float32, so even the exact position is rounded by up to that much (2e-6 m at the
    stadium's 40 m rows, 1.06e-6 of a figure's diagonal); all the rest must be within the tolerance.
    Measured on the layered dualQuat float32 stadium: 1.08e-6 with the rounding, 5.7e-7 without."""
    spacing = 0.5 * np.spacing(np.abs(expected).astype(np.float32)).astype(np.float64)
    return float(np.maximum(np.abs(got - expected) - spacing, 0.0).max())


def check_probe(page: ViewerPage, asset, instance: int, t: float) -> tuple[float, float]:
    """Probe the page and compare with the decoder at the level of detail the page drew (the
    probe's ``lod``; 0 without levels); returns (position error / diagonal, normal error)."""
    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, t])
    level = result.get("lod") or 0
    assert level >= 0, f"instance {instance} is culled: nothing to probe"
    positions = np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(result["normals"], dtype=np.float64).reshape(-1, 3)
    expected_positions, expected_normals = reference_instance(asset, instance, t, level)
    assert positions.shape == expected_positions.shape
    assert normals.shape == expected_normals.shape
    diagonal = float(np.linalg.norm(expected_positions.max(0) - expected_positions.min(0)))
    position_error = world_error(positions, expected_positions) / diagonal
    normal_error = float(np.abs(normals - expected_normals).max()) if normals.size else 0.0
    return position_error, normal_error


def check_skin_binding(page: ViewerPage, skin: str) -> None:
    """Every crowd of the page draws with ``skin``: pulled geometries keep no bone attributes
    and carry skin records; attribute geometries keep them."""
    state = page.page.evaluate("""() => window.vbusd.crowds.flatMap((crowd) => crowd.meshes.map((mesh) => ({
        skin: crowd.skin, material: mesh.material.userData.virtualBones.skin,
        depth: mesh.customDepthMaterial.userData.virtualBones.skin,
        distance: mesh.customDistanceMaterial.userData.virtualBones.skin,
        attributes: Object.keys(mesh.geometry.attributes).filter((name) => name.startsWith('vb_bone')).length,
        records: mesh.geometry.userData.virtualBones.skin?.records.length ?? 0})))""")
    assert state
    for mesh in state:
        assert mesh["skin"] == mesh["material"] == mesh["depth"] == mesh["distance"] == skin, mesh
        assert (mesh["attributes"] == 0 and mesh["records"] > 0) if skin == "pulled" else mesh["attributes"] >= 2


NO_ADAPTER = "this Chromium offers no WebGPU adapter (see vbusd.web.browser.WEBGPU_ARGS)"


def open_engine_page(browser, server: ViewerServer, query: str = PAGE, **kwargs) -> ViewerPage:
    """The page of ``server`` (``vbusd view --engine ...``) at ``query``; a three-webgpu page in a
    Chromium without a WebGPU adapter skips (or fails where the browser is required) in one line."""
    page = ViewerPage(browser, server.url + query, **kwargs)
    if "WebGPU is not available" in " ".join(page.messages):
        page.close()
        unavailable("browser", NO_ADAPTER)
    return page


def engine_probe_errors(browser, path: Path, engine: str, probes, *, query: str = "", asset=None, backend=None,
                        check=None, then=None, timeout_s: float = 60.0) -> list:
    """(position error / diagonal, normal error) of each (instance, time) probe of ``path`` drawn by
    ``engine`` (``vbusd view --engine ENGINE``, at :data:`PAGE` + ``query``) against
    :func:`reference_instance`; the page names the engine (and ``backend``), logs no error, and
    loads everything from the server (offline). ``check(page)`` looks at the page first;
    ``then(page)``, after the probes on the same page load, returns more (error, error) pairs; the
    page has ``timeout_s`` seconds to load."""
    asset = asset or vbusd.read_asset(path)
    with ViewerServer(path, engine=engine) as server:
        page = open_engine_page(browser, server, PAGE + query, timeout_s=timeout_s)
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("window.vbusd.engine") == engine
            if backend is not None:
                assert page.page.evaluate("window.vbusd.backend") == backend
            if check is not None:
                check(page)
            errors = [check_probe(page, asset, instance, t) for instance, t in probes]
            if then is not None:
                errors += then(page)
            assert page.errors() == [], page.errors()
            # Offline: the page, the engine, the runtime and the asset all come from the server.
            assert page.requests and all(url.startswith(server.url) for url in page.requests), page.requests
        finally:
            page.close()
    return errors


PACKED_EVALUATE = """async ([arg, keys]) => {
  const value = {...(await (%s)(arg))};
  for (const key of keys.filter((key) => value[key] != null)) {
    const bytes = new Uint8Array(Float64Array.from(value[key]).buffer);
    let text = '';
    for (let at = 0; at < bytes.length; at += 0x8000) text += String.fromCharCode(...bytes.subarray(at, at + 0x8000));
    value[key] = btoa(text);
  }
  return value;
}"""


def evaluate_arrays(page, function: str, arg=None, arrays=()) -> dict:
    """``page.evaluate(function, arg)`` of a function returning (a Promise of) an object whose
    fields ``arrays`` are long arrays of numbers (a frame's pixels): those come back as float64
    numpy arrays, sent as the base64 bytes of a Float64Array (every JS number exactly). As JSON
    lists the page's serialization and the driver's per-element checks cost seconds a frame."""
    import base64

    value = page.evaluate(PACKED_EVALUATE % function, [arg, list(arrays)])
    for key in arrays:
        if isinstance(value.get(key), str):  # absent or null ones stay as they came
            value[key] = np.frombuffer(base64.b64decode(value[key]), dtype="<f8").copy()
    return value


PROBE_ARRAYS = ("positions", "normals", "previousPositions")


def read_probe(page, instance: int, t: float, *, previous: bool = False) -> dict:
    """``window.vbusd.probe(instance, t)`` of ``page`` (a playwright page), its vertex arrays as
    float64 numpy arrays (:func:`evaluate_arrays`); with ``previous``, the previous-frame pose too.
    For probes of thousands of vertices, read many times (a figure of the stadium is cheap either way)."""
    options = "" if previous else ", {previous: false}"
    return evaluate_arrays(page, f"([i, t]) => window.vbusd.probe(i, t{options})", [instance, t], PROBE_ARRAYS)


def assert_within(errors, what: str = "") -> None:
    """Every probe's position error within :data:`POSITION_TOLERANCE`, normal error within :data:`NORMAL_TOLERANCE`."""
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE, (what, errors)
        assert normal_error <= NORMAL_TOLERANCE, (what, errors)


def run_probes(browser, path: Path, probes, skin: str = "attributes") -> list:
    """The three.js WebGL page's probes in skin binding ``skin`` (checked on every crowd first)."""
    return engine_probe_errors(browser, path, "three", probes, query=f"&skin={skin}",
                               check=lambda page: check_skin_binding(page, skin))


def package_probe_errors(browser, package: Path, engine: str, asset, probes, query: str = "", check=None) -> list:
    """Position errors (/ diagonal) of probes of a runtime package drawn through ``engine``'s glTF
    loader, against the numpy decoder of the USD ``asset`` it was exported from, in the package's
    vertex order (:func:`package_vertices`); normals within :data:`NORMAL_TOLERANCE` where the
    asset has them, none where it has none. ``check(page)`` looks at the page first."""
    errors = []
    with ViewerServer(package, engine=engine) as server:
        page = open_engine_page(browser, server, PAGE + query)
        try:
            assert page.error == "", page.error
            if check is not None:
                check(page)
            for instance, t in probes:
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, t])
                expected_positions, expected_normals = reference_instance(asset, instance, t)
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                expected = package_vertices(asset, expected_positions)
                assert positions.shape == expected.shape
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                errors.append(float(np.abs(positions - expected).max()) / diagonal)
                normals = np.asarray(result["normals"]).reshape(-1, 3)
                assert normals.shape == expected_normals.shape
                if normals.size:
                    assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE
            assert page.errors() == [], page.errors()
            assert page.requests and all(url.startswith(server.url) for url in page.requests), page.requests
        finally:
            page.close()
    print(engine, package.name, errors)
    return errors


def crossfading_bar_crowd(bar_crowd: Path, path: Path, *, for_sockets: bool = False) -> Path:
    """The bar crowd with a crossfade per instance (format 1.1), written to ``path``: each instance
    a fade clip, offset, rate and weight of its own (weights 0, 1 and between; for the socket
    checks, a ramp from 0 to 1)."""
    asset = vbusd.read_asset(bar_crowd)
    crowd = asset.crowds[0]
    count = crowd.instance_count
    clips = len(asset.animations[0].clips)
    if for_sockets:
        fade = dict(fade_clip=((np.arange(count) + 1) % clips).astype(np.int32),
                    fade_time_offset=np.linspace(-0.3, 0.9, count).astype(np.float32),
                    fade_playback_rate=np.linspace(0.6, 1.4, count).astype(np.float32),
                    fade_weight=np.linspace(0.0, 1.0, count).astype(np.float32))
    else:
        fade = dict(fade_clip=((np.arange(count) + 2) % clips).astype(np.int32),
                    fade_time_offset=np.linspace(-0.5, 1.0, count).astype(np.float32),
                    fade_playback_rate=np.linspace(0.5, 1.5, count).astype(np.float32),
                    fade_weight=np.array([0.0, 1.0, 0.25, 0.5, 0.75] * (count // 5), dtype=np.float32))
    path.parent.mkdir(parents=True, exist_ok=True)
    vbusd.write_asset(dataclasses.replace(asset, crowds=(dataclasses.replace(crowd, **fade),)), path)
    return path


def check_crowd_sockets(browser, path: Path, engine: str, matrix_array: str) -> None:
    """``crowd.socketMatrix(i, bone, t)`` of every instance of the page's first crowd, for every
    bone at two times, equals the decoder's ``crowd_joint_transforms`` (placement times the
    crossfaded joint) within 1e-6 of the crowd's extent. ``matrix_array`` is the JS expression
    turning the engine's matrix ``m`` into its 16 numbers (three's column-major ``elements``,
    Babylon's row-vector ``m``: the same numbers)."""
    from vbusd.decoders.reference import crowd_joint_transforms

    asset = vbusd.read_asset(path)
    vb, crowd = asset.animations[0], asset.crowds[0]
    count = crowd.instance_count
    extent = float(np.linalg.norm(np.ptp(np.asarray(crowd.positions), axis=0))) + 1.0
    with ViewerServer(path, engine=engine) as server:
        page = open_engine_page(browser, server)
        try:
            assert page.error == "", page.error
            for bone in range(vb.layout.bone_count):
                for t in (0.0, 0.61):
                    got = np.asarray(page.page.evaluate(
                        f"""([bone, t, n]) => Array.from({{ length: n }}, (_, i) => {{
                            const m = window.vbusd.crowds[0].socketMatrix(i, bone, t); return {matrix_array}; }})""",
                        [bone, t, count]))
                    expected = crowd_joint_transforms(vb, crowd, bone, t)
                    got = got.reshape(count, 4, 4).transpose(0, 2, 1)
                    assert np.abs(got - expected).max() <= 1e-6 * extent, (bone, t)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def run_docs_example(browser, folder: Path, section: str, shows, inspect: str = None):
    """docs/engines.md's example page of ``section`` (its first ```html block), as written, on a
    folder laid out as the docs say (the wheel's static files and a ``vbusd export`` package of the
    stadium crowd, ``crowd.glb``), served by a plain HTTP server: screenshots until ``shows(luminance)``
    (:func:`settle`). Returns (console messages, last picture, its luminance, ``inspect``'s result:
    a JS function evaluated on the page then, or None)."""
    import functools
    import http.server
    import re
    import threading

    from vbusd.io.gltf_package import export_gltf
    from vbusd.web.static_files import copy_static

    text = (REPO / "docs" / "engines.md").read_text(encoding="utf-8")
    html = re.search(r"```html\n(.*?)```", text[text.index(section):], re.S).group(1)
    copy_static(REPO, folder / "site")  # what the wheel ships (setup.py's build step)
    (folder / "site" / "example.html").write_text(html, encoding="utf-8")
    export_gltf(vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda"), folder / "site" / "crowd.glb")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder / "site")))
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": SHUTDOWN_POLL_S},
                              name="docs-example", daemon=True)
    thread.start()
    inspected = None
    try:
        page = browser.new_page(viewport={"width": 480, "height": 270}, device_scale_factor=1)
        messages = []
        page.on("console", lambda message: messages.append(f"{message.type}: {message.text}"))
        page.on("pageerror", lambda error: messages.append(f"pageerror: {error}"))
        page.goto(f"http://127.0.0.1:{server.server_address[1]}/example.html")
        # Load, compile and a few frames on SwiftShader: until the picture is there.
        picture, luminance = settle(page, lambda image: shows(image, messages))
        if inspect is not None:
            inspected = page.evaluate(inspect)
        (folder / "example.png").write_bytes(picture)
        page.close()
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
    return messages, picture, luminance, inspected


def package_vertices(asset, positions: np.ndarray) -> np.ndarray:
    """Points in the runtime package's vertex order: with faceVarying normals each corner of a face
    of 3 or more vertices is its own vertex (spec/runtime-package.md), else the asset's points."""
    parts, at = [], 0
    for mesh in (m for vb in asset.animations for m in vb.meshes):
        count = mesh.points.shape[0]
        block = positions[at:at + count]
        at += count
        if mesh.normals_interpolation == "faceVarying":
            counts = np.asarray(mesh.face_vertex_counts)
            corners = np.split(np.asarray(mesh.face_vertex_indices), np.cumsum(counts)[:-1])
            block = block[np.concatenate([c for c in corners if len(c) >= 3])]
        parts.append(block)
    return np.concatenate(parts)


SCREEN = (640, 360)
CAMERA = "0,11,38,0,2.5,44"  # above the front rows, looking down at the stand: figures apart
SCREENSHOT_TIME = 2.5


def rasterize(points_ndc: np.ndarray, triangles: np.ndarray, width: int, height: int,
              budget: int = 4_000_000) -> np.ndarray:
    """Coverage at pixel centres (GL's rule, ties aside) of triangles given in clip-divided NDC.

    Every pixel of every triangle's bounding box is tested against its three edges, vectorized
    over chunks of about ``budget`` (triangle, pixel) pairs.
    """
    mask = np.zeros((height, width), dtype=bool)
    pixels = np.empty_like(points_ndc[:, :2])
    pixels[:, 0] = (points_ndc[:, 0] + 1.0) * 0.5 * width
    pixels[:, 1] = (1.0 - points_ndc[:, 1]) * 0.5 * height  # image rows run downward
    corners = pixels[triangles]  # (n, 3, 2)
    lo = np.floor(corners.min(axis=1) - 0.5).astype(np.int64).clip(0, [width - 1, height - 1])
    hi = np.ceil(corners.max(axis=1) - 0.5).astype(np.int64).clip(0, [width - 1, height - 1])
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = np.flatnonzero(area != 0)
    spans = (hi - lo + 1)[keep]
    counts = spans[:, 0] * spans[:, 1]
    ends = np.cumsum(counts)
    start = 0
    while start < len(keep):
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + budget, side="right")))
        n = counts[start:stop]
        which = np.repeat(np.arange(stop - start), n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        width_of = spans[start:stop, 0][which]
        triangle = keep[start:stop][which]
        xs = lo[triangle, 0] + local % width_of
        ys = lo[triangle, 1] + local // width_of
        sign = np.sign(area[triangle])
        inside = np.ones(xs.shape, dtype=bool)
        for p, q in ((a, b), (b, c), (c, a)):
            p, q = p[triangle], q[triangle]
            inside &= ((q[:, 0] - p[:, 0]) * (ys + 0.5 - p[:, 1])
                       - (q[:, 1] - p[:, 1]) * (xs + 0.5 - p[:, 0])) * sign >= 0
        mask[ys[inside], xs[inside]] = True
        start = stop
    return mask


def screenshot_luminance(png_bytes: bytes) -> np.ndarray:
    """The PNG a screenshot returns as an (height, width) array of 8-bit grey (the mean of R, G, B)."""
    import png

    width, height, rows, _ = png.Reader(bytes=png_bytes).asRGBA8()
    rgba = np.vstack([np.frombuffer(bytes(row), dtype=np.uint8) for row in rows]).reshape(height, width, 4)
    return rgba[:, :, :3].mean(axis=2)


def check_silhouette(browser, engine: str = "three", backend_query: str = "") -> None:
    """The page of ``engine`` (unlit white on black) against the silhouette rasterized from the
    decoder's vertices with the page's own camera: IoU >= 0.98, and < 0.9 0.3 s later."""
    path = SAMPLE / "stadium_crowd_vb.usda"
    asset = vbusd.read_asset(path)
    width, height = SCREEN
    query = (f"?time={SCREENSHOT_TIME}&paused=1&ui=0&silhouette=1&antialias=0&pixelRatio=1"
             f"&width={width}&height={height}&camera={CAMERA}&fov=30{backend_query}")
    with ViewerServer(path, engine=engine) as server:
        page = ViewerPage(browser, server.url + query, width=width, height=height)
        try:
            assert page.error == ""
            page.page.evaluate("window.vbusd.render()")
            image = screenshot_luminance(page.page.locator("#view").screenshot())
            camera = page.page.evaluate(
                "({p: window.vbusd.camera.projectionMatrix.elements, v: window.vbusd.camera.matrixWorldInverse.elements})")
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    shown = image > 127
    assert shown.shape == (height, width)

    vb, crowd = asset.animations[0], asset.crowds[0]
    mesh = vb.meshes[0]
    view_projection = np.asarray(camera["p"]).reshape(4, 4).T @ np.asarray(camera["v"]).reshape(4, 4).T
    triangles = np.asarray(mesh.face_vertex_indices).reshape(-1, 3)
    offsets = (np.arange(crowd.instance_count) * mesh.points.shape[0])[:, None, None]
    all_triangles = (triangles[None] + offsets).reshape(-1, 3)

    def silhouette(t: float) -> np.ndarray:
        points, _ = skin_crowd(vb, mesh, crowd, t)
        homogeneous = np.concatenate([points.reshape(-1, 3), np.ones((points.shape[0] * points.shape[1], 1))], axis=1)
        clip = homogeneous @ view_projection.T
        assert (clip[:, 3] > 0).all()  # the whole crowd is in front of the camera: no clipping needed
        ndc = clip[:, :3] / clip[:, 3:]
        visible = (np.abs(ndc[all_triangles][:, :, :2]) <= 1.05).any(axis=(1, 2))
        return rasterize(ndc, all_triangles[visible], width, height)

    def iou(a: np.ndarray, b: np.ndarray) -> float:
        return float((a & b).sum() / (a | b).sum())

    expected = silhouette(SCREENSHOT_TIME)
    print(f"IoU {iou(shown, expected):.4f}, {expected.sum()} silhouette pixels")
    assert 0.2 < expected.mean() < 0.8  # the camera sees figures and the gaps between them
    assert iou(shown, expected) >= 0.98
    # The comparison can fail: the same crowd 0.3 s later is another picture.
    assert iou(shown, silhouette(SCREENSHOT_TIME + 0.3)) < 0.9


def settle(page, shows, *, timeout_s: float = 300.0, interval_ms: int = 1000):
    """Screenshots of ``page`` until ``shows(luminance)`` holds (a page drawn as it should be) or
    ``timeout_s`` passes; returns the last (png bytes, luminance). Waits on what the page shows, not
    for a fixed time: a slow machine takes longer, a fast one returns at once. A screenshot of a page
    busy compiling on SwiftShader may itself take long on a loaded machine: each gets the time left."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        picture = page.screenshot(timeout=max(30_000, (deadline - time.monotonic()) * 1000))
        luminance = screenshot_luminance(picture)
        if shows(luminance) or time.monotonic() > deadline:
            return picture, luminance
        page.wait_for_timeout(interval_ms)


def layered_stadium(folder: Path, encoding: str = "quatTranslation", texel_format: str = "float16") -> Path:
    """The stadium converted with masks upper=spine and arm=R_upperArm, its crowd given two layers per
    instance on top of a crossfade (format 1.2), written to ``folder/layered/layered.usda``."""
    converted = folder / "c" / "stadium.usda"
    vbusd.convert(SAMPLE / "stadium_crowd.usda", converted,
                  vbusd.ConvertOptions(encoding=encoding, texel_format=texel_format, check_rows=0,
                                       masks=("upper=spine", "arm=R_upperArm")))
    asset = vbusd.read_asset(converted)
    crowd = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda").crowds[0]
    n = crowd.instance_count
    weight = np.zeros((n, 2), np.float32)
    weight[:6, 0] = [0.0, 1.0, 0.25, 0.5, 0.8, 0.6]
    weight[:6, 1] = [0.0, 0.0, 0.0, 0.7, 1.0, 0.0]
    layered = dataclasses.replace(
        crowd, layer_clip=np.zeros((n, 2), np.int32), layer_mask=np.tile(np.array([0, 1], np.int32), (n, 1)),
        layer_time_offset=np.tile(np.array([3.25, 7.5], np.float32), (n, 1)),
        layer_playback_rate=np.tile(np.array([1.0, 0.5], np.float32), (n, 1)), layer_weight=weight,
        fade_clip=np.zeros(n, np.int32), fade_time_offset=np.full(n, 1.5, np.float32),
        fade_playback_rate=np.ones(n, np.float32),
        fade_weight=np.array([0, 0, 0, 0, 0, 0.4] + [0] * (n - 6), np.float32))
    path = folder / "layered" / "layered.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(layered,), crowd_animation=(0,)), path)
    return path


def check_previous(page: ViewerPage, asset, instance: int, t: float, dt: float) -> tuple[float, float]:
    """Probe the page's previous-frame pose (spec virtual-bones.md 21) of ``instance`` at ``t`` and
    compare it with the numpy decoder at scene time ``t - dt`` (every clip-local time at timeOffset
    + playbackRate * (t - dt), wrapped or clamped by its clip; fades and layers at t - dt): returns
    (previous-position error / diagonal, the largest distance the instance's points moved between
    t - dt and t / diagonal: the motion the velocity pass sees, so a probe that returned the
    current pose as the previous one fails)."""
    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])
    assert abs(result["dt"] - dt) <= 1e-12, (result["dt"], dt)
    previous = np.asarray(result["previousPositions"], dtype=np.float64).reshape(-1, 3)
    expected_previous, _ = reference_instance(asset, instance, t - dt)
    expected_current, _ = reference_instance(asset, instance, t)
    assert previous.shape == expected_previous.shape
    diagonal = float(np.linalg.norm(expected_current.max(0) - expected_current.min(0)))
    error = world_error(previous, expected_previous) / diagonal
    moved = float(np.linalg.norm(expected_current - expected_previous, axis=1).max()) / diagonal
    return error, moved


def across_clip_time(crowd, instance: int, boundary: float, dt: float) -> float:
    """The scene time t at which ``instance``'s clip-local time timeOffset + playbackRate * t is half
    a frame past ``boundary`` (a loop's end, a clamped clip's end): t - dt lies half a frame before it."""
    offset = float(crowd.time_offset[instance])
    rate = float(crowd.playback_rate[instance])
    return (boundary - offset) / rate + 0.5 * dt


def rasterize_nearest(clip: np.ndarray, triangles: np.ndarray, width: int, height: int,
                      budget: int = 4_000_000) -> tuple[np.ndarray, np.ndarray]:
    """A depth-tested rasterization of ``triangles`` given in clip space (x, y, z, w; all w > 0):
    per pixel centre the nearest triangle (NDC depth, linear in screen space) as its index (-1:
    none) and its perspective-correct barycentric weights (height, width, 3), as a GPU's
    interpolation of a varying uses them. Chunked over (triangle, pixel) pairs as :func:`rasterize`."""
    ndc = clip[:, :3] / clip[:, 3:]
    pixels = np.empty((len(clip), 2))
    pixels[:, 0] = (ndc[:, 0] + 1.0) * 0.5 * width
    pixels[:, 1] = (1.0 - ndc[:, 1]) * 0.5 * height
    corners = pixels[triangles]
    lo = np.floor(corners.min(axis=1) - 0.5).astype(np.int64).clip(0, [width - 1, height - 1])
    hi = np.ceil(corners.max(axis=1) - 0.5).astype(np.int64).clip(0, [width - 1, height - 1])
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = np.flatnonzero(area != 0)
    spans = (hi - lo + 1)[keep]
    counts = spans[:, 0] * spans[:, 1]
    ends = np.cumsum(counts)
    depth = np.full(width * height, np.inf)
    nearest = np.full(width * height, -1, dtype=np.int64)
    weights = np.zeros((width * height, 3))
    start = 0
    while start < len(keep):
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + budget, side="right")))
        n = counts[start:stop]
        which = np.repeat(np.arange(stop - start), n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        width_of = spans[start:stop, 0][which]
        triangle = keep[start:stop][which]
        xs = lo[triangle, 0] + local % width_of + 0.5
        ys = lo[triangle, 1] + local // width_of + 0.5
        p, q, r = a[triangle], b[triangle], c[triangle]
        total = area[triangle]
        l0 = ((q[:, 0] - xs) * (r[:, 1] - ys) - (q[:, 1] - ys) * (r[:, 0] - xs)) / total
        l1 = ((r[:, 0] - xs) * (p[:, 1] - ys) - (r[:, 1] - ys) * (p[:, 0] - xs)) / total
        l2 = 1.0 - l0 - l1
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        triangle, l0, l1, l2 = triangle[inside], l0[inside], l1[inside], l2[inside]
        index = (ys[inside] - 0.5).astype(np.int64) * width + (xs[inside] - 0.5).astype(np.int64)
        vertices = triangles[triangle]
        z = l0 * ndc[vertices[:, 0], 2] + l1 * ndc[vertices[:, 1], 2] + l2 * ndc[vertices[:, 2], 2]
        order = np.lexsort((z, index))
        first = order[np.r_[True, index[order][1:] != index[order][:-1]]] if len(order) else order
        better = z[first] < depth[index[first]]
        chosen = first[better]
        at = index[chosen]
        depth[at] = z[chosen]
        nearest[at] = triangle[chosen]
        # Perspective-correct: screen-space weights over each corner's w, renormalized.
        inverse_w = 1.0 / clip[vertices[chosen], 3]
        perspective = np.stack([l0[chosen], l1[chosen], l2[chosen]], axis=1) * inverse_w
        weights[at] = perspective / perspective.sum(axis=1, keepdims=True)
        start = stop
    return nearest.reshape(height, width), weights.reshape(height, width, 3)
