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
import math
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

import numpy as np

import vbusd  # noqa: F401  (registers the Virtual Bones USD schema before pxr builds its registry)


def build_rig(path: Path, frames: int, points: int, joints: int, tcps: float = 24.0, normals: bool = False) -> dict:
    """Write the rig: a branching skeleton over a grid mesh; returns what was made.

    ``normals=True`` also authors the grid's vertex normals (those of its surface
    ``y = 0.25 * sqrt(x^2 + z^2)``, computed by hand), so that a conversion checks its skinned
    normals against UsdSkel's; the benchmark's rig has none.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    rng = np.random.default_rng(7)
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(tcps)
    stage.SetFramesPerSecond(tcps)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    UsdGeom.SetStageUpAxis(stage, "Y")
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())

    # Skeleton: 10 chains of joints/10 joints each, fanned out from a root, along +Y.
    chains = 10
    per_chain = max(1, (joints - 1) // chains)
    names, parents, heads = ["root"], [-1], [np.zeros(3)]
    for c in range(chains):
        parent, name = 0, "root"
        angle = 2 * math.pi * c / chains
        for k in range(per_chain):
            name = f"{name}/c{c}_{k}"
            names.append(name)
            parents.append(parent)
            heads.append(np.array([math.cos(angle) * (k + 1), 0.5 * (k + 1), math.sin(angle) * (k + 1)]))
            parent = len(names) - 1
    count = len(names)
    skel = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(names))
    binds = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, h))) for h in heads]
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(binds))
    local = [heads[i] - (heads[parents[i]] if parents[i] >= 0 else 0) for i in range(count)]
    rests = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, t))) for t in local]
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rests))

    anim = UsdSkel.Animation.Define(stage, "/Rig/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(names))
    t_attr, r_attr, s_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
    s_attr.Set(Vt.Vec3hArray.FromNumpy(np.ones((count, 3), dtype=np.float16)))
    local = np.array(local, dtype=np.float32)
    phase = rng.uniform(0, 2 * math.pi, count)
    speed = rng.uniform(0.5, 2.0, count)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for frame in range(1, frames + 1):
        t = frame / tcps
        angle = 0.4 * np.sin(speed * t + phase)  # radians, about each joint's own axis
        quats = np.concatenate([np.cos(angle / 2)[:, None], axes * np.sin(angle / 2)[:, None]], axis=1)
        r_attr.Set(Vt.QuatfArray.FromNumpy(quats.astype(np.float32)), frame)
        offset = local + 0.05 * np.sin(t + phase)[:, None]
        t_attr.Set(Vt.Vec3fArray.FromNumpy(offset.astype(np.float32)), frame)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([Sdf.Path("/Rig/Skel/Anim")])

    # Mesh: a square grid of about `points` points spanning the skeleton's footprint.
    side = int(round(math.sqrt(points)))
    xs = np.linspace(-per_chain, per_chain, side)
    gx, gz = np.meshgrid(xs, xs, indexing="ij")
    gy = 0.25 * np.sqrt(gx ** 2 + gz ** 2)
    pts = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    quads = []
    for i in range(side - 1):
        row = np.arange(side - 1) + i * side
        quads.append(np.stack([row, row + side, row + side + 1, row + 1], axis=1))
    fvi = np.concatenate(quads).reshape(-1)
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Grid")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(fvi) // 4, 4, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(fvi.astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr("none")
    if normals:
        # The surface's normal is (-dy/dx, 1, -dy/dz), dy/dx = 0.25 x / r; (0, 1, 0) at the apex.
        r = np.maximum(np.sqrt(gx ** 2 + gz ** 2), 1e-12).reshape(-1)
        slope = np.where(r > 1e-9, 0.25 / r, 0.0)
        n = np.stack([-slope * gx.reshape(-1), np.ones_like(r), -slope * gz.reshape(-1)], axis=-1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(n.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    # Influences: the 4 nearest joint heads, weighted by inverse distance.
    head_array = np.array(heads)
    distance = np.linalg.norm(pts[:, None, :] - head_array[None], axis=-1)
    nearest = np.argsort(distance, axis=1)[:, :4]
    d = np.take_along_axis(distance, nearest, axis=1)
    w = 1.0 / (d + 0.25)
    w /= w.sum(axis=1, keepdims=True)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([Sdf.Path("/Rig/Skel")])
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(nearest.reshape(-1).astype(np.int32)))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(w.reshape(-1).astype(np.float32)))
    stage.GetRootLayer().Save()
    return {"joints": count, "points": int(len(pts)), "frames": frames}


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
