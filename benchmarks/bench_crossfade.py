"""What a crossfade costs the warp decoder (spec virtual-bones.md 8.3, format 1.1).

The stadium crowd (18 bones, 202 vertices) replicated to N instances, skinned by
``vbusd.decoders.warp.Decoder.skin_crowd`` every frame with no crossfade (every fade weight 0: the
single-clip path), with every instance crossfading (weight 0.5, a second clip time), and with half
of them crossfading. Each configuration is first checked against the numpy reference on the first
instances, then timed (median of the frames, after warm-up; device synchronized).

Usage: ``python benchmarks/bench_crossfade.py --device cuda --instances 100000 [--encodings ...]``
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


def _sample_module():
    path = ROOT / "samples" / "stadium_crowd.py"
    spec = importlib.util.spec_from_file_location("vbusd_sample_stadium_crowd", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def crowd_of(n: int, fading: float, seed: int = 15):
    from vbusd.format.model import Crowd

    rng = np.random.default_rng(seed)
    quats = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
    weight = np.zeros(n, np.float32)
    weight[: int(round(fading * n))] = 0.5
    return Crowd("/Crowd", positions=rng.uniform(-50, 50, (n, 3)).astype(np.float32), orientations=quats,
                 clip=np.zeros(n, np.int32), time_offset=rng.uniform(0, 10, n).astype(np.float32),
                 playback_rate=rng.uniform(0.8, 1.2, n).astype(np.float32), fade_clip=np.zeros(n, np.int32),
                 fade_time_offset=rng.uniform(0, 10, n).astype(np.float32),
                 fade_playback_rate=np.ones(n, np.float32), fade_weight=weight)


def run(device: str, instances: int, encodings, frames: int) -> list:
    import warp as wp

    from vbusd.decoders.reference import skin_crowd
    from vbusd.decoders.warp import Decoder

    sample = _sample_module()
    rows = []
    for encoding in encodings:
        vb = sample.bake_reference(encoding=encoding, texel_format="float16")
        decoder = Decoder(vb, device=device)
        for label, fading in (("no crossfade", 0.0), ("half crossfading", 0.5), ("all crossfading", 1.0)):
            crowd = crowd_of(instances, fading)
            uploaded = decoder.upload_crowd(crowd)
            out = decoder.allocate(instances)
            check = dataclasses.replace(crowd, **{k: getattr(crowd, k)[:64] for k in (
                "positions", "orientations", "clip", "time_offset", "playback_rate", "fade_clip",
                "fade_time_offset", "fade_playback_rate", "fade_weight")})
            expected, _ = skin_crowd(vb, vb.meshes[0], check, 1.7)
            got = decoder.skin_crowd(uploaded, 1.7, out=out).points.numpy()[:64]
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
