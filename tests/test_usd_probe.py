"""Corrupt crate files are refused with one line in bounded time and memory (vbusd/io/usd_probe.py).

The fixtures are mutants that, opened in-process by OpenUSD, crash, loop or allocate gigabytes
(tests/fixtures/corrupt_usdc/README.md). Each command runs as a child process whose peak memory,
its own and its children's, is measured by the kernel (getrusage), not by vbusd.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # seconds each: outside the fast tier (-m unit)

FIXTURES = Path(__file__).parent / "fixtures"
CORRUPT = [FIXTURES / "corrupt_usdc" / f"{name}.usdc"
           for name in ("crash_or_huge_alloc", "endless_value_read", "four_gigabyte_value")]


@pytest.mark.cli
@pytest.mark.slow
@pytest.mark.parametrize("path", CORRUPT, ids=[p.stem for p in CORRUPT])
def test_corrupt_crate_is_one_line_in_bounded_time_and_memory(path, tmp_path):
    # A fresh parent process runs the command, so its RUSAGE_CHILDREN peak is this run's alone
    # (the command and the probe it starts).
    watcher = ("import resource, subprocess, sys; "
               "done = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
               "sys.stdout.write(done.stderr); "
               "print(done.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    run = subprocess.run([sys.executable, "-c", watcher, sys.executable, "-m", "vbusd", "info", str(path)],
                         capture_output=True, text=True, timeout=180, cwd=tmp_path)
    *lines, last = run.stdout.strip().splitlines()
    status, peak_kb = map(int, last.split())
    assert status == 2
    assert len(lines) == 1 and lines[0].startswith(f"vbusd: {path}: usd.open: "), run.stdout
    assert peak_kb / 1024 <= 500, f"{peak_kb / 1024:.0f} MB"


def test_a_valid_crate_passes_the_probe(tmp_path):
    from pxr import Sdf, Usd, UsdGeom

    from vbusd.io.usd_probe import needs_probe, probe_crate

    path = tmp_path / "ok.usdc"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Mesh.Define(stage, "/M").GetPointsAttr().Set([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    stage.GetRootLayer().Save()
    assert needs_probe(path) and not needs_probe(Path(__file__))
    assert probe_crate(path).ok
    assert Sdf.Layer.FindOrOpen(str(path)) is not None


def test_a_probe_over_its_memory_limit_refuses(tmp_path, monkeypatch):
    from pxr import Usd

    from vbusd.io import usd_probe

    path = tmp_path / "ok.usdc"
    stage = Usd.Stage.CreateNew(str(path))
    stage.GetRootLayer().Save()
    monkeypatch.setattr(usd_probe, "_BASE_MEMORY", 8 << 20)  # too little even to import pxr
    result = usd_probe.probe_crate(path)
    assert not result.ok and "needs more than 8 MiB" in result.problem


def test_a_value_that_fails_its_lazy_read_during_convert_is_usd_value(tmp_path, capsys):
    # Mutant 3194: the crate opens and reads whole, but UsdPrim's property list fails a USD
    # verification when the UsdSkel converter traverses it. One line, exit 2, no output.
    from vbusd.cli import main

    path = FIXTURES / "corrupt_usdc" / "property_spec_type.usdc"
    assert main(["convert", str(path), "-o", str(tmp_path / "out" / "o.usda")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"vbusd: {path}: usd.value: "), err
    assert not (tmp_path / "out").exists()


def _small_crate(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Mesh.Define(stage, "/M").GetPointsAttr().Set([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    stage.GetRootLayer().Save()
    return path


def test_one_probe_server_serves_many_files_and_a_dead_one_is_replaced(tmp_path):
    # Each file is read in its own forked child; the server that imported pxr is started once,
    # and one that died is started again rather than failing the next file.
    from vbusd.io import usd_probe

    first, second = _small_crate(tmp_path / "a.usdc"), _small_crate(tmp_path / "b.usdc")
    assert usd_probe.probe_crate(first).ok
    server = usd_probe._SERVER.process.pid
    assert usd_probe.probe_crate(second).ok
    assert usd_probe._SERVER.process.pid == server
    usd_probe._SERVER.process.kill()
    usd_probe._SERVER.process.wait()
    third = _small_crate(tmp_path / "c.usdc")
    assert usd_probe.probe_crate(third).ok
    assert usd_probe._SERVER.process.pid != server


def test_a_read_that_never_ends_is_stopped_at_the_time_limit(tmp_path, monkeypatch):
    # A FIFO with no writer blocks USD's open forever: the child's alarm ends it.
    import os
    import time

    from vbusd.io import usd_probe

    fifo = tmp_path / "blocked.usdc"
    os.mkfifo(fifo)
    assert usd_probe.probe_crate(_small_crate(tmp_path / "warm.usdc")).ok  # the server started: not timed
    monkeypatch.setattr(usd_probe, "_BASE_SECONDS", 1.0)
    started = time.monotonic()
    result = usd_probe.probe_crate(fifo)
    assert not result.ok and "takes more than 1 s" in result.problem, result
    assert time.monotonic() - started < 8  # the alarm, not the server watchdog (11 s)


def _usdz(path, member: Path) -> Path:
    """A .usdz package of one file (stored, its data 64-byte aligned as the usdz spec asks)."""
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        info = zipfile.ZipInfo(member.name)
        start = archive.fp.tell() + 30 + len(member.name.encode()) + 4
        padding = -start % 64
        info.extra = b"\x86\x19" + padding.to_bytes(2, "little") + bytes(padding)
        archive.writestr(info, member.read_bytes())
    return path


@pytest.mark.cli
def test_a_corrupt_crate_inside_a_usdz_package_is_probed_too(tmp_path):
    # The package's bytes start with the zip magic, not the crate's; opened in-process unprobed,
    # this one crashed vbusd (signal 11) with no message.
    package = _usdz(tmp_path / "bad.usdz", CORRUPT[0])
    run = subprocess.run([sys.executable, "-m", "vbusd", "convert", str(package), "-o", str(tmp_path / "out" / "o.usda")],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 2, run
    lines = run.stderr.strip().splitlines()
    # Under the memory limit this mutant either crashes USD or fails an allocation, run to run.
    assert len(lines) == 1 and lines[0].startswith(f"vbusd: {package}: usd.open: USD "), lines
    assert "crashes reading it" in lines[0] or "needs more than" in lines[0], lines
    assert not (tmp_path / "out").exists()


def test_a_server_killed_during_a_probe_is_replaced_and_the_file_read_again(tmp_path, monkeypatch):
    # The server dies while the file is read (the OOM killer, an operator): that says nothing
    # about the file, so a fresh server reads it once more.
    import os
    import signal
    import threading

    from vbusd.io import usd_probe

    fifo = tmp_path / "slow.usdc"
    os.mkfifo(fifo)
    usd_probe.prestart()
    server = usd_probe._SERVER.process.pid
    killer = threading.Timer(1.0, os.kill, (server, signal.SIGKILL))
    killer.start()
    monkeypatch.setattr(usd_probe, "_BASE_SECONDS", 3.0)
    result = usd_probe.probe_crate(fifo)  # the first server dies; the second one's child times out
    killer.join()
    assert usd_probe._SERVER.process.pid != server
    assert not result.ok and "takes more than 3 s" in result.problem, result


@pytest.mark.cli
def test_a_server_with_threads_reads_each_file_in_a_fresh_process(tmp_path):
    # fork() is unsafe once a process has several threads; a server started with BLAS threads
    # (numpy) falls back to one fresh process per file and answers the same.
    import json
    import os

    good = _small_crate(tmp_path / "good.usdc")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2", PYTHONSAFEPATH="1")
    requests = "".join(json.dumps({"path": str(path), "memory": 384 << 20, "seconds": 60}) + "\n"
                       for path in (good, CORRUPT[1]))
    run = subprocess.run([sys.executable, "-m", "vbusd.io.usd_probe", "--serve"], input=requests, env=env,
                         capture_output=True, text=True, timeout=180)
    ready, first, second = (json.loads(line) for line in run.stdout.splitlines())
    assert ready == {"ready": True}
    assert first["returncode"] == 0
    assert second["returncode"] == 3 and "Corrupt asset" in second["stderr"], second


def test_a_large_corrupt_source_is_probed_ahead_and_still_one_line(tmp_path, monkeypatch, capsys):
    """convert probes a large source while it loads the bake kernels (vbusd.jobs.conversion._prepare_for);
    a refusal there changes nothing: the reader's own probe gives the same one line."""
    from vbusd.jobs import conversion as convert_module
    from vbusd.cli import main

    monkeypatch.setattr(convert_module, "LARGE_SOURCE_BYTES", 0)  # every source counts as large
    source = CORRUPT[0]
    assert main(["convert", str(source), "-o", str(tmp_path / "out.usda")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"vbusd: {source}: usd.open: "), err
    assert not (tmp_path / "out.usda").exists()
