"""Mutation run: thousands of corrupted inputs through convert, validate, info and decode.

Every mutant is a copy of a valid seed (a Virtual Bones asset in .usda or .usdc with its EXR or PNG
texture and sidecar, a UsdSkel source, a glTF or GLB source) with one file corrupted: bytes
flipped, cut short, spans inserted, deleted or duplicated, PNG chunks altered with a valid CRC,
numbers in text replaced by extremes (NaN, 1e308, 2**32 + 5...), strings replaced by hostile ones
(paths leaving the folder, control bytes, non-UTF-8), lines deleted or duplicated. Each command
runs in a long-lived worker process (``vbusd.cli.main`` in-process, stdout and stderr captured at
the file-descriptor level so USD's C++ messages are seen too), watched by the parent:

* traceback: an exception escaped ``main``, or "Traceback" reached stdout or stderr;
* hang: no answer within ``--timeout`` seconds (the worker is killed and replaced);
* memory: the worker's peak resident set passed ``--max-rss-mb`` while handling the input (the
  worker is replaced after such an input, so every input is measured from a fresh baseline);
* partial: a failed convert or decode left a file in its output folder;
* clobbered: an existing output (written before the run, ``--force`` given) or an input file
  changed although the command failed;
* raw: a line on stderr that is not vbusd's own (``vbusd...`` or the command name), e.g. a raw
  USD warning.

Usage::

    python benchmarks/mutation_run.py --mutants 5000 --jobs 2 --json benchmarks/results/mutation.json

The suite runs a small slice of it (tests/test_mutation_smoke.py).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import select
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VALID = ROOT / "tests" / "fixtures" / "validate" / "valid"
GLTF = ROOT / "tests" / "fixtures" / "gltf"
SAMPLE = ROOT / "samples" / "stadium_crowd"

NUMBERS = [b"-1e308", b"1e308", b"nan", b"inf", b"-inf", b"-1", b"0", b"4294967301", b"99999999",
           b"1e-320", b"65536", b"2147483648", b"0.5", b"-0"]
STRINGS = [b"../../../../etc/passwd", b"/etc/hostname", b"http://example.invalid/x", b"", b"\xff\xfe\x00",
           b"\x1b[31mred", b"a" * 5000, b"con", b"nul:", b"x.exr", b"//?/c:/x"]


# --------------------------------------------------------------------------------------------
# seeds and mutants
# --------------------------------------------------------------------------------------------


def _usdc_copy(folder: Path) -> None:
    """Add asset.usdc (a binary copy of asset.usda) to a seed folder."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(folder / "asset.usda"))
    layer.Export(str(folder / "asset.usdc"))


def make_seeds(root: Path) -> list:
    """Copy the seeds into ``root``; returns ``(name, folder, entry file, kind)`` per seed.

    ``kind`` is ``asset`` (a Virtual Bones asset: decode/info/validate succeed on the seed) or
    ``source`` (UsdSkel or glTF: convert succeeds on the seed).
    """
    seeds = []
    for name in sorted(p.name for p in VALID.iterdir() if (VALID / p.name / "asset.usda").exists()):
        folder = root / "seeds" / name
        shutil.copytree(VALID / name, folder)
        (folder / "expected.json").unlink(missing_ok=True)
        seeds.append((name, folder, "asset.usda", "asset"))
        if name.startswith("crossMatrix") or name.startswith("quatTranslation"):
            usdc = root / "seeds" / f"{name}_usdc"
            shutil.copytree(folder, usdc)
            _usdc_copy(usdc)
            (usdc / "asset.usda").unlink()
            seeds.append((f"{name}_usdc", usdc, "asset.usdc", "asset"))
    source = root / "seeds" / "stadium_source"
    source.mkdir(parents=True)
    shutil.copy(SAMPLE / "stadium_crowd.usda", source / "stadium_crowd.usda")
    seeds.append(("stadium_source", source, "stadium_crowd.usda", "source"))
    for name in ("bar.gltf", "bar.glb", "bar_sparse.gltf", "two_skins.gltf"):
        folder = root / "seeds" / name.replace(".", "_")
        folder.mkdir(parents=True)
        shutil.copy(GLTF / name, folder / name)
        seeds.append((name.replace(".", "_"), folder, name, "source"))
    return seeds


def _fix_png_crcs(data: bytearray) -> bytearray:
    """Recompute every chunk CRC so a mutation inside a chunk reaches the chunk's parser."""
    at = 8
    while at + 12 <= len(data):
        length = struct.unpack(">I", data[at:at + 4])[0]
        end = at + 12 + length
        if end > len(data):
            break
        data[end - 4:end] = struct.pack(">I", zlib.crc32(bytes(data[at + 4:end - 4])) & 0xFFFFFFFF)
        at = end
    return data


def mutate(data: bytes, suffix: str, rng: random.Random) -> tuple:
    """One corrupted version of ``data``; returns ``(bytes, operation name)``."""
    text_like = suffix in (".usda", ".json", ".gltf")
    ops = ["flip", "truncate", "insert", "delete", "duplicate"]
    if text_like:
        ops += ["number", "number", "number", "string", "line_delete", "line_duplicate"]
    if suffix == ".png":
        ops += ["png_chunk", "png_chunk"]
    if suffix in (".exr", ".usdc", ".glb"):
        ops += ["word", "word"]
    op = rng.choice(ops)
    out = bytearray(data)
    n = max(len(out), 1)
    if op == "flip":
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(n)
            if i < len(out):
                out[i] ^= 1 << rng.randrange(8)
    elif op == "truncate":
        out = out[:rng.randrange(n)]
    elif op == "insert":
        i = rng.randrange(n)
        out[i:i] = bytes(rng.randrange(256) for _ in range(rng.choice((1, 4, 16, 300))))
    elif op == "delete":
        i = rng.randrange(n)
        del out[i:i + rng.choice((1, 4, 16, 300))]
    elif op == "duplicate":
        i = rng.randrange(n)
        span = out[i:i + rng.choice((4, 16, 300, 4000))]
        out[i:i] = span
    elif op == "word":  # a 32-bit little-endian word (sizes, offsets, counts) set to an extreme
        i = rng.randrange(max(n - 4, 1)) & ~3
        out[i:i + 4] = struct.pack("<I", rng.choice((0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 65536, 1 << 24)))
    elif op == "number":
        matches = list(re.finditer(rb"-?\d+(\.\d+)?(e[-+]?\d+)?", bytes(out)))
        if matches:
            m = rng.choice(matches)
            out[m.start():m.end()] = rng.choice(NUMBERS)
    elif op == "string":
        matches = list(re.finditer(rb'"([^"\\\n]{0,200})"', bytes(out)))
        if matches:
            m = rng.choice(matches)
            out[m.start() + 1:m.end() - 1] = rng.choice(STRINGS)
    elif op in ("line_delete", "line_duplicate"):
        lines = bytes(out).split(b"\n")
        i = rng.randrange(len(lines))
        if op == "line_delete":
            del lines[i]
        else:
            lines.insert(i, lines[i])
        out = bytearray(b"\n".join(lines))
    elif op == "png_chunk":
        if len(out) > 40:
            i = rng.randrange(8, len(out))
            for _ in range(rng.randint(1, 4)):
                j = min(len(out) - 1, i + rng.randrange(16))
                out[j] = rng.randrange(256)
            out = _fix_png_crcs(out)
    return bytes(out), op


def _peak_rss_mb() -> float:
    """This worker's peak resident set, in MB: VmHWM of its own address space. (``ru_maxrss`` is
    preserved across execve, so a worker started by a large process, pytest after a long session
    say, would report its parent's peak.)"""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def make_mutants(root: Path, count: int, seed: int) -> list:
    """Write ``count`` mutant folders under ``root``; returns one job description per mutant."""
    rng = random.Random(seed)
    seeds = make_seeds(root)
    jobs = []
    for i in range(count):
        name, folder, entry, kind = seeds[i % len(seeds)]
        files = sorted(p.name for p in folder.iterdir() if p.is_file())
        target_name = entry if rng.random() < 0.4 else rng.choice(files)
        mutant = root / "mutants" / f"{i:05d}"
        shutil.copytree(folder, mutant)
        data = (mutant / target_name).read_bytes()
        new, op = mutate(data, Path(target_name).suffix, rng)
        (mutant / target_name).write_bytes(new)
        jobs.append({"id": i, "seed": name, "kind": kind, "folder": str(mutant), "entry": entry,
                     "mutated": target_name, "op": op})
    return jobs


def commands_for(job: dict, out: Path) -> list:
    """The command lines one mutant runs, each with its output path (or None)."""
    entry = str(Path(job["folder"]) / job["entry"])
    mutated = str(Path(job["folder"]) / job["mutated"])
    runs = [(["validate", entry], None), (["info", entry], None),
            (["decode", entry, "-o", str(out / "decode" / "cache.usda")], out / "decode" / "cache.usda"),
            (["convert", entry, "-o", str(out / "convert" / "asset.usda"), "--check-rows", "4"],
             out / "convert" / "asset.usda")]
    if mutated != entry and Path(mutated).suffix in (".exr", ".png", ".json"):
        runs += [(["validate", mutated], None), (["info", mutated], None)]
    return runs


# --------------------------------------------------------------------------------------------
# worker: runs vbusd.cli.main in-process, one command at a time
# --------------------------------------------------------------------------------------------


def _digest_folder(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def worker() -> int:
    """Read jobs (JSON lines) on stdin; answer each with one JSON line on the saved stdout."""
    import resource
    import traceback

    answer = os.fdopen(os.dup(1), "w", buffering=1)
    from vbusd.cli import main

    capture, errors = tempfile.TemporaryFile(), tempfile.TemporaryFile()
    for line in sys.stdin:
        job = json.loads(line)
        argv, output = job["argv"], job.get("output")
        folder = Path(job["folder"])
        before = _digest_folder(folder)
        sentinel = None
        if output:
            Path(output).parent.mkdir(parents=True, exist_ok=True)
            if job.get("existing"):
                Path(output).write_bytes(b"old output\n")
                sentinel = hashlib.sha256(b"old output\n").hexdigest()
                argv = argv + ["--force"]
        for f in (capture, errors):
            f.seek(0)
            f.truncate()
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(capture.fileno(), 1)
        os.dup2(errors.fileno(), 2)
        escaped = None
        start = time.perf_counter()
        try:
            status = main(argv)
        except SystemExit as done:
            status = done.code if isinstance(done.code, int) else 2
        except BaseException:  # noqa: BLE001 - what escapes main is what this run looks for
            escaped = traceback.format_exc()
            status = None
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        seconds = time.perf_counter() - start
        capture.seek(0)
        errors.seek(0)
        stderr = errors.read().decode("utf-8", "replace")
        text = capture.read().decode("utf-8", "replace") + stderr
        left = []
        clobbered = before != _digest_folder(folder)
        if output:
            out_dir = Path(output).parent
            names = sorted(p.name for p in out_dir.iterdir())
            if status != 0:
                if sentinel:
                    ok = Path(output).exists() and hashlib.sha256(Path(output).read_bytes()).hexdigest() == sentinel
                    clobbered = clobbered or not ok
                    left = [n for n in names if n != Path(output).name]
                else:
                    left = names
            shutil.rmtree(out_dir, ignore_errors=True)
        command = argv[0]
        raw = [l for l in stderr.splitlines() if l.strip() and not l.startswith(("vbusd", f"{command}:"))]
        rss_mb = _peak_rss_mb()
        answer.write(json.dumps({"status": status, "escaped": escaped, "traceback": "Traceback (most recent" in text,
                                 "left": left, "clobbered": clobbered, "raw": raw[:3], "rss_mb": rss_mb,
                                 "seconds": seconds, "first_line": stderr.strip().splitlines()[0][:300] if stderr.strip() else ""})
                     + "\n")
    return 0


class Worker:
    """One worker process and its pipes."""

    def __init__(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
        self.baseline_mb = None

    def ask(self, job: dict, timeout: float):
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not ready:
            return None
        line = self.proc.stdout.readline()
        return json.loads(line) if line else {"status": None, "escaped": "worker died", "traceback": True,
                                              "left": [], "clobbered": False, "raw": [], "rss_mb": 0,
                                              "seconds": 0, "first_line": "worker died"}

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()


def run(jobs: list, out_root: Path, *, workers: int = 2, timeout: float = 60.0, max_rss_mb: float = 500.0,
        progress=None) -> dict:
    """Run every command of every mutant; returns counts and the failing cases."""
    import threading

    tasks = []
    for job in jobs:
        for k, (argv, output) in enumerate(commands_for(job, out_root / f"m{job['id']:05d}")):
            tasks.append({"job": job, "argv": argv, "folder": job["folder"],
                          "output": None if output is None else str(output),
                          "existing": (job["id"] + k) % 2 == 1})
    results = [None] * len(tasks)
    lock = threading.Lock()
    cursor = {"next": 0, "done": 0}

    def loop():
        w = Worker()
        while True:
            with lock:
                i = cursor["next"]
                cursor["next"] += 1
            if i >= len(tasks):
                break
            task = tasks[i]
            answer = w.ask({k: task[k] for k in ("argv", "folder", "output", "existing")}, timeout)
            if answer is None:
                w.kill()
                answer = {"status": None, "hang": True}
                w = Worker()
            elif answer.get("escaped") == "worker died":
                w = Worker()
            elif answer["rss_mb"] > max_rss_mb:
                answer["memory"] = True
                w.kill()
                w = Worker()
            results[i] = answer
            with lock:
                cursor["done"] += 1
                if progress:
                    progress(cursor["done"], len(tasks))
        w.kill()

    threads = [threading.Thread(target=loop) for _ in range(workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    counts = Counter()
    failures = []
    by_command = Counter()
    statuses = Counter()
    for task, answer in zip(tasks, results):
        command = task["argv"][0]
        by_command[command] += 1
        statuses[f"{command}:{answer.get('status')}"] += 1
        problems = []
        if answer.get("hang"):
            problems.append("hang")
        if answer.get("escaped") or answer.get("traceback"):
            problems.append("traceback")
        if answer.get("memory"):
            problems.append("memory")
        if answer.get("left"):
            problems.append("partial")
        if answer.get("clobbered"):
            problems.append("clobbered")
        if answer.get("raw"):
            problems.append("raw")
        for p in problems:
            counts[p] += 1
        if problems:
            failures.append({"problems": problems, "argv": task["argv"], "seed": task["job"]["seed"],
                             "mutated": task["job"]["mutated"], "op": task["job"]["op"],
                             "detail": (answer.get("escaped") or "")[-1500:] or answer.get("first_line", ""),
                             "raw": answer.get("raw"), "left": answer.get("left")})
    peak = max((a.get("rss_mb", 0) for a in results if a), default=0)
    return {"mutants": len(jobs), "runs": len(tasks), "by_command": dict(by_command),
            "statuses": dict(sorted(statuses.items())),
            "problems": {k: counts.get(k, 0) for k in ("traceback", "hang", "memory", "partial", "clobbered", "raw")},
            "peak_rss_mb": round(peak, 1), "failures": failures}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--mutants", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds before a run counts as a hang")
    parser.add_argument("--max-rss-mb", type=float, default=500.0)
    parser.add_argument("--json", type=Path, help="write the summary and failures here")
    parser.add_argument("--keep", type=Path, help="build the mutants here and keep them")
    args = parser.parse_args(argv)
    if args.worker:
        return worker()
    root = Path(tempfile.mkdtemp(prefix="vbusd-mutants-")) if args.keep is None else args.keep
    start = time.perf_counter()
    jobs = make_mutants(root, args.mutants, args.seed)
    last = [0.0]

    def progress(done, total):
        now = time.perf_counter()
        if now - last[0] > 5 or done == total:
            last[0] = now
            print(f"\r{done}/{total} runs, {now - start:.0f} s", end="", file=sys.stderr, flush=True)

    summary = run(jobs, root / "out", workers=args.jobs, timeout=args.timeout, max_rss_mb=args.max_rss_mb,
                  progress=progress)
    summary["seconds"] = round(time.perf_counter() - start, 1)
    summary["command"] = "python benchmarks/mutation_run.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(file=sys.stderr)
    shown = {k: v for k, v in summary.items() if k != "failures"}
    print(json.dumps(shown, indent=2))
    for failure in summary["failures"][:20]:
        print(f"{'/'.join(failure['problems'])}: {' '.join(failure['argv'][:2])} [{failure['seed']}: "
              f"{failure['mutated']} {failure['op']}]: {failure['detail'][-300:]} {failure['raw'] or ''}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if not any(summary["problems"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
