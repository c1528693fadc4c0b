"""The fault-injection harness of vbusd's writers: each writer's old and new command, the sources
they run on, a folder's fingerprint and validity, one case (a writer killed or failed at step N)
and its verdict, independently of the writer's own bookkeeping.

Used by tests/test_faults.py and tests/test_writes.py (fast subsets) and by
benchmarks/fault_sweep.py (every writer at every step; its docstring says what is checked).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import vbusd  # noqa: F401  (before pxr: registers the Virtual Bones schema)

from tests.helpers import scenes

REPO = Path(__file__).resolve().parents[2]
ERRNOS = ("enospc", "edquot", "erofs", "eacces", "eio", "enametoolong")
"""Errors injected besides SIGKILL: ENOSPC at every step, each other one at every fifth step in turn."""


def vbusd_argv(*args) -> list:
    """The command line of one ``vbusd`` process run with this interpreter."""
    return [sys.executable, "-m", "vbusd", *[str(a) for a in args]]


def child_env(**extra) -> dict:
    """The environment of a ``vbusd`` child: the checkout never shadows the installed package."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("VBUSD_FAULT")}
    env.update(PYTHONSAFEPATH="1", VBUSD_LOCK_TIMEOUT="20")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def run_process(args: list, env: dict) -> tuple:
    """Run ``vbusd ARGS`` as a child process with ``env`` added; return (exit status, stderr)."""
    process = subprocess.run(vbusd_argv(*args), env=child_env(**env), capture_output=True, text=True,
                             timeout=600)
    return process.returncode, process.stderr


def run_in_process(args: list, env: dict, *, quiet: bool = False) -> tuple:
    """Run ``vbusd ARGS`` in this process with ``env`` set (the fault counter reset before and after);
    return (exit status, ""). For set-up runs that must succeed, where a child process would only
    cost time; ``quiet`` adds ``--quiet`` to convert and decode."""
    from vbusd.cli import main
    from vbusd.io import files

    saved = {name: os.environ.get(name) for name in list(env) + [files.FAULT_ENV, files.FAULT_TRACE_ENV]}
    try:
        for name in (files.FAULT_ENV, files.FAULT_TRACE_ENV):
            os.environ.pop(name, None)
        os.environ.update({name: str(value) for name, value in env.items()})
        files._fault_steps = 0
        extra = ["--quiet"] if quiet and args[0] in ("convert", "decode") else []
        return main([str(a) for a in args] + extra), ""
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        files._fault_steps = 0


@dataclass
class Writer:
    """One vbusd writer: how to make the old output and the command that replaces it."""

    name: str
    target: str
    old: Callable[[Path, Path], list]
    new: Callable[[Path, Path], list]
    kind: str  # "usd", "cache", "gltf", "glb" or "text": how the output is validated
    in_use: Optional[Callable] = None  # for recovery, as the writer passes it to Commit
    inputs: tuple = ()  # source files copied into the output folder first (a crowd's characters)


def _usd_in_use():
    from vbusd.io.usd import asset_files_in_use

    return asset_files_in_use


def _gltf_in_use():
    from vbusd.io.gltf_package import package_files_in_use

    return package_files_in_use


WRITERS = {
    "convert": Writer("convert", "a.usda",
                      lambda s, o: ["convert", s / "rig.usda", "-o", o, "--quiet"],
                      lambda s, o: ["convert", s / "rig.usda", "-o", o, "--texel-format", "float32", "--quiet"],
                      "usd", _usd_in_use),
    "convert-ktx2": Writer("convert-ktx2", "a.usda",
                           lambda s, o: ["convert", s / "rig.usda", "-o", o, "--container", "ktx2", "--quiet"],
                           lambda s, o: ["convert", s / "rig.usda", "-o", o, "--container", "ktx2",
                                         "--texel-format", "float32", "--quiet"],
                           "usd", _usd_in_use),
    "decode": Writer("decode", "cache.usda",
                     lambda s, o: ["decode", s / "a16.usda", "-o", o, "--quiet"],
                     lambda s, o: ["decode", s / "a32.usda", "-o", o, "--quiet"],
                     "cache", _usd_in_use),
    "export-gltf": Writer("export-gltf", "p.gltf",
                          lambda s, o: ["export", s / "a16.usda", "-o", o],
                          lambda s, o: ["export", s / "a32.usda", "-o", o],
                          "gltf", _gltf_in_use),
    "export-glb": Writer("export-glb", "p.glb",
                         lambda s, o: ["export", s / "a16.usda", "-o", o],
                         lambda s, o: ["export", s / "a32.usda", "-o", o],
                         "glb", _gltf_in_use),
    "crowd": Writer("crowd", "crowd.usda",
                    lambda s, o: ["crowd", o.parent / "a16.usda", "-o", o, "--count", "6", "--seed", "1"],
                    lambda s, o: ["crowd", o.parent / "a16.usda", "-o", o, "--count", "9", "--seed", "2"],
                    "usd", inputs=("a16.usda", "a16.Skel.exr", "a16.Skel.exr.json")),
    "shader": Writer("shader", "skin.glsl",
                     lambda s, o: ["shader", "--lang", "glsl", "-o", o],
                     lambda s, o: ["shader", "--lang", "glsl", "--encoding", "dualQuat", "-o", o],
                     "text"),
}


def make_sources(folder: Path, runner: Callable = run_process) -> Path:
    """A small UsdSkel rig (the tests' fixture) and its float16 and float32 Virtual Bones assets."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    scenes.write_stage(folder / "rig.usda", [scenes.RigSpec()])
    for name, fmt in (("a16.usda", "float16"), ("a32.usda", "float32")):
        _checked(runner, ["convert", folder / "rig.usda", "-o", folder / name, "--texel-format", fmt, "--quiet"], {})
    return folder


# -- what a folder holds ------------------------------------------------------------------------

_DIGEST = re.compile(rb"\.[0-9a-f]{12}(?=\.(?:exr|png|ktx2|bin)\b)")


def _normal(name: bytes) -> bytes:
    return _DIGEST.sub(b"", name)


def named_files(target: Path) -> list:
    """Visible files beside ``target`` whose name the target holds (quoted, or as ``@./name@``)."""
    data = target.read_bytes()
    found = []
    for entry in sorted(os.listdir(target.parent)):
        if entry.startswith(".") or entry == target.name:
            continue
        raw = entry.encode("utf-8")
        if b'"' + raw + b'"' in data or b"@./" + raw + b"@" in data or b"@" + raw + b"@" in data:
            found.append(target.parent / entry)
    return found


def fingerprint(target: Path) -> Optional[str]:
    """The output's content, independent of file names' digest parts: None if it is missing."""
    if not target.is_file():
        return None
    digest = hashlib.sha256(_normal(target.read_bytes()))
    for path in named_files(target):
        digest.update(b"\0" + _normal(path.name.encode("utf-8")) + b"\0")
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


def leftovers(target: Path, before: set) -> tuple:
    """(hidden, visible) files beside ``target`` that are neither it, nor named by it, nor in ``before``."""
    keep = {target.name} | {p.name for p in named_files(target)} if target.is_file() else set()
    extra = sorted(set(os.listdir(target.parent)) - keep - before)
    return [n for n in extra if n.startswith(".")], [n for n in extra if not n.startswith(".")]


def validate(target: Path, kind: str) -> list:
    """Problems of the output: vbusd's validator (USD assets: no error, no warning), a point cache's
    animated meshes (opened with pxr), buffer sizes (glTF), header length (GLB)."""
    if not target.is_file():
        return ["missing"]
    if kind == "usd":
        from pxr import Sdf

        from vbusd.validators.api import validate as run_validator

        cached = Sdf.Layer.Find(str(target))  # a layer this process still holds: read the file anew
        if cached is not None:
            cached.Reload(True)
        report = run_validator(target)
        bad = [f"{f.code}: {f.message}" for f in report.findings if f.severity in ("error", "warning")]
        return bad or ([] if report.valid else ["errors"])
    if kind == "cache":  # a point cache is no Virtual Bones asset: it opens and its meshes move
        from pxr import Sdf, Usd, UsdGeom

        cached = Sdf.Layer.Find(str(target))
        if cached is not None:
            cached.Reload(True)
        stage = Usd.Stage.Open(str(target))
        moving = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)
                  and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 1]
        return [] if moving else ["no animated mesh"]
    if kind == "gltf":
        document = json.loads(target.read_text(encoding="utf-8"))
        problems = []
        for buffer in document.get("buffers", []):
            path = target.parent / buffer["uri"]
            if not path.is_file() or path.stat().st_size != buffer["byteLength"]:
                problems.append(f"buffer {buffer['uri']} missing or of another length")
        return problems
    if kind == "glb":
        data = target.read_bytes()
        magic, version, length = struct.unpack("<III", data[:12])
        return [] if (magic, version, length) == (0x46546C67, 2, len(data)) else ["bad GLB header"]
    return []


# -- one case -----------------------------------------------------------------------------------

@dataclass
class Case:
    """What one faulted run did and left."""

    fault: str
    status: int
    lines: list
    state: str  # "old", "new" or "other"
    problems: list
    hidden: list
    visible: list
    after_state: str = ""
    after_left: list = field(default_factory=list)
    verdict: str = "ok"

    def to_json(self) -> dict:
        return dict(self.__dict__)


def state_of(target: Path, old: str, new: str) -> str:
    """``old``, ``new``, ``missing`` or ``other`` (a mix, or anything else)."""
    current = fingerprint(target)
    return "missing" if current is None else "old" if current == old else "new" if current == new else "other"


@dataclass
class Bench:
    """A prepared writer: sources, the pristine old output and the two reference fingerprints."""

    writer: Writer
    sources: Path
    old_dir: Path
    case_dir: Path
    old: str
    new: str
    steps: list

    @property
    def target(self) -> Path:
        return self.case_dir / self.writer.target


def prepare(writer: Writer, sources: Path, work: Path, runner: Callable = run_process) -> Bench:
    """Make the old output, a reference new output and the step list of the replacing run.

    ``runner(args, env) -> (status, stderr)`` runs one vbusd command (default: a child process).
    """
    work = work / writer.name
    shutil.rmtree(work, ignore_errors=True)
    old_dir, ref_dir, case_dir = work / "old" / "out", work / "ref" / "out", work / "case" / "out"
    for folder, command in ((old_dir, writer.old), (ref_dir, writer.new)):
        folder.mkdir(parents=True)
        for name in writer.inputs:
            shutil.copy2(sources / name, folder / name)
        _checked(runner, command(sources, folder / writer.target), {})
    trace = work / "trace.txt"
    reset(old_dir, case_dir)
    _checked(runner, writer.new(sources, case_dir / writer.target) + ["--force"], {"VBUSD_FAULT_TRACE": trace})
    steps = [line.split(" ", 1)[1] for line in trace.read_text(encoding="utf-8").splitlines()]
    old, new = fingerprint(old_dir / writer.target), fingerprint(ref_dir / writer.target)
    if fingerprint(case_dir / writer.target) != new or old == new:
        raise RuntimeError(f"{writer.name}: the replacing run is not reproducible or equals the old output")
    return Bench(writer, sources, old_dir, case_dir, old, new, steps)


def _checked(runner: Callable, args: list, env: dict) -> None:
    status, stderr = runner(args, env)
    if status != 0:
        raise RuntimeError(f"vbusd {' '.join(map(str, args))} exited {status}: {stderr.strip()[-500:]}")


def reset(old_dir: Path, case_dir: Path) -> None:
    """Put a fresh copy of the old output into the case folder."""
    shutil.rmtree(case_dir.parent, ignore_errors=True)
    shutil.copytree(old_dir, case_dir, symlinks=True)


def run_case(bench: Bench, fault: str, *, recover: bool = True, runner: Callable = run_process) -> Case:
    """Replace the old output with ``VBUSD_FAULT=fault`` set and judge what is left.

    ``fault`` is ``kill:N`` or ``<errno>:N`` (see :data:`vbusd.io.files.FAULT_ENV`); ``recover``
    then runs the recovery the next writer runs and judges the folder again.
    """
    reset(bench.old_dir, bench.case_dir)
    before = set(os.listdir(bench.case_dir)) - {bench.writer.target} - {p.name for p in named_files(bench.target)}
    status, stderr = runner(bench.writer.new(bench.sources, bench.target) + ["--force"], {"VBUSD_FAULT": fault})
    hidden, visible = leftovers(bench.target, before)
    case = Case(fault=fault, status=status, lines=stderr.strip().splitlines(),
                state=state_of(bench.target, bench.old, bench.new),
                problems=validate(bench.target, bench.writer.kind), hidden=hidden, visible=visible)
    if recover:
        from vbusd.io.files import recover as recover_output

        in_use = bench.writer.in_use() if bench.writer.in_use else None
        recover_output(bench.target, in_use=in_use, lock_timeout=0)
        case.after_state = state_of(bench.target, bench.old, bench.new)
        case.after_left = sum(leftovers(bench.target, before), [])
    case.verdict = judge(case, bench)
    return case


def judge(case: Case, bench: Bench) -> str:
    """``ok`` or what is wrong, by the guarantee of spec 12.4."""
    kind, _, number = case.fault.partition(":")
    step = bench.steps[int(number) - 1] if number.isdigit() and 0 < int(number) <= len(bench.steps) else ""
    after_commit = step.split(" ")[0] in ("discard", "remove")
    if case.state not in ("old", "new"):
        return f"output is {case.state}"
    if case.problems:
        return "does not validate: " + "; ".join(case.problems[:3])
    if any("Traceback" in line for line in case.lines):
        return "traceback"
    if kind == "kill":
        if case.status not in (-9, 137):
            return f"exit status {case.status} after a kill"
        # Working files (lock, journal, staged files) and files renamed into place that no layer
        # names yet may stay until the next run (spec 12.4): recovery is checked below.
    elif case.status == 2:
        if len(case.lines) != 1:
            return f"{len(case.lines)} lines on stderr"
        if case.state != "old":
            return "failed but the output changed"
        if case.hidden or case.visible:
            return f"leftovers {case.hidden + case.visible}"
    elif case.status == 0:
        if case.state != "new":
            return "exit 0 but the old output"
        if (case.hidden or case.visible) and not after_commit:
            return f"leftovers {case.hidden + case.visible}"
    else:
        return f"exit status {case.status}"
    if case.after_state and case.after_state != case.state:
        return f"recovery changed the output to {case.after_state}"
    if case.after_left:
        return f"left after recovery {case.after_left}"
    return "ok"


# -- the sweep ----------------------------------------------------------------------------------
