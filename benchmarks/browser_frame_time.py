"""Frame time of ``vbusd view`` in headless Chromium with SOFTWARE WebGL 2 (SwiftShader), issue 14.

What it runs: the stadium crowd sample (202 vertices, 18 bones, crossMatrix float16) as ``vbusd
view`` serves it, with 1,200 instances (the sample) and 10,000 instances (the sample's stand
repeated nine times, then cut to 10,000; every instance keeps its clip, time offset and rate), at a
fixed 1280 x 720 canvas (pixel ratio 1, antialiasing on), with the default camera that frames the
whole crowd. ``window.vbusd.measureFrames(n)`` advances the clock by 1/60 s, renders and reads one
pixel back (so every frame is finished, not only queued), n times; the figure is the mean.

Five variants per crowd, measured one after another in this order for each count:

* ``lit + shadows``: the viewer as it opens (patched MeshStandardMaterial, a 2048^2 shadow map
  drawn with the patched depth material, fog, ACES tone mapping): two skinned passes;
* ``unlit``: ``silhouette=1`` (patched MeshBasicMaterial, no shadow pass): one skinned pass;
* each of those two in both skin bindings (spec/shaders.md, "Skin bindings"; the page's
  ``?skin=``): ``attributes`` (bone indices and weights as vertex attributes) and ``pulled`` (the
  skin records in an RGBA32UI texture read by ``gl_VertexID``);
* ``static``: the same InstancedMesh and lights with the materials replaced by unpatched ones (the
  rest pose, no texture fetches): what instancing costs without Virtual Bones skinning.

What it tells: the relative cost of Virtual Bones skinning against static instancing, and of the
shadow pass, on one CPU rasterizer; that 10,000 skinned instances run in a browser at all. What it
does NOT tell: frame times on a GPU. SwiftShader runs every vertex and fragment on the CPU (here 2
shared cores), so the absolute numbers are orders of magnitude above any hardware GPU's.

Usage::

    python benchmarks/browser_frame_time.py [--frames 5] [--counts 1200 10000] [--repeats 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

import vbusd
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
WIDTH, HEIGHT = 1280, 720

UNPATCH = """() => {
  for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
    mesh.material = new mesh.material.constructor({ color: 0xb7bcc6, roughness: 0.65, metalness: 0.0 });
    mesh.customDepthMaterial = undefined;
    mesh.customDistanceMaterial = undefined;
  }
}"""


def crowd_asset(count: int, folder: Path) -> Path:
    """The sample with ``count`` instances: its stand repeated on a 3 x 3 grid, cut to ``count``."""
    asset = vbusd.read_asset(SAMPLE)
    if count == asset.crowds[0].instance_count:
        return SAMPLE
    crowd = asset.crowds[0]
    positions = np.asarray(crowd.positions)
    extent = positions.max(0) - positions.min(0)
    copies = -(-count // crowd.instance_count)
    shifts = [np.array([(i % 3 - 1) * (extent[0] + 4.0), 0.0, (i // 3) * (extent[2] + 6.0)]) for i in range(copies)]
    tiled = np.concatenate([positions + shift for shift in shifts])[:count].astype(np.float32)

    def repeat(values):
        return None if values is None else np.concatenate([np.asarray(values)] * copies)[:count]

    many = dataclasses.replace(crowd, positions=tiled, orientations=repeat(crowd.orientations),
                               scales=repeat(crowd.scales), clip=repeat(crowd.clip),
                               time_offset=repeat(crowd.time_offset), playback_rate=repeat(crowd.playback_rate),
                               fade_clip=repeat(crowd.fade_clip), fade_time_offset=repeat(crowd.fade_time_offset),
                               fade_playback_rate=repeat(crowd.fade_playback_rate),
                               fade_weight=repeat(crowd.fade_weight))
    path = folder / f"crowd_{count}" / "crowd.usda"
    path.parent.mkdir(parents=True)
    vbusd.write_asset(dataclasses.replace(asset, crowds=(many,)), path)
    return path


VARIANTS = (("lit", "attributes"), ("lit", "pulled"), ("unlit", "attributes"), ("unlit", "pulled"),
            ("static", "attributes"))


def measure(browser, path: Path, variant: str, frames: int, skin: str = "attributes") -> float:
    """Mean milliseconds per finished frame of one variant in skin binding ``skin``."""
    query = f"?ui=0&paused=1&time=1.0&pixelRatio=1&width={WIDTH}&height={HEIGHT}&skin={skin}"
    if variant == "unlit":
        query += "&silhouette=1"
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url + query, width=WIDTH, height=HEIGHT, timeout_s=300)
        try:
            if page.error:
                raise RuntimeError(page.error)
            if variant == "static":
                page.page.evaluate(UNPATCH)
            page.page.evaluate("window.vbusd.measureFrames(3)")  # compile and warm up
            milliseconds = page.page.evaluate(f"window.vbusd.measureFrames({frames})")
            if page.errors():
                raise RuntimeError(page.errors())
        finally:
            page.close()
    return float(milliseconds)


def main() -> None:
    """Print the frame-time table (markdown) for the requested instance counts."""
    parser = argparse.ArgumentParser(description="vbusd view frame time in headless Chromium (software WebGL)")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--counts", type=int, nargs="+", default=[1200, 10000])
    parser.add_argument("--repeats", type=int, default=1,
                        help="measure every variant this many times, interleaved, and print each round")
    args = parser.parse_args()
    reason = unavailable_reason()
    if reason:
        raise SystemExit(f"browser_frame_time: {reason}")
    with tempfile.TemporaryDirectory() as folder, chromium() as browser:
        print(f"SOFTWARE rendering (SwiftShader), Chromium {browser.version}, {platform.processor() or platform.machine()}, "
              f"{WIDTH} x {HEIGHT}, {args.frames} frames each, {os.cpu_count()} CPUs, "
              f"load average {os.getloadavg()[0]:.1f} at the start")
        print("| round | instances | skinned vertices per pass | lit + shadows, attributes (ms) | lit + shadows, "
              "pulled (ms) | unlit, attributes (ms) | unlit, pulled (ms) | static, unpatched (ms) |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for count in args.counts:
            path = crowd_asset(count, Path(folder))
            for round_ in range(1, args.repeats + 1):
                times = [measure(browser, path, variant, args.frames, skin) for variant, skin in VARIANTS]
                print(f"| {round_} | {count:,} | {count * 202:,} | " + " | ".join(f"{t:.1f}" for t in times) + " |",
                      flush=True)


if __name__ == "__main__":
    main()
