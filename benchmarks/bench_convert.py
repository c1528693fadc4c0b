"""Benchmark: ``vbusd convert`` against ``UsdSkel.BakeSkinning`` on one large UsdSkel rig.

Generates a rig of about 100 joints, 10,000 frames and 50,000 points (one grid mesh, 4 influences
per point, every joint rotating and translating each frame) as a .usdc, then, in one run:

* compiles vbusd's bake kernels into warp's cache (``python -m vbusd.kernels.bake``: once per
  machine and vbusd version; nothing to do when the cache is warm) and reports how long that took;
* ``vbusd convert`` as a command in a fresh process (Python's start-up and every import included);
* ``vbusd.jobs.conversion.convert`` of the whole animation to a Virtual Bones asset (.usdc + EXR texture +
  JSON sidecar), with the accuracy check limited to ``--check-rows`` rows, ``--repeat`` times in
  this process: the first call also starts the process's crate-probe server and imports warp, the
  later ones are the conversion alone (their median is the steady figure, as a batch worker or any
  long-lived host pays it);
* ``UsdSkel.BakeSkinning`` of the same stage to a point cache (time-sampled points and extents on the
  mesh, saved as .usdc), over ``--bake-frames`` frames (default 1,000: BakeSkinning's cache grows by
  50,000 x 12 bytes per frame, so the full 10,000 frames need about 6 GB of memory and disk; the
  wall time and bytes for all frames are then extrapolated linearly and labelled so; pass
  ``--bake-frames all`` to measure them).

Prints a Markdown table (wall seconds, bytes written, the ratio to BakeSkinning for each way of
running vbusd) for benchmarks/README.md, and writes the figures as JSON with ``--json FILE``. Not
part of the test suite.

    python benchmarks/bench_convert.py [--frames 10000] [--points 50000] [--joints 101]
                                       [--bake-frames 1000|all] [--check-rows 16] [--repeat 6]
                                       [--keep DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


import vbusd  # noqa: F401  (registers the Virtual Bones USD schema before pxr builds its registry)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))  # run as a script: the rig is tests/helpers/rigs.py

from tests.helpers.rigs import build_rig  # noqa: E402  (bench_batch.py imports it from here too)


def _bytes(paths) -> int:
    return sum(Path(p).stat().st_size for p in paths if Path(p).exists())


def run_vbusd(source: Path, folder: Path, check_rows: int) -> dict:
    """One ``vbusd.jobs.conversion.convert`` of ``source`` into ``folder`` (a new asset: give a fresh folder)."""
    from vbusd.jobs.conversion import ConvertOptions, convert

    output = folder / "rig.vb.usdc"
    cpu, started = _cpu_seconds(), time.perf_counter()
    report = convert(source, output, ConvertOptions(check_rows=check_rows, force=True))
    seconds = time.perf_counter() - started
    animation = report.animations[0]
    return {"seconds": seconds, "cpu": _cpu_seconds() - cpu, "bytes": sum(report.files.values()), "steps": report.seconds,
            "texture": f"{animation.width}x{animation.height} {animation.encoding} {animation.texel_format}",
            "error": animation.meshes[0].max_error, "fraction": animation.meshes[0].max_error_fraction,
            "rows_checked": animation.meshes[0].rows_checked, "files": report.files}


def run_bake_skinning(source: Path, folder: Path, frames) -> dict:
    """UsdSkel.BakeSkinning over frames 1..frames, then save the baked layer (.usdc)."""
    from pxr import Gf, Sdf, Usd, UsdSkel

    baked = folder / "rig.baked.usdc"
    cpu, started = _cpu_seconds(), time.perf_counter()
    layer = Sdf.Layer.CreateNew(str(baked))
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(source)))
    stage = Usd.Stage.Open(layer)
    ok = UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath("/Rig")), Gf.Interval(1, frames))
    if not ok:
        raise RuntimeError("UsdSkel.BakeSkinning failed")
    layer.Save()
    seconds = time.perf_counter() - started
    return {"seconds": seconds, "cpu": _cpu_seconds() - cpu, "bytes": baked.stat().st_size}


def _cpu_seconds() -> float:
    """CPU time of this process, every thread (user + system). The crate probe's child is the probe
    server's child, not this process's: its 0.1 s is not counted."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_cli(source: Path, folder: Path, check_rows: int) -> float:
    """Wall seconds of ``python -m vbusd convert`` in a fresh process (start-up and imports included)."""
    output = folder / "cli" / "rig.vb.usdc"
    command = [sys.executable, "-m", "vbusd", "convert", str(source), "-o", str(output), "--force", "--quiet",
               "--check-rows", str(check_rows)]
    started = time.perf_counter()
    subprocess.run(command, check=True)
    return time.perf_counter() - started


def warm_kernel_cache() -> float:
    """Seconds ``python -m vbusd.kernels.bake`` took (compiling the kernels when warp's cache is cold)."""
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "vbusd.kernels.bake"], check=True)
    return time.perf_counter() - started


def _steps(run: dict) -> str:
    steps = run["steps"]
    return ", ".join(f"{name} {steps.get(name, 0):.2f} s" for name in ("read", "bake", "check", "write"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--joints", type=int, default=101)
    parser.add_argument("--bake-frames", default="1000", help="frames UsdSkel.BakeSkinning bakes, or 'all'")
    parser.add_argument("--check-rows", type=int, default=16)
    parser.add_argument("--repeat", type=int, default=6, help="conversions in this process (at least 2)")
    parser.add_argument("--keep", default=None, help="folder to keep the files in (default: a temporary one)")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    bake_frames = args.frames if args.bake_frames == "all" else min(args.frames, int(args.bake_frames))
    repeat = max(2, args.repeat)

    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="vbusd-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        source = folder / "rig.usdc"
        started = time.perf_counter()
        made = build_rig(source, args.frames, args.points, args.joints)
        build_seconds = time.perf_counter() - started
        print(f"rig: {made['joints']} joints, {made['points']} points, {made['frames']} frames, "
              f"{source.stat().st_size} bytes (.usdc), built in {build_seconds:.1f} s", file=sys.stderr)
        kernels = warm_kernel_cache()
        print(f"bake kernels ready in {kernels:.1f} s", file=sys.stderr)
        cli = run_cli(source, folder, args.check_rows)
        print(f"vbusd convert (command, fresh process): {cli:.2f} s", file=sys.stderr)
        runs = []
        for index in range(repeat):
            # Each a new asset, as in a batch: a copy of the source (probed again, as a new file is)
            # into a new folder (replacing an output would also hash the old one).
            (folder / f"convert{index}").mkdir()
            copy = shutil.copyfile(source, folder / f"convert{index}" / source.name)
            runs.append(run_vbusd(Path(copy), folder / f"convert{index}", args.check_rows))
            print(f"vbusd.convert: {runs[-1]['seconds']:.2f} s ({_steps(runs[-1])})", file=sys.stderr)
        bake = run_bake_skinning(source, folder, bake_frames)
        print(f"UsdSkel.BakeSkinning {bake_frames} frames: {bake['seconds']:.1f} s, {bake['bytes']} bytes",
              file=sys.stderr)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    scale = args.frames / bake_frames
    label = "measured" if bake_frames == args.frames else f"extrapolated x{scale:g} from {bake_frames} frames"
    baked_seconds = bake["seconds"] * scale
    first, later = runs[0], runs[1:]
    steady = statistics.median(r["seconds"] for r in later)
    vb = sorted(later, key=lambda r: r["seconds"])[len(later) // 2]  # a median run, for its steps
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    print(f"Rig: {made['joints']} joints, {made['points']} points (4 influences each), {made['frames']} frames "
          f"at 24 time codes per second. Machine: {machine}. Texture {vb['texture']}; max error against "
          f"UsdSkel {vb['error']:.3g} ({vb['fraction']:.1e} of the bounding box), {vb['rows_checked']} rows checked.\n")
    print("| | wall time | BakeSkinning / this | bytes written | notes |")
    print("|---|--:|--:|--:|---|")
    print(f"| `vbusd.convert`, steady (median of {len(later)} calls after the first) | {steady:.2f} s | "
          f"**{baked_seconds / steady:.1f}x** | {vb['bytes']:,} | runs {min(r['seconds'] for r in later):.2f} to "
          f"{max(r['seconds'] for r in later):.2f} s; {_steps(vb)} (check overlaps the write) |")
    print(f"| `vbusd.convert`, first call in the process | {first['seconds']:.2f} s | "
          f"{baked_seconds / first['seconds']:.1f}x | {first['bytes']:,} | also starts the crate-probe server and, for a large source, "
          f"imports warp; {_steps(first)} |")
    print(f"| `vbusd convert` command, fresh process | {cli:.2f} s | {baked_seconds / cli:.1f}x | | "
          f"Python start-up and every import included |")
    print(f"| `UsdSkel.BakeSkinning` ({bake_frames} frames, measured) | {bake['seconds']:.1f} s | | "
          f"{bake['bytes']:,} | points + extents per frame, .usdc; CPU time {bake['cpu']:.1f} s |")
    if bake_frames != args.frames:
        print(f"| `UsdSkel.BakeSkinning` (all {args.frames} frames, {label}) | {baked_seconds:.0f} s | | "
              f"{int(bake['bytes'] * scale):,} | linear in frames |")
    steady_cpu = statistics.median(r["cpu"] for r in later)
    print(f"\nCPU time (every thread of the process): vbusd {steady_cpu:.2f} s a steady conversion, BakeSkinning "
          f"{bake['cpu'] * scale:.1f} s: {bake['cpu'] * scale / steady_cpu:.1f}x.")
    print(f"\nBake kernels ready in {kernels:.1f} s (`python -m vbusd.kernels.bake`; compiling them, when "
          f"warp's cache is cold, is once per machine and vbusd version). Bytes: BakeSkinning / vbusd = "
          f"{bake['bytes'] * scale / vb['bytes']:.0f}x.")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "rig": made, "machine": machine, "check_rows": args.check_rows, "kernel_cache_seconds": kernels,
            "cli_seconds": cli, "convert_seconds": [r["seconds"] for r in runs],
            "convert_steps": [r["steps"] for r in runs], "steady_seconds": steady,
            "bake_skinning": {"frames": bake_frames, "seconds": bake["seconds"], "bytes": bake["bytes"],
                              "all_frames_seconds": baked_seconds, "label": label},
            "ratio_steady": baked_seconds / steady, "ratio_first": baked_seconds / first["seconds"],
            "ratio_cli": baked_seconds / cli, "steady_cpu_seconds": steady_cpu,
            "bake_skinning_cpu_seconds": bake["cpu"] * scale, "vbusd_bytes": vb["bytes"], "max_error": vb["error"],
            "max_error_fraction": vb["fraction"]}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
