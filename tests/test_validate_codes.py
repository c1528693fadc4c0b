"""The code registry, spec/ISSUES.md generated from it, and the JSON report against its schema."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest

from vbusd.format import codes
from vbusd.validators.api import validate
from vbusd.format.diagnostics import FileLocation, Finding, JsonPointer, TexelAddress, UsdSite, finding
from vbusd.validators.report import build_report

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures" / "validate"
SPEC = ROOT / "spec"


def test_issues_md_is_generated_from_the_registry():
    committed = (SPEC / "ISSUES.md").read_text(encoding="utf-8")
    assert committed == codes.markdown(), (
        "spec/ISSUES.md is stale: run `python -m vbusd.format.codes --markdown > spec/ISSUES.md`")


@pytest.mark.cli
def test_generator_command_prints_the_same_text():
    result = subprocess.run([sys.executable, "-m", "vbusd.format.codes", "--markdown"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    assert result.stdout == (SPEC / "ISSUES.md").read_text(encoding="utf-8")


def test_codes_are_stable_dotted_names_with_known_severities_and_spec_anchors():
    anchors = set(re.findall(r'<a id="([^"]+)">', (SPEC / "virtual-bones.md").read_text(encoding="utf-8")))
    for code in codes.REGISTRY.values():
        assert re.fullmatch(r"[a-z][A-Za-z0-9]*(\.[a-z][A-Za-z0-9]*)+", code.code), code.code
        assert code.severity in set(codes.Severity)
        assert code.location in {"usd", "json", "texel", "file", "option"}
        document, _, anchor = code.spec.partition("#")
        if document == "virtual-bones.md":
            assert anchor in anchors, f"{code.code}: spec anchor #{anchor} not in spec/virtual-bones.md"
        else:
            assert document in {"validation.md", "gltf-conversion.md", "usd-conversion.md", "ktx2.md",
                                "runtime-package.md", "batch.md"}, code.code
            text = (SPEC / document).read_text(encoding="utf-8")
            assert f'<a id="{anchor}">' in text, f"{code.code}: no anchor #{anchor} in spec/{document}"


def test_code_filters_match_whole_dotted_segments():
    assert codes.matches("texture.padding.nonZero", ["texture"])
    assert codes.matches("texture.padding.nonZero", ["texture.padding"])
    assert codes.matches("texture.nonFinite", ["texture.nonFinite"])
    assert not codes.matches("texture.nonFinite", ["texture.non"])
    assert not codes.matches("textures.x", ["texture"])


def test_finding_with_an_unregistered_code_is_a_programming_error():
    with pytest.raises(KeyError):
        finding("no.such.code", "x", FileLocation("f"))


def _schema():
    schema = json.loads((ROOT / "vbusd" / "schema" / "validation-report.schema.json").read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_json_report_of_fixtures_matches_its_schema():
    validator = _schema()
    kinds = set()
    for name in ("binding.indices.range", "texture.nonFinite", "metadata.schema", "metadata.json",
                 "valid/quatTranslation_unorm16"):
        document = validate(FIXTURES / name / "asset.usda").to_json()
        errors = list(validator.iter_errors(document))
        assert not errors, [e.message for e in errors]
        kinds |= {f["location"]["kind"] for f in document["findings"]}
    assert kinds == {"usd", "texel", "json", "file"}


def test_schema_rejects_a_report_without_counts():
    document = validate(FIXTURES / "valid" / "crossMatrix_float16" / "asset.usda").to_json()
    del document["counts"]
    assert list(_schema().iter_errors(document))


def test_counts_truncation_and_filters():
    findings = [
        finding("texture.padding.fraction", "info", UsdSite("/A", "vb:texture")),
        finding("texture.nonFinite", "nan", TexelAddress("t.exr", 1, 2, 0, 2, 1)),
        finding("binding.weights.sum", "sum", UsdSite("/M", "primvars:vb:boneWeights")),
        finding("encoding.affine.scale", "hint", TexelAddress("t.exr", 0, 0, 0, 0)),
        finding("metadata.schema", "schema", JsonPointer("t.exr.json", "/boneCount")),
    ]
    report = build_report("a.usda", findings, max_issues=2)
    assert report.counts == {"error": 3, "warning": 0, "info": 1, "hint": 1}
    assert report.truncated and len(report.findings) == 2
    assert [f.code for f in report.findings] == ["texture.nonFinite", "binding.weights.sum"]
    assert report.exit_status == 1
    only = build_report("a.usda", findings, only=["texture"])
    assert {f.code for f in only.findings} == {"texture.padding.fraction", "texture.nonFinite"}
    assert only.counts["error"] == 1 and not only.truncated
    ignored = build_report("a.usda", findings, ignore=["texture", "binding", "metadata"])
    assert ignored.exit_status == 0 and ignored.counts["hint"] == 1


def test_text_report_groups_by_severity_with_locations():
    findings = [finding("texture.padding.fraction", "25% padding", UsdSite("/A", "vb:texture")),
                Finding("texture.nonFinite", codes.Severity.ERROR, "a NaN", TexelAddress("t.exr", 3, 5, 1, 2, 0))]
    text = build_report("a.usda", findings).to_text()
    assert text.index("errors (1):") < text.index("texture.nonFinite") < text.index("info (1):")
    assert "t.exr[row 3, column 5, bone 1, texel 2, channel R]" in text
    assert "/A.vb:texture" in text
    assert text.rstrip().endswith("INVALID: 1 error(s), 0 warning(s), 1 info, 0 hint(s)")


# Dotted names in the validators that are not validation codes: the codes of exceptions raised
# before any report exists (vbusd.format.errors, exit 2), and format / resource names.
NOT_CODES = {"vbusd.layout", "vbusd.schema", "vbusd.validationReport", "vbusd.virtualBones"}
"""Dotted strings in the sources that are names, not codes (metadata keys, schema ids)."""

ERROR_TYPES = {"VbusdError", "InputError", "OptionsError", "UnsupportedError", "VersionError"}
CODE_TAKING_CALLS = {"finding", "report", "error", "fail", "_bad"}


def _sources() -> list:
    return sorted(p for folder in ("vbusd", "converters", "validators", "dcc") for p in (ROOT / folder).rglob("*.py"))


@pytest.mark.slow
def test_every_code_string_in_the_sources_is_registered():
    """Static scan of every module: a code given to an error, a finding or a reader's report, a
    class's default code, and any string of a registered area's dotted form, is in the registry.

    One registry for errors and findings alike (issue 10): a code typed anywhere but missing from
    the registry would print an unlisted code, or surface as ``asset.internal``."""
    import ast

    # Underscores too: a snake_case code would break the registry's naming rule unnoticed.
    pattern = re.compile(r"[a-z][A-Za-z0-9_]*(\.[a-zA-Z_][A-Za-z0-9_]*)+")
    areas = {code.split(".")[0] for code in codes.REGISTRY}
    unregistered = []
    for source in _sources():
        name = source.relative_to(ROOT)
        for node in ast.walk(ast.parse(source.read_text(encoding="utf-8"))):
            candidates = []
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and pattern.fullmatch(node.value) \
                    and node.value.split(".")[0] in areas:
                candidates.append(node.value)
            if isinstance(node, ast.keyword) and node.arg == "code" and isinstance(node.value, ast.Constant):
                candidates.append(node.value.value)
            if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "default_code" for t in node.targets):
                candidates.append(node.value.value)
            if isinstance(node, ast.Call):
                func = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
                if func in {"finding", "report"} and node.args and isinstance(node.args[0], ast.Constant):
                    candidates.append(node.args[0].value)
            for value in candidates:
                if value not in codes.REGISTRY and value not in NOT_CODES:
                    unregistered.append(f"{name}:{node.lineno}: {value}")
    assert not unregistered, unregistered


@pytest.mark.slow
def test_every_error_names_its_code():
    """Every error vbusd raises for input names a registered code explicitly (the class defaults
    exist for third-party converters); option errors may use ``options.invalid``."""
    import ast

    missing = []
    for source in _sources():
        for node in ast.walk(ast.parse(source.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ERROR_TYPES - {"OptionsError"} \
                    and not any(k.arg == "code" for k in node.keywords):
                missing.append(f"{source.relative_to(ROOT)}:{node.lineno}: {node.func.id} without code=")
    assert not missing, missing


@pytest.mark.slow
def test_findings_carry_the_location_kind_their_code_registers():
    """In a USD asset every finding's location is of the kind ISSUES.md lists for its code; and the
    JSON report of every golden fixture follows the report schema."""
    wrong = []
    schema = _schema()
    for asset in sorted(FIXTURES.rglob("asset.usda")):
        report = validate(asset)
        errors = [e.message for e in schema.iter_errors(json.loads(report.to_json_text()))]
        assert not errors, (asset.parent.name, errors)
        for item in report.findings:
            if item.location.kind != codes.get(item.code).location:
                wrong.append(f"{asset.parent.name}: {item.code} at {item.location.kind}, registered "
                             f"{codes.get(item.code).location}")
    assert not wrong, wrong
