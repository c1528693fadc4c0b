"""Levels of detail in ``vbusd view`` (headless Chromium, SOFTWARE WebGL 2), issue 29.

What it runs: the stadium spectator converted with ``vbusd convert --lod-ratios 0.5,0.2`` (LOD 0:
352 triangles, K = 4; LOD 1: 176, K = 2; LOD 2: 70, K = 1; default thresholds 0.01 and 0.001),
instanced 10,000 times (the sample's stand repeated nine times, cut to 10,000; each instance keeps
its clip, offset and rate, as benchmarks/browser_frame_time.py builds it), exported as a runtime
package (MSFT_lod) and opened in the viewer page at 1280 x 720, pixel ratio 1, unlit
(``silhouette=1``: one skinned pass), at two cameras: the default one framing the whole crowd, and
a ``stand`` camera at the crowd's front looking across it. Each camera is measured with the three
levels and with LOD 0 alone (the same package with its MSFT_lod nodes removed, so the runtime draws
every instance at LOD 0 as before issue 29). ``window.vbusd.measureFrames(n)`` advances the clock,
selects every instance's level (``crowd.updateLevels``, in JavaScript on the CPU, part of the frame),
renders and reads one pixel back; the figure is the mean. ``window.vbusd.levels()`` gives the
triangles drawn and each instance's level.

What it does NOT tell: GPU frame times. SwiftShader runs every vertex on the CPU (here 2 shared
cores), so the absolute figures are far above any GPU's; the H100 comparison is
``benchmarks/draw_cost.py run --plan issue29``.

Usage::

    python benchmarks/browser_lod.py [--frames 5] [--count 10000]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

import vbusd
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
WIDTH, HEIGHT = 1280, 720


def _frame_time_module():
    spec = importlib.util.spec_from_file_location("vbusd_bench_browser_frame_time", REPO / "benchmarks" / "browser_frame_time.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def packages(count: int, folder: Path) -> tuple:
    """(the crowd with three levels, the same with LOD 0 only) as .glb runtime packages, and the crowd."""
    from vbusd.io.gltf_package import export_gltf

    character = folder / "stadium_lods.usda"
    vbusd.convert(SOURCE, character, vbusd.ConvertOptions(lod_ratios=(0.5, 0.2), check_rows=0))
    asset = vbusd.read_asset(character)
    sample = vbusd.read_asset(REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda")
    tiled = vbusd.read_asset(_frame_time_module().crowd_asset(count, folder)) if count != 1200 else sample
    crowd = dataclasses.replace(tiled.crowds[0], path="/StadiumCrowd/Crowd")
    lods = dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,))
    export_gltf(lods, folder / "lods.glb")
    vb = asset.animations[0]
    one = dataclasses.replace(vb, meshes=tuple(m for m in vb.meshes if m.lod == 0), lods=None)
    export_gltf(dataclasses.replace(lods, animations=(one,)), folder / "lod0.glb")
    return folder / "lods.glb", folder / "lod0.glb", crowd


def stand_camera(crowd) -> str:
    """``camera=`` for the viewer: 6 m up, 5 m in front of the crowd's front row, looking across it."""
    positions = np.asarray(crowd.positions, np.float64)
    low, high = positions.min(0), positions.max(0)
    centre_x = 0.5 * (low[0] + high[0])
    eye = (centre_x, 6.0, high[2] + 5.0)
    target = (centre_x, 0.0, low[2])
    return ",".join(f"{v:.3f}" for v in (*eye, *target))


def measure(browser, package: Path, frames: int, camera: str = "") -> dict:
    query = f"?ui=0&paused=1&time=1.0&pixelRatio=1&width={WIDTH}&height={HEIGHT}&silhouette=1"
    if camera:
        query += f"&camera={camera}"
    with ViewerServer(package) as server:
        page = ViewerPage(browser, server.url + query, width=WIDTH, height=HEIGHT, timeout_s=600)
        try:
            if page.error:
                raise RuntimeError(page.error)
            page.page.evaluate("window.vbusd.measureFrames(3)")  # compile and warm up
            milliseconds = page.page.evaluate(f"window.vbusd.measureFrames({frames})")
            levels = page.page.evaluate("window.vbusd.levels()")
            if page.errors():
                raise RuntimeError(page.errors())
        finally:
            page.close()
    lod = np.asarray(levels["lod"])
    return {"ms": float(milliseconds), "triangles": int(levels["triangles"]),
            "per_level": [int((lod == k).sum()) for k in range(3)], "culled": int((lod < 0).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description="levels of detail in vbusd view (headless Chromium, software WebGL)")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--count", type=int, default=10_000)
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args()
    reason = unavailable_reason()
    if reason:
        raise SystemExit(f"browser_lod: {reason}")
    with tempfile.TemporaryDirectory() as folder, chromium() as browser:
        with_levels, lod0, crowd = packages(args.count, Path(folder))
        print(f"SOFTWARE rendering (SwiftShader), Chromium {browser.version}, {platform.processor() or platform.machine()}, "
              f"{WIDTH} x {HEIGHT}, unlit, {args.frames} frames each, {os.cpu_count()} CPUs, "
              f"load average {os.getloadavg()[0]:.1f} at the start")
        print("| camera | instances | levels | frame (ms) | triangles drawn | LOD 0 / 1 / 2, culled |")
        print("| --- | ---: | --- | ---: | ---: | --- |")
        results = []
        for camera_name, camera in (("whole crowd (default)", ""), ("stand: across the crowd", stand_camera(crowd))):
            for label, package in (("1 (LOD 0 only)", lod0), ("3", with_levels)):
                figures = measure(browser, package, args.frames, camera)
                results.append({"camera": camera_name, "levels": label, **figures})
                per = " / ".join(f"{c:,}" for c in figures["per_level"]) + f", {figures['culled']:,} culled"
                if label.startswith("1"):
                    per = f"{args.count:,} / 0 / 0, not culled per instance"
                print(f"| {camera_name} | {args.count:,} | {label} | {figures['ms']:.0f} | {figures['triangles']:,} | {per} |",
                      flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
