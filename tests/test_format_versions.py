"""One upgrade path for both sources of truth (issue 10 item 3): an animation prim's USD attributes
and the texture's layout metadata are read into the same versioned dict and upgraded by the same
registered functions; a newer major version is refused with one line by every command."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from vbusd.cli import main
from vbusd.format import versioning


VALID = Path(__file__).parent / "fixtures" / "validate" / "valid" / "crossMatrix_float16"


@pytest.fixture
def asset(tmp_path):
    # A hand-made 1.0 asset: the golden fixture's generator writes format 1.0 (no minor version).
    shutil.copytree(VALID, tmp_path / "a")
    path = tmp_path / "a" / "asset.usda"
    assert "vb:formatVersion = 1" in path.read_text() and "formatMinorVersion" not in path.read_text()
    return path


def test_usd_attributes_and_metadata_go_through_the_same_registered_upgrade(asset, monkeypatch):
    import vbusd

    seen = []
    original = versioning.UPGRADES[versioning.Version(1, 0)]

    def spy(document):
        # Layout metadata names its generator; the prim's attributes read into the same keys do not.
        seen.append("texture" if "generator" in document else "usd")
        return original(document)

    monkeypatch.setitem(versioning.UPGRADES, versioning.Version(1, 0), spy)
    loaded = vbusd.read_asset(asset)
    assert loaded.animations[0].layout.bone_count > 0
    # Both the prim's attributes and the texture's metadata were upgraded from 1.0 by the one function.
    assert "usd" in seen and "texture" in seen, seen


@pytest.mark.parametrize("command", ["info", "decode"])
def test_a_newer_major_version_in_usd_is_one_line(asset, tmp_path, capsys, command):
    asset.write_text(asset.read_text().replace("vb:formatVersion = 1", "vb:formatVersion = 2"))
    args = [command, str(asset)] + (["-o", str(tmp_path / "cache.usda")] if command == "decode" else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ".vb:formatVersion: format.version: " in err[0] and "2" in err[0], err
    assert not (tmp_path / "cache.usda").exists()


def test_validate_reports_a_newer_major_version_as_one_finding(asset, capsys):
    asset.write_text(asset.read_text().replace("vb:formatVersion = 1", "vb:formatVersion = 2"))
    assert main(["validate", str(asset)]) == 1
    out = capsys.readouterr().out
    assert "format.version" in out and "INVALID: 1 error(s)" in out


def test_a_newer_major_version_in_the_texture_metadata_is_one_line(asset, capsys):
    # Embedded metadata and sidecar both say 2.0 (rewritten with OpenEXR itself).
    import json

    import OpenEXR

    exr = next(asset.parent.glob("*.exr"))
    source = OpenEXR.File(str(exr))
    header, channels = dict(source.header()), source.channels()
    meta = json.loads(header["vbusd.layout"])
    meta["formatVersion"] = 2
    header["vbusd.layout"] = json.dumps(meta)
    OpenEXR.File(header, channels).write(str(exr))
    exr.with_name(exr.name + ".json").write_text(json.dumps(meta))
    assert main(["info", str(exr)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"vbusd: {exr}: header/vbusd.layout/formatVersion: format.version: formatVersion 2 is newer "
                   f"than this reader (version {versioning.CURRENT}); upgrade vbusd to read it"]


def test_a_prim_may_declare_a_higher_minor_version_than_its_metadata_not_a_lower_one():
    """Spec 16: the prim declares what the whole asset needs (levels of detail make it 1.2 with its
    metadata at 1.0 or 1.1); a prim below its metadata is too old for what it mirrors, and a version
    newer than the reader's is reported. The rule every reader and validate share (compare_declared)."""
    from vbusd.format.declared import Declared, compare_declared
    from vbusd.format.versioning import FORMAT_MINOR_VERSION

    def declared(minor, rows=8):
        return Declared("metadata", {"formatVersion": 1, "formatMinorVersion": minor, "rowCount": rows},
                        locate=lambda key: f"/{key}")

    def codes(prim, metadata):
        return [(f.code, f.location) for f in compare_declared(declared(prim), declared(metadata),
                                                                "metadata.mismatch", "the prim")]

    assert codes(2, 0) == codes(2, 1) == codes(FORMAT_MINOR_VERSION, 2) == codes(2, 2) == []
    assert codes(1, 2) == [("metadata.mismatch", "/formatMinorVersion")]
    assert codes(2, FORMAT_MINOR_VERSION + 1) == [("metadata.mismatch", "/formatMinorVersion")]
    assert codes(FORMAT_MINOR_VERSION + 1, 2) == [("metadata.mismatch", "/formatMinorVersion")]
    assert compare_declared(declared(2), declared(2, rows=9), "metadata.mismatch", "the prim")[0].location == "/rowCount"
