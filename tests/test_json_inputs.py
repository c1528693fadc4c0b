"""Every JSON input vbusd reads: a value of the wrong JSON kind (``null`` above all) is a finding or
a one-line error with a registered code and a place, never "valid" and never "absent".

The inputs: the layout metadata (the sidecar ``<texture>.json`` and the copy embedded in an EXR,
PNG or KTX2 texture), the glTF JSON of a source (its ``extensions`` and ``extras``), and batch
manifests. The runtime package's ``VBUSD_virtual_bones`` extension is in
tests/test_package_validate.py. Expected codes and locations come from the mutation each test
applies (which file, which key it broke), as in tests/fixtures/validate/make_fixtures.py, whose
valid base asset these tests start from.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vbusd.cli import main
from vbusd.format.errors import InputError, OptionsError
from vbusd.validators.api import validate

from tests.helpers import scripts

FIXTURES = Path(__file__).parent / "fixtures"
NOT_OBJECTS = ["null", "[]", "3", '"text"', "true"]
"""JSON documents that are valid JSON but not objects."""


MF = scripts.load("tests/fixtures/validate/make_fixtures.py")
CONTAINERS = {"exr": ("crossMatrix", "float16"), "png": ("quatTranslation", "unorm16"),
              "ktx2": ("dualQuat", "float32")}
EMBEDDED_AT = {"exr": "header/vbusd.layout", "png": "iTXt vbusd.layout", "ktx2": "kvd/vbusd.layout"}
"""Where each container holds its metadata (spec/virtual-bones.md, spec/ktx2.md)."""


def _asset(folder: Path, container: str) -> Path:
    """The valid base asset of the golden fixtures, its texture in ``container``; returns the texture."""
    from vbusd.io.usd import write_asset

    encoding, texel_format = CONTAINERS[container]
    folder.mkdir(parents=True)
    write_asset(MF.build_asset(encoding, texel_format), folder / "asset.usda",
                texture_container="ktx2" if container == "ktx2" else None)
    texture = folder / f"asset.Animation.{container}"
    assert texture.is_file() and Path(str(texture) + ".json").is_file()
    return texture


def _embed(texture: Path, container: str, text: str) -> None:
    """Rewrite ``texture`` with the same texels and ``text`` as its embedded metadata."""
    from vbusd.io import exr, ktx2, png
    from vbusd.io.textures import read_texture

    texels = read_texture(texture, check_sidecar=False).texels
    if container == "exr":
        exr.write_exr(texture, texels, text, compression="zip")
    elif container == "png":
        texture.write_bytes(png.png_bytes(texels, text))
    else:
        texture.write_bytes(ktx2.ktx2_bytes(texels, text))


def _findings(report) -> list:
    return [(f["code"], f["location"]) for f in report.to_json()["findings"]]


def _only_the_broken_copy(report, file: str, part: str = "/") -> None:
    """One ``metadata.json`` error on ``file`` (at ``part``) and otherwise only what the valid asset has."""
    found = _findings(report)
    assert ("metadata.json", {"kind": "file", "file": file, "part": part}) in [
        (code, {k: v for k, v in where.items() if k in ("kind", "file", "part")}) for code, where in found], found
    assert {code for code, _ in found} <= {"metadata.json", "texture.padding.fraction"}, found
    assert report.exit_status == 1 and not report.valid


@pytest.mark.parametrize("text", NOT_OBJECTS)
def test_a_sidecar_that_is_not_an_object_is_a_finding(tmp_path, text):
    texture = _asset(tmp_path / "a", "exr")
    sidecar = Path(str(texture) + ".json")
    sidecar.write_text(text, encoding="utf-8")
    _only_the_broken_copy(validate(tmp_path / "a" / "asset.usda"), sidecar.name)
    # The texture given on its own: the sidecar beside it is a finding too.
    _only_the_broken_copy(validate(texture), str(sidecar))


@pytest.mark.slow
@pytest.mark.parametrize("container", sorted(CONTAINERS))
@pytest.mark.parametrize("place", ["sidecar", "embedded"])
@pytest.mark.parametrize("text", ["null", "[1, 2]"])
def test_null_or_a_list_as_metadata_is_a_finding_in_every_container(tmp_path, container, place, text):
    texture = _asset(tmp_path / "a", container)
    if place == "sidecar":
        broken, part = Path(str(texture) + ".json"), "/"
        broken.write_text(text, encoding="utf-8")
    else:
        broken, part = texture, EMBEDDED_AT[container]
        _embed(texture, container, text)
    _only_the_broken_copy(validate(tmp_path / "a" / "asset.usda"), broken.name, part)


@pytest.mark.parametrize("place", ["sidecar", "embedded"])
def test_strict_readers_refuse_a_null_copy(tmp_path, place):
    """read_texture (behind info, decode, read_asset) read a null sidecar as "no sidecar" before."""
    from vbusd.io.textures import read_texture

    texture = _asset(tmp_path / "a", "exr")
    broken = Path(str(texture) + ".json") if place == "sidecar" else texture
    if place == "sidecar":
        broken.write_text("null", encoding="utf-8")
    else:
        _embed(texture, "exr", "null")
    with pytest.raises(InputError) as caught:
        read_texture(texture)
    assert caught.value.code == "metadata.json" and caught.value.file == str(broken)


def test_the_command_says_invalid_with_exit_1(tmp_path, capsys):
    texture = _asset(tmp_path / "a", "exr")
    Path(str(texture) + ".json").write_text("null", encoding="utf-8")
    assert main(["validate", str(tmp_path / "a" / "asset.usda"), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert not report["valid"] and "metadata.json" in [f["code"] for f in report["findings"]]
    # A sidecar given on its own that is not an object cannot be read at all: exit 2, one line.
    assert main(["validate", str(texture) + ".json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metadata.json" in err[0] and "JSON null" in err[0]


# --------------------------------------------------------------------------------------------
# glTF sources: the document, extensions and extras
# --------------------------------------------------------------------------------------------


def _convert_gltf(tmp_path, change):
    from vbusd.jobs.conversion import ConvertOptions, convert

    document = json.loads((FIXTURES / "gltf" / "bar.gltf").read_text(encoding="utf-8"))
    document = change(document) or document
    source = tmp_path / "bar.gltf"
    tmp_path.mkdir(parents=True, exist_ok=True)
    source.write_text(json.dumps(document), encoding="utf-8")
    return convert(source, tmp_path / "out" / "bar.usda", ConvertOptions(check_rows=0, force=True))


def _set(pointer: str, value):
    def change(document):
        *parents, key = pointer.strip("/").split("/")
        target = document
        for part in parents:
            target = target[int(part)] if isinstance(target, list) else target[part]
        target[key] = value
    return change


@pytest.mark.parametrize("pointer", ["/extensions", "/nodes/0/extensions", "/meshes/0/primitives/0/extensions",
                                     "/skins/0/extensions", "/accessors/0/extensions", "/asset/extensions"])
@pytest.mark.parametrize("value", [None, [], 3, "text"])
def test_gltf_extensions_that_are_not_objects_are_refused_at_their_place(tmp_path, pointer, value):
    with pytest.raises(InputError) as caught:
        _convert_gltf(tmp_path, _set(pointer, value))
    assert (caught.value.code, caught.value.location) == ("gltf.value", pointer)


def test_a_gltf_extension_whose_body_is_null_is_refused(tmp_path):
    with pytest.raises(InputError) as caught:
        _convert_gltf(tmp_path, _set("/nodes/0/extensions", {"EXT_example": None}))
    assert (caught.value.code, caught.value.location) == ("gltf.value", "/nodes/0/extensions/EXT_example")


@pytest.mark.parametrize("text", ["null", "[]", "3"])
def test_a_gltf_document_that_is_not_an_object_is_refused(tmp_path, text):
    from vbusd.jobs.conversion import ConvertOptions, convert

    (tmp_path / "bad.gltf").write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as caught:
        convert(tmp_path / "bad.gltf", tmp_path / "out.usda", ConvertOptions(check_rows=0))
    assert (caught.value.code, caught.value.location) == ("gltf.json", "/")
    assert "JSON " + {"null": "null", "[]": "array", "3": "number"}[text] in caught.value.message


@pytest.mark.slow
@pytest.mark.parametrize("value", [None, [], 3, "text"])
def test_gltf_extras_of_any_json_kind_are_accepted(tmp_path, value):
    """glTF 2.0 lets extras hold any value; pygltflib failed on a list or a number without a place."""
    from vbusd.io.usd import read_asset

    def everywhere(document):
        for pointer in ("/extras", "/nodes/0/extras", "/meshes/0/primitives/0/extras", "/asset/extras"):
            _set(pointer, value)(document)

    plain = read_asset(_convert_gltf(tmp_path / "plain", lambda d: None).output)
    with_extras = read_asset(_convert_gltf(tmp_path / "extras", everywhere).output)
    assert [vb.path for vb in plain.animations] == [vb.path for vb in with_extras.animations]
    for a, b in zip(plain.animations, with_extras.animations):
        assert (a.texels == b.texels).all()


# --------------------------------------------------------------------------------------------
# Batch manifests
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, where", [
    ("null", ""),
    ('{"assets": null}', ""),
    ("[null]", ":/0"),
    ('[{"source": "a.usda", "options": null}]', ":/0/options"),
    ('[{"source": "a.usda", "options": [1]}]', ":/0/options"),
    ('[{"source": "a.usda", "output": 5}]', ":/0/output"),
    ('[{"source": "a.usda", "output": null}]', ":/0/output"),
    ('[{"source": "a.usda", "encoding": null}]', ":/0/encoding"),
    ('{"assets": [{"source": "a.usda", "options": {"texel-format": null}}]}', ":/assets/0/options/texel-format"),
    ('[{"source": "a.usda", "rows_per_second": NaN}]', ""),
])
def test_a_manifest_value_of_the_wrong_json_kind_is_one_error_at_its_place(tmp_path, text, where):
    from vbusd.jobs.batch import read_manifest

    manifest = tmp_path / "m.json"
    manifest.write_text(text, encoding="utf-8")
    with pytest.raises(OptionsError) as caught:
        read_manifest(manifest)
    assert caught.value.code == "batch.manifest"
    assert caught.value.file == f"{manifest}{where}"


def test_a_manifest_with_a_byte_order_mark_reads(tmp_path):
    from vbusd.jobs.batch import read_manifest

    (tmp_path / "m.json").write_text('\ufeff[{"source": "a.usda", "texel-format": "float32"}]', encoding="utf-8")
    (tmp_path / "m.csv").write_text("\ufeffsource,texel-format\na.usda,float32\n", encoding="utf-8")
    for name in ("m.json", "m.csv"):
        [item] = read_manifest(tmp_path / name)
        assert item.source == str(tmp_path / "a.usda") and item.options == {"texel_format": "float32"}


def test_the_command_prints_one_line_for_a_bad_manifest(tmp_path, capsys):
    manifest = tmp_path / "m.json"
    manifest.write_text('[{"source": "a.usda", "options": [1]}]', encoding="utf-8")
    assert main(["convert", "--manifest", str(manifest), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "batch.manifest" in err[0] and "/0/options" in err[0], err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# Batch cache records (vbusd's own files, but a disk can hold anything)
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("text", ["null", "[]", '"text"', '{"state": "done", "files": null, "inputs": null}'])
def test_a_cache_record_of_the_wrong_kind_vouches_for_nothing(tmp_path, capsys, text):
    """Such a record is no record: the output it would vouch for is not the batch's own, so it is
    replaced only with --force (one line naming it), never 'cached' and never a crash."""
    library = tmp_path / "lib"
    library.mkdir()
    for name in ("a", "b"):
        (library / f"{name}.gltf").write_bytes((FIXTURES / "gltf" / "bar.gltf").read_bytes())
    args = ["convert", str(library), "-o", str(tmp_path / "out"), "--jobs", "1", "--check-rows", "2",
            "--format", "json"]
    assert main(args) == 0
    capsys.readouterr()
    records = sorted((tmp_path / "out" / ".vbusd-cache").glob("*.json"))
    assert len(records) == 2
    records[0].write_text(text, encoding="utf-8")
    assert main(args) == 1
    assets = json.loads(capsys.readouterr().out)["assets"]
    assert sorted(a["status"] for a in assets) == ["cached", "failed"]
    (failed,) = [a for a in assets if a["status"] == "failed"]
    assert failed["code"] == "options.invalid" and "--force" in failed["error"]
    assert main([*args, "--force"]) == 0
    assert sorted(a["status"] for a in json.loads(capsys.readouterr().out)["assets"]) == ["cached", "converted"]
