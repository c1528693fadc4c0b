"""Golden fixtures of ``vbusd validate``: every code has an invalid asset beside its expected report.

The expected findings (code and location, never message text) were written by
tests/fixtures/validate/make_fixtures.py from the mutation it applied, not by running the
validator. Locations in expected.json may omit keys; only the keys given are compared.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vbusd.format import codes
from vbusd.validators.api import validate

from tests.helpers import scripts

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
INVALID = sorted(p for p in FIXTURES.iterdir() if p.is_dir() and p.name != "valid" and
                 (p / "expected.json").exists())
VALID = sorted(p for p in (FIXTURES / "valid").iterdir() if (p / "expected.json").exists())
NO_FIXTURE = {"asset.internal": "only a validator bug produces it; tests/test_validate_api.py forces one"}


def _load(folder: Path):
    return json.loads((folder / "expected.json").read_text(encoding="utf-8"))


def _match(expected: list, actual: list) -> tuple[list, list]:
    """Pair expected with actual findings; return (missing, unexpected)."""
    remaining = list(actual)
    missing = []
    for item in expected:
        for candidate in remaining:
            if candidate["code"] == item["code"] and all(
                    candidate["location"].get(k) == v for k, v in item["location"].items()):
                remaining.remove(candidate)
                break
        else:
            missing.append(item)
    return missing, remaining


def _check(folder: Path):
    expected = _load(folder)
    report = validate(folder / expected["asset"])
    actual = [{"code": f["code"], "location": f["location"]} for f in report.to_json()["findings"]]
    missing, unexpected = _match(expected["findings"], actual)
    assert not missing and not unexpected, (
        f"{folder.name}: missing {json.dumps(missing)}\nunexpected {json.dumps(unexpected)}")
    return report


def test_every_code_has_a_fixture():
    named = {p.name for p in INVALID}
    lacking = set(codes.FINDINGS) - named - set(NO_FIXTURE)
    assert not lacking, f"codes without an invalid fixture: {sorted(lacking)}"
    assert named <= set(codes.REGISTRY), f"fixtures named after unknown codes: {sorted(named - set(codes.REGISTRY))}"


@pytest.mark.slow
@pytest.mark.parametrize("folder", INVALID, ids=[p.name for p in INVALID])
def test_invalid_fixture_reports_its_code(folder):
    report = _check(folder)
    assert folder.name in {f.code for f in report.findings}
    severity = codes.get(folder.name).severity
    assert report.exit_status == (1 if any(f.severity.value == "error" for f in report.findings) else 0)
    if severity is codes.Severity.ERROR:
        assert report.exit_status == 1


@pytest.mark.parametrize("folder", VALID, ids=[p.name for p in VALID])
def test_valid_fixture_has_no_error(folder):
    report = _check(folder)
    assert report.error_count == 0 and report.exit_status == 0
    assert report.counts["warning"] == 0


@pytest.mark.slow
def test_committed_fixtures_are_what_the_generator_writes(tmp_path):
    """The goldens are made by make_fixtures.py, not edited by hand: regenerate and compare."""
    module = scripts.load("tests/fixtures/validate/make_fixtures.py")
    module.generate(tmp_path)
    committed = sorted(p.relative_to(FIXTURES) for p in FIXTURES.rglob("expected.json"))
    fresh = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("expected.json"))
    assert committed == fresh
    for relative in committed:
        assert json.loads((tmp_path / relative).read_text(encoding="utf-8")) == _load(FIXTURES / relative.parent), relative
        files = sorted(p.name for p in (FIXTURES / relative.parent).iterdir())
        assert files == sorted(p.name for p in (tmp_path / relative.parent).iterdir()), relative
