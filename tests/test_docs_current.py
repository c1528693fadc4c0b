"""The pages that state facts of the code state the current ones (issue 35 item 16): each fact is
read from the page and compared with where it lives (the spec's status line, the Encoding enum,
the runtime's default skin, the browser flags vbusd launches Chromium with, the tests collected).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.capabilities import unavailable

ROOT = Path(__file__).resolve().parents[1]


def test_spec_readme_states_the_current_version_encodings_and_version_form():
    from vbusd.format.layout import Encoding

    readme = (ROOT / "spec" / "README.md").read_text()
    spec = (ROOT / "spec" / "virtual-bones.md").read_text()
    (current,) = re.findall(r"Format version: \*\*(\d+\.\d+)\*\*", spec)
    assert f"Current format version: **{current}**" in readme
    words = {2: "two", 3: "three", 4: "four", 5: "five", 6: "six"}
    assert f"the {words[len(Encoding)]} encodings" in readme
    assert all(f"`{e.value}`" in readme for e in Encoding)
    assert "an integer" not in readme and "major.minor" in readme
    assert re.search(rf"^\| {re.escape(current)} \|", readme, flags=re.M), "no change-log row for " + current


def test_engines_page_names_every_engine_and_one_default_skin():
    from vbusd.web.engines import ENGINES

    page = (ROOT / "docs" / "engines.md").read_text()
    title = page.splitlines()[0]
    names = {"three": "three.js", "three-webgpu": "three.js", "babylon": "Babylon.js"}
    assert all(names[e] in title for e in ENGINES), title
    (default,) = re.findall(r"export const DEFAULT_SKIN = '(\w+)'", (ROOT / "web" / "src" / "skin.js").read_text())
    other = {"pulled": "attributes", "attributes": "pulled"}[default]
    assert f"`{default}` by default" in page
    assert f"keeps `{other}` as its default" not in page and f"`{other}` by default" not in page


def test_documented_headless_webgpu_flags_are_the_ones_vbusd_launches():
    from vbusd.web.browser import CHROMIUM_ARGS, WEBGPU_ARGS

    page = (ROOT / "docs" / "engines.md").read_text()
    (bullet,) = re.findall(r"\* \*\*Headless Chromium\.\*\*(.*?)(?=\n\* |\n\n)", page, flags=re.S)
    text = " ".join(bullet.split())
    graphics = [a for a in CHROMIUM_ARGS if "swiftshader" in a or "angle" in a or a == "--headless"]
    for flag in graphics + WEBGPU_ARGS:
        assert flag in text, f"docs/engines.md's headless WebGPU flags omit {flag}"


@pytest.mark.cli  # collects the Blender tests in another pytest process
def test_blender_page_counts_the_tests_there_are():
    """The tested-versions table's count for the CI's Blender equals the tests collected."""
    page = (ROOT / "docs" / "blender.md").read_text()
    (row,) = [line for line in page.splitlines() if "the `blender` extra" in line and line.startswith("|")]
    (stated,) = re.findall(r"all (\d+) pass", row)
    done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                           "tests/test_blender.py", "tests/test_blender_extension.py"],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    collected = re.search(r"(\d+) tests? collected", done.stdout)
    if collected is None or "skipped" in done.stdout.splitlines()[-1]:
        unavailable("blender", "the Blender tests do not collect here (no bpy wheel)")
    assert int(stated) == int(collected.group(1)), (stated, done.stdout.splitlines()[-1])
