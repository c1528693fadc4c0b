"""Fault injection (issue 11): writers killed at every kind of commit step, failed at every step,
two writers racing, a held lock, a point cache killed while USD writes it, a real full disk.

What is checked owes nothing to the writer's own bookkeeping (``benchmarks/fault_sweep.py``, whose
helpers these tests use, says how): the output is the old one or the new one by content (compared
with reference runs of each command), ``vbusd validate`` finds no error or warning in it, a failed
run printed one line with exit status 2, and the folder holds the output and the files it names,
nothing else (a killed run's working files: after the recovery the next writer runs first).
The exhaustive sweep (every step, every injected errno, every writer) is the benchmark
``benchmarks/fault_sweep.py``; its figures are in benchmarks/README.md.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest


import vbusd  # noqa: E402,F401  (before pxr: registers the schema)
from vbusd.cli import main  # noqa: E402
from vbusd.io import files  # noqa: E402

from tests.helpers import faults as sweep

pytestmark = pytest.mark.slow  # seconds each: outside the fast tier (-m unit)

REPO = Path(__file__).resolve().parents[1]
STADIUM_VB = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"




@pytest.fixture()
def in_process(monkeypatch, capfd):
    """A runner for the sweep's helpers that calls ``vbusd.cli.main`` here (no kill: no SIGKILL)."""

    def run(args, env):
        for name in (files.FAULT_ENV, files.FAULT_TRACE_ENV):
            monkeypatch.delenv(name, raising=False)
        for name, value in env.items():
            monkeypatch.setenv(name, str(value))
        monkeypatch.setattr(files, "_fault_steps", 0)
        capfd.readouterr()
        status = main([str(a) for a in args])
        for name in env:
            monkeypatch.delenv(name, raising=False)
        return status, capfd.readouterr().err

    return run


def run_here(args, env):
    """The sweep's in-process runner, for module fixtures (set-up runs that must succeed)."""
    return sweep.run_in_process(args, env, quiet=True)


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    return sweep.make_sources(tmp_path_factory.mktemp("faults") / "src", runner=run_here)


@pytest.fixture(scope="module")
def convert_bench(sources, tmp_path_factory):
    return sweep.prepare(sweep.WRITERS["convert"], sources, tmp_path_factory.mktemp("convert"), runner=run_here)


def _step(bench, kind, nth=0):
    """The number (1-based) of the ``nth`` step of ``kind`` (``rename``, ``commit`` ...)."""
    numbers = [i + 1 for i, step in enumerate(bench.steps) if step.split(" ")[0] == kind]
    return numbers[nth]


def test_the_commit_renames_the_layer_last_and_cleans_up_after(convert_bench):
    kinds = [step.split(" ")[0] for step in convert_bench.steps]
    assert kinds[0] == "lock" and kinds[-1] == "remove"  # the journal goes last
    # The new texture differs from the old one of the same name: it is made current under a digest
    # name, then a second commit under the same lock gives it the plain name back (spec 12.4).
    ends = [i for i, k in enumerate(kinds) if k == "remove"]
    assert len(ends) == 2 and kinds.count("lock") == 1, convert_bench.steps
    for start, end in zip([0] + [e + 1 for e in ends[:-1]], ends):
        phase = kinds[start:end + 1]
        commit = phase.index("commit")
        assert convert_bench.steps[start + commit] == "commit a.usda"
        # Every other file is renamed into place before the layer; the old files go after it.
        assert max(i for i, k in enumerate(phase) if k == "rename") < commit < min(
            i for i, k in enumerate(phase) if k == "discard")
        assert {"export", "exported", "fsync", "journal"} <= set(phase[:commit])
    second = convert_bench.steps[ends[0] + 1:]
    assert {s.split(" ", 1)[1] for s in second if s.startswith("rename ")} == {"a.Skel.exr", "a.Skel.exr.json"}
    assert [s for s in second if s.startswith("discard ")] and all(
        len(s.split(" ", 1)[1].split(".")) >= 4 for s in second if s.startswith("discard "))  # digest names


@pytest.mark.parametrize("kind,nth", [("export", 0), ("commit", 0), ("discard", 0), ("link", 0), ("commit", 1),
                                      ("discard", 1)])
def test_a_kill_at_each_kind_of_step_leaves_old_or_new_and_the_next_run_cleans_up(convert_bench, kind, nth):
    number = _step(convert_bench, kind, nth)
    case = sweep.run_case(convert_bench, f"kill:{number}")
    assert case.status in (-9, 137)
    assert case.verdict == "ok", case
    # Before the layer's rename the old asset is current, from the rename on the new one.
    assert case.state == ("old" if number <= _step(convert_bench, "commit") else "new")
    assert case.after_left == [] and case.after_state == case.state


def test_a_killed_run_is_cleaned_up_by_the_next_convert(convert_bench):
    commit = _step(convert_bench, "commit")  # the last rename before it: the new files are in place
    last_rename = max(n for n in range(1, commit) if convert_bench.steps[n - 1].startswith("rename "))
    case = sweep.run_case(convert_bench, f"kill:{last_rename}", recover=False)
    assert case.verdict == "ok" and case.state == "old", case
    assert case.hidden and case.visible  # lock, journal, staged layer; new texture + sidecar in place
    status, stderr = sweep.run_process(convert_bench.writer.new(convert_bench.sources, convert_bench.target)
                                       + ["--force"], {})
    assert status == 0, stderr
    assert sweep.state_of(convert_bench.target, convert_bench.old, convert_bench.new) == "new"
    assert sweep.leftovers(convert_bench.target, set()) == ([], [])


def test_enospc_at_every_step_is_one_line_and_leaves_the_old_asset(convert_bench, in_process):
    commit = _step(convert_bench, "commit")
    for number in range(1, len(convert_bench.steps) + 1):
        case = sweep.run_case(convert_bench, f"enospc:{number}", runner=in_process)
        assert case.verdict == "ok", (convert_bench.steps[number - 1], case)
        if number <= commit:
            assert case.status == 2 and case.state == "old" and case.hidden == case.visible == []
            assert "convert.write" in case.lines[0] and "No space left on device" in case.lines[0]
        else:  # removing the old files failed after the commit: the next run removes them
            assert case.status == 0 and case.state == "new"


def test_other_injected_errors_are_one_line(convert_bench, in_process):
    expected = {"edquot": "Disk quota exceeded", "erofs": "Read-only file system", "eacces": "Permission denied",
                "eio": "Input/output error", "enametoolong": "File name too long"}
    for number, (kind, text) in zip((3, 5, 9, 13, _step(convert_bench, "commit")), expected.items()):
        case = sweep.run_case(convert_bench, f"{kind}:{number}", runner=in_process)
        assert case.verdict == "ok" and case.status == 2 and case.state == "old", case
        assert text in case.lines[0]


def _race(sources, target, force):
    env = sweep.child_env()
    commands = [sweep.vbusd_argv("convert", sources / "rig.usda", "-o", target, "--texel-format", fmt, "--quiet",
                                 *(["--force"] if force else [])) for fmt in ("float16", "float32")]
    processes = [subprocess.Popen(c, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for c in commands]
    return [(p.wait(timeout=300), p.stderr.read()) for p in processes]


@pytest.mark.cli
def test_two_writers_of_a_new_output_one_wins_the_other_is_refused(convert_bench, tmp_path):
    target = tmp_path / "a.usda"
    results = _race(convert_bench.sources, target, force=False)
    assert sorted(status for status, _ in results) == [0, 2], results
    (loser,) = [err for status, err in results if status == 2]
    assert len(loser.strip().splitlines()) == 1 and "exists" in loser
    winner = "old" if results[0][0] == 0 else "new"  # float16 is the bench's old asset
    assert sweep.state_of(target, convert_bench.old, convert_bench.new) == winner
    assert sweep.validate(target, "usd") == [] and sweep.leftovers(target, {"rig.usda"}) == ([], [])


@pytest.mark.cli
def test_two_writers_with_force_never_mix(convert_bench, tmp_path):
    target = tmp_path / "a.usda"
    shutil.copytree(convert_bench.old_dir, tmp_path, dirs_exist_ok=True)
    results = _race(convert_bench.sources, target, force=True)
    assert [status for status, _ in results] == [0, 0], results
    assert sweep.state_of(target, convert_bench.old, convert_bench.new) in ("old", "new")
    assert sweep.validate(target, "usd") == [] and sweep.leftovers(target, set()) == ([], [])


def test_a_held_lock_stops_the_second_writer_with_one_line_naming_the_first(convert_bench, tmp_path):
    target = tmp_path / "a.usda"
    with files.Commit(target, replace=False):
        status, stderr = sweep.run_process(["convert", convert_bench.sources / "rig.usda", "-o", target],
                                           {"VBUSD_LOCK_TIMEOUT": "0.2"})
    assert status == 2 and len(stderr.strip().splitlines()) == 1
    assert "write.locked" in stderr and f"pid {os.getpid()}" in stderr
    assert sorted(os.listdir(tmp_path)) == []  # nothing written, and the lock file went with the lock


# -- point caches -------------------------------------------------------------------------------

@pytest.mark.cli
def test_decode_killed_while_usd_writes_a_large_cache_leaves_nothing(tmp_path):
    assert STADIUM_VB.is_file(), f"the committed sample {STADIUM_VB} is missing"
    output = tmp_path / "out" / "cache.usda"
    process = subprocess.Popen(sweep.vbusd_argv("decode", STADIUM_VB, "-o", output, "--quiet"),
                               env=sweep.child_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    staged_size = 0
    deadline = time.monotonic() + 300
    while process.poll() is None and time.monotonic() < deadline:
        staged = [p for p in output.parent.glob(".cache.usda.vbusd-tmp-*")] if output.parent.is_dir() else []
        sizes = [p.stat().st_size for p in staged if p.exists()]
        if sizes and max(sizes) > 1 << 20:  # USD is half way through the 8 MB cache
            staged_size = max(sizes)
            process.send_signal(signal.SIGKILL)
            break
        time.sleep(0.002)
    status = process.wait(timeout=60)
    assert staged_size and status == -signal.SIGKILL, "the decode ended before it could be killed"
    left = os.listdir(output.parent)
    assert "cache.usda" not in left and all(name.startswith(".") for name in left), left
    from vbusd.io.usd import asset_files_in_use

    files.recover(output, in_use=asset_files_in_use)  # what the next run writing there does first
    assert os.listdir(output.parent) == []


@pytest.fixture(scope="module")
def decode_bench(sources, tmp_path_factory):
    return sweep.prepare(sweep.WRITERS["decode"], sources, tmp_path_factory.mktemp("decode"), runner=run_here)


def test_decode_failed_at_every_step_keeps_the_old_cache(decode_bench, in_process):
    commit = _step(decode_bench, "commit")
    for number in range(1, len(decode_bench.steps) + 1):
        case = sweep.run_case(decode_bench, f"enospc:{number}", runner=in_process)
        assert case.verdict == "ok", (decode_bench.steps[number - 1], case)
        if number <= commit:
            assert case.status == 2 and "decode.write" in case.lines[0] and case.state == "old"


def test_decode_killed_before_its_commit_keeps_the_old_cache(decode_bench):
    for kind, state in (("exported", "old"),):
        case = sweep.run_case(decode_bench, f"kill:{_step(decode_bench, kind, -1)}")
        assert case.verdict == "ok" and case.state == state, case


# -- a real full disk and a read-only file system (a tmpfs in a private mount namespace) ----------

def _unshare_works() -> bool:
    if not shutil.which("unshare") or sys.platform != "linux":
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt 2>/dev/null "
                            "|| mount -t tmpfs -o size=64k tmpfs \"$TMPDIR\""], capture_output=True,
                           env={**os.environ, "TMPDIR": os.environ.get("TMPDIR", "/tmp")})
    return probe.returncode == 0


@pytest.mark.cli
def test_a_full_tmpfs_and_a_read_only_one_leave_the_old_asset(convert_bench, tmp_path):
    if not _unshare_works():
        pytest.skip("cannot mount a tmpfs here (unshare -rm and mount not permitted)")
    pages = (0, 2, 8)  # beyond the old asset's pages: full at different writes, then room
    result = subprocess.run(
        ["unshare", "-rm", sys.executable, str(REPO / "benchmarks" / "fault_sweep.py"), "--tmpfs-child",
         json.dumps({"writer": "convert", "sources": str(convert_bench.sources),
                     "old_dir": str(convert_bench.old_dir), "mount": str(tmp_path / "mnt"),
                     "old": convert_bench.old, "new": convert_bench.new, "pages": pages})],
        capture_output=True, text=True, env=sweep.child_env(), timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    cases = json.loads(result.stdout)
    assert len(cases) == len(pages) + 1 and cases[-1]["fault"] == "read-only"
    full = [c for c in cases[:-1] if c["status"] == 2]
    assert full and cases[-2]["status"] == 0 and cases[-2]["state"] == "new", cases
    for case in cases:
        assert case["verdict"] == "ok", case
        if case["status"] == 2:
            assert case["state"] == "old" and len(case["lines"]) == 1
    assert any("No space left on device" in c["lines"][0] for c in full)
    assert "Read-only file system" in cases[-1]["lines"][0]
