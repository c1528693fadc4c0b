"""Slices of the mutation run (benchmarks/mutation_run.py): corrupted assets and sources through
convert, validate, info and decode give no traceback, hang, partial or clobbered file, raw
third-party line, or input over 500 MB. The full run (5,000 mutants) and its figures are in
benchmarks/README.md; this slice uses another seed each release only when the harness changes."""

from __future__ import annotations


import pytest

from tests.helpers import mutation_run


def _harness(repo_root):
    return mutation_run  # the harness of benchmarks/mutation_run.py


@pytest.mark.slow
def test_mutants_never_escape_as_tracebacks_hangs_or_partial_files(repo_root, tmp_path):
    harness = _harness(repo_root)
    jobs = harness.make_mutants(tmp_path, 80, seed=20261125)
    summary = harness.run(jobs, tmp_path / "out", workers=2, timeout=60.0, max_rss_mb=500.0)
    assert summary["runs"] >= 4 * 80
    shown = [f"{'/'.join(f['problems'])}: {' '.join(f['argv'][:1])} {f['seed']} {f['mutated']} {f['op']}: "
             f"{f['detail'][-400:]} {f['raw'] or ''}" for f in summary["failures"][:10]]
    assert not any(summary["problems"].values()), (summary["problems"], shown)
    # The corpus is not vacuous: every command both refused some mutants and accepted others.
    statuses = summary["statuses"]
    assert statuses.get("validate:1", 0) + statuses.get("validate:2", 0) > 0
    assert statuses.get("info:0", 0) > 0 and statuses.get("info:2", 0) > 0


@pytest.mark.slow
def test_format_1_2_mutants_never_escape_and_the_readers_agree(repo_root, tmp_path):
    """A slice of the format 1.2 run (--surfaces compact,package,lod,mask): compact assets in EXR
    and KTX2, runtime packages, levels of detail, masks and a layered crowd, corrupted by bytes and
    by structure (JSON values, KTX2 headers and key/value data, compact words and ranges, minor
    versions, LOD, mask and layer attributes), through validate, info, decode, export, the Python
    API and view's check: no traceback, internal error, hang, partial or clobbered file, raw line,
    and no file that one reader accepts and another refuses."""
    harness = _harness(repo_root)
    jobs = harness.make_mutants_1_2(tmp_path, 40, seed=20261207, surfaces={"compact", "package", "lod", "mask"})
    summary = harness.run(jobs, tmp_path / "out", workers=2, timeout=60.0, max_rss_mb=500.0)
    shown = [f"{'/'.join(f['problems'])}: {' '.join(f['argv'][:1])} {f['seed']} {f['mutated']} {f['op']}: "
             f"{f['detail'][-400:]} {f['raw'] or ''}" for f in summary["failures"][:10]]
    assert not any(summary["problems"].values()), (summary["problems"], shown)
    assert {j["seed"].split("_")[0] for j in jobs} >= {"compact", "lod", "mask", "layered", "package"}
    statuses = summary["statuses"]
    for command in ("validate", "info", "view"):
        assert statuses.get(f"{command}:0", 0) > 0, (command, statuses)
    assert statuses.get("validate:1", 0) + statuses.get("validate:2", 0) > 0


def test_the_harness_runs_its_own_tree_on_one_thread_per_worker(repo_root):
    """On a fresh machine of many cores (`--jobs 0`: one worker per usable core) each worker imports
    the vbusd of the tree the script is in, and is held to one thread, so that N workers do not start
    N threads per core each; a thread count the caller sets is kept."""
    harness = _harness(repo_root)
    env = harness.worker_environment({"PYTHONPATH": "/elsewhere", "OMP_NUM_THREADS": "3"})
    assert env["PYTHONPATH"].split(":") == [str(repo_root), "/elsewhere"]
    assert env["VBUSD_THREADS"] == "1" and env["OPENBLAS_NUM_THREADS"] == "1" and env["OMP_NUM_THREADS"] == "3"
    harness.REQUIREMENTS["test"] = ("vbusd_no_such_module", "install it")
    try:
        assert harness.missing_requirements(["test"]) == [
            "--surfaces test: vbusd_no_such_module is not installed; install it"]
    finally:
        del harness.REQUIREMENTS["test"]


def test_the_harness_table_is_the_readme_table(repo_root):
    """The Markdown the run writes beside its JSON: runs and exit statuses per command, the problems
    and the accepted-bad split, as benchmarks/README.md shows them."""
    harness = _harness(repo_root)
    summary = {"mutants": 2, "runs": 5, "by_command": {"validate": 3, "info": 2},
               "statuses": {"validate:0": 1, "validate:1": 1, "validate:3": 1, "info:None": 1, "info:2": 1},
               "problems": {"traceback": 1, "internal": 1, "hang": 0, "memory": 0, "partial": 0, "clobbered": 0,
                            "raw": 0, "accepted_bad": 1},
               "accepted_bad": {"validate_missed": 1, "reader_accepted": 0, "expected_refusal": 0},
               "peak_rss_mb": 150.0, "seconds": 1234.5, "workers": 16, "cores": 16}
    lines = harness.markdown_table(summary).splitlines()
    assert lines[2] == "| validate | 3 | 1 | 1 |  | 1 |  |"
    assert lines[3] == "| info | 2 |  |  | 1 |  | 1 |"
    assert lines[7] == "| 1 | 1 | 0 | 0 | 0 | 0 | 0 | 1 (1 / 0 / 0) |"
    assert lines[9] == "2 mutants, 5 runs in 1,234.5 s on 16 workers (16 usable cores); peak worker memory 150.0 MB."


def test_a_metadata_mask_mutant_always_changes_the_metadata(repo_root, tmp_path, monkeypatch):
    """The oracle expects every reader to refuse a metadata_names or metadata_weight mutant; with one
    mask the mutator could "rename" the mask to its own name (masks[-1] is masks[0]) and leave the
    document as it was: a valid copy counted as 6 expected_refusal cases (--seed 6, mutant 280). Each
    edit now changes the document, or declines."""
    import copy
    import random

    harness = _harness(repo_root)
    original = {"masks": [{"name": "upper", "weights": [0.0, 1.0, 1.0]}]}
    edits = []

    def capture(folder, seed, edit, rng):
        document = copy.deepcopy(original)
        edits.append((edit(document), document))
        return None

    monkeypatch.setattr(harness, "_edit_metadata", capture)
    for n in range(400):  # the other kinds of mask mutants edit the layer: a fresh one each time
        (tmp_path / "st.usda").write_text('uniform token[] vb:maskNames = ["upper"]\n', encoding="utf-8")
        harness.m_mask_attr(tmp_path, {}, random.Random(n))
    assert len(edits) > 20
    for result, document in edits:
        assert result is False or document != original, document
