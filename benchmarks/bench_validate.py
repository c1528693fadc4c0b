"""Benchmark of ``vbusd validate`` on a 4096 x 4096 float16 crossMatrix texture.

Two measurements:

1. the texel checks alone on an in-memory texture (non-finite, padding, crossMatrix orthonormality
   and alpha, hemisphere / loop checks, SHA-256 digest), with wall time and the peak of Python-level
   allocations (tracemalloc, which numpy reports its buffers to);
2. the whole command, ``vbusd validate asset.usda`` in a fresh process (USD open, EXR decode,
   metadata, every check), with wall time and the process's peak resident set size
   (``ru_maxrss`` that each validate process reports for itself on exit).

Usage::

    python benchmarks/bench_validate.py [--size 4096] [--repeat 3] [--keep DIR]

The texture holds 1365 bones (4095 used columns, padded to 4096) x 4096 rows of random rotations
in one looping clip.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np


def make_texels(size: int, seed: int = 1):
    """A (size, size, 4) float16 crossMatrix texture of random rotations, and its layout."""
    from vbusd.format.quaternion import quat_to_matrix
    from vbusd.format.layout import Layout

    bones = size // 3
    layout = Layout("crossMatrix", "float16", bones, size)
    texels = np.zeros(layout.shape, np.float16)
    rng = np.random.default_rng(seed)
    for start in range(0, size, 256):
        rows = min(256, size - start)
        q = rng.normal(size=(rows, bones, 4)).astype(np.float32)
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        rotation = quat_to_matrix(q)
        block = np.empty((rows, bones, 3, 4), np.float32)
        block[..., 0, :3] = rotation[..., :, 0]  # crossMatrix texels 0 and 1: the x and y axes
        block[..., 1, :3] = rotation[..., :, 1]
        block[..., 2, :3] = rng.normal(size=(rows, bones, 3)).astype(np.float32)
        block[..., 3] = 1.0
        texels[start:start + rows, :layout.used_width] = block.reshape(rows, -1, 4).astype(np.float16)
    return texels, layout


def bench_checks(texels, layout, repeat: int) -> dict:
    from vbusd.validators import checks_texels as ct

    clips = [{"name": "all", "firstRow": 0, "rowCount": layout.row_count, "loop": True}]

    def run():
        findings = []
        findings += ct.check_non_finite(texels, "t.exr", layout)
        findings += ct.check_padding(texels, "t.exr", layout)
        findings += ct.check_encoding(texels, "t.exr", layout, None, clips)
        findings += ct.check_loop_jumps(texels, "t.exr", layout, None, clips)
        ct.content_digest(texels)
        return findings

    times, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        findings = run()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    tracemalloc.start()
    run()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"seconds_best": min(times), "seconds_all": times, "cpu_seconds_best": min(cpu),
            "tracemalloc_peak_mib": peak / 2 ** 20,
            "texture_mib": texels.nbytes / 2 ** 20, "errors": [f.code for f in findings if f.severity.value == "error"]}


def write_asset(texels, layout, folder: Path) -> Path:
    from vbusd.format.model import Clip, VirtualBones, VirtualBonesAsset
    from vbusd.io.usd import write_asset as write

    bones = tuple(f"bone{i}" for i in range(layout.bone_count))
    clip = Clip("all", 0, layout.row_count, 30.0, True, 0.0)
    vb = VirtualBones(layout, texels, bones, (clip,), None, (), "/Bench/Animation")
    path = folder / "bench.usda"
    write(VirtualBonesAsset(animations=(vb,), default_prim="Bench"), path)
    return path


_COMMAND = """
import resource, sys
from vbusd.cli import main
status = main(sys.argv[1:])
sys.stderr.write("maxrss_kib=%d\\n" % resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
sys.exit(status)
"""


def bench_command(path: Path, repeat: int) -> dict:
    """Time ``vbusd validate`` in fresh processes; each reports its own peak RSS on exit."""
    exe = [sys.executable, "-c", _COMMAND, "validate", str(path), "--format", "json"]
    import resource

    times, cpu, peaks, report = [], [], [], None
    for _ in range(repeat):
        # CPU time (user + system) of the child as well as wall time: on a shared machine the
        # wall time grows with the load, the CPU time much less.
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        result = subprocess.run(exe, capture_output=True, text=True, timeout=600)
        times.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
        report = json.loads(result.stdout)
        peaks.append(int(result.stderr.strip().rsplit("maxrss_kib=", 1)[1]) / 1024)
    peak = max(peaks)
    return {"seconds_best": min(times), "seconds_all": times, "cpu_seconds_best": min(cpu), "peak_rss_mib": peak,
            "exit_status": result.returncode, "counts": report["counts"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4096)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--keep", type=Path, default=None, help="write the asset here and keep it")
    parser.add_argument("--prepare", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.prepare is not None:  # child process: write the asset and exit
        texels, layout = make_texels(args.size)
        write_asset(texels, layout, args.prepare)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        # The asset is written by a child process, and the command is timed before this process
        # allocates the texture: on Linux a child's ru_maxrss includes the pages it shared with
        # its parent at fork time, which would inflate the measured peak.
        subprocess.run([sys.executable, __file__, "--size", str(args.size), "--prepare", str(folder)],
                       check=True, timeout=900)
        path = folder / "bench.usda"
        exr = next(folder.glob("*.exr"))
        command = bench_command(path, args.repeat)
        command["exr_mib"] = os.path.getsize(exr) / 2 ** 20
    texels, layout = make_texels(args.size)
    checks = bench_checks(texels, layout, args.repeat)
    out = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
           "texture": f"{layout.width}x{layout.height} {layout.texel_format.value} {layout.encoding.value}, "
                      f"{layout.bone_count} bones", "checks": checks, "command": command}
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
