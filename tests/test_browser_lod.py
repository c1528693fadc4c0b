"""Levels of detail in the three.js runtime (format 1.2, spec/virtual-bones.md 20.2), in headless Chromium.

The stadium spectator with 3 generated levels (``vbusd convert --lod-ratios 0.5,0.2``), five
instances in a row at chosen distances, exported as a runtime package (MSFT_lod) and opened with
``vbusd view``'s page at a fixed camera. Checked against independent references:

* the level ``window.vbusd.probe`` reports for each instance equals OpenUSD's own choice,
  ``UsdLodScreenSizeHeuristic.ComputeLOD`` with a ``GfFrustum`` of the page's camera (field of
  view, aspect, position) and the package's thresholds; an instance behind the camera, to which
  UsdLod gives screen size 0, is culled (-1);
* the skinned vertices the GPU returns for each instance are that level's mesh skinned by vbusd's
  numpy decoder, within 1e-6 of the bounding-box diagonal plus one float32 rounding of the world
  coordinate (the far instances stand 90 m away);
* the triangles drawn equal the levels' triangle counts summed over the instances, fewer than
  five LOD 0 characters.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import vbusd
from vbusd.decoders.reference import skin_crowd
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer


from tests.helpers.lod_row import DISTANCES, PAGE, STADIUM, make_row_package
from tests.helpers.lod_row import usdlod_levels as _usdlod_levels


@pytest.fixture(scope="module")
def row_package(tmp_path_factory):
    """The spectator with 3 levels, five instances along -Z, as a .glb."""
    return make_row_package(tmp_path_factory.mktemp("lod_browser"))


def test_runtime_selects_the_level_usdlod_selects_and_skins_it(browser, row_package):
    asset, package = row_package
    vb = asset.animations[0]
    expected_levels = _usdlod_levels(asset)
    assert sorted(set(expected_levels)) == [-1, 0, 1, 2], expected_levels  # every level, and one culled
    meshes = {m.lod: m for m in vb.meshes}
    t = 1.37
    with ViewerServer(package) as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            page.page.evaluate("() => window.vbusd.render()")
            levels = page.page.evaluate("() => window.vbusd.levels()")
            assert levels["lod"] == expected_levels
            triangles = [len(meshes[level].face_vertex_counts) for level in expected_levels if level >= 0]
            assert levels["triangles"] == sum(triangles) < len(DISTANCES) * len(meshes[0].face_vertex_counts)
            crowd = asset.crowds[0]
            for instance, level in enumerate(expected_levels):
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, t])
                assert result["lod"] == level
                if level < 0:
                    continue  # culled: nothing drawn to compare
                one = dataclasses.replace(crowd, **{f: getattr(crowd, f)[instance:instance + 1] for f in
                                                    ("positions", "orientations", "clip", "time_offset", "playback_rate")})
                expected, _ = skin_crowd(vb, meshes[level], one, t)
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                assert positions.shape == expected[0].shape
                diagonal = float(np.linalg.norm(expected[0].max(0) - expected[0].min(0)))
                # 1e-6 of the diagonal, plus one float32 rounding of a world coordinate: an instance
                # 90 m away is placed in float32 (its ulp is 7.6e-6 m there).
                tolerance = 1e-6 * diagonal + np.finfo(np.float32).eps * float(np.abs(expected[0]).max())
                assert np.abs(positions - expected[0]).max() <= tolerance
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def test_vbusd_view_of_a_usd_crowd_with_levels_draws_one_level_per_instance(browser, tmp_path):
    """The plain files of a USD asset carry the levels too: ``vbusd view`` of the 3-level stadium crowd
    (USD, not a package) draws each instance at one level, never every level at once."""
    asset_path = tmp_path / "stadium.usda"
    vbusd.convert(STADIUM, asset_path, vbusd.ConvertOptions(lod_ratios=(0.5, 0.2), check_rows=0))
    from vbusd.cli import main

    crowd = tmp_path / "crowd.usda"
    assert main(["crowd", str(asset_path), "-o", str(crowd), "--count", "40", "-q"]) == 0
    with ViewerServer(crowd) as server:
        page = ViewerPage(browser, server.url + "?paused=1&ui=0&silhouette=1&width=320&height=180")
        try:
            assert page.error == "", page.error
            page.page.evaluate("() => window.vbusd.render()")
            state = page.page.evaluate("""() => window.vbusd.crowds.map((crowd) => ({
                levels: crowd.levels ? crowd.levels.length : 0,
                drawn: crowd.levels ? crowd.levels.map((meshes) => meshes[0].count) : [],
                lod: Array.from({ length: crowd.capacity }, (_, i) => crowd.levelOf(i))}))""")
            (only,) = state
            assert only["levels"] == 3
            assert sum(only["drawn"]) == sum(1 for level in only["lod"] if level >= 0) > 0
            assert page.errors() == [], page.errors()
        finally:
            page.close()
