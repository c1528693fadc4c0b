"""The README's picture is what scripts/make_readme_image.py makes now.

The README opens with docs/images/stadium_crowd.png (the stadium crowd in ``vbusd view``); this test
runs the script as a user would, into a temporary file, and compares the result with the committed
picture pixel by pixel, so a change to the viewer, the runtime, the sample or the script that
changes the picture fails here until the picture is made again. A small tolerance allows for
another Chromium build's rasterization (SwiftShader's rounding, antialiasing at edges); a wrong
pose, camera or lighting changes far more pixels than it allows.

Skips with one line when Chromium or playwright is missing (scripts/install-system-deps.sh).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import png
import pytest


REPO = Path(__file__).resolve().parents[1]
PICTURE = REPO / "docs" / "images" / "stadium_crowd.png"
SCRIPT = REPO / "scripts" / "make_readme_image.py"
CHANNEL_TOLERANCE = 24  # of 255: a pixel counts as different beyond this in any channel
DIFFERENT_PIXELS = 0.01  # at most this fraction of the picture may differ


def read_rgb(path: Path) -> np.ndarray:
    width, height, rows, _ = png.Reader(filename=str(path)).asRGBA8()
    return np.vstack([np.frombuffer(bytes(row), dtype=np.uint8) for row in rows]).reshape(height, width, 4)[:, :, :3]


def test_readme_opens_with_the_picture():
    lines = [line for line in (REPO / "README.md").read_text(encoding="utf-8").splitlines() if line.strip()]
    assert lines[0].startswith("# ")
    assert lines[1].startswith("![") and "(docs/images/stadium_crowd.png)" in lines[1], lines[1]
    assert PICTURE.is_file()


@pytest.mark.browser
@pytest.mark.cli
def test_picture_is_what_the_script_makes_now(tmp_path):
    made = tmp_path / "stadium_crowd.png"
    result = subprocess.run([sys.executable, str(SCRIPT), "-o", str(made)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-4000:]
    committed, fresh = read_rgb(PICTURE), read_rgb(made)
    assert committed.shape == fresh.shape, "run python scripts/make_readme_image.py"
    different = (np.abs(committed.astype(np.int16) - fresh.astype(np.int16)).max(axis=2) > CHANNEL_TOLERANCE).mean()
    print(f"{different:.4%} of the pixels differ")
    assert different <= DIFFERENT_PIXELS, \
        f"{different:.2%} of the picture changed: run python scripts/make_readme_image.py and commit the picture"
    # The picture shows a crowd, not an empty or failed page: many light-grey (lit figure) pixels.
    assert (fresh.mean(axis=2) > 110).mean() > 0.04
