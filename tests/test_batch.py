"""``vbusd convert`` on a library (issue 17): many sources, the cache, crash and resume, a failing
asset among good ones, byte-identical output, manifests, a process pool and a Dask LocalCluster.

Independent facts used: the bytes of files converted in fresh folders by separate processes (and by
a Dask worker), the files a SIGKILLed run leaves (listed from the disk), file modification times of
skipped assets, and the sources' own references (a USD sublayer, a glTF .bin buffer) edited by hand.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest


from tests.helpers.cli import run
from vbusd.jobs.batch import BatchItem, cache_key, dependencies, plan_batch, read_manifest, run_batch  # noqa: E402
from vbusd.cli import main  # noqa: E402
from vbusd.jobs.conversion import ConvertOptions  # noqa: E402
from vbusd.format.errors import OptionsError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STADIUM = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
FAST = ["--check-rows", "4"]
"""Options that keep every conversion here well under a second (4 rows checked against UsdSkel)."""


def _library(folder: Path, names=("a", "b", "c")) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copyfile(STADIUM, folder / f"{name}.usda")
    return folder


def _files(folder: Path) -> dict:
    """Visible files below a folder (the cache and hidden lock files left out) and their bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)}


def _run_json(args, capsys) -> tuple:
    status = main(["convert", *args, "--format", "json", *FAST])
    return status, json.loads(capsys.readouterr().out)


def _statuses(report) -> dict:
    return {Path(a["source"]).name: a["status"] for a in report["assets"]}


# --------------------------------------------------------------------------------------------


def test_failing_asset_among_good_ones(tmp_path, capsys):
    library = _library(tmp_path / "lib", ("a", "b"))
    (library / "broken.usda").write_text("#usda 1.0\n(\n  this is not usd\n", encoding="utf-8")
    report_file = tmp_path / "report.json"
    status, report = _run_json([str(library), "-o", str(tmp_path / "out"), "--jobs", "1",
                                "--report", str(report_file)], capsys)
    assert status == 1  # some failed
    assert _statuses(report) == {"a.usda": "converted", "b.usda": "converted", "broken.usda": "failed"}
    broken = next(a for a in report["assets"] if a["status"] == "failed")
    assert broken["code"] == "usd.open" and "broken.usda" in broken["error"] and "\n" not in broken["error"]
    assert broken["files"] == {} and broken["bytes"] == 0
    good = [a for a in report["assets"] if a["status"] == "converted"]
    for asset in good:
        assert asset["bytes"] == sum(os.path.getsize(f) for f in asset["files"]) > 0
        assert 0 < asset["maxErrorFraction"] < 2e-3  # float16 texels against UsdSkel's skinning
    assert not list((tmp_path / "out").glob("broken*"))  # nothing at all for the failed asset
    assert json.loads(report_file.read_text()) == report  # --report holds what --format json printed


def test_text_table_and_exit_two_when_none_converts(tmp_path, capsys):
    library = tmp_path / "lib"
    library.mkdir()
    (library / "x.usda").write_text("not usd", encoding="utf-8")
    (library / "y.glb").write_bytes(b"glTF\x02\x00\x00\x00")
    status = main(["convert", str(library), "-o", str(tmp_path / "out"), "--jobs", "1", *FAST])
    out, err = capsys.readouterr()
    assert status == 2  # none could be converted
    assert "x.usda" in out and "y.glb" in out and "0 converted" in out and "2 failed" in out
    # Each failed asset's error: one unwrapped line on stderr, as a single convert prints it.
    lines = err.strip().splitlines()
    assert len(lines) == 2 and all(line.startswith("vbusd: ") and ": usd.open: " in line or ": gltf." in line
                                   for line in lines), lines
    assert not (tmp_path / "out").exists()  # nothing converted: no output folder, no cache records


def test_nothing_to_convert_is_a_usage_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["convert", str(tmp_path / "empty"), str(STADIUM), "-o", str(tmp_path / "o")]) == 2
    assert "batch.plan" in capsys.readouterr().err
    with pytest.raises(OptionsError, match="would both write"):
        plan_batch([str(STADIUM), str(STADIUM)], str(tmp_path / "o"))
    manifest = tmp_path / "m.json"  # one stem, two layer suffixes: their textures would collide
    manifest.write_text(json.dumps([{"source": str(STADIUM), "output": "x.usda"},
                                    {"source": str(STADIUM), "output": "x.usdc"}]))
    with pytest.raises(OptionsError, match="would both write x"):
        plan_batch([], str(tmp_path / "o"), manifest=str(manifest))


def test_folders_keep_their_structure_and_globs_expand(tmp_path):
    _library(tmp_path / "lib" / "heroes", ("a",))
    _library(tmp_path / "lib" / "crowd", ("a", "b"))
    items = plan_batch([str(tmp_path / "lib")], str(tmp_path / "out"))
    outputs = sorted(str(Path(i.output).relative_to(tmp_path / "out")) for i in items)
    assert outputs == ["crowd/a.usda", "crowd/b.usda", "heroes/a.usda"]
    globbed = plan_batch([str(tmp_path / "lib" / "*" / "b.usda")], str(tmp_path / "out"))
    assert [Path(i.output).name for i in globbed] == ["b.usda"]


def test_sources_from_different_trees_do_not_mirror_their_absolute_paths(tmp_path):
    """Issue 24: outputs were placed below the common folder of all sources, so sources in
    different trees wrote OUT/<their whole paths>. Each is now placed below its own argument."""
    hero = _library(tmp_path / "x" / "deep" / "heroes", ("hero",)) / "hero.usda"
    library = tmp_path / "y" / "other" / "lib"
    _library(library / "crowd", ("walker",))
    _library(tmp_path / "z" / "globbed" / "set1", ("extra",))
    out = tmp_path / "out"
    items = plan_batch([str(hero), str(library), str(tmp_path / "z" / "globbed" / "*" / "*.usda")], str(out))
    outputs = sorted(str(Path(i.output).relative_to(out)) for i in items)
    assert outputs == ["crowd/walker.usda", "hero.usda", "set1/extra.usda"]
    with pytest.raises(OptionsError, match="would both write hero"):  # one stem twice in one folder
        plan_batch([str(hero), str(_library(tmp_path / "w", ("hero",)) / "hero.usda")], str(out))


# --------------------------------------------------------------------------------------------
# Cache


def _with_sublayer(folder: Path) -> tuple:
    """A source whose skeleton and mesh come from a sublayer (the stadium sample)."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(STADIUM, folder / "rig.usda")
    (folder / "char.usda").write_text('#usda 1.0\n(\n    subLayers = [@./rig.usda@]\n)\n', encoding="utf-8")
    return folder / "char.usda", folder / "rig.usda"


@pytest.mark.slow
def test_cache_skips_unchanged_and_reconverts_a_changed_referenced_file(tmp_path, capsys):
    source, sublayer = _with_sublayer(tmp_path / "lib")
    shutil.copyfile(STADIUM, tmp_path / "lib" / "other.usda")
    out = tmp_path / "out"
    args = [str(source), str(tmp_path / "lib" / "other.usda"), "-o", str(out), "--jobs", "1"]
    status, first = _run_json(args, capsys)
    assert status == 0 and _statuses(first) == {"char.usda": "converted", "other.usda": "converted"}
    stamps = {p: p.stat().st_mtime_ns for p in out.iterdir() if p.is_file()}

    status, second = _run_json(args, capsys)  # nothing changed: nothing converted or rewritten
    assert status == 0 and _statuses(second) == {"char.usda": "cached", "other.usda": "cached"}
    assert {p: p.stat().st_mtime_ns for p in out.iterdir() if p.is_file()} == stamps
    assert second["assets"][0]["files"] == first["assets"][0]["files"]

    # Edit the sublayer only (char.usda itself is unchanged): char reconverts, other does not.
    text = sublayer.read_text(encoding="utf-8")
    sublayer.write_text(text.replace("float3[] extent", "float3[] extent", 1) + '\ndef "Extra"\n{\n}\n',
                        encoding="utf-8")
    status, third = _run_json(args, capsys)
    assert status == 0 and _statuses(third) == {"char.usda": "converted", "other.usda": "cached"}

    # An output damaged or removed since: reconverted (the cache checks sizes and SHA-256).
    texture = next(out.glob("other.*.exr"))
    texture.write_bytes(texture.read_bytes()[:-7] + b"garbage")
    status, fourth = _run_json(args, capsys)
    assert _statuses(fourth) == {"char.usda": "cached", "other.usda": "converted"}
    # Options are part of the key.
    status, fifth = _run_json([*args, "--texel-format", "float32"], capsys)
    assert _statuses(fifth) == {"char.usda": "converted", "other.usda": "converted"}
    # --no-cache converts everything again.
    status, sixth = _run_json([*args, "--texel-format", "float32", "--no-cache", "--force"], capsys)
    assert _statuses(sixth) == {"char.usda": "converted", "other.usda": "converted"}


def test_a_reference_that_appears_later_reconverts(tmp_path, capsys):
    # A missing asset path counts by its name; the parent cannot tell from the record whether it
    # exists now, so the worker computes the key again: unchanged -> cached, appeared -> converted.
    source, _ = _with_sublayer(tmp_path / "lib")
    source.write_text(source.read_text(encoding="utf-8") + 'def "Look"\n{\n    asset tint = @./tint.png@\n}\n',
                      encoding="utf-8")
    args = [str(source), str(tmp_path / "lib" / "rig.usda"), "-o", str(tmp_path / "out"), "--jobs", "1"]
    status, first = _run_json(args, capsys)
    assert status == 0 and _statuses(first) == {"char.usda": "converted", "rig.usda": "converted"}
    status, second = _run_json(args, capsys)
    assert _statuses(second) == {"char.usda": "cached", "rig.usda": "cached"}
    (tmp_path / "lib" / "tint.png").write_bytes(b"not even a PNG: only its bytes count")
    status, third = _run_json(args, capsys)
    assert status == 0 and _statuses(third) == {"char.usda": "converted", "rig.usda": "cached"}


@pytest.mark.cli
def test_a_corrupt_crate_fails_alone(tmp_path, capsys):
    # Planning once opened every USD source in the command's own process to find its
    # dependencies: this crate crashed the whole batch (signal 11). Now it is one failed asset.
    library = _library(tmp_path / "lib", ("a", "b"))
    shutil.copyfile(REPO / "tests" / "fixtures" / "corrupt_usdc" / "crash_or_huge_alloc.usdc", library / "bad.usdc")
    run = subprocess.run([sys.executable, "-m", "vbusd", "convert", str(library), "-o", str(tmp_path / "out"),
                          "--jobs", "2", "--format", "json", *FAST], capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stderr
    report = json.loads(run.stdout)
    assert _statuses(report) == {"a.usda": "converted", "b.usda": "converted", "bad.usdc": "failed"}
    bad = next(a for a in report["assets"] if a["status"] == "failed")
    assert bad["code"] == "usd.open" and bad["error"].startswith(f"{library / 'bad.usdc'}: usd.open: "), bad
    assert run.stderr == ""  # no progress line on a pipe without --progress, however slow the machine


def test_gltf_buffers_and_images_are_inputs(tmp_path):
    gltf = tmp_path / "rig.gltf"
    (tmp_path / "rig.bin").write_bytes(b"\x00" * 64)
    (tmp_path / "skin.png").write_bytes(b"\x89PNG fake")
    gltf.write_text(json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "rig.bin", "byteLength": 64}],
                                "images": [{"uri": "skin.png"}, {"uri": "data:image/png;base64,AAAA"}]}))
    assert dependencies(gltf)[1:] == [str((tmp_path / "rig.bin").resolve()), str((tmp_path / "skin.png").resolve())]
    options = ConvertOptions()
    key, _ = cache_key(gltf, options)
    assert cache_key(gltf, options)[0] == key  # stable
    (tmp_path / "rig.bin").write_bytes(b"\x01" + b"\x00" * 63)
    changed, _ = cache_key(gltf, options)
    assert changed != key
    (tmp_path / "skin.png").unlink()
    assert cache_key(gltf, options)[0] != changed  # a vanished image too
    assert cache_key(gltf, ConvertOptions(texel_format="float32"))[0] != cache_key(gltf, options)[0]


# --------------------------------------------------------------------------------------------
# Crash and resume


def _cli(args, env=None, cwd=None):
    """``vbusd convert ARGS`` as a process of its own: for a run that is killed, and for a fault trace
    (steps are counted per process)."""
    return subprocess.run([sys.executable, "-m", "vbusd", "convert", *args, *FAST], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, cwd=cwd, timeout=600)


def _here(capfd, args):
    """``vbusd convert ARGS`` in this process (what it finds on disk and reports is the point, not
    its process): the same result as :func:`_cli`'s, without a second of start-up."""
    return run(capfd, "convert", *args, *FAST)


@pytest.mark.cli
def test_sigkill_leaves_no_partial_asset_and_the_next_run_does_only_the_rest(tmp_path, capfd):
    library = _library(tmp_path / "lib")
    out = tmp_path / "out"
    trace = tmp_path / "trace.txt"
    clean = _cli([str(library), "-o", str(tmp_path / "clean"), "--jobs", "1"], {"VBUSD_FAULT_TRACE": str(trace)})
    assert clean.returncode == 0, clean.stderr
    steps = trace.read_text().splitlines()
    # Kill between b's texture rename and its layer commit: the most delicate moment.
    step = next(int(line.split()[0]) for line in steps if line.split()[1:] == ["rename", "b.Skeleton.exr"])
    killed = _cli([str(library), "-o", str(out), "--jobs", "1"], {"VBUSD_FAULT": f"kill:{step}"})
    assert killed.returncode == -9  # SIGKILL
    assert (out / "a.usda").is_file() and not (out / "b.usda").exists() and not (out / "c.usda").exists()

    resumed = _here(capfd, [str(library), "-o", str(out), "--jobs", "1", "--format", "json"])
    assert resumed.returncode == 0, resumed.stderr
    report = json.loads(resumed.stdout)
    assert _statuses(report) == {"a.usda": "cached", "b.usda": "converted", "c.usda": "converted"}
    # Nothing of the killed run is left, and the result is byte for byte the clean run's.
    assert _files(out) == _files(tmp_path / "clean")
    assert not [p for p in out.iterdir() if "vbusd-tmp" in p.name or p.name.endswith("vbusd-journal")]


@pytest.mark.cli
def test_killed_after_the_commit_before_the_record(tmp_path, capfd):
    """Killed after b's layer is committed but before its cache record: the pending record marks the
    output as the batch's own, so the next run replaces it without --force."""
    library = _library(tmp_path / "lib", ("a", "b"))
    trace = tmp_path / "trace.txt"
    assert _cli([str(library), "-o", str(tmp_path / "clean"), "--jobs", "1"],
                {"VBUSD_FAULT_TRACE": str(trace)}).returncode == 0
    steps = trace.read_text().splitlines()
    step = next(int(line.split()[0]) for line in steps if line.split()[1:] == ["commit", "b.usda"]) + 1
    out = tmp_path / "out"
    assert _cli([str(library), "-o", str(out), "--jobs", "1"], {"VBUSD_FAULT": f"kill:{step}"}).returncode == -9
    assert (out / "b.usda").is_file()
    resumed = _here(capfd, [str(library), "-o", str(out), "--jobs", "1", "--format", "json"])
    assert resumed.returncode == 0, resumed.stderr
    assert _statuses(json.loads(resumed.stdout)) == {"a.usda": "cached", "b.usda": "converted"}
    assert _files(out) == _files(tmp_path / "clean")


@pytest.mark.cli
def test_a_batch_resumed_over_another_run_gives_the_clean_runs_files_and_names(tmp_path, capfd):
    """Issue 24: a batch killed and run again over outputs of other content (here an earlier run
    with other options) ended with textures named by digest (a.Skeleton.5e354db5539d.exr) where a
    clean run has plain names. Killed between the commit that used the digest name and the one
    that gives the plain name back, then resumed: the clean run's files, name for name."""
    library = _library(tmp_path / "lib", ("a", "b"))
    new_options = ["--jobs", "1", "--texel-format", "float32"]
    assert _here(capfd, [str(library), "-o", str(tmp_path / "clean"), *new_options]).returncode == 0
    out, traced = tmp_path / "out", tmp_path / "traced"
    for folder in (out, traced):
        assert _here(capfd, [str(library), "-o", str(folder), "--jobs", "1"]).returncode == 0  # float16 first
    trace = tmp_path / "trace.txt"
    assert _cli([str(library), "-o", str(traced), *new_options], {"VBUSD_FAULT_TRACE": str(trace)}).returncode == 0
    assert _files(traced) == _files(tmp_path / "clean")  # replaced without a kill: the clean run's files
    steps = [line.split(" ", 1) for line in trace.read_text().splitlines()]
    first_commit = next(int(n) for n, step in steps if step == "commit a.usda")
    killed = _cli([str(library), "-o", str(out), *new_options], {"VBUSD_FAULT": f"kill:{first_commit + 1}"})
    assert killed.returncode == -9
    assert any(".Skeleton." in name and name.endswith(".exr") and len(name.split(".")) == 4
               for name in os.listdir(out)), os.listdir(out)  # killed while a's texture had a digest name
    resumed = _here(capfd, [str(library), "-o", str(out), *new_options, "--format", "json"])
    assert resumed.returncode == 0, resumed.stderr
    assert _files(out) == _files(tmp_path / "clean")


@pytest.mark.cli
def test_a_batch_shows_the_converters_warnings_as_a_single_conversion_does(tmp_path, capfd):
    """Issue 24: the converters' warnings (a skinned mesh node whose transform glTF ignores) showed
    in a single conversion but neither on stderr nor in --report in a batch, converted or cached."""
    bar = REPO / "tests" / "fixtures" / "gltf" / "bar.gltf"
    node = json.loads(bar.read_text())["nodes"][3]
    assert "skin" in node and any(key in node for key in ("translation", "rotation", "scale", "matrix"))
    library = _library(tmp_path / "lib", ("a",))
    shutil.copyfile(bar, library / "bar.gltf")
    single = _here(capfd, [str(bar), "-o", str(tmp_path / "single" / "bar.usda")])
    assert single.returncode == 0, single.stderr
    (expected,) = [line[len("vbusd: warning: "):] for line in single.stderr.splitlines()
                   if line.startswith("vbusd: warning: ")]
    assert "skinned mesh node's transform is not identity" in expected
    report = tmp_path / "report.json"
    for status in ("converted", "cached"):
        batch = _here(capfd, [str(library), "-o", str(tmp_path / "out"), "--jobs", "2", "--report", str(report)])
        assert batch.returncode == 0, batch.stderr
        assert batch.stderr.splitlines() == [f"vbusd: warning: {library / 'bar.gltf'}: {expected}"], batch.stderr
        assets = {Path(a["source"]).name: a for a in json.loads(report.read_text())["assets"]}
        assert {name: a["status"] for name, a in assets.items()} == {"a.usda": status, "bar.gltf": status}
        assert assets["bar.gltf"]["warnings"] == [expected] and assets["a.usda"]["warnings"] == []
    quiet = _here(capfd, [str(library), "-o", str(tmp_path / "out"), "--quiet"])
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_an_existing_output_of_someone_else_needs_force(tmp_path, capsys):
    library = _library(tmp_path / "lib", ("a",))
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.usda").write_text("#usda 1.0\n", encoding="utf-8")
    status, report = _run_json([str(library), "-o", str(out), "--jobs", "1"], capsys)
    assert status == 2 and "--force" in report["assets"][0]["error"]
    assert (out / "a.usda").read_text() == "#usda 1.0\n"
    status, report = _run_json([str(library), "-o", str(out), "--jobs", "1", "--force"], capsys)
    assert status == 0 and _statuses(report) == {"a.usda": "converted"}


# --------------------------------------------------------------------------------------------
# Determinism, manifests, pool, Dask


@pytest.mark.cli
def test_two_conversions_are_byte_identical(tmp_path):
    """Two runs in two processes into fresh folders give the same bytes for every writer: EXR
    (float16, float32), 16-bit PNG, KTX2, the layer as .usda and .usdc, the JSON sidecars (no
    timestamp, host, process or random name in any of them)."""
    entries = [{"source": str(STADIUM), "output": "half.usda"},
               {"source": str(STADIUM), "output": "binary.usdc"},
               {"source": str(STADIUM), "output": "full.usda", "texel-format": "float32"},
               {"source": str(STADIUM), "output": "unorm.usda", "texel-format": "unorm16"},
               {"source": str(STADIUM), "output": "ktx.usda", "container": "ktx2"}]
    runs = []
    for name in ("one", "two"):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "m.json").write_text(json.dumps(entries))
        result = _cli(["--manifest", str(folder / "m.json"), "-o", str(folder), "--jobs", "1", "--no-cache"])
        assert result.returncode == 0, result.stdout + result.stderr
        runs.append(_files(folder))
    assert runs[0] == runs[1]
    suffixes = {Path(name).suffix for name in runs[0]}
    assert suffixes >= {".usda", ".usdc", ".exr", ".png", ".ktx2", ".json"}, suffixes


def test_manifest_csv_with_per_asset_options(tmp_path, capsys):
    library = _library(tmp_path / "lib", ("a", "b"))
    manifest = tmp_path / "lib" / "library.csv"
    manifest.write_text("source,output,texel-format,max-influences\n"
                        "a.usda,../out/hero/a.usdc,unorm16,\n"
                        "b.usda,,,2\n", encoding="utf-8")
    items = read_manifest(manifest)
    assert items[0] == BatchItem(str(library / "a.usda"), str(library / "../out/hero/a.usdc"),
                                 {"texel_format": "unorm16"}, f"{manifest}:2")
    assert items[1].options == {"max_influences": 2} and items[1].output == ""
    status, report = _run_json(["--manifest", str(manifest), "-o", str(tmp_path / "out"), "--jobs", "1"], capsys)
    assert status == 0
    files = [f for a in report["assets"] for f in a["files"]]
    assert any(f.endswith("hero/a.usdc") for f in files) and any(f.endswith("hero/a.Skeleton.png") for f in files)
    assert any(f.endswith(str(Path("out") / "b.usda")) for f in files)
    manifest.write_text("source,texel_fmt\na.usda,float32\n", encoding="utf-8")
    assert main(["convert", "--manifest", str(manifest), "-o", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "library.csv:2" in err and "texel_fmt" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_process_pool_matches_one_process(tmp_path, capsys):
    library = _library(tmp_path / "lib", ("a", "b"))
    status, report = _run_json([str(library), "-o", str(tmp_path / "pool"), "--jobs", "2"], capsys)
    assert status == 0 and _statuses(report) == {"a.usda": "converted", "b.usda": "converted"}
    assert len({a["worker"] for a in report["assets"]}) >= 1
    status, _ = _run_json([str(library), "-o", str(tmp_path / "one"), "--jobs", "1"], capsys)
    assert _files(tmp_path / "pool") == _files(tmp_path / "one")


_IDLE_THREADS = """
import multiprocessing, os, sys, time
from concurrent.futures import ProcessPoolExecutor


def convert_then_idle(task):
    from vbusd.jobs.batch import convert_one

    status = convert_one(task)["status"]
    def ticks():  # CPU time (user + system, clock ticks) of each thread of this process, by the kernel
        found = {}
        for thread in os.listdir("/proc/self/task"):
            try:
                fields = open(f"/proc/self/task/{thread}/stat").read().rsplit(") ", 1)[1].split()
            except FileNotFoundError:  # the thread ended between the listing and the read
                continue
            found[thread] = int(fields[11]) + int(fields[12])
        return found
    before = ticks()
    time.sleep(1.0)
    after = ticks()
    return status, max(after[t] - before.get(t, 0) for t in after) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    from vbusd.jobs.batch import _pool_initializer

    task = {"source": sys.argv[1], "output": sys.argv[2], "options": {"check_rows": 4}, "key": None,
            "cache": None, "force": True}
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_pool_initializer) as pool:
        print(*pool.submit(convert_then_idle, task).result())
"""


@pytest.mark.cli
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc to read thread CPU times")
def test_an_idle_pool_worker_burns_no_cpu(tmp_path):
    # Each worker converts on one core. Limiting OpenUSD's threads after they started left one
    # spinning at 100% of a core in every worker, which halved --jobs 2 on two cores.
    from pxr import Usd

    source = tmp_path / "rig.usdc"
    Usd.Stage.Open(str(STADIUM)).Export(str(source))  # a crate file: read through the probe server too
    script = tmp_path / "idle.py"
    script.write_text(_IDLE_THREADS)
    done = subprocess.run([sys.executable, str(script), str(source), str(tmp_path / "out" / "rig.usda")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    status, busiest = done.stdout.split()
    assert status == "converted"
    assert float(busiest) < 0.2, f"a thread of the idle worker used {busiest} s of CPU in 1 s"
    assert "PXR_WORK_THREAD_LIMIT" not in done.stderr  # no banner for the override


@pytest.mark.slow
def test_dask_local_cluster(tmp_path):
    import distributed
    library = _library(tmp_path / "lib", ("a", "b"))
    (library / "broken.usda").write_text("nope", encoding="utf-8")
    items = plan_batch([str(library)], str(tmp_path / "dask"))
    base = {"check_rows": 4}
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        report = run_batch(items, base, scheduler=cluster.scheduler_address)
        again = run_batch(items, base, scheduler=cluster.scheduler_address)
    assert [a.status for a in report.assets] == ["converted", "converted", "failed"]
    assert report.exit_status == 1 and report.assets[2].code == "usd.open"
    assert all(a.worker and a.worker.startswith(("tcp://", "inproc://")) for a in report.assets[:2])
    assert [a.status for a in again.assets] == ["cached", "cached", "failed"]
    local = run_batch(plan_batch([str(library)], str(tmp_path / "local")), base, jobs=1)
    assert [a.status for a in local.assets] == ["converted", "converted", "failed"]
    assert _files(tmp_path / "dask") == _files(tmp_path / "local")  # any worker, the same bytes


@pytest.mark.slow
@pytest.mark.parametrize("scheduler,said", [("tcp://127.0.0.1:9", "connection refused"),
                                             ("tcp://127.0.0.1", "missing port"), ("no address", "missing port"),
                                             ("tcp://127.0.0.1:port", "expected tcp://HOST:PORT")])
def test_unreachable_or_malformed_scheduler_is_one_line(tmp_path, capsys, scheduler, said):
    # Said at once: not after Dask's 10 s connect timeout, nor as Dask's ValueError from inside
    # Client (an internal error, then its half-made client's traceback after 20 s).
    import distributed  # noqa: F401  (the test extra has it)
    library = _library(tmp_path / "lib", ("a",))
    status = main(["convert", str(library), "-o", str(tmp_path / "o"), "--scheduler", scheduler])
    err = capsys.readouterr().err
    assert status == 2 and "batch.scheduler" in err and len(err.strip().splitlines()) == 1, err
    assert said in err, err
    assert not (tmp_path / "o").exists()


def test_one_source_into_a_layer_name_as_a_batch_is_refused_without_a_contradicting_note(tmp_path, capsys):
    """`--report` (or --scheduler) makes one source a batch; a .usda output is then refused, and the
    note that -o names a folder (it does not) is not said before it."""
    status = main(["convert", str(STADIUM), "-o", str(tmp_path / "x.usda"), "--report", str(tmp_path / "r.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "batch.plan" in err[0], err
    assert not (tmp_path / "x.usda").exists()


def test_several_sources_into_a_usd_file_name_is_refused(tmp_path, capsys):
    # `-o x.usda` with several sources would make a folder called x.usda: refused, nothing made.
    library = tmp_path / "lib"
    library.mkdir()
    (library / "a.usda").write_text("not usd", encoding="utf-8")
    (library / "b.usda").write_text("not usd", encoding="utf-8")
    out = tmp_path / "out" / "x.usda"
    assert main(["convert", str(library / "a.usda"), str(library / "b.usda"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "batch.plan" in err[0] and "not a USD file" in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("existing", [True, False])
def test_one_source_into_a_folder_is_a_batch_either_way_and_says_so(tmp_path, capsys, existing):
    """Issue 24: `-o existing_dir/` with one source switched to a batch without a word, while
    `-o new_dir/` was refused ("the output must be a USD layer"). Both are a batch of one, said so."""
    folder = tmp_path / "out"
    if existing:
        folder.mkdir()
    status = main(["convert", str(STADIUM), "-o", f"{folder}/", *FAST])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert (folder / "stadium_crowd.usda").is_file()
    assert captured.err.splitlines() == [
        f"vbusd: note: -o {folder}/ names a folder: {STADIUM} is converted into it as a batch of one "
        f"({folder / 'stadium_crowd.usda'}); name a .usda file for the single conversion"], captured.err
    assert "1 converted" in captured.out
    assert main(["convert", str(STADIUM), "-o", str(folder), "--quiet", *FAST]) == 0  # cached, and quiet
    assert capsys.readouterr().err == ""


def test_batch_options_on_one_source_are_named_not_ignored(tmp_path, capsys):
    output = tmp_path / "one.usda"
    assert main(["convert", str(STADIUM), "-o", str(output), "--jobs", "2", "--no-cache", *FAST]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vbusd: warning: --jobs, --no-cache apply to a batch (several sources, a folder, a glob or "
                   "--manifest, or -o a folder); one source converts in this process, uncached"], err
    assert output.is_file() and not (tmp_path / ".vbusd-cache").exists()


def _with_a_stalling_source(folder: Path) -> Path:
    """A library whose third source never finishes reading: a FIFO no one writes (a hung network
    share looks the same to the worker: blocked in ``open``, no progress)."""
    library = _library(folder, ("a", "b"))
    os.mkfifo(library / "stuck.usda")
    return library


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_stalled_worker_is_ended_and_the_batch_goes_on(tmp_path, capsys):
    library = _with_a_stalling_source(tmp_path / "lib")
    status, report = _run_json([str(library), "-o", str(tmp_path / "out"), "--jobs", "2", "--stall-timeout", "3"],
                               capsys)
    assert _statuses(report) == {"a.usda": "converted", "b.usda": "converted", "stuck.usda": "failed"}
    stuck = next(a for a in report["assets"] if a["source"].endswith("stuck.usda"))
    assert stuck["code"] == "batch.stalled" and "stuck.usda" in stuck["error"]
    assert status == 1
    assert sorted(_files(tmp_path / "out")) == ["a.Skeleton.exr", "a.Skeleton.exr.json", "a.usda",
                                               "b.Skeleton.exr", "b.Skeleton.exr.json", "b.usda"]


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_stalled_dask_task_is_ended_and_the_batch_goes_on(tmp_path):
    import distributed
    library = _with_a_stalling_source(tmp_path / "lib")
    items = plan_batch([str(library)], str(tmp_path / "dask"))
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        report = run_batch(items, {"check_rows": 4}, scheduler=cluster.scheduler_address, stall_timeout=3)
        with distributed.Client(cluster) as client:  # the worker loaded vbusd in its own main thread
            from vbusd.jobs import warmup

            prepared = list(client.run(warmup.prepared_by, "batch").values())
    statuses = {Path(a.source).name: (a.status, a.code) for a in report.assets}
    assert statuses["stuck.usda"] == ("failed", "batch.stalled")
    assert statuses["a.usda"][0] == statuses["b.usda"][0] == "converted"
    assert prepared == ["MainThread"]



def test_a_stall_timeout_must_be_positive(tmp_path):
    library = _library(tmp_path / "lib", ("a", "b"))
    with pytest.raises(OptionsError):
        run_batch(plan_batch([str(library)], str(tmp_path / "o")), {}, jobs=2, stall_timeout=0)


def test_a_completed_run_removes_the_cache_temporaries_a_killed_run_left(tmp_path, capfd):
    """Issue 35 item 19: killed while a cache record's temporary was written (before its rename),
    the run left ``.vbusd-cache/.<digest>.json.vbusd-tmp-<id>.json``; the run that resumes and
    completes removes it (no other run is using the cache), and its records are whole JSON."""
    library = _library(tmp_path / "lib", ("a", "b"))
    trace = tmp_path / "trace.txt"
    assert _cli([str(library), "-o", str(tmp_path / "clean"), "--jobs", "1"],
                {"VBUSD_FAULT_TRACE": str(trace)}).returncode == 0
    steps = [line.split(" ", 1) for line in trace.read_text().splitlines()]
    # The last record write's fsync: its temporary is full, not yet renamed over the record.
    step = max(int(n) for n, name in steps if name.startswith("fsync .") and ".json.vbusd-tmp-" in name)
    out = tmp_path / "out"
    assert _cli([str(library), "-o", str(out), "--jobs", "1"], {"VBUSD_FAULT": f"kill:{step}"}).returncode == -9
    cache = out / ".vbusd-cache"
    assert [p.name for p in cache.iterdir() if ".vbusd-tmp-" in p.name], sorted(os.listdir(cache))
    resumed = _here(capfd, [str(library), "-o", str(out), "--jobs", "1", "--format", "json"])
    assert resumed.returncode == 0, resumed.stderr
    assert sorted(p.name for p in cache.iterdir() if p.name.startswith(".")) == [], sorted(os.listdir(cache))
    for record in cache.iterdir():
        assert json.loads(record.read_text())["state"] == "done"
    assert _files(out) == _files(tmp_path / "clean")
