"""Defects the fuzzing of issue 35 found (items 1, 2, 6-11), one test per item.

Each input is a valid asset of the golden fixtures (tests/fixtures/validate/make_fixtures.py: 4
bones, clips 'walk' and 'idle', one 8-point mesh, a crowd of 3) or the runtime package exported
from it, with one thing changed; what each reader must say follows from the change and the spec's
rule, not from running the code: bad input is one line naming the file and the problem (exit 2)
for ``info``, ``view``, ``decode`` and ``export``, and a finding (exit 1) for ``validate``, never
an internal error; every reader refuses what the others refuse.
"""

from __future__ import annotations

import importlib.util
import json
import struct
from pathlib import Path

import pytest

from vbusd.cli import main
from vbusd.format.errors import InputError

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
EXTENSION = "/extensions/VBUSD_virtual_bones"


def _make_fixtures():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MF = _make_fixtures()


@pytest.fixture(params=["glb", "gltf"])
def package(request, tmp_path) -> Path:
    from vbusd.io.gltf_package import export_gltf

    out = tmp_path / "pkg" / f"asset.{request.param}"
    export_gltf(MF.build_asset(), out)
    return out


def _glb_parts(data: bytes) -> tuple:
    """(JSON document, BIN chunk bytes) of a GLB."""
    length = struct.unpack_from("<I", data, 12)[0]
    binary_length = struct.unpack_from("<I", data, 20 + length)[0]
    return json.loads(data[20:20 + length]), data[28 + length:28 + length + binary_length]


def _rewrite(path: Path, change, binary_change=None) -> None:
    """Apply ``change`` to the package's JSON and ``binary_change`` to its texture's bytes (the
    BIN chunk of a .glb, the .bin / .ktx2 files beside a .gltf); see :func:`_texture_bytes`."""
    from vbusd.io.gltf_package import glb_bytes

    if path.suffix == ".gltf":
        document = json.loads(path.read_text(encoding="utf-8"))
        change(document)
        path.write_text(json.dumps(document), encoding="utf-8")
        return
    document, binary = _glb_parts(path.read_bytes())
    change(document)
    binary = bytearray(binary)
    if binary_change is not None:
        binary_change(document, binary)
    path.write_bytes(glb_bytes(document, bytes(binary)))


def _refused_everywhere(path: Path, capsys, code: str, pointer: str = None) -> None:
    """``validate`` finds ``code`` (exit 1) and ``info`` and ``view`` refuse the file in one line
    naming it and the same code (exit 2)."""
    from vbusd.validators.api import validate
    from vbusd.web.server import ViewerServer

    report = validate(path)
    found = [(f["code"], f["location"].get("pointer")) for f in report.to_json()["findings"]]
    assert report.exit_status == 1 and any(c == code and (pointer is None or p == pointer) for c, p in found), found
    assert main(["validate", "-q", str(path)]) == 1
    capsys.readouterr()
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"vbusd: {path}") and f": {code}: " in err[0], err
    with pytest.raises(InputError) as raised:
        ViewerServer(path)
    assert raised.value.code == code


# ------------------------------------------------------------------------------------------------
# Item 2: "animations": 5 in the root extension
# ------------------------------------------------------------------------------------------------


def test_item2_animations_that_are_no_array_are_a_finding_not_an_internal_error(package, capsys):
    """The schema makes ``animations`` an array; validate said ``command.internal`` (exit 3)."""
    _rewrite(package, lambda d: d["extensions"]["VBUSD_virtual_bones"].__setitem__("animations", 5))
    _refused_everywhere(package, capsys, "package.extension", f"{EXTENSION}/animations")
