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
