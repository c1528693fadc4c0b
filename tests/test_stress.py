"""The short stress run (issue 23): tens of conversions with every core busy and signals at random
moments, each under a watchdog; none may hang, fail, leave files or processes behind, or write an
invalid asset. The long run (1,000+ conversions) is ``python benchmarks/stress.py``; its figures
are in benchmarks/README.md.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


@pytest.mark.cli
@pytest.mark.slow
def test_conversions_under_full_load_never_hang(repo_root, tmp_path):
    # Every core busy: a CPU hog for each core the suite's other workers (pytest-xdist) leave free;
    # under `-n auto` they already fill them, and a hog would only slow the rest of the suite.
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    hogs = max(0, (os.cpu_count() or 1) - workers)
    out = tmp_path / "stress.json"
    done = subprocess.run([sys.executable, str(repo_root / "benchmarks" / "stress.py"), "--conversions", "20",
                           "--hogs", str(hogs), "--no-dask", "--timeout", "120", "--seed", "7", "--out", str(out),
                           "--work", str(tmp_path / "work")],
                          capture_output=True, text=True, timeout=1200)
    summary = json.loads(out.read_text())
    assert summary["conversions"] >= 20
    assert summary["runs"] >= 10
    for count in ("hangs", "failures", "leftovers", "invalid", "orphans"):
        assert summary[count] == 0, (count, summary["problems"], done.stderr[-3000:])
    assert done.returncode == 0
