"""Fault sweep (issue 11): every vbusd writer killed, and failed, at every step of its commit.

For each writer (``convert`` with EXR and with KTX2 textures, ``decode``, ``export`` to ``.gltf``
and ``.glb``, ``crowd``, ``shader -o``) the script makes an old output, learns how many fault
points (:func:`vbusd.io.files.fault_point`) the run that replaces it passes (``VBUSD_FAULT_TRACE``),
then, for every step N, starts from a copy of the old output and runs the replacing command with
``VBUSD_FAULT=kill:N`` (SIGKILL at step N) and with ``VBUSD_FAULT=<errno>:N`` (step N fails with
ENOSPC, EDQUOT, EROFS, EACCES, EIO or ENAMETOOLONG). After each run it checks, independently of the
writer's own bookkeeping:

* the output is the old one or the new one (a fingerprint of the target's bytes and of every
  file whose name the target contains, digest parts of names removed, compared with a reference
  run of each command in an empty folder), never a mix and never missing;
* it validates: ``vbusd validate`` finds no error and no warning (USD outputs), every buffer a
  ``.gltf`` names exists with its ``byteLength`` and a ``.glb``'s header length is its size;
* a failed run said so in exactly one line on stderr, exit status 2, without a traceback, and
  left nothing (no file, visible or hidden, that the old output did not have); a killed run left
  no visible file that the output does not name;
* after recovery (:func:`vbusd.io.files.recover`, what the next run writing there does first) the
  folder holds the output and the files it names, nothing else, and the output is unchanged.

Run it (about 6 minutes on the 2-core CI machine)::

    python benchmarks/fault_sweep.py               # a table per writer
    python benchmarks/fault_sweep.py --format json --writers convert,decode

The harness (writers, cases, verdicts) is tests/helpers/faults.py, shared with ``tests/test_faults.py``
and ``tests/test_writes.py`` (fast subsets of the same checks).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))  # run as a script: the harness is tests/helpers/faults.py

from tests.helpers.faults import (ERRNOS, WRITERS, Bench, Case, _checked, child_env, judge,  # noqa: E402
                                  leftovers, make_sources, named_files, prepare, run_case, run_process, state_of,
                                  validate, vbusd_argv)


def sweep(names: list, work: Path, errnos: tuple = ERRNOS, log=print) -> list:
    """Every writer in ``names``: kill and each errno at every step. Returns one summary per writer."""
    sources = make_sources(work / "src")
    summaries = []
    for name in names:
        clock = time.perf_counter()
        bench = prepare(WRITERS[name], sources, work)
        cases = []
        others = [e for e in errnos if e != "enospc"]
        for number in range(1, len(bench.steps) + 1):
            kinds = ["kill"] + (["enospc"] if "enospc" in errnos else []) + \
                ([others[number % len(others)]] if others else [])
            for kind in kinds:
                cases.append(run_case(bench, f"{kind}:{number}"))
        bad = [c for c in cases if c.verdict != "ok"]
        kills = [c for c in cases if c.fault.startswith("kill")]
        errors = [c for c in cases if not c.fault.startswith("kill")]
        summary = {
            "writer": name, "steps": len(bench.steps), "cases": len(cases),
            "killed_old": sum(c.state == "old" for c in kills), "killed_new": sum(c.state == "new" for c in kills),
            "killed_left": sum(bool(c.hidden or c.visible) for c in kills),
            "killed_visible_left": sum(bool(c.visible) for c in kills),
            "failed_one_line_old": sum(c.status == 2 and c.state == "old" for c in errors),
            "failed_after_commit_new": sum(c.status == 0 and c.state == "new" for c in errors),
            "not_ok": len(bad), "problems": [(c.fault, c.verdict) for c in bad][:10],
            "step_names": sorted({s.split(" ")[0] for s in bench.steps}),
            "seconds": round(time.perf_counter() - clock, 1)}
        log(json.dumps(summary) if log is not print else
            f"{name}: {summary['cases']} cases over {summary['steps']} steps, {summary['not_ok']} not ok "
            f"({summary['seconds']} s)")
        summaries.append(summary)
    return summaries


def race(sources: Path, work: Path, trials: int, old: str, new: str) -> dict:
    """``trials`` times: two ``vbusd convert`` runs started together into one output, without and
    with ``--force`` (float16 and float32, so the winner is known by content). Counts outcomes."""
    counts = {"trials": trials, "new_path_one_refused": 0, "new_path_both_exit_0": 0,
              "force_both_exit_0": 0, "not_ok": 0, "problems": []}
    for trial in range(trials):
        for force in (False, True):
            folder = work / f"race{trial}{'f' if force else ''}"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            target = folder / "a.usda"
            if force:  # replacing an existing asset
                _checked(run_process, ["convert", sources / "rig.usda", "-o", target, "--quiet",
                                       "--texel-format", "unorm16"], {})
            commands = [vbusd_argv("convert", sources / "rig.usda", "-o", target, "--texel-format", fmt, "--quiet",
                                   *(["--force"] if force else [])) for fmt in ("float16", "float32")]
            processes = [subprocess.Popen(c, env=child_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                          text=True) for c in commands]
            results = [(p.wait(timeout=600), p.stderr.read()) for p in processes]
            statuses = sorted(status for status, _ in results)
            state = state_of(target, old, new)
            left = sum(leftovers(target, set()), [])
            problems = validate(target, "usd")
            if force:
                counts["force_both_exit_0"] += statuses == [0, 0]
                ok = statuses == [0, 0] and state in ("old", "new")
            else:
                counts["new_path_one_refused"] += statuses == [0, 2]
                counts["new_path_both_exit_0"] += statuses == [0, 0]
                winner = "old" if results[0][0] == 0 else "new"
                ok = statuses == [0, 2] and state == winner and \
                    len([e for s, e in results if s == 2][0].strip().splitlines()) == 1
            if not ok or left or problems:
                counts["not_ok"] += 1
                counts["problems"].append((trial, force, statuses, state, left, problems[:2]))
    return counts


def big_decode(work: Path, kill_at_bytes: int) -> dict:
    """``vbusd decode --crowd`` of the stadium-crowd sample (every instance: a cache of about 3 GB)
    over an existing small cache, SIGKILLed once its staged file holds ``kill_at_bytes``.

    Returns what was seen: bytes staged when killed, seconds, whether the old cache is byte for byte
    intact, the files left (all hidden working files?) and what recovery left.
    """
    sample = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    folder = work / "big"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    target = folder / "cache.usdc"
    _checked(run_process, ["decode", sample, "-o", target, "--quiet"], {})  # the old cache: no crowd, 8 MB
    old = hashlib.sha256(target.read_bytes()).hexdigest()
    clock = time.perf_counter()
    process = subprocess.Popen(vbusd_argv("decode", sample, "-o", target, "--crowd", "--force", "--quiet"),
                               env=child_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    staged, peak = 0, 0
    while process.poll() is None:
        sizes = [p.stat().st_size for p in folder.glob(".cache.usdc.vbusd-tmp-*") if p.exists()]
        peak = max([peak] + sizes)
        if peak >= kill_at_bytes:
            process.kill()
            staged = peak
            break
        time.sleep(0.01)
    status = process.wait()
    seconds = time.perf_counter() - clock
    left = sorted(os.listdir(folder))
    intact = target.is_file() and hashlib.sha256(target.read_bytes()).hexdigest() == old
    from vbusd.io.files import recover as recover_output
    from vbusd.io.usd import asset_files_in_use

    recover_output(target, in_use=asset_files_in_use, lock_timeout=0)
    after = sorted(os.listdir(folder))
    return {"status": status, "killed_at_bytes": staged, "peak_staged_bytes": peak, "seconds": round(seconds, 1),
            "old_cache_intact": intact, "left": left, "after_recovery": after,
            "ok": status == -9 and staged > 0 and intact and all(n.startswith(".") for n in left if n != target.name)
            and after == [target.name]}


def markdown(summaries: list) -> str:
    """The benchmarks/README.md table."""
    rows = ["| writer | fault points | runs | killed: old / new output | killed: files left until the next run "
            "(of which visible) | errno: exit 2, one line, old output | errno after the commit point: exit 0, "
            "new output | not ok |",
            "|---|--:|--:|--:|--:|--:|--:|--:|"]
    for s in summaries:
        rows.append(f"| {s['writer']} | {s['steps']} | {s['cases']} | {s['killed_old']} / {s['killed_new']} "
                    f"| {s['killed_left']} ({s['killed_visible_left']}) | {s['failed_one_line_old']} "
                    f"| {s['failed_after_commit_new']} | {s['not_ok']} |")
    return "\n".join(rows)


def tmpfs_child(spec: dict) -> list:
    """Inside a private mount namespace (``unshare -rm``): real full and read-only file systems.

    For each size in ``spec["pages"]`` (4 KiB pages beyond what the old output occupies) a tmpfs of
    that size is mounted at ``spec["mount"]``, the old output copied in and the replacing command
    run; then once more on a tmpfs remounted read-only. Returns the judged cases (fault
    ``tmpfs:<bytes>`` or ``read-only``).
    """
    writer = WRITERS[spec["writer"]]
    sources, old_dir, mount = Path(spec["sources"]), Path(spec["old_dir"]), Path(spec["mount"])
    mount.mkdir(parents=True, exist_ok=True)
    pages = sum(-(-p.stat().st_size // 4096) for p in old_dir.iterdir())
    bench = Bench(writer, sources, old_dir, mount / "out", spec["old"], spec["new"], [])
    cases = []
    for extra in list(spec["pages"]) + ["read-only"]:
        size = (pages + (64 if extra == "read-only" else extra)) * 4096
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)], check=True)
        try:
            shutil.copytree(old_dir, bench.case_dir, symlinks=True)
            if extra == "read-only":
                subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
            before = set(os.listdir(bench.case_dir)) - {writer.target} - {p.name for p in named_files(bench.target)}
            status, stderr = run_process(writer.new(sources, bench.target) + ["--force"], {})
            hidden, visible = leftovers(bench.target, before)
            case = Case(fault="read-only" if extra == "read-only" else f"tmpfs:{size}", status=status,
                        lines=stderr.strip().splitlines(), state=state_of(bench.target, bench.old, bench.new),
                        problems=validate(bench.target, writer.kind), hidden=hidden, visible=visible)
            case.verdict = judge(case, bench)
            cases.append(case.to_json())
        finally:
            subprocess.run(["umount", str(mount)], check=True)
    return cases


def tmpfs_sweep(names: list, work: Path, pages: int, log=print) -> list:
    """Every writer on real small file systems: a tmpfs 0 .. ``pages`` 4 KiB pages larger than the
    old output (full at each write in turn, until the new output fits), then a read-only one.

    Needs ``unshare -rm`` (a private user and mount namespace); returns one summary per writer.
    """
    sources = make_sources(work / "src")
    summaries = []
    for name in names:
        bench = prepare(WRITERS[name], sources, work)
        result = subprocess.run(
            ["unshare", "-rm", sys.executable, str(Path(__file__).resolve()), "--tmpfs-child",
             json.dumps({"writer": name, "sources": str(sources), "old_dir": str(bench.old_dir),
                         "mount": str(work / name / "mnt"), "old": bench.old, "new": bench.new,
                         "pages": list(range(pages + 1))})],
            capture_output=True, text=True, env=child_env(), timeout=3600)
        if result.returncode != 0:
            raise RuntimeError(f"tmpfs child failed: {result.stderr.strip()[-800:]}")
        cases = json.loads(result.stdout)
        sized, read_only = cases[:-1], cases[-1]
        full = [c for c in sized if c["status"] == 2]
        reasons = sorted({c["lines"][0].rsplit(": ", 1)[-1] for c in full if c["lines"]})
        summary = {"writer": name, "sizes": len(sized), "full_exit_2_old": sum(c["state"] == "old" for c in full),
                   "fitted_exit_0_new": sum(c["status"] == 0 and c["state"] == "new" for c in sized),
                   "read_only": "exit 2, old" if read_only["status"] == 2 and read_only["state"] == "old" else "?",
                   "reasons": reasons + [read_only["lines"][0].rsplit(": ", 1)[-1]] if read_only["lines"] else reasons,
                   "not_ok": sum(c["verdict"] != "ok" for c in cases),
                   "problems": [(c["fault"], c["verdict"]) for c in cases if c["verdict"] != "ok"][:10]}
        log(json.dumps(summary))
        summaries.append(summary)
    return summaries


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--writers", default=",".join(WRITERS), help="comma-separated: " + ", ".join(WRITERS))
    parser.add_argument("--errnos", default=",".join(ERRNOS), help="injected errors besides kill")
    parser.add_argument("--format", choices=("text", "markdown", "json"), default="markdown")
    parser.add_argument("--work", help="scratch folder (default: a temporary one, removed after)")
    parser.add_argument("--races", type=int, default=10, help="trials of two racing convert runs (0: none)")
    parser.add_argument("--big-decode", type=float, metavar="GB",
                        help="only this: kill decode --crowd of the stadium sample (a ~3 GB cache) once GB are staged")
    parser.add_argument("--tmpfs", type=int, metavar="PAGES",
                        help="only this: real tmpfs file systems 0..PAGES pages larger than the old output, "
                             "then a read-only one (needs unshare -rm)")
    parser.add_argument("--tmpfs-child", metavar="JSON", help=argparse.SUPPRESS)  # see tmpfs_child
    args = parser.parse_args(argv)
    if args.tmpfs_child:
        print(json.dumps(tmpfs_child(json.loads(args.tmpfs_child))))
        return 0
    names = [n for n in args.writers.split(",") if n]
    unknown = [n for n in names if n not in WRITERS]
    if unknown:
        parser.error(f"unknown writer {unknown[0]!r}")
    errnos = tuple(e for e in args.errnos.split(",") if e)
    if args.tmpfs is not None:
        with tempfile.TemporaryDirectory(prefix="vbusd-tmpfs-", dir=args.work) as scratch:
            summaries = tmpfs_sweep(names, Path(scratch), args.tmpfs,
                                    log=lambda text: print(text, file=sys.stderr))
        if args.format == "json":
            print(json.dumps(summaries, indent=1))
        else:
            print("| writer | tmpfs sizes | full: exit 2, one line, old output | fits: exit 0, new output "
                  "| read-only | messages | not ok |\n|---|--:|--:|--:|---|---|--:|")
            for s in summaries:
                print(f"| {s['writer']} | {s['sizes']} | {s['full_exit_2_old']} | {s['fitted_exit_0_new']} "
                      f"| {s['read_only']} | {'; '.join(s['reasons'])} | {s['not_ok']} |")
        return 1 if any(s["not_ok"] for s in summaries) else 0
    if args.big_decode:
        with tempfile.TemporaryDirectory(prefix="vbusd-big-", dir=args.work) as scratch:
            result = big_decode(Path(scratch), int(args.big_decode * 1e9))
        print(json.dumps(result, indent=1))
        return 0 if result["ok"] else 1
    clock = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="vbusd-faults-") as scratch:
        work = Path(args.work) if args.work else Path(scratch)
        log = (lambda text: print(text, file=sys.stderr)) if args.format != "json" else (lambda text: None)
        summaries = sweep(names, work, errnos, log=log)
        races = None
        if args.races:
            bench = prepare(WRITERS["convert"], work / "src", work / "race-refs")
            races = race(work / "src", work / "races", args.races, bench.old, bench.new)
            log(json.dumps(races))
    total = time.perf_counter() - clock
    if args.format == "json":
        print(json.dumps({"writers": summaries, "races": races, "seconds": round(total, 1)}, indent=1))
    else:
        print(markdown(summaries))
        print(f"\n{sum(s['cases'] for s in summaries)} runs in {total:.0f} s; "
              f"{sum(s['not_ok'] for s in summaries)} not ok")
        for s in summaries:
            for fault, verdict in s["problems"]:
                print(f"  {s['writer']} {fault}: {verdict}")
        if races:
            print(f"\nraces ({races['trials']} trials each): new path, no --force: one refused "
                  f"{races['new_path_one_refused']}, both exit 0 {races['new_path_both_exit_0']}; "
                  f"--force over an asset: both exit 0 {races['force_both_exit_0']}; not ok {races['not_ok']}")
            for problem in races["problems"]:
                print(f"  race {problem}")
    return 1 if any(s["not_ok"] for s in summaries) or (races and races["not_ok"]) else 0


if __name__ == "__main__":
    sys.exit(main())
