"""No import off the main thread, and nothing loaded while a helper runs (vbusd/process/threads.py).

Each case runs whole conversions in a fresh interpreter (so nothing is imported yet) under
``vbusd.process.threads.ImportGuard``, which records every module a thread other than the main one asks
for, and snapshots the loaded modules and shared libraries the moment the accuracy check's thread
is started: nothing may be imported or mapped after that moment, by any thread, until the
conversion returns. That is the condition under which two threads cannot deadlock on the
dynamic loader's lock and Python's lock (the hang of issue 23).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
from tests.helpers.capabilities import require

_SCRIPT = textwrap.dedent("""
    import json, sys, threading
    from pathlib import Path
    import vbusd
    from vbusd.process import threads as _threads
    from vbusd.kernels import bake as bake_kernels
    import vbusd.jobs.conversion as convert_module

    kernels, out = sys.argv[1], Path(sys.argv[2])
    sources = sys.argv[3:]
    if kernels == "on":  # every compiled twin, however small the work
        bake_kernels.MIN_ITEMS = 0
        convert_module.LARGE_SOURCE_BYTES = 0
    else:
        bake_kernels.MIN_ITEMS = 1 << 62
        convert_module.LARGE_SOURCE_BYTES = 1 << 62

    snapshot = {}
    real_pool = convert_module.ThreadPoolExecutor

    class Watched(real_pool):
        def submit(self, *args, **kwargs):
            # the moment before the check's helper thread starts
            snapshot["modules"] = set(sys.modules)
            snapshot["libraries"] = _threads.loaded_libraries()
            return super().submit(*args, **kwargs)

    convert_module.ThreadPoolExecutor = Watched
    results = []
    for index, source in enumerate(sources):
        snapshot.clear()
        with _threads.ImportGuard() as guard:
            report = vbusd.convert(source, out / f"asset{index}.usda",
                                   vbusd.ConvertOptions(texel_format="float32"))
        helpers = sorted(t.name for t in threading.enumerate() if t.name.startswith("vbusd-"))
        results.append({
            "source": source,
            "max_error": max(m.max_error for a in report.animations for m in a.meshes),
            "helper_imports": guard.offenders,
            "imported_after_helper_start": sorted(set(sys.modules) - snapshot.get("modules", set(sys.modules))),
            "loaded_after_helper_start": sorted(_threads.loaded_libraries() - snapshot.get("libraries", set())),
            "checked_in_a_helper": bool(snapshot),
            "kernels_loaded": bake_kernels._state.get("kernels") is not None,
        })
    print(json.dumps(results))
""")


def _run(tmp_path, kernels: str, sources: list) -> list:
    env = {k: v for k, v in os.environ.items() if k != "VBUSD_THREADS"}
    env["VBUSD_THREADS"] = "2"  # split work even on one core: the split threads are helpers too
    done = subprocess.run([sys.executable, "-c", _SCRIPT, kernels, str(tmp_path), *map(str, sources)],
                          capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _sources(repo_root, shared_assets=None) -> list:
    found = [repo_root / "samples" / "stadium_crowd" / "stadium_crowd.usda"]
    if shared_assets is not None:
        found += [shared_assets / "gltf" / "Fox" / "Fox.glb",
                  shared_assets / "gltf" / "CesiumMan" / "CesiumMan.glb"]
        found += sorted((shared_assets / "usdskel" / "usdwg_RiggedFigure").glob("*.usd*"))[:1]
    return [s for s in found if s.exists()]


@pytest.mark.cli
@pytest.mark.slow
@pytest.mark.parametrize("kernels", ["off", "on"])
def test_no_helper_imports_and_nothing_loads_while_helpers_run(tmp_path, repo_root, kernels, request):
    try:
        shared = request.getfixturevalue("shared_assets")
    except pytest.skip.Exception:
        shared = None
    sources = _sources(repo_root, shared)
    if kernels == "on":
        require("warp")
    results = _run(tmp_path, kernels, sources)
    assert len(results) == len(sources)
    kinds = {os.path.splitext(r["source"])[1] for r in results}
    for result in results:
        where = f"{result['source']} (kernels {kernels})"
        assert result["checked_in_a_helper"], where  # the overlap this test is about took place
        assert result["helper_imports"] == [], f"{where}: imported off the main thread: {result['helper_imports']}"
        assert result["imported_after_helper_start"] == [], \
            f"{where}: imported while a helper ran: {result['imported_after_helper_start']}"
        assert result["loaded_after_helper_start"] == [], \
            f"{where}: shared libraries loaded while a helper ran: {result['loaded_after_helper_start']}"
        assert result["max_error"] >= 0.0
    if kernels == "on" and results:
        assert any(r["kernels_loaded"] for r in results), "the compiled kernels were never used"
    assert ".usda" in kinds


def test_the_guard_sees_an_import_from_another_thread():
    """The hook itself: an import in a second thread is recorded, one in the owner thread is not."""
    import threading

    from vbusd.process.threads import ImportGuard

    for name in ("colorsys", "this_module_does_not_exist_vbusd"):
        sys.modules.pop(name, None)
    with ImportGuard() as guard:
        import colorsys  # noqa: F401 - the owner's own import is allowed

        def other():
            try:
                import this_module_does_not_exist_vbusd  # noqa: F401
            except ImportError:
                pass

        thread = threading.Thread(target=other, name="vbusd-test")
        thread.start()
        thread.join()
    assert guard.offenders == [("this_module_does_not_exist_vbusd", "vbusd-test")]


def test_kernels_are_never_loaded_by_a_helper(monkeypatch):
    """A helper asking for kernels that the job did not load gets the numpy twin (None)."""
    import threading

    from vbusd.kernels import bake as bake_kernels

    monkeypatch.setattr(bake_kernels, "_state", {})
    seen = []
    thread = threading.Thread(target=lambda: seen.append(bake_kernels._kernels()), name="vbusd-check_0")
    thread.start()
    thread.join()
    assert seen == [None]
    assert "kernels" not in bake_kernels._state  # nothing was loaded, nor marked unavailable


_JOB_SCRIPT = textwrap.dedent("""
    import json, sys, threading
    import vbusd.cli
    from vbusd.process.threads import HELPER_PREFIX, ImportGuard

    started = []
    real_start = threading.Thread.start

    def start(self, *args, **kwargs):
        started.append(self.name)
        return real_start(self, *args, **kwargs)

    threading.Thread.start = start
    with ImportGuard() as guard:
        try:
            status = vbusd.cli.main(sys.argv[1:])
        except SystemExit as stop:
            status = stop.code
    print(json.dumps({"status": status, "offenders": guard.offenders,
                      "helpers": sorted({n for n in started if n.startswith(HELPER_PREFIX)})}))
""")


def _job(tmp_path, *args) -> dict:
    env = dict(os.environ, VBUSD_THREADS="2")  # split work even on one core: the split threads are helpers too
    done = subprocess.run([sys.executable, "-c", _JOB_SCRIPT, *map(str, args)], capture_output=True, text=True,
                          timeout=600, env=env, cwd=tmp_path)
    assert done.stdout.strip(), done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.cli
@pytest.mark.slow
def test_no_job_kind_imports_off_the_main_thread(tmp_path, repo_root):
    """Every job kind, run as its command in a fresh interpreter under the import guard: the
    threads each one starts (its signal watcher, split work, the accuracy check, a batch's
    watchers) import nothing (issue 32: by structure, with no list of modules to load first)."""
    source = repo_root / "samples" / "stadium_crowd" / "stadium_crowd.usda"
    asset = tmp_path / "asset.usda"
    jobs = {
        "convert": ["convert", source, "-o", asset, "--check-rows", "8"],
        "batch": ["convert", source, repo_root / "tests" / "fixtures" / "gltf" / "bar.gltf", "-o", tmp_path / "many",
                  "--jobs", "1", "--check-rows", "4"],
        "crowd": ["crowd", asset, "-o", tmp_path / "crowd.usda", "--count", "8"],
        "export": ["export", tmp_path / "crowd.usda", "-o", tmp_path / "crowd.glb"],
        "decode": ["decode", asset, "-o", tmp_path / "cache.usda"],
        "validate": ["validate", tmp_path / "crowd.usda"],
        "info": ["info", tmp_path / "crowd.glb"],
    }
    for kind, args in jobs.items():  # in this order: each uses what the one before wrote
        result = _job(tmp_path, *args)
        assert result["status"] == 0, (kind, result)
        assert result["helpers"], f"{kind} started no helper thread: the guard saw nothing to guard"
        assert result["offenders"] == [], f"{kind}: imported off the main thread: {result['offenders']}"
