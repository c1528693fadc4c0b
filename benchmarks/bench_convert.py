"""Benchmark: ``vbusd convert`` against ``UsdSkel.BakeSkinning`` on one large UsdSkel rig.

Generates a rig of about 100 joints, 10,000 frames and 50,000 points (one grid mesh, 4 influences
per point, every joint rotating and translating each frame) as a .usdc, then, in one run:

* ``vbusd.convert.convert`` of the whole animation to a Virtual Bones asset (.usdc + EXR texture +
  JSON sidecar), with the accuracy check limited to ``--check-rows`` rows;
* ``UsdSkel.BakeSkinning`` of the same stage to a point cache (time-sampled points and extents on the
  mesh, saved as .usdc), over ``--bake-frames`` frames (default 1,000: BakeSkinning's cache grows by
  50,000 x 12 bytes per frame, so the full 10,000 frames need about 6 GB of memory and disk; the
  wall time and bytes for all frames are then extrapolated linearly and labelled so; pass
  ``--bake-frames all`` to measure them).

Prints a Markdown table (wall seconds, bytes written) for benchmarks/README.md. Not part of the
test suite.

    python benchmarks/bench_convert.py [--frames 10000] [--points 50000] [--joints 101]
                                       [--bake-frames 1000|all] [--check-rows 16] [--keep DIR]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import vbusd  # noqa: F401  (registers the Virtual Bones USD schema before pxr builds its registry)


def build_rig(path: Path, frames: int, points: int, joints: int, tcps: float = 24.0) -> dict:
    """Write the rig: a branching skeleton over a grid mesh; returns what was made."""
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
    from vbusd.convert import ConvertOptions, convert

    output = folder / "rig.vb.usdc"
    started = time.perf_counter()
    report = convert(source, output, ConvertOptions(check_rows=check_rows, force=True))
    seconds = time.perf_counter() - started
    animation = report.animations[0]
    return {"seconds": seconds, "bytes": sum(report.files.values()), "steps": report.seconds,
            "texture": f"{animation.width}x{animation.height} {animation.encoding} {animation.texel_format}",
            "error": animation.meshes[0].max_error, "fraction": animation.meshes[0].max_error_fraction,
            "rows_checked": animation.meshes[0].rows_checked, "files": report.files}


def run_bake_skinning(source: Path, folder: Path, frames) -> dict:
    """UsdSkel.BakeSkinning over frames 1..frames, then save the baked layer (.usdc)."""
    from pxr import Gf, Sdf, Usd, UsdSkel

    baked = folder / "rig.baked.usdc"
    started = time.perf_counter()
    layer = Sdf.Layer.CreateNew(str(baked))
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(source)))
    stage = Usd.Stage.Open(layer)
    ok = UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath("/Rig")), Gf.Interval(1, frames))
    if not ok:
        raise RuntimeError("UsdSkel.BakeSkinning failed")
    layer.Save()
    seconds = time.perf_counter() - started
    return {"seconds": seconds, "bytes": baked.stat().st_size}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--joints", type=int, default=101)
    parser.add_argument("--bake-frames", default="1000", help="frames UsdSkel.BakeSkinning bakes, or 'all'")
    parser.add_argument("--check-rows", type=int, default=16)
    parser.add_argument("--keep", default=None, help="folder to keep the files in (default: a temporary one)")
    args = parser.parse_args(argv)
    bake_frames = args.frames if args.bake_frames == "all" else min(args.frames, int(args.bake_frames))

    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="vbusd-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        source = folder / "rig.usdc"
        started = time.perf_counter()
        made = build_rig(source, args.frames, args.points, args.joints)
        build_seconds = time.perf_counter() - started
        print(f"rig: {made['joints']} joints, {made['points']} points, {made['frames']} frames, "
              f"{source.stat().st_size} bytes (.usdc), built in {build_seconds:.1f} s", file=sys.stderr)
        vb = run_vbusd(source, folder, args.check_rows)
        print(f"vbusd convert: {vb['seconds']:.1f} s {vb['steps']}", file=sys.stderr)
        bake = run_bake_skinning(source, folder, bake_frames)
        print(f"UsdSkel.BakeSkinning {bake_frames} frames: {bake['seconds']:.1f} s, {bake['bytes']} bytes",
              file=sys.stderr)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    scale = args.frames / bake_frames
    label = "measured" if bake_frames == args.frames else f"extrapolated x{scale:g} from {bake_frames} frames"
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    print(f"Rig: {made['joints']} joints, {made['points']} points (4 influences each), {made['frames']} frames "
          f"at 24 time codes per second. Machine: {machine}.\n")
    print("| | wall time | bytes written | notes |")
    print("|---|---|---|---|")
    print(f"| vbusd convert (all {args.frames} frames) | {vb['seconds']:.1f} s | {vb['bytes']:,} | "
          f"{vb['texture']}; read {vb['steps'].get('read', 0):.1f} s, bake {vb['steps'].get('bake', 0):.1f} s, "
          f"check {vb['rows_checked']} rows {vb['steps'].get('check', 0):.1f} s, write "
          f"{vb['steps'].get('write', 0):.1f} s; max error {vb['error']:.3g} ({vb['fraction']:.1e} of bbox) |")
    print(f"| UsdSkel.BakeSkinning ({bake_frames} frames, measured) | {bake['seconds']:.1f} s | {bake['bytes']:,} | "
          f"points + extents per frame, .usdc |")
    if bake_frames != args.frames:
        print(f"| UsdSkel.BakeSkinning (all {args.frames} frames, {label}) | {bake['seconds'] * scale:.0f} s | "
              f"{int(bake['bytes'] * scale):,} | linear in frames |")
    print(f"\nRatio for all frames: BakeSkinning / vbusd = {bake['seconds'] * scale / vb['seconds']:.1f}x time, "
          f"{bake['bytes'] * scale / vb['bytes']:.0f}x bytes.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
