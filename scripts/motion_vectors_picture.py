"""The picture of docs/engines.md ("Motion vectors"): three's TRAA on a moving vbusd crowd under
WebGPURenderer, with the crowd's motion vectors (spec virtual-bones.md 21) and without them.

What it runs: ``vbusd view --engine three-webgpu`` on the stadium sample's front row (100 of its
1,200 cheering figures, seen from just in front of it) in headless Chromium on SwiftShader's WebGPU (:data:`vbusd.web.browser.WEBGPU_ARGS`), the page
asked for three's TRAA (``?post=traa``: three/addons/tsl/display/TRAANode.js, fed by an MRT
``velocity`` output). The clock advances ``--frames`` frames of ``--dt`` seconds, each rendered
and finished, then the canvas is captured twice over:

* ``with``: the crowd's materials write the previous frame's skinned position into three's
  ``positionPrevious`` (the default): TRAA reprojects each pixel's history to where that surface was;
* ``without`` (``?velocity=0``): the crowd writes its current skinned position there, as an
  instanced mesh without vbusd's previous pose would: the velocity buffer says the limbs did not
  move, TRAA blends history from the wrong place and moving arms leave ghosts.

It also renders the same last frame without TRAA (``reference``) and prints each TRAA image's mean
absolute difference from it (8-bit grey levels, over the pixels the crowd covers in either): the
ghosting as a number. Writes the side-by-side ``traa_motion_vectors.png`` (left: with, right:
without) and ``traa_reference.png`` into ``--out``.

Usage::

    python scripts/motion_vectors_picture.py [--out docs/images] [--frames 24] [--dt 0.0667]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
CAMERA = "0,1.1,35.2,0,1.05,40"  # in front of the first row: a few figures, their arms large
INSTANCES = 100  # the front row (the sample's first 100 instances): figures against the dark sky

RUN = """async ([t0, dt, frames]) => {
  const v = window.vbusd;
  const finish = () => v.renderer.backend.device.queue.onSubmittedWorkDone();
  for (let k = 0; k <= frames; ++k) {
    v.setTime(t0 + k * dt, dt);
    v.render();
    await finish();
  }
}"""


def capture(browser, url: str, t0: float, dt: float, frames: int, width: int, height: int) -> bytes:
    from vbusd.web.browser import ViewerPage

    page = ViewerPage(browser, url, width=width, height=height, timeout_s=300)
    try:
        if page.error:
            raise RuntimeError(page.error)
        if page.page.evaluate("window.vbusd.backend") != "webgpu":
            raise RuntimeError("this Chromium offers no WebGPU adapter (see vbusd.web.browser.WEBGPU_ARGS)")
        page.page.evaluate(RUN, [t0, dt, frames])
        picture = page.page.locator("#view").screenshot(timeout=300_000)
        errors = page.errors()
        if errors:
            raise RuntimeError("; ".join(errors))
        return picture
    finally:
        page.close()


def grey(png_bytes: bytes) -> np.ndarray:
    import png

    width, height, rows, _ = png.Reader(bytes=png_bytes).asRGBA8()
    rgba = np.vstack([np.frombuffer(bytes(row), dtype=np.uint8) for row in rows]).reshape(height, width, 4)
    return rgba


def side_by_side(images: list[np.ndarray], gap: int = 6) -> np.ndarray:
    height = max(image.shape[0] for image in images)
    parts = []
    for index, image in enumerate(images):
        if index:
            parts.append(np.full((height, gap, 4), 255, np.uint8))
        parts.append(image)
    return np.concatenate(parts, axis=1)


def write_png(path: Path, rgba: np.ndarray) -> None:
    import png

    height, width, _ = rgba.shape
    with open(path, "wb") as handle:
        png.Writer(width, height, greyscale=False, alpha=True).write(handle, rgba.reshape(height, -1))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--frames", type=int, default=24, help="frames TRAA accumulates before the capture")
    parser.add_argument("--dt", type=float, default=1 / 15, help="seconds per frame (a fast clock moves arms far per frame)")
    parser.add_argument("--time", type=float, default=2.0, help="scene time of the first frame")
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=270)
    args = parser.parse_args(argv)

    from vbusd.web.browser import chromium, unavailable_reason
    from vbusd.web.server import ViewerServer

    reason = unavailable_reason()
    if reason:
        print(f"motion_vectors_picture: {reason}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    query = (f"?paused=1&ui=0&antialias=0&pixelRatio=1&width={args.width}&height={args.height}"
             f"&camera={CAMERA}&fov=30&time={args.time}&dt={args.dt!r}&instances={INSTANCES}")
    pictures = {}
    with chromium(webgpu=True) as browser, ViewerServer(SAMPLE, engine="three-webgpu") as server:
        for name, extra in (("with_velocity", "&post=traa"), ("without_velocity", "&post=traa&velocity=0"),
                            ("reference", "")):
            pictures[name] = capture(browser, server.url + query + extra, args.time, args.dt, args.frames,
                                     args.width, args.height)
    (args.out / "traa_reference.png").write_bytes(pictures["reference"])
    print(f"wrote {args.out / 'traa_reference.png'}")
    images = {name: grey(data) for name, data in pictures.items()}
    reference = images["reference"][..., :3].mean(axis=2)
    background = np.median(reference)
    for name in ("with_velocity", "without_velocity"):
        image = images[name][..., :3].mean(axis=2)
        region = (np.abs(reference - background) > 8) | (np.abs(image - background) > 8)
        print(f"TRAA {name.replace('_', ' ')}: mean |difference| from the frame without TRAA "
              f"{np.abs(image - reference)[region].mean():.2f} grey levels over {int(region.sum())} pixels")
    combined = side_by_side([images["with_velocity"], images["without_velocity"]])
    write_png(args.out / "traa_motion_vectors.png", combined)
    print(f"wrote {args.out / 'traa_motion_vectors.png'} (left: vbusd's motion vectors; right: none for the skinning)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
