"""Bad glTF input: one line with the JSON pointer (or byte offset) and a stable code, no output.

Each fixture in tests/fixtures/gltf/bad/ is the valid bar asset with one mutation, made by
make_fixtures.py; the table BAD there lists the code and location every one must give. The
problems are those Khronos' glTF-Validator reports as errors (ACCESSOR_JOINTS_INDEX_OOB,
ACCESSOR_WEIGHTS_NEGATIVE, ACCESSOR_WEIGHTS_NON_NORMALIZED, INVALID_IBM_ACCESSOR_COUNT,
ANIMATION_SAMPLER_INPUT_ACCESSOR_NON_INCREASING, ANIMATION_SAMPLER_OUTPUT_ACCESSOR_INVALID_COUNT,
NODE_LOOP, NODE_PARENT_OVERRIDE, BUFFER_VIEW_TOO_LONG, ACCESSOR_TOO_LONG, ...) plus the safety
rules of spec/gltf-conversion.md (URIs, limits).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from vbusd.converters import gltf
from vbusd.format.errors import InputError, VbusdError

from tests.helpers import scripts

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
BAD_DIR = FIXTURES / "bad"


BAD = scripts.load("tests/fixtures/gltf/make_fixtures.py").BAD


def _file(name: str) -> Path:
    (path,) = BAD_DIR.glob(f"{name}.gl*")
    return path


def test_every_bad_fixture_is_listed():
    assert {p.stem for p in BAD_DIR.iterdir()} == set(BAD)
    assert len(BAD) >= 20


STRICT_WEIGHTS = {"weights_sum", "weights_zero"}
"""Weights that do not sum to one are renormalized by default (issue 12); --strict-weights refuses
them as glTF-Validator reports them (tests/test_real_characters_gltf.py checks the default)."""


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_input_code_and_location(name):
    from vbusd.format.model import ReadOptions

    code, location = BAD[name]
    with pytest.raises(VbusdError) as info:     # InputError, or UnsupportedError for extensions
        gltf.read(_file(name), ReadOptions(strict_weights=name in STRICT_WEIGHTS))
    error = info.value
    assert (error.code, error.location) == (code, location)
    assert error.file == str(_file(name))
    line = str(error)
    assert "\n" not in line and line.startswith(f"{error.file}: {location}: {code}: ")


def test_the_base_of_every_mutation_is_valid():
    # Guards the fixtures: the bad files differ from bar.gltf only by their mutation.
    assert gltf.read(FIXTURES / "bar.gltf").animations


@pytest.mark.parametrize("text,code,location", [
    (b"not json at all", "gltf.json", "byte 0"),
    (b'{"asset": {"version": "2.0"},}', "gltf.json", "byte 29"),
    (b'{"nodes": []}', "gltf.asset.version", "/asset"),
    (b'{"asset": ' + b"[" * 200000 + b"]" * 200000 + b"}", "gltf.json", None),
    (b'{"asset": {}}', "gltf.asset.version", "/asset"),
    (b'{"asset": {"version": "2.0"}, "nodes": 3}', "gltf.json", "/nodes"),
    (b'{"asset": {"version": "two"}}', "gltf.asset.version", "/asset/version"),
    (b'{"asset": {"version": "2.0", "minVersion": "2.1"}}', "gltf.asset.version", "/asset/minVersion"),
    (b'{"asset": {"version": "2.0"}, "extensionsRequired": ["KHR_draco_mesh_compression"]}',
     "gltf.extension.required", "/extensionsRequired/0"),
    (b'glTF\x01\x00\x00\x00\x14\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00', "gltf.asset.version",
     "byte 4"),
    (b'{"asset": {"version": "2.0"}}', "gltf.noSkin", "/skins"),
])
def test_container_errors(tmp_path, text, code, location):
    path = tmp_path / "x.gltf"
    path.write_bytes(text)
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    assert info.value.code == code
    assert info.value.location == location


def test_missing_external_buffer(tmp_path):
    text = (FIXTURES / "bar_external.gltf").read_text()
    (tmp_path / "bar.gltf").write_text(text)
    with pytest.raises(InputError) as info:
        gltf.read(tmp_path / "bar.gltf")
    assert (info.value.code, info.value.location) == ("gltf.buffer.missing", "/buffers/0/uri")


def test_cli_convert_reports_one_line_and_writes_nothing(tmp_path, capsys):
    """Through `vbusd convert` (a subprocess run is in tests/test_gltf_cli.py)."""
    from vbusd import cli

    out = tmp_path / "out.usda"
    status = cli.main(["convert", str(_file("weights_sum")), "-o", str(out), "--strict-weights"])
    captured = capsys.readouterr()
    assert status == 2
    assert "gltf.skin.weights" in captured.err
    assert "Traceback" not in captured.err
    assert list(tmp_path.iterdir()) == []
