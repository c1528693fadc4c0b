"""The side-by-side benchmark's own correctness logic (benchmarks/engines_side_by_side.py, issue 27).

Its pose-difference column is only worth something if three's SkinnedMesh clones play the same
clip time as the vbusd instances: at a tiny crowd of the Khronos CesiumMan (shared assets; skips
without them or without Chromium), vbusd's probe and three's CPU skinning of the clone agree within
the bake's float16 error (< 5e-3 of the diagonal), and the same comparison with the clone 0.25 s
off disagrees (> 2e-2): the measure can fail. The table row's figures are positive and the GPU
bytes follow the stated formula (texture + 92 bytes per instance; 64 bytes per joint per clone).
"""

from __future__ import annotations


import pytest

from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers import engines_side_by_side
from tests.helpers.capabilities import shared_asset



@pytest.fixture(scope="module")
def bench():
    return engines_side_by_side  # the harness of benchmarks/engines_side_by_side.py


def test_clones_play_the_vbusd_clip_time(bench, webgpu_browser, tmp_path):
    browser = webgpu_browser
    source = shared_asset("gltf", "CesiumMan", "CesiumMan.glb")
    crowd = bench.build_crowd(source, tmp_path, 4)
    with ViewerServer(crowd, engine="three-webgpu", allow_outside_paths=True) as server:
        page = ViewerPage(browser, server.url + "?ui=0&paused=1&silhouette=1&width=320&height=180")
        try:
            assert page.error == "", page.error
            ours = page.page.evaluate(bench.MEASURE, [1, "vbusd", ""])
            texture = page.page.evaluate("((l) => l.width * l.height * 4 * 2)(window.vbusd.animations[0].layout)")
            assert ours["bytes"] == texture + 4 * 92 and ours["frame"] > 0 and ours["cpu"] > 0
            result = page.page.evaluate(bench.MEASURE, [1, "clones", server.url + "asset/source.glb"])
            joints = page.page.evaluate("window.vbusdClones[0].clone.getObjectByProperty('isSkinnedMesh', true)"
                                        ".skeleton.bones.length")
            assert result["bytes"] == 4 * joints * 64 and result["frame"] > 0 and result["cpu"] > 0
            same = max(bench.pose_difference(page, i, t) for i in range(4) for t in bench.PROBE_TIMES)
            page.page.evaluate("for (const c of window.vbusdClones) c.offset += 0.25")
            shifted = max(bench.pose_difference(page, i, t) for i in range(4) for t in bench.PROBE_TIMES)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    print(f"pose difference {same:.2e}, clones 0.25 s off {shifted:.2e}")
    assert same < 5e-3
    assert shifted > 2e-2


def test_babylon_bva_plays_the_vbusd_clip_time(bench, browser, tmp_path):
    """The Babylon rows: Babylon's BakedVertexAnimationManager, baked from the same glTF and set to
    each vbusd instance's offset and rate, is posed like vbusd's probe within its frame hold (no
    interpolation between its frames: < 0.1 of the diagonal), and 0.25 s off it is clearly further
    (the measure can fail). The bytes follow the stated formulas (vbusd: texture + 96 bytes per
    instance; BVA: (joints + 1) float32 4x4 matrices per frame + 80 bytes per instance)."""
    source = shared_asset("gltf", "CesiumMan", "CesiumMan.glb")
    crowd = bench.build_crowd(source, tmp_path, 4)
    with ViewerServer(crowd, engine="babylon", allow_outside_paths=True) as server:
        page = ViewerPage(browser, server.url + "?ui=0&paused=1&silhouette=1&width=320&height=180")
        try:
            assert page.error == "", page.error
            ours = page.page.evaluate(bench.MEASURE_BABYLON, [1, "vbusd", ""])
            texture = page.page.evaluate("((l) => l.width * l.height * 4 * 2)(window.vbusd.animations[0].layout)")
            assert ours["bytes"] == texture + 4 * 96 and ours["frame"] > 0 and ours["cpu"] > 0
            result = page.page.evaluate(bench.MEASURE_BABYLON, [1, "bva", server.url + "asset/source.glb"])
            per, rows = page.page.evaluate("[window.vbusdBVA.per, window.vbusd.animations[0].clips[0].rowCount]")
            assert result["bytes"] == per * 4 * rows + 4 * 80 and result["frame"] > 0 and result["cpu"] > 0
            same = max(bench.pose_difference(page, i, t, bench.BVA_POSE) for i in range(4) for t in bench.PROBE_TIMES)
            page.page.evaluate("""() => { const { settings } = window.vbusdBVA;
                for (let i = 0; i < settings.length / 4; ++i) settings[4 * i + 2] += 0.25 * settings[4 * i + 3]; }""")
            shifted = max(bench.pose_difference(page, i, t, bench.BVA_POSE) for i in range(4) for t in bench.PROBE_TIMES)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    print(f"BVA pose difference {same:.2e}, 0.25 s off {shifted:.2e}")
    assert same < 0.1
    assert shifted > 2 * same
