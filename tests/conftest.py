"""Shared pytest configuration for the vbusd test suite: tiers, capabilities, the time per tier.

Tests import vbusd from the checkout (``python -m pytest`` puts the current folder first on
``sys.path``, and pyproject's ``pythonpath = ["."]`` does so for a bare ``pytest``); the shared
helpers are the package :mod:`tests.helpers` (``from tests.helpers import ...``).

**Tiers** (markers; ``python -m pytest -m unit`` is the fast tier a developer runs):

=========  ===========================================================================================
unit       none of the others: in-process, no external tool (given to every test without another tier)
cli        starts the ``vbusd`` command (``python -m vbusd``) or another Python process
gl         an EGL OpenGL context or the shader compilers (glslang, spirv-cross)
browser    headless Chromium (one per xdist worker, pages per test)
node       Node.js and the npm packages
blender    the bpy wheel
gpu        a CUDA device
slow       otherwise in-process, but more than a few seconds
=========  ===========================================================================================

**Capabilities** (:mod:`tests.helpers.capabilities`): a test needing one calls ``require(NAME)``
(the markers browser, node, blender and gpu do it for every test they mark). In CI (``CI`` set) or
with ``VBUSD_REQUIRE=all`` a missing one fails the test naming it; elsewhere the test skips, one
summary line per capability.

The run ends with its time per tier (:func:`pytest_terminal_summary`).
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path

import pytest

# Before any test module touches pxr.Usd: OpenUSD builds its schema registry once per process, and
# the Virtual Bones types are in it only if vbusd registered its plugin first (vbusd.io.usd_plugin).
# Importing vbusd here makes that independent of which test files run and in which order.
import vbusd  # noqa: F401
from tests.helpers import capabilities
from tests.helpers.capabilities import require

pytest_plugins = ["tests.helpers.fixtures"]

TIERS = {
    "blender": "the bpy wheel (Blender as a Python module)",
    "browser": "headless Chromium (playwright)",
    "gpu": "a CUDA device through warp",
    "node": "Node.js and the npm packages",
    "gl": "an EGL OpenGL context or glslang/spirv-cross",
    "cli": "starts the vbusd command or another Python process",
    "slow": "in-process, more than a few seconds",
    "unit": "in-process, no external tool: the fast tier (python -m pytest -m unit)",
}
"""The tiers in the order that picks a test's one tier for the time summary (its first marker here)."""

CAPABILITY_MARKERS = ("browser", "node", "blender", "gpu")
"""Markers that require their capability for every test they mark."""

BROWSER_FIXTURES = {"browser", "webgpu_browser"}


def pytest_configure(config):
    for name, description in TIERS.items():
        config.addinivalue_line("markers", f"{name}: tier: {description}")
    config.addinivalue_line(
        "markers", "packaging: builds the wheel (needs the 'build' tool and, without the build backend "
                   "installed, network access); deselect with -m 'not packaging'")
    config.addinivalue_line(
        "markers", "parity(feature, engine=None): a cell of docs/engines.md's feature x engine table "
                   "(the engine from the test's `engine` parameter unless given); --parity-json records it")


def pytest_addoption(parser):
    parser.addoption("--parity-json", default=None, metavar="PATH",
                     help="record the feature x engine cells the parity tests ran (passed, failed or skipped) into "
                          "PATH (JSON, merged with what it holds); scripts/engine_table.py renders docs/engines.md from it")


_PARITY_CELLS: dict = {}
"""feature -> {engine: cell}, collected from the reports (the controller's, under xdist)."""


def _parity_cell(item, report) -> None:
    """A ``parity`` test's outcome as its cell of the feature x engine table (--parity-json), put in
    the report's user properties: the controller's pytest_runtest_logreport collects it, also under
    xdist (whose workers would otherwise each write the file)."""
    marker = item.get_closest_marker("parity")
    if marker is None or not item.config.getoption("--parity-json"):
        return
    if report.when == "setup" and not report.skipped:
        return
    if report.when not in ("setup", "call"):
        return
    engine = marker.kwargs.get("engine") or getattr(getattr(item, "callspec", None), "params", {}).get("engine")
    name = item.nodeid.split("::", 1)[1].split("[", 1)[0]
    cell = {"test": f"{Path(str(item.fspath)).name}::{name}"}
    notes = [value for key, value in item.user_properties if key == "parity_note"]
    if notes:
        cell["note"] = notes[-1]
    if report.passed:
        cell["outcome"] = "passed"
    elif report.skipped:
        cell["outcome"] = "skipped"
        cell["note"] = str(report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr).removeprefix("Skipped: ")
    else:
        cell["outcome"] = "failed"
    report.user_properties.append(("parity_cell", (marker.args[0], engine, cell)))


def pytest_sessionfinish(session):
    path = session.config.getoption("--parity-json")
    cells = _PARITY_CELLS
    if not path or not cells or hasattr(session.config, "workerinput"):
        return
    path = Path(path)
    recorded = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    for feature, engines in cells.items():
        recorded.setdefault(feature, {}).update(engines)
    path.write_text(json.dumps(recorded, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def pytest_report_header(config):
    needed = capabilities.required()
    lines = []
    for name, (_, description) in capabilities.CAPABILITIES.items():
        if name == "gpu" and name not in needed:
            continue  # probing CUDA costs seconds; tests that want it say so
        reason = capabilities.missing(name)
        state = "yes" if reason is None else f"MISSING ({reason})"
        lines.append(f"  {name:8} {'required' if name in needed else 'optional'}: {state}")
    return ["vbusd capabilities (CI=true or VBUSD_REQUIRE=all makes a missing one fail its tests):", *lines]


def _tier(item) -> str:
    for name in TIERS:
        if item.get_closest_marker(name) is not None:
            return name
    return "unit"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Every test gets its tier: a browser fixture makes a test ``browser``; a test without a tier
    marker is ``unit``. Runs before ``-m`` selects."""
    for item in items:
        if BROWSER_FIXTURES & set(getattr(item, "fixturenames", ())) and item.get_closest_marker("browser") is None:
            item.add_marker(pytest.mark.browser)
        tier = _tier(item)
        if tier == "unit" and item.get_closest_marker("unit") is None:
            item.add_marker(pytest.mark.unit)
        item.user_properties.append(("vbusd_tier", tier))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """A capability's skip is reported at tests.helpers.capabilities.unavailable, wherever it was
    raised (pytest reports a fixture's skip at the test's line): ``-ra`` then folds every skip of one
    capability into one line."""
    report = _at_unavailable((yield))
    _parity_cell(item, report)
    return report


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector):
    """The same for a module skipped whole at collection (the Blender modules without bpy)."""
    report = _at_unavailable((yield))
    return report


def _at_unavailable(report):
    longrepr = report.longrepr
    if report.skipped and isinstance(longrepr, tuple) and len(longrepr) == 3:
        message = str(longrepr[2])
        if message.removeprefix("Skipped: ").startswith(capabilities.SKIP_PREFIX):
            report.longrepr = (capabilities.__file__, capabilities.unavailable.__code__.co_firstlineno, message)
    return report


def pytest_runtest_setup(item):
    for name in CAPABILITY_MARKERS:
        if item.get_closest_marker(name) is not None:
            require(name)


_STARTED = time.monotonic()
_TIER_TIMES: dict = defaultdict(lambda: [0, 0.0, defaultdict(int)])
"""tier -> [tests, seconds, {outcome: tests}], from the reports (under xdist, the workers' reports
reach the controller's hook too)."""


def pytest_runtest_logreport(report):
    properties = dict(report.user_properties)
    if "parity_cell" in properties:
        feature, engine, cell = properties["parity_cell"]
        _PARITY_CELLS.setdefault(feature, {})[engine] = cell
    tier = properties.get("vbusd_tier", "unit")
    entry = _TIER_TIMES[tier]
    entry[1] += report.duration
    if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
        entry[0] += 1
        entry[2][report.outcome] += 1
    elif report.when == "teardown" and report.outcome == "failed":
        entry[2]["error"] += 1


def pytest_terminal_summary(terminalreporter, config):
    tiers = _TIER_TIMES
    if not tiers:
        return
    wall = time.monotonic() - _STARTED
    write = terminalreporter.write_line
    terminalreporter.section("time per tier")
    workers = getattr(config.option, "numprocesses", None)
    write(f"{'tier':8} {'tests':>6} {'seconds':>9}  outcomes   (seconds: setup + call + teardown, summed over "
          f"{'workers' if workers else 'the one process'})")
    total = 0.0
    for name in TIERS:
        if name not in tiers:
            continue
        count, seconds, outcomes = tiers[name]
        total += seconds
        write(f"{name:8} {count:6d} {seconds:9.1f}  " + ", ".join(f"{n} {k}" for k, n in sorted(outcomes.items())))
    write(f"{'all':8} {sum(t[0] for t in tiers.values()):6d} {total:9.1f}  wall clock {wall:.1f} s")
    missing = [f"{name} ({capabilities.missing(name)})" for name in capabilities.CAPABILITIES
               if name != "gpu" and capabilities.missing(name)]
    if missing:
        write("capabilities missing here (their tests skipped, or failed where required): " + "; ".join(missing))
    from tests.helpers.browser import FULL_MATRIX

    if not FULL_MATRIX:
        write("browser tests ran their covering matrix (tests/helpers/browser.py: every encoding, texel format and "
              "skin binding); VBUSD_FULL_MATRIX=1 runs every combination")

