"""Benchmark: bytes of the glTF runtime package against the other forms of the same crowd, and the
times to build and export crowds (issue 13 item 8).

For the stadium crowd of samples/ (one 18-bone, 202-vertex character, a 10 s cheer in a 64 x 512
float16 texture, 1,200 instances) and for a 100,000-instance crowd of the same character built by
``vbusd crowd`` (a disc, rates 0.9 .. 1.1), it measures:

* the **USD asset**: the Virtual Bones layer, its EXR texture and sidecar (for the 100,000 crowd:
  the crowd layer plus the character it references);
* the **runtime package** (``vbusd export -o OUT.glb``), plain and with Zstandard KTX2;
* the **UsdSkel fallback** (``vbusd export --as usdskel``) as ``.usdc`` and ``.usda``;
* the **point cache** (``vbusd decode``): the character alone is decoded and measured; the crowd's
  cache (``vbusd decode --crowd``: every instance's points and normals at every row) is several GB
  (stadium) or hundreds of GB (100,000), so it is decoded for two small sub-crowds (``--probe``
  instances) and extrapolated linearly in the instance count, and labelled so;
* a **vertex animation texture** of the same clip, computed: positions and normals of every vertex
  at every row (the reference decoder's output), as two RGBA float16 textures of vertices x rows,
  plus what a VAT crowd also needs: the rest mesh (positions, normals, triangle indices) and the
  same per-instance data as the package (translation, rotation, clip, time offset, rate);
* wall times of ``build_crowd``, the glTF export and the UsdSkel export (one run each, after a
  warm-up of the imports; the machine is shared, so they are indicative);
* the fallback's accuracy: UsdSkel's own skinning (``SkinningQuery.ComputeSkinnedPoints``) of the
  stadium fallback against the reference decode, at row times of the character and at arbitrary
  times of 24 crowd instances (between rows UsdSkel slerps, the spec interpolates linearly).

Prints Markdown tables for benchmarks/README.md and writes the figures as JSON. Not part of the test
suite.

    python benchmarks/bench_package.py [--instances 100000] [--probe 4 8] [--keep DIR]
                                       [--json benchmarks/results/package_sizes.json]
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import vbusd  # noqa: F401  (registers the Virtual Bones USD schema before pxr builds its registry)

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "stadium_crowd"


def size(*paths) -> int:
    """Bytes of files (a folder counts its files)."""
    total = 0
    for path in map(Path, paths):
        total += sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size
    return total


CPU_SECONDS: dict = {}
"""Process CPU seconds of the last :func:`timed` call per function name (the machine is shared:
wall time includes waiting for a core, CPU time does not)."""


def timed(function, *args, **kwargs):
    started, cpu = time.perf_counter(), time.process_time()
    result = function(*args, **kwargs)
    CPU_SECONDS[function.__name__] = time.process_time() - cpu
    return result, time.perf_counter() - started


def asset_files(layer: Path) -> list:
    """The layer, every layer and asset it depends on (USD's own walk), and the textures' sidecars."""
    from pxr import UsdUtils

    layers, assets, _ = UsdUtils.ComputeAllDependencies(str(layer))
    files = {Path(item.realPath) for item in layers} | {Path(a) for a in assets}
    files |= {Path(str(f) + ".json") for f in files if Path(str(f) + ".json").is_file()}
    return sorted(files)


def vat_bytes(vb, instances: int, with_scale: bool) -> dict:
    """A vertex animation texture of clip 0, computed with the reference decoder."""
    from vbusd.decoders.reference import skin_mesh_at_rows

    textures = 0
    rest = 0
    for mesh in vb.meshes:
        points, normals = skin_mesh_at_rows(vb, mesh, 0)
        rows, vertices = points.shape[0], points.shape[1]
        rgba = np.ones((rows, vertices, 4), np.float16)
        rgba[..., :3] = points
        textures += rgba.nbytes
        if normals is not None:
            rgba[..., :3] = normals if normals.shape[1] == vertices else 0  # faceVarying: not a VAT case
            textures += rgba.nbytes
        triangles = int(np.sum(np.maximum(np.asarray(mesh.face_vertex_counts) - 2, 0)))
        rest += vertices * (12 + 12) + triangles * 3 * (2 if vertices <= 65535 else 4)
    per_instance = 4 * (3 + 4 + (3 if with_scale else 0) + 3)  # TRS + clip, offset, rate as floats
    return {"texture": textures, "restMesh": rest, "instanceData": per_instance * instances,
            "total": textures + rest + per_instance * instances, "rows": rows, "vertices": vertices}


def subcrowd(asset, count: int):
    from vbusd.format.model import Crowd

    crowd = asset.crowds[0]
    pick = slice(0, count)
    small = Crowd(path=crowd.path, positions=crowd.positions[pick], orientations=crowd.orientations[pick],
                  clip=crowd.clip[pick], time_offset=crowd.time_offset[pick],
                  playback_rate=crowd.playback_rate[pick],
                  scales=None if crowd.scales is None else crowd.scales[pick])
    return replace(asset, crowds=(small,), crowd_animation=(asset.crowd_animation[0],))


def point_cache(asset, folder: Path, probe: tuple) -> dict:
    """Character cache measured; crowd cache per instance from two probe sub-crowds (extrapolated)."""
    from vbusd.jobs.pointcache import decode
    from vbusd.io.usd import write_asset

    character = folder / "character" / "character.usda"
    character.parent.mkdir(parents=True)
    write_asset(replace(asset, crowds=(), crowd_animation=()), character)
    single = decode(character, folder / "character_cache.usdc")
    sizes = []
    for count in probe:
        path = folder / f"probe{count}" / "probe.usda"
        path.parent.mkdir(parents=True)
        write_asset(subcrowd(asset, count), path)
        report = decode(path, folder / f"probe{count}_cache.usdc", crowds=True)
        sizes.append(report.bytes)
    per_instance = (sizes[1] - sizes[0]) / (probe[1] - probe[0])
    return {"character": single.bytes, "characterSamples": single.meshes[0]["samples"],
            "perInstance": per_instance, "base": sizes[0] - per_instance * probe[0], "probes": dict(zip(probe, sizes))}


def fallback_accuracy(fallback: Path, asset) -> dict:
    """UsdSkel's skinning of the stadium fallback against the reference decode (metres)."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    from vbusd.decoders.reference import skin_crowd

    stage = Usd.Stage.Open(str(fallback))
    vb, crowd = asset.animations[0], asset.crowds[0]
    mesh = vb.meshes[0]
    tcps = stage.GetTimeCodesPerSecond()
    worst = 0.0
    cache = UsdSkel.Cache()
    picks = range(0, crowd.instance_count, max(1, crowd.instance_count // 24))
    for t in (0.0, 1.2345, 4.321, 7.77):
        reference, _ = skin_crowd(vb, mesh, crowd, t)
        for i in picks:
            root = UsdSkel.Root(stage.GetPrimAtPath(f"/StadiumCrowd/Crowd/i{i:04d}"))
            cache.Populate(root, Usd.PrimDefaultPredicate)
            for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
                transforms = cache.GetSkelQuery(binding.GetSkeleton()).ComputeSkinningTransforms(t * tcps)
                for target in binding.GetSkinningTargets():
                    points = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(t * tcps)
                    target.ComputeSkinnedPoints(transforms, points, t * tcps)
                    world = UsdGeom.Xformable(target.GetPrim()).ComputeLocalToWorldTransform(t * tcps)
                    skinned = np.array([world.Transform(Gf.Vec3d(p)) for p in points])
                    worst = max(worst, float(np.linalg.norm(skinned - reference[i], axis=1).max()))
    return {"crowdArbitraryTimes": worst, "instancesChecked": len(picks), "times": 4}


def row_accuracy(folder: Path, asset) -> float:
    """Largest UsdSkel-vs-reference distance at the character's row times (metres)."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    from vbusd.decoders.reference import skin_mesh_at_rows
    from vbusd.jobs.export_usdskel import export_usdskel

    character_asset = replace(asset, crowds=(), crowd_animation=())
    out = folder / "character_fallback.usdc"
    export_usdskel(character_asset, out)
    stage = Usd.Stage.Open(str(out))
    vb = asset.animations[0]
    clip = vb.clips[0]
    reference, _ = skin_mesh_at_rows(vb, vb.meshes[0], 0)
    (root,) = [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(root), Usd.PrimDefaultPredicate)
    (binding,) = cache.ComputeSkelBindings(UsdSkel.Root(root), Usd.PrimDefaultPredicate)
    query = cache.GetSkelQuery(binding.GetSkeleton())
    (target,) = binding.GetSkinningTargets()
    worst = 0.0
    for row in range(0, clip.row_count, 3):
        code = (clip.start_time + row / clip.rows_per_second) * stage.GetTimeCodesPerSecond()
        points = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(code)
        target.ComputeSkinnedPoints(query.ComputeSkinningTransforms(code), points, code)
        world = UsdGeom.Xformable(target.GetPrim()).ComputeLocalToWorldTransform(code)
        skinned = np.array([world.Transform(Gf.Vec3d(p)) for p in points])
        worst = max(worst, float(np.linalg.norm(skinned - reference[row], axis=1).max()))
    return worst


def measure(label: str, crowd_layer: Path, folder: Path, cache: dict, *, usda: bool) -> dict:
    from vbusd.jobs.export_usdskel import export_usdskel
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.usd import read_asset

    asset, read_seconds = timed(read_asset, crowd_layer)
    crowd = asset.crowds[0]
    vb = asset.animations[asset.crowd_animation[0]]
    n = crowd.instance_count
    row = {"label": label, "instances": n, "usdAsset": size(*asset_files(crowd_layer)),
           "readSeconds": read_seconds, "readCpuSeconds": CPU_SECONDS["read_asset"]}
    report, row["glbSeconds"] = timed(export_gltf, asset, folder / f"{label}.glb")
    row["glbCpuSeconds"] = CPU_SECONDS["export_gltf"]
    row["glb"] = size(folder / f"{label}.glb")
    export_gltf(asset, folder / f"{label}.zstd.glb", supercompression="zstd")
    row["glbZstd"] = size(folder / f"{label}.zstd.glb")
    report, row["usdskelSeconds"] = timed(export_usdskel, asset, folder / f"{label}.skel.usdc", source=crowd_layer)
    row["usdskelCpuSeconds"] = CPU_SECONDS["export_usdskel"]
    row["usdskelUsdc"] = size(folder / f"{label}.skel.usdc")
    if usda:
        export_usdskel(asset, folder / f"{label}.skel.usda", source=crowd_layer)
        row["usdskelUsda"] = size(folder / f"{label}.skel.usda")
    row["pointCacheCharacter"] = cache["character"]
    row["pointCacheCrowd"] = cache["base"] + cache["perInstance"] * n
    row["vat"] = vat_bytes(vb, n, crowd.scales is not None)
    from vbusd.io import ktx2
    from vbusd.format import metadata as md

    row["vbTextureKtx2"] = len(ktx2.ktx2_bytes(vb.texels, md.dumps(md.to_dict(vb, generator=GENERATOR))))
    return row


def human(n: float) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:,.3g} {unit}" if n / scale < 100 else f"{n / scale:,.0f} {unit}"
    return f"{int(n)} B"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instances", type=int, default=100_000)
    parser.add_argument("--probe", type=int, nargs=2, default=(4, 8))
    parser.add_argument("--keep", type=Path, default=None, help="Keep the files in this folder.")
    parser.add_argument("--json", type=Path, default=None, help="Write the figures here as JSON.")
    args = parser.parse_args(argv)

    from vbusd.jobs.crowd import CrowdOptions, build_crowd
    from vbusd.io.usd import read_asset

    folder = Path(tempfile.mkdtemp(prefix="vbusd_bench_package_")) if args.keep is None else args.keep
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for path in SAMPLE.glob("stadium_crowd_vb*"):
            shutil.copy(path, folder / path.name)
        stadium = folder / "stadium_crowd_vb.usda"
        asset = read_asset(stadium)
        cache = point_cache(asset, folder / "caches", tuple(args.probe))
        rows = [measure("stadium", stadium, folder, cache, usda=True)]
        big = folder / f"crowd{args.instances}.usda"
        report, build_seconds = timed(build_crowd, [stadium], big,
                                      CrowdOptions(layout="disc", count=args.instances, spacing=0.8,
                                                   playback_rate=(0.9, 1.1), seed=1))
        rows.append(measure(f"crowd{args.instances}", big, folder, cache, usda=True))
        rows[-1]["crowdBuildSeconds"] = build_seconds
        rows[-1]["crowdBuildCpuSeconds"] = CPU_SECONDS["build_crowd"]
        accuracy = fallback_accuracy(folder / "stadium.skel.usdc", asset)
        accuracy["characterAtRows"] = row_accuracy(folder, asset)
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)

    print(f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs; "
          f"point-cache probes {tuple(args.probe)} instances, per instance {cache['perInstance']:,.0f} bytes\n")
    print("| form | " + " | ".join(f"{r['label']} ({r['instances']:,} instances)" for r in rows) + " |")
    print("|---|" + "---:|" * len(rows))
    lines = [
        ("USD asset (layer + EXR + sidecar; crowd layer + character)", "usdAsset"),
        ("runtime package `.glb`", "glb"),
        ("runtime package `.glb`, Zstandard KTX2", "glbZstd"),
        ("UsdSkel fallback `.usdc`", "usdskelUsdc"),
        ("UsdSkel fallback `.usda`", "usdskelUsda"),
        ("point cache of one character (`vbusd decode`, measured)", "pointCacheCharacter"),
        ("point cache of the crowd (`vbusd decode --crowd`, extrapolated)", "pointCacheCrowd"),
    ]
    for name, key in lines:
        print(f"| {name} | " + " | ".join(human(r[key]) if key in r else "–" for r in rows) + " |")
    print("| VAT: positions + normals textures (RGBA float16, vertices x rows) | "
          + " | ".join(human(r["vat"]["texture"]) for r in rows) + " |")
    print("| VAT crowd: textures + rest mesh + per-instance data | "
          + " | ".join(human(r["vat"]["total"]) for r in rows) + " |")
    print("| Virtual Bones texture alone (KTX2) | " + " | ".join(human(r["vbTextureKtx2"]) for r in rows) + " |")
    print()
    print("| seconds: wall (CPU) | " + " | ".join(r["label"] for r in rows) + " |")
    print("|---|" + "---:|" * len(rows))
    for name, key in (("`build_crowd` (`vbusd crowd`)", "crowdBuild"), ("read the asset or crowd", "read"),
                      ("write the `.glb` (after reading)", "glb"), ("write the UsdSkel `.usdc` (after reading)",
                                                                     "usdskel")):
        print(f"| {name} | " + " | ".join(f"{r[key + 'Seconds']:.2f} ({r[key + 'CpuSeconds']:.2f})"
                                          if key + "Seconds" in r else "–" for r in rows) + " |")
    print()
    print(f"UsdSkel fallback vs reference decode: character at row times {accuracy['characterAtRows'] * 1000:.3f} mm; "
          f"{accuracy['instancesChecked']} crowd instances at {accuracy['times']} arbitrary times "
          f"{accuracy['crowdArbitraryTimes'] * 1000:.3f} mm")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "pointCache": cache, "fallbackAccuracy": accuracy,
                                         "python": platform.python_version(), "cpus": os.cpu_count()},
                                        indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
