"""Acceptance bounds of the accuracy table (benchmarks/accuracy.py) on the stadium-crowd sample.

The reference is exact skinning in float64 computed by the benchmark itself from the generator's
matrices (LBS; DQS for dualQuat), independently of vbusd's decoder. Bounds, at row times, as a
fraction of the rest mesh's bounding-box diagonal:

* float32, every encoding: at most 1e-6 (against its own skinning method);
* float16 crossMatrix (the talk's choice): at most 2e-3; the other encodings too.

At mid-row times the same bounds hold for the texel format alone (against the spec's row blend of
the exact float64 matrices). The table in benchmarks/README.md must be the script's current output.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import accuracy as accuracy_harness

pytestmark = pytest.mark.slow  # seconds each: outside the fast tier (-m unit)

REPO = Path(__file__).resolve().parents[1]
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")


@pytest.fixture(scope="module")
def accuracy():
    return accuracy_harness  # the harness of benchmarks/accuracy.py


@pytest.fixture(scope="module")
def results(accuracy):
    return {(r.encoding, r.texel_format): r for r in accuracy.measure_all()}


def test_table_covers_every_encoding_and_texel_format(results):
    assert set(results) == {(e, f) for e in ENCODINGS for f in ("float16", "float32", "unorm16")}
    for (encoding, texel_format), r in results.items():
        assert (r.width, r.height) == (64, 512)
        assert r.used_width == 18 * (3 if "Matrix" in encoding else 2)
        assert r.texel_bytes == 64 * 512 * 4 * (4 if texel_format == "float32" else 2)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_float32_is_exact_to_one_millionth_of_the_diagonal(results, encoding):
    r = results[(encoding, "float32")]
    assert r.method_row_fraction <= 1e-6
    if encoding != "dualQuat":
        assert r.row_fraction <= 1e-6


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_float16_within_two_thousandths_of_the_diagonal(results, encoding):
    assert results[(encoding, "float16")].method_row_fraction <= 2e-3


def test_float16_cross_matrix_is_the_talks_precision(results):
    r = results[("crossMatrix", "float16")]
    assert r.row_fraction <= 2e-3
    assert r.row_fraction > 1e-5  # half floats do round: the check is not vacuous


def test_mid_row_error_shows_interpolation(results):
    r = results[("crossMatrix", "float32")]
    # Between rows the format blends linearly, the generator moves along arcs: a visible but small
    # difference, far larger than float32 rounding.
    assert 100 * r.row_fraction < r.mid_fraction < 2e-3


def test_dqs_reference_equals_lbs_for_single_influences(accuracy):
    # The two oracles (the benchmark's DQS, the generator's LBS) agree where DQS and LBS must.
    gen = accuracy.load_generator()
    rig = gen.build_rig()
    single = dataclasses.replace(rig, bone_indices=rig.bone_indices[:, :1],
                                 bone_weights=np.ones((rig.points.shape[0], 1)))
    matrices = gen.skinning_matrices(np.linspace(0.0, 10.0, 7))
    dqs = accuracy.exact_dqs(rig.points, single.bone_indices, single.bone_weights, matrices)
    np.testing.assert_allclose(dqs, gen.skin(single, matrices), atol=1e-12)
    assert np.abs(dqs - dqs[0]).max() > 0.3  # the poses differ: not a comparison of rest meshes


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_texel_format_error_between_rows_keeps_the_bounds(results, encoding):
    # Mid-row, with the interpolation method taken out: what the stored precision costs there.
    assert results[(encoding, "float32")].mid_format_fraction <= 1e-6
    assert results[(encoding, "float16")].mid_format_fraction <= 2e-3
    # Not vacuous: half floats round between rows too, and float32 is far finer.
    assert results[(encoding, "float16")].mid_format_fraction > 100 * results[(encoding, "float32")].mid_format_fraction


def test_readme_table_is_the_scripts_output(accuracy, results):
    # Every row of the script's markdown must be in benchmarks/README.md. Numbers are compared to
    # 1 % (they are printed to 3 significant digits; another BLAS may flip a last digit), text exactly.
    readme = (REPO / "benchmarks" / "README.md").read_text(encoding="utf-8")
    readme_rows = {tuple(c.strip() for c in line.strip("|").split("|"))[:2]: line
                   for line in readme.splitlines() if line.startswith("| ") and line.count("|") > 8}
    ordered = [results[(e, f)] for e in ENCODINGS for f in accuracy.TEXEL_FORMATS]
    fresh = [line for line in accuracy.markdown(ordered).splitlines() if line.startswith("| ")][1:]
    assert len(fresh) == 12
    hint = "benchmarks/README.md is stale: paste `python benchmarks/accuracy.py --format markdown`"
    assert [c.strip() for c in readme.split("| encoding |", 1)[1].split("\n", 1)[0].strip("|").split("|")] \
        == list(accuracy.HEADERS[1:]), hint
    for line in fresh:
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert tuple(cells[:2]) in readme_rows, f"{hint}: no row {cells[:2]}"
        theirs = [c.strip() for c in readme_rows[tuple(cells[:2])].strip("|").split("|")]
        assert len(theirs) == len(cells), f"{hint}: columns of {cells[:2]}"
        for ours, old in zip(cells[2:], theirs[2:]):
            try:
                assert float(old.replace(",", "")) == pytest.approx(float(ours.replace(",", "")), rel=0.01), \
                    f"{hint}: {cells[:2]} has {old}, a fresh run gives {ours}"
            except ValueError:  # text cells ("64x512 (54 used)")
                assert old == ours, f"{hint}: {cells[:2]} has {old!r}, a fresh run gives {ours!r}"
