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

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from vbusd.converters import gltf
from vbusd.errors import InputError, VbusdError

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
BAD_DIR = FIXTURES / "bad"


def _bad_table() -> dict:
    spec = importlib.util.spec_from_file_location("gltf_make_fixtures", FIXTURES / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.BAD


BAD = _bad_table()


def _file(name: str) -> Path:
    (path,) = BAD_DIR.glob(f"{name}.gl*")
    return path


def test_every_bad_fixture_is_listed():
    assert {p.stem for p in BAD_DIR.iterdir()} == set(BAD)
    assert len(BAD) >= 20


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_input_code_and_location(name):
    code, location = BAD[name]
    with pytest.raises(VbusdError) as info:     # InputError, or UnsupportedError for extensions
        gltf.read(_file(name))
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


def test_one_line_no_traceback_in_a_subprocess(tmp_path):
    """A user process sees exactly the one-line message (the CLI prints str(error))."""
    script = ("import sys\nfrom vbusd.converters import gltf\nfrom vbusd.errors import VbusdError\n"
              "try:\n    gltf.read(sys.argv[1])\nexcept VbusdError as e:\n"
              "    print(e, file=sys.stderr); sys.exit(e.exit_status)\n")
    result = subprocess.run([sys.executable, "-c", script, str(_file("node_loop"))],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "gltf.node.loop" in result.stderr and "Traceback" not in result.stderr


def test_cli_convert_reports_one_line_and_writes_nothing(tmp_path, capsys):
    """Through `vbusd convert` once it exists (another helper's command)."""
    from vbusd import cli

    if importlib.util.find_spec("vbusd.commands.convert") is None:
        pytest.skip("vbusd convert not available yet")
    out = tmp_path / "out.usda"
    status = cli.main(["convert", str(_file("weights_sum")), "-o", str(out)])
    captured = capsys.readouterr()
    assert status == 2
    assert "gltf.skin.weights" in captured.err
    assert "Traceback" not in captured.err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("mutate,code,location", [
    (lambda d: d["meshes"][0]["primitives"][0].update(attributes={}), "gltf.mesh.attribute",
     "/meshes/0/primitives/0/attributes"),
    (lambda d: d["animations"][0]["samplers"].__setitem__(0, None), "gltf.json",
     "/animations/0/samplers/0"),
    (lambda d: d["animations"][0]["channels"][0].update(target=3), "gltf.json",
     "/animations/0/channels/0/target"),
    (lambda d: d["nodes"][2].update(rotation=[0, 0, 1]), "gltf.node.transform", "/nodes/2/rotation"),
    (lambda d: d["accessors"][0].update(count=-6), "gltf.value", "/accessors/0/count"),
])
def test_values_of_the_wrong_kind(tmp_path, mutate, code, location):
    """Found by tests/test_gltf_fuzz.py's harness: pygltflib keeps such values as they are."""
    import json

    doc = json.loads((FIXTURES / "bar.gltf").read_text())
    mutate(doc)
    path = tmp_path / "x.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    assert (info.value.code, info.value.location) == (code, location)
