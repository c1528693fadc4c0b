"""Make the README's picture: the stadium crowd in ``vbusd view``, drawn by headless Chromium.

The sample crowd (samples/stadium_crowd/stadium_crowd_vb.usda: 1,200 spectators, one 64 x 512
float16 texture) is served by :class:`vbusd.web.server.ViewerServer` exactly as ``vbusd view``
serves it, and the viewer page is opened in Debian's chromium (software WebGL 2, SwiftShader)
through playwright (:mod:`vbusd.web.browser`) at a fixed camera and time, lit, with shadows, fog and
tone mapping; the canvas is saved as a PNG.

Usage (needs what scripts/install-system-deps.sh installs)::

    python scripts/make_readme_image.py                # writes docs/images/stadium_crowd.png
    python scripts/make_readme_image.py -o other.png

tests/test_readme_image.py runs it and compares the result with the committed picture, so the
picture cannot go stale without a failing test. Exit status 2 with one line when the browser is
missing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ASSET = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
OUTPUT = REPO / "docs" / "images" / "stadium_crowd.png"

WIDTH, HEIGHT = 960, 400
TIME = 3.2  # seconds into the looping cheer: arms at different heights across the stand
CAMERA = "-16,7,27,4,2.2,46"  # x,y,z of the eye, then of the target (Y up, metres): the field side
FOV = 34


def page_query() -> str:
    """The viewer's query string for the picture (fixed size, camera and time; no panel)."""
    return (f"?time={TIME}&paused=1&ui=0&pixelRatio=1&width={WIDTH}&height={HEIGHT}"
            f"&camera={CAMERA}&fov={FOV}")


def render_png(asset: Path = ASSET) -> bytes:
    """The PNG bytes of the viewer's canvas for ``asset`` (raises RuntimeError on a page error)."""
    from vbusd.web.browser import ViewerPage, chromium
    from vbusd.web.server import ViewerServer

    with chromium() as browser, ViewerServer(asset) as server:
        page = ViewerPage(browser, server.url + page_query(), width=WIDTH, height=HEIGHT)
        try:
            if page.error:
                raise RuntimeError(f"the viewer failed: {page.error}")
            page.page.evaluate("window.vbusd.render()")
            data = page.page.locator("#view").screenshot()
            errors = page.errors()
            if errors:
                raise RuntimeError(f"console errors: {errors}")
        finally:
            page.close()
    return data


def main(argv=None) -> int:
    """Render the picture and write it atomically.

    Args:
        argv: Command-line arguments (default: ``sys.argv[1:]``).

    Returns:
        0 when written, 2 when Chromium or playwright is missing (one line on stderr says which).
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", type=Path, default=OUTPUT, help="PNG to write (default: %(default)s)")
    args = parser.parse_args(argv)
    from vbusd.io.files import atomic_write
    from vbusd.web.browser import unavailable_reason

    reason = unavailable_reason()
    if reason:
        print(f"make_readme_image: {reason}", file=sys.stderr)
        return 2
    data = render_png()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.output) as handle:
        handle.write(data)
    print(f"make_readme_image: wrote {args.output} ({WIDTH} x {HEIGHT}, {len(data):,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
