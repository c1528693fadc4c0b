"""Rules of the test suite itself that a run on one machine would not catch.

* One playwright driver per process: playwright's sync API refuses to start a driver while another
  one's event loop runs in the same thread, so a module that opened its own (``sync_playwright()``
  or ``vbusd.web.browser.chromium()``) failed only when xdist happened to give one worker both
  modules (CI, not this machine). Browsers come from the session fixtures in
  tests/helpers/fixtures.py.
"""

from __future__ import annotations

import re

from tests.helpers.capabilities import REPO

DRIVER = re.compile(r"\bsync_playwright\s*\(|\bchromium\s*\(\s*(webgpu\s*=\s*\w+\s*)?\)")


def test_only_the_session_fixture_starts_a_playwright_driver():
    owners = {"tests/helpers/fixtures.py",
              # the side-by-side benchmark's command line (its main) launches its own; tests check its logic only
              "tests/helpers/engines_side_by_side.py"}
    offenders = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        relative = path.relative_to(REPO).as_posix()
        if relative in owners or "node_modules" in relative or relative == "tests/test_suite_rules.py":
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if DRIVER.search(line) and not line.lstrip().startswith("#"):
                offenders.append(f"{relative}:{number}: {line.strip()}")
    assert not offenders, "use the session's browser / webgpu_browser fixtures:\n" + "\n".join(offenders)


def test_the_rule_sees_a_driver():
    assert DRIVER.search("    with sync_playwright() as p:")
    assert DRIVER.search("with chromium() as launched:")
    assert DRIVER.search("with chromium(webgpu=True) as launched:")
    assert not DRIVER.search("from vbusd.web.browser import chromium_executable")
