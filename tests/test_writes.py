"""Every writer's failed write (issue 11 item 4): one line, exit status 2, the old output intact,
nothing left.

Writers: ``vbusd convert`` with KTX2 textures, ``vbusd export`` (``.gltf`` with its buffers, and
``.glb``), ``vbusd crowd`` and ``vbusd shader -o`` (``convert`` with EXR textures and ``decode`` are
in tests/test_faults.py). Each is failed with ENOSPC at every step of its write (``VBUSD_FAULT``,
the project's file layer), and with real errors the file system gives: a name too long for it and
a folder where a file should be. The output is judged by content against reference runs
(``benchmarks/fault_sweep.py``'s helpers), its validity by ``vbusd validate`` (USD) or its buffers'
sizes (glTF), and the folder by listing it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest


import vbusd  # noqa: E402,F401  (before pxr: registers the schema)

from tests.helpers import faults as sweep

REPO = Path(__file__).resolve().parents[1]




def run_here(args, env):
    """The sweep's in-process runner, for module fixtures (set-up runs that must succeed)."""
    return sweep.run_in_process(args, env, quiet=False)


@pytest.fixture()
def in_process(capfd):
    """The same, keeping stderr (fd level: USD's own diagnostics would show there too)."""

    def run(args, env):
        capfd.readouterr()
        status, _ = run_here(args, env)
        return status, capfd.readouterr().err

    return run


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    return sweep.make_sources(tmp_path_factory.mktemp("writes") / "src", runner=run_here)


WRITERS = ("convert-ktx2", "export-gltf", "export-glb", "crowd", "shader")


@pytest.fixture(scope="module", params=WRITERS)
def bench(request, sources, tmp_path_factory):
    return sweep.prepare(sweep.WRITERS[request.param], sources, tmp_path_factory.mktemp(request.param),
                         runner=run_here)


@pytest.mark.slow
def test_enospc_at_every_step_of_every_writer(bench, in_process):
    kinds = [step.split(" ")[0] for step in bench.steps]
    assert kinds[0] == "lock" and "commit" in kinds  # every writer goes through the one commit
    commit = kinds.index("commit") + 1
    for number in range(1, len(bench.steps) + 1):
        case = sweep.run_case(bench, f"enospc:{number}", runner=in_process)
        assert case.verdict == "ok", (bench.writer.name, bench.steps[number - 1], case)
        if number <= commit:
            assert case.status == 2 and case.state == "old" and case.hidden == case.visible == []
            assert "No space left on device" in case.lines[0] and str(bench.target) in case.lines[0]


def test_a_name_too_long_for_the_file_system_is_one_line(bench, in_process, tmp_path):
    long_name = "n" * (250 - len(Path(bench.writer.target).suffix)) + Path(bench.writer.target).suffix
    target = tmp_path / long_name
    for name in bench.writer.inputs:  # a crowd's characters
        (tmp_path / name).write_bytes((bench.sources / name).read_bytes())
    before = sorted(os.listdir(tmp_path))
    status, stderr = in_process(bench.writer.new(bench.sources, target), {})
    lines = stderr.strip().splitlines()
    assert status == 2 and len(lines) == 1, stderr
    assert "File name too long" in lines[0]
    assert sorted(os.listdir(tmp_path)) == before


def test_a_folder_where_a_file_should_be(bench, in_process, tmp_path):
    """A folder in the way of the output itself, and (with --force) of a file of the new output."""
    target = tmp_path / "out" / bench.writer.target
    for name in bench.writer.inputs:
        (target.parent / name).parent.mkdir(parents=True, exist_ok=True)
        (target.parent / name).write_bytes((bench.sources / name).read_bytes())
    target.mkdir(parents=True)
    if not bench.writer.name.startswith("convert"):  # convert takes a folder as its batch output folder
        status, stderr = in_process(bench.writer.new(bench.sources, target) + ["--force"], {})
        assert status == 2 and len(stderr.strip().splitlines()) == 1, stderr
        assert target.is_dir() and list(target.iterdir()) == []
    target.rmdir()
    # A folder named as one of the other files the writer makes (texture, sidecar, buffer).
    reference = bench.old_dir.parent.parent / "ref" / "out"
    others = sorted(p.name for p in reference.iterdir() if p.name != bench.writer.target
                    and not p.name.startswith(".") and p.name not in bench.writer.inputs)
    for other in others:
        (target.parent / other).mkdir()
        before = sorted(os.listdir(target.parent))
        status, stderr = in_process(bench.writer.new(bench.sources, target) + ["--force"], {})
        assert status == 2 and len(stderr.strip().splitlines()) == 1, (other, stderr)
        assert sorted(os.listdir(target.parent)) == before, other
        (target.parent / other).rmdir()


def test_replacing_a_gltf_package_never_mixes_and_leaves_only_its_files(sources, tmp_path):
    """A .gltf's buffer that the current .gltf uses with other bytes takes a digest name for the
    commit, then its plain name back (issue 24: the files must not depend on what was there)."""
    bench = sweep.prepare(sweep.WRITERS["export-gltf"], sources, tmp_path, runner=run_here)
    # Killed after the new buffers are in place, before the .gltf's rename: the old package whole.
    case = sweep.run_case(bench, f"kill:{[s.split(' ')[0] for s in bench.steps].index('commit')}")
    assert case.verdict == "ok" and case.state == "old" and case.after_left == [], case
    # The replacing run renamed the texture twice: to a digest name, then back (a second commit).
    assert [s.split(" ")[0] for s in bench.steps].count("commit") == 2, bench.steps
    assert run_here(bench.writer.new(bench.sources, bench.target) + ["--force"], {})[0] == 0
    document = json.loads(bench.target.read_text(encoding="utf-8"))
    uris = sorted(buffer["uri"] for buffer in document["buffers"])
    # The same files, name for name and byte for byte, as the same export into an empty folder.
    reference = bench.old_dir.parent.parent / "ref" / "out"
    assert uris == ["p.Skel.ktx2", "p.bin"]
    for name in uris + ["p.gltf"]:
        assert (bench.target.parent / name).read_bytes() == (reference / name).read_bytes(), name
    assert sorted(os.listdir(bench.target.parent)) == sorted(uris + ["p.gltf"])
    assert sweep.validate(bench.target, "gltf") == []
    assert sweep.state_of(bench.target, bench.old, bench.new) == "new"
