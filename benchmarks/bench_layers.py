"""What layers with bone masks cost the warp decoder (spec virtual-bones.md 8.6, format 1.2).

The stadium crowd (18 bones, 202 vertices, the cheer) with its bone parents and bind transforms
and the mask "upper" (spine and every bone above it: 12 of 18 bones), replicated to N instances and
skinned by ``vbusd.decoders.warp.Decoder.skin_crowd`` every frame: without layers (every layer weight
0: the path of format 1.1, plus the layer kernel's check that nothing changes), with half of the
instances playing one layer (the cheer at another time, weight 0.8, under "upper"), and with all of
them. Each configuration is first checked against the numpy reference on the first instances, then
timed (median of the frames, after warm-up; device synchronized).

Usage: ``python benchmarks/bench_layers.py --device cuda --instances 100000 [--encodings ...]``
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CHECKED = 16
"""Instances compared with the numpy reference (which skins a layered crowd one instance at a time)."""


def _sample_module():
    path = ROOT / "samples" / "stadium_crowd.py"
    spec = importlib.util.spec_from_file_location("vbusd_sample_stadium_crowd", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def layered_animation(sample, encoding: str):
    """The cheer baked with the sample's joint hierarchy and bind transforms and the mask "upper"."""
    from vbusd.baking.baker import bake

    animation = dataclasses.replace(sample.make_skinned_animation(), bind_transforms=sample.bind_matrices(),
                                    bone_parents=tuple(int(p) for p in sample.PARENTS))
    return bake(animation, sample.reference_bake_options(encoding=encoding, masks=(("upper", "spine"),)))


def crowd_of(n: int, layered: float, seed: int = 15):
    from vbusd.format.model import Crowd

    rng = np.random.default_rng(seed)
    weight = np.zeros((n, 1), np.float32)
    weight[: int(round(layered * n))] = 0.8
    return Crowd("/Crowd", positions=rng.uniform(-50, 50, (n, 3)).astype(np.float32),
                 orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                 clip=np.zeros(n, np.int32), time_offset=rng.uniform(0, 10, n).astype(np.float32),
                 playback_rate=rng.uniform(0.8, 1.2, n).astype(np.float32),
                 layer_clip=np.zeros((n, 1), np.int32), layer_time_offset=rng.uniform(0, 10, (n, 1)).astype(np.float32),
                 layer_playback_rate=np.ones((n, 1), np.float32), layer_weight=weight,
                 layer_mask=np.zeros((n, 1), np.int32))


def run(device: str, instances: int, encodings, frames: int) -> list:
    import warp as wp

    from vbusd.decoders.reference import skin_crowd
    from vbusd.decoders.warp import Decoder

    sample = _sample_module()
    rows = []
    for encoding in encodings:
        vb = layered_animation(sample, encoding)
        decoder = Decoder(vb, device=device)
        for label, layered in (("no layers", 0.0), ("half layered", 0.5), ("all layered", 1.0)):
            crowd = crowd_of(instances, layered)
            if layered == 0.0:
                crowd = dataclasses.replace(crowd, layer_clip=None, layer_time_offset=None, layer_playback_rate=None,
                                            layer_weight=None, layer_mask=None)
            uploaded = decoder.upload_crowd(crowd)
            out = decoder.allocate(instances)
            fields = [f.name for f in dataclasses.fields(crowd)
                      if f.name not in ("path", "fade_samples", "scales") and getattr(crowd, f.name) is not None]
            check = dataclasses.replace(crowd, **{k: getattr(crowd, k)[:CHECKED] for k in fields})
            expected, _ = skin_crowd(vb, vb.meshes[0], check, 1.7)
            got = decoder.skin_crowd(uploaded, 1.7, out=out).points.numpy()[:CHECKED]
            error = float(np.abs(got - expected).max())
            assert error < 1e-4, f"{encoding} {label}: {error}"
            times = []
            for frame in range(frames + 5):
                wp.synchronize_device(device)
                start = time.perf_counter()
                decoder.skin_crowd(uploaded, 0.02 * frame, out=out)
                wp.synchronize_device(device)
                if frame >= 5:
                    times.append(time.perf_counter() - start)
            rows.append({"encoding": encoding, "case": label, "instances": instances,
                         "ms": 1000 * statistics.median(times), "checkError": error})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--instances", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--encodings", nargs="*", default=["crossMatrix", "quatTranslation", "dualQuat"])
    parser.add_argument("--format", choices=["markdown", "json"], default="markdown")
    args = parser.parse_args(argv)
    rows = run(args.device, args.instances, args.encodings, args.frames)
    if args.format == "json":
        print(json.dumps(rows, indent=2))
        return 0
    print("| encoding | case | instances | ms per frame (median) |")
    print("|---|---|--:|--:|")
    for row in rows:
        print(f"| {row['encoding']} | {row['case']} | {row['instances']:,} | {row['ms']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
