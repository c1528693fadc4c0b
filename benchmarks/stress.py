"""Conversions under full CPU load, with signals at random moments: counts hangs, failures,
leftovers and invalid outputs (issue 23).

Usage::

    python benchmarks/stress.py                       # >= 1,000 conversions (tens of minutes)
    python benchmarks/stress.py --conversions 40      # the short run the test suite makes
    python benchmarks/stress.py --python /path/to/other/venv/bin/python   # another vbusd build

What it runs, in a repeating mix, while one CPU hog per core keeps every core busy:

* single conversions by the command, ``vbusd convert SRC -o OUT`` (glTF and UsdSkel sources,
  float16 and float32), a quarter of them sent SIGTERM or SIGINT at a random moment;
* two library calls at once, ``vbusd.convert(...)`` in two Python processes;
* ``--jobs 2`` batches of several small sources;
* a batch on a Dask LocalCluster (two worker processes), when ``distributed`` is installed.

Every run has a watchdog (``--timeout``): a run still going then is a **hang** (it is killed with
SIGKILL). A **failure** is an exit status other than 0, or, for a signalled run, other than
130/143 (or death by the signal before vbusd's handlers were installed), or a signalled run that
took more than 5 s to end. **Leftovers** are the write's hidden files (``.vbusd-tmp-*``, journals,
lock files), an output folder left empty, and vbusd processes still running after their run
(probe servers, batch workers). An **invalid output** is a finished asset that ``vbusd.validate``
reports errors for, or a signalled run's output that is neither whole nor absent.

Sources: the stadium sample, and the shared assets (``$VBUSD_SHARED_ASSETS`` or
``../shared/assets``) when present: Fox, CesiumMan and RiggedFigure (glTF), RiggedFigure and
CesiumMan (UsdSkel). Results go to ``--out`` as JSON, and progress to stderr, one line per run.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SIGNAL_BOUND_S = 5.0
SIGNAL_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}


def _shared_assets():
    for candidate in (os.environ.get("VBUSD_SHARED_ASSETS"), REPO.parent / "shared" / "assets"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def sources() -> dict:
    """``{"gltf": [...], "usd": [...]}``: the sources the runs draw from."""
    found = {"gltf": [], "usd": [REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"]}
    shared = _shared_assets()
    if shared is not None:
        for name in ("Fox/Fox.glb", "CesiumMan/CesiumMan.glb", "RiggedFigure/RiggedFigure.glb"):
            if (shared / "gltf" / name).exists():
                found["gltf"].append(shared / "gltf" / name)
        for folder in ("usdwg_RiggedFigure", "usdwg_CesiumMan"):
            found["usd"] += sorted((shared / "usdskel" / folder).glob("*.usdz"))[:1]
    return found


def _hog(parent: int) -> None:  # pragma: no cover - runs in the hog processes
    from vbusd.process.signals import die_with_parent

    die_with_parent(signal.SIGKILL, parent)  # a killed stress run leaves no hog spinning
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    value = 0
    while True:
        value = (value * 1103515245 + 12345) & 0xFFFFFFFF


def start_hogs(count: int) -> list:
    """One busy process per core (spawned: they import nothing of vbusd)."""
    context = multiprocessing.get_context("spawn")
    hogs = [context.Process(target=_hog, args=(os.getpid(),), daemon=True) for _ in range(count)]
    for hog in hogs:
        hog.start()
    return hogs


def _leftovers(folder: Path) -> list:
    if not folder.exists():
        return []
    found = [str(p.relative_to(folder)) for p in folder.rglob("*")
             if ".vbusd-tmp-" in p.name or p.name.endswith((".vbusd-journal", ".vbusd-lock"))]
    found += [str(p.relative_to(folder)) + "/ (empty)" for p in folder.rglob("*") if p.is_dir() and not any(p.iterdir())
              and p.name != ".vbusd-cache"]
    return found


RUN_ENV = "VBUSD_STRESS_RUN"
"""Every run's processes carry its folder in this variable (a probe server or a worker inherits it),
so only this run's processes are counted, never another program's on the same machine."""


def _vbusd_processes(marker: str) -> list:
    """Processes of the run whose folder is ``marker`` still running: their command line names it, or
    their environment has ``VBUSD_STRESS_RUN=marker`` (probe servers, pool workers)."""
    found = []
    tag = f"{RUN_ENV}={marker}".encode()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode("utf-8", "replace")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            environ = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if state[0] == "Z":
            continue
        if marker in command or tag in environ:
            found.append(f"{entry.name}: {command[:160]}")
    return found


def _lingering(marker: str) -> list:
    """The run's processes still running once they have had the bound they are given to end with their
    parent (SIGNAL_BOUND_S: a worker or probe server is sent SIGTERM when the run's process ends)."""
    deadline = time.monotonic() + SIGNAL_BOUND_S
    found = _vbusd_processes(marker)
    while found and time.monotonic() < deadline:
        time.sleep(0.1)
        found = _vbusd_processes(marker)
    return found


def _validate(layer: Path) -> list:
    import vbusd

    report = vbusd.validate(str(layer))
    if report.valid:
        return []
    return [f"{f.code}: {f.message}"[:200] for f in report.findings if f.severity.value == "error"] or ["invalid"]


def _run(command: list, timeout: float, *, env=None, signal_at=None, signum=None) -> dict:
    started = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                               start_new_session=True)
    signalled = None
    try:
        if signal_at is not None:
            try:
                process.wait(timeout=signal_at)
            except subprocess.TimeoutExpired:
                process.send_signal(signum)
                signalled = time.monotonic()
        process.wait(timeout=max(0.1, timeout - (time.monotonic() - started)))
        hung = False
    except subprocess.TimeoutExpired:
        hung = True
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    stderr = process.stderr.read()
    return {"status": process.returncode, "hung": hung, "seconds": time.monotonic() - started,
            "after_signal": None if signalled is None else time.monotonic() - signalled,
            "signalled": signalled is not None, "stderr": stderr[-600:],
            # Python's own start-up (site) interrupted: before any vbusd code ran
            "python_startup": process.returncode == 1 and ("init_import_site" in stderr
                                                           or "Could not import runpy module" in stderr)}


def _check_output(layer: Path, whole_expected: bool) -> list:
    """Problems with a run's output: a finished asset must validate; otherwise none or whole."""
    problems = []
    folder = layer.parent
    files = [p for p in folder.iterdir() if not p.name.startswith(".")] if folder.exists() else []
    if whole_expected:
        if not layer.exists():
            return ["no output after exit 0"]
        problems += _validate(layer)
    elif layer.exists():
        problems += _validate(layer)  # a signal after the commit point: the whole new asset
    elif files:
        problems.append(f"partial output: {sorted(p.name for p in files)}")
    return problems


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--conversions", type=int, default=1000, help="Stop after this many conversions.")
    parser.add_argument("--timeout", type=float, default=120.0, help="Watchdog per single conversion (s).")
    parser.add_argument("--hogs", type=int, default=os.cpu_count() or 1, help="CPU hog processes.")
    parser.add_argument("--batch-size", type=int, default=8, help="Sources per --jobs 2 batch.")
    parser.add_argument("--no-dask", action="store_true", help="Leave out the Dask LocalCluster batches.")
    parser.add_argument("--python", default=sys.executable, help="The Python whose vbusd is stressed.")
    parser.add_argument("--kinds", default=None,
                        help="Comma-separated run kinds to cycle (single,library2,batch,dask); default: the mix.")
    parser.add_argument("--source", action="append", default=None,
                        help="Only sources whose file name is this (repeatable), e.g. Fox.glb.")
    parser.add_argument("--texel-format", default=None, help="Always this texel format (default: float16 or float32).")
    parser.add_argument("--signal-fraction", type=float, default=0.25, help="Share of single runs sent a signal.")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=None, help="Write the results as JSON here.")
    parser.add_argument("--work", default=None, help="Folder for outputs (default: a temporary one, removed).")
    args = parser.parse_args(argv)

    rng = random.Random(args.seed)
    found = sources()
    work = Path(args.work or tempfile.mkdtemp(prefix="vbusd-stress-"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONSAFEPATH="1")
    vbusd = [args.python, "-m", "vbusd.cli"]
    try:
        import distributed  # noqa: F401

        dask = not args.no_dask
    except ImportError:
        dask = False
    kinds = ["single", "single", "single", "single", "library2", "batch"] + (["dask"] if dask else [])
    if args.kinds:
        kinds = [k for k in args.kinds.split(",") if k != "dask" or dask]
    if args.source:
        found = {kind: [s for s in found[kind] if s.name in args.source] for kind in found}
        if not any(found.values()):
            parser.error(f"no source named {args.source}")
    counts = {"conversions": 0, "runs": 0, "hangs": 0, "failures": 0, "leftovers": 0, "invalid": 0,
              "signalled": 0, "orphans": 0}
    problems = []
    hogs = start_hogs(args.hogs)
    started = time.monotonic()
    run_index = 0
    try:
        while counts["conversions"] < args.conversions:
            kind = kinds[run_index % len(kinds)]
            run_index += 1
            folder = work / f"run{run_index:05d}"
            record = {"run": run_index, "kind": kind}
            if kind == "single":
                source = rng.choice(found["gltf"] + found["usd"])
                layer = folder / "out" / f"{source.stem}.usda"
                command = vbusd + ["convert", str(source), "-o", str(layer), "-q",
                                   "--texel-format", args.texel_format or rng.choice(["float16", "float32"])]
                signum = rng.choice([signal.SIGTERM, signal.SIGINT]) if rng.random() < args.signal_fraction else None
                at = rng.uniform(0.0, 4.0) if signum else None
                result = _run(command, args.timeout, env={**env, RUN_ENV: str(folder)}, signal_at=at, signum=signum)
                record.update(source=source.name, signal=signum and signal.Signals(signum).name, at=at)
                outputs = [(layer, result["status"] == 0)]
                expected = {0} | ({SIGNAL_STATUS[signum], -signum} if result["signalled"] else set())
                conversions = 1
            elif kind == "library2":
                source = rng.choice(found["gltf"] + found["usd"])
                script = ("import sys, vbusd; vbusd.convert(sys.argv[1], sys.argv[2], "
                          "vbusd.ConvertOptions(texel_format='float32'))")
                runs = [subprocess.Popen([args.python, "-c", script, str(source), str(folder / f"p{i}" / "a.usda")],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                                         start_new_session=True) for i in range(2)]
                statuses, hung, stderr = [], False, ""
                deadline = time.monotonic() + args.timeout
                for process in runs:
                    try:
                        process.wait(timeout=max(0.1, deadline - time.monotonic()))
                    except subprocess.TimeoutExpired:
                        hung = True
                        os.killpg(process.pid, signal.SIGKILL)
                        process.wait()
                    statuses.append(process.returncode)
                    stderr += process.stderr.read()[-300:]
                result = {"status": max(statuses, key=abs), "hung": hung, "signalled": False, "after_signal": None,
                          "stderr": stderr, "seconds": args.timeout - max(0.0, deadline - time.monotonic())}
                record.update(source=source.name)
                outputs = [(folder / f"p{i}" / "a.usda", s == 0) for i, s in enumerate(statuses)]
                expected, conversions = {0}, 2
            else:
                library = folder / "src"
                library.mkdir(parents=True)
                pool = found["gltf"] + found["usd"]
                chosen = [rng.choice(pool) for _ in range(args.batch_size)]
                for index, source in enumerate(chosen):
                    shutil.copyfile(source, library / f"s{index}{source.suffix}")
                if kind == "batch":
                    command = vbusd + ["convert", str(library), "-o", str(folder / "out"), "--jobs", "2", "-q"]
                else:
                    script = ("import sys, distributed, vbusd.jobs.batch as b\n"
                              "with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,"
                              " dashboard_address=None) as c:\n"
                              "    r = b.run_batch(b.plan_batch([sys.argv[1]], sys.argv[2]), {},"
                              " scheduler=c.scheduler_address)\n"
                              "sys.exit(r.exit_status)")
                    command = [args.python, "-c", script, str(library), str(folder / "out")]
                result = _run(command, args.timeout * 3, env={**env, RUN_ENV: str(folder)})
                outputs = [(folder / "out" / f"s{i}.usda", result["status"] == 0) for i in range(len(chosen))]
                expected, conversions = {0}, len(chosen)
            counts["runs"] += 1
            counts["conversions"] += conversions
            issues = []
            if result["hung"]:
                counts["hangs"] += 1
                issues.append("hang")
            elif result["status"] not in expected and not (result["signalled"] and result.get("python_startup")):
                counts["failures"] += 1
                issues.append(f"exit {result['status']}: {result['stderr'].strip()[-300:]}")
            if result["signalled"]:
                counts["signalled"] += 1
                if not result["hung"] and result["after_signal"] > SIGNAL_BOUND_S:
                    counts["failures"] += 1
                    issues.append(f"ended {result['after_signal']:.1f} s after the signal")
            left = _leftovers(folder)
            if left:
                counts["leftovers"] += 1
                issues.append(f"leftovers: {left[:5]}")
            orphans = _lingering(str(folder))
            if orphans:
                counts["orphans"] += 1
                issues.append(f"still running: {orphans[:3]}")
                for line in orphans:
                    os.kill(int(line.split(":")[0]), signal.SIGKILL)
            if not result["hung"]:
                for layer, whole in outputs:
                    bad = _check_output(layer, whole)
                    if bad:
                        counts["invalid"] += 1
                        issues.append(f"{layer.name}: {bad[:3]}")
            record.update(status=result["status"], seconds=round(result["seconds"], 2), issues=issues)
            if issues:
                problems.append(record)
            print(f"stress: run {run_index} {kind} {record.get('source', '')} exit {result['status']} "
                  f"{result['seconds']:.1f} s; {counts['conversions']}/{args.conversions} conversions, "
                  f"{counts['hangs']} hangs, {counts['failures']} failures, {counts['leftovers']} leftovers, "
                  f"{counts['invalid']} invalid{' ; ' + '; '.join(issues) if issues else ''}",
                  file=sys.stderr, flush=True)
            if not issues:
                shutil.rmtree(folder, ignore_errors=True)
    finally:
        for hog in hogs:
            hog.kill()
        if args.work is None and not problems:
            shutil.rmtree(work, ignore_errors=True)
    summary = {"python": args.python, "conversions": counts["conversions"], "runs": counts["runs"],
               "hangs": counts["hangs"], "failures": counts["failures"], "leftovers": counts["leftovers"],
               "invalid": counts["invalid"], "orphans": counts["orphans"], "signalled": counts["signalled"],
               "hogs": len(hogs), "cores": os.cpu_count(), "seconds": round(time.monotonic() - started, 1),
               "seed": args.seed, "problems": problems[:50]}
    text = json.dumps(summary, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    print(json.dumps({k: v for k, v in summary.items() if k != "problems"}))
    bad = counts["hangs"] + counts["failures"] + counts["leftovers"] + counts["invalid"] + counts["orphans"]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
