"""Benchmark: ``vbusd convert`` on a generated character library (issue 17).

Generates a library of ``--assets`` sources (default 200): generated UsdSkel rigs of several sizes
(``bench_convert.build_rig``: 21 to 61 joints, 1,024 to 4,096 points, 120 to 480 frames) and copies
of the shared third-party assets that convert (../shared/assets or $VBUSD_SHARED_ASSETS; skipped
when absent), then converts the whole library, each run into a fresh output folder, with the same
options:

1. ``vbusd convert LIB -o OUT1 --jobs 1`` (one worker process: the baseline);
2. ``--jobs 2`` (two worker processes; speed-up = 1 / 2);
3. ``--scheduler`` on a ``distributed.LocalCluster`` of 2 worker processes, 1 thread each (when
   Dask's distributed is installed): Dask against the process pool;
4. run 2 again into the same folder: every asset cached (the second run as a fraction of the first).

Every run is a separate ``vbusd`` process (start-up included), timed wall-clock, and must exit 0.
Outputs of runs 1-3 are compared byte for byte (determinism across workers). Then, from the
measured per-asset costs, an estimate for a 10,000-character library on a 100-node Dask cluster.

Prints Markdown for benchmarks/README.md. Not part of the test suite.

    python benchmarks/bench_batch.py [--assets 200] [--check-rows 16] [--keep DIR] [--node-cores 16]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

SHARED_SOURCES = ["usdskel/usdwg_BrainStem/BrainStem.usdz", "usdskel/usdwg_CesiumMan/CesiumMan.usdz",
                  "usdskel/usdwg_RiggedFigure/RiggedFigure.usdz", "usdskel/usdwg_RiggedSimple/RiggedSimple.usdz",
                  "usdskel/SkinnedArm/skinnedArm.usda", "usdskel/TwoBends/twoBends.usda",
                  "gltf/CesiumMan/CesiumMan.glb", "gltf/Fox/Fox.glb", "gltf/RiggedFigure/RiggedFigure.glb",
                  "gltf/RiggedSimple/RiggedSimple.glb"]
"""Shared assets copied into the library (each converts with the default options)."""

RIG_SIZES = [(21, 1024, 120), (41, 2048, 240), (61, 4096, 480), (31, 1024, 480), (51, 4096, 120)]
"""(joints, points, frames) of the generated rigs, in turn."""


def shared_assets() -> Path | None:
    for candidate in (os.environ.get("VBUSD_SHARED_ASSETS"), HERE.parent.parent / "shared" / "assets"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def build_library(folder: Path, count: int) -> dict:
    """Write ``count`` sources into ``folder``: shared copies (up to a quarter) and generated rigs."""
    from bench_convert import build_rig

    folder.mkdir(parents=True, exist_ok=True)
    shared = shared_assets()
    made = {"generated": 0, "shared copies": 0}
    sources = []
    if shared is not None:
        sources = [shared / s for s in SHARED_SOURCES if (shared / s).is_file()]
    copies = min(count // 4, 4 * len(sources)) if sources else 0
    for index in range(copies):
        source = sources[index % len(sources)]
        (folder / "shared").mkdir(exist_ok=True)
        shutil.copyfile(source, folder / "shared" / f"{source.stem}_{index:03d}{source.suffix}")
        made["shared copies"] += 1
    (folder / "rigs").mkdir(exist_ok=True)
    for index in range(count - copies):
        joints, points, frames = RIG_SIZES[index % len(RIG_SIZES)]
        build_rig(folder / "rigs" / f"rig_{index:03d}.usdc", frames, points, joints)
        made["generated"] += 1
    return made


def run(args: list, label: str) -> dict:
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "vbusd", "convert", *args, "--format", "json", "--quiet"],
                          capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode not in (0, 1):
        raise SystemExit(f"{label}: exit {done.returncode}: {done.stderr.strip()[-2000:]}")
    report = json.loads(done.stdout)
    failed = [a for a in report["assets"] if a["status"] == "failed"]
    if failed:
        print(f"{label}: {len(failed)} failed, first: {failed[0]['error']}", file=sys.stderr)
    print(f"{label}: {seconds:.1f} s ({report['converted']} converted, {report['cached']} cached, "
          f"{report['failed']} failed)", file=sys.stderr, flush=True)
    return {"seconds": seconds, "report": report}


def visible_files(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=int, default=200)
    parser.add_argument("--check-rows", type=int, default=16)
    parser.add_argument("--keep", default=None, help="folder to keep the library and outputs in")
    parser.add_argument("--node-cores", type=int, default=16, help="cores per node of the on-paper cluster")
    parser.add_argument("--nodes", type=int, default=100)
    parser.add_argument("--characters", type=int, default=10_000)
    parser.add_argument("--no-dask", action="store_true")
    args = parser.parse_args(argv)

    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="vbusd-batch-"))
    folder.mkdir(parents=True, exist_ok=True)
    common = ["--check-rows", str(args.check_rows)]
    try:
        library = folder / "library"
        started = time.perf_counter()
        made = build_library(library, args.assets)
        size = sum(p.stat().st_size for p in library.rglob("*") if p.is_file())
        print(f"library: {made}, {size:,} bytes, built in {time.perf_counter() - started:.0f} s",
              file=sys.stderr, flush=True)

        one = run([str(library), "-o", str(folder / "jobs1"), "--jobs", "1", *common], "--jobs 1")
        two = run([str(library), "-o", str(folder / "jobs2"), "--jobs", "2", *common], "--jobs 2")
        dask = None
        if not args.no_dask:
            try:
                from distributed import LocalCluster
            except ImportError:
                print("Dask's distributed is not installed: no Dask run (pip install 'vbusd[dask]')", file=sys.stderr)
            else:
                with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
                    # A fresh cluster's workers import vbusd on their first task, as the pool's do.
                    dask = run([str(library), "-o", str(folder / "dask"), "--scheduler", cluster.scheduler_address,
                                *common], "Dask LocalCluster, 2 workers")
        cached = run([str(library), "-o", str(folder / "jobs2"), "--jobs", "2", *common], "--jobs 2 again (cached)")
        identical = visible_files(folder / "jobs1") == visible_files(folder / "jobs2")
        if dask is not None:
            identical = identical and visible_files(folder / "jobs1") == visible_files(folder / "dask")
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    assets = one["report"]["assets"]
    converted = [a for a in assets if a["status"] == "converted"]
    per_asset = sum(a["seconds"] for a in converted) / max(1, len(converted))
    out_bytes = sum(a["bytes"] for a in converted)
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    print(f"Library: {len(assets)} sources ({made['generated']} generated UsdSkel rigs, {made['shared copies']} "
          f"copies of shared assets), {size / 1e6:.1f} MB. Machine: {machine}; load average before the runs "
          f"{os.getloadavg()[0]:.1f}.\n")
    print("| run | wall time | converted / cached / failed | notes |")
    print("|---|--:|--:|---|")
    rows = [("`--jobs 1`", one, "baseline"),
            ("`--jobs 2`", two, f"speed-up {one['seconds'] / two['seconds']:.2f}x over --jobs 1")]
    if dask is not None:
        rows.append(("Dask LocalCluster, 2 workers x 1 thread", dask,
                     f"{dask['seconds'] / two['seconds']:.2f}x the process pool's time"))
    rows.append(("`--jobs 2` again (cached)", cached,
                 f"{100 * cached['seconds'] / two['seconds']:.1f}% of the first --jobs 2 run"))
    for label, result, note in rows:
        r = result["report"]
        print(f"| {label} | {result['seconds']:.1f} s | {r['converted']} / {r['cached']} / {r['failed']} | {note} |")
    print(f"\nOutputs of the --jobs 1, --jobs 2{' and Dask' if dask else ''} runs byte-identical: {identical}. "
          f"Mean conversion time per asset (in its worker, --jobs 1): {per_asset:.2f} s; "
          f"{out_bytes / max(1, len(converted)) / 1e3:.0f} kB written per asset.")
    cores = args.nodes * args.node_cores
    seconds = args.characters * per_asset / cores
    print(f"\nOn paper, {args.characters:,} characters on {args.nodes} nodes x {args.node_cores} cores "
          f"({cores:,} Dask worker processes): {args.characters:,} x {per_asset:.2f} s / {cores:,} = "
          f"{seconds:.1f} s of conversion if the per-asset cost holds, plus reading "
          f"{args.characters * size / max(1, len(assets)) / 1e9:.1f} GB and writing "
          f"{args.characters * out_bytes / max(1, len(converted)) / 1e9:.1f} GB through the shared file system.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
