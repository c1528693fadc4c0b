"""The VBUSD_virtual_bones proposal (spec/extensions/VBUSD_virtual_bones, issue 28).

* The README has the sections of a Khronos extension and its relative links lead to files.
* The proposal's split schemas (Khronos style, referencing the glTF core schemas) accept what the
  self-contained vbusd/schema/VBUSD_virtual_bones.schema.json accepts and refuse what it refuses, on the
  sample's objects, the spec's example and broken variants of them.
* The sample folder (glTF-Sample-Assets layout) holds the model, a README with the screenshot and a
  license; the model is what ``vbusd export`` writes now, and the Khronos glTF-Validator reports no
  error and no warning on it.
"""

from __future__ import annotations

import copy
import json
import re
import struct
from pathlib import Path

import pytest
from tests.helpers import node as node_tools

from tests.helpers import scripts

REPO = Path(__file__).resolve().parents[1]
PROPOSAL = REPO / "spec" / "extensions" / "VBUSD_virtual_bones"
SAMPLE = PROPOSAL / "examples" / "StadiumCrowd"
MODEL = SAMPLE / "glTF-Binary" / "StadiumCrowd.glb"
NAME = "VBUSD_virtual_bones"

# The two glTF 2.0 core schemas the extension schemas reference, as the glTF 2.0 specification
# defines them (schema/glTFid.schema.json, schema/glTFProperty.schema.json of KhronosGroup/glTF).
GLTF_CORE = {
    "glTFid.schema.json": {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": "glTFid.schema.json",
                           "title": "glTF Id", "type": "integer", "minimum": 0},
    "glTFProperty.schema.json": {"$schema": "https://json-schema.org/draft/2020-12/schema",
                                 "$id": "glTFProperty.schema.json", "title": "glTF Property", "type": "object",
                                 "properties": {"extensions": {"type": "object"}, "extras": {}}},
}


def _glb_json(path: Path) -> dict:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def _validators():
    """(split: {root, primitive}, whole: {root, primitive}) jsonschema validators."""
    import jsonschema
    from referencing import Registry, Resource

    resources = [(key, Resource.from_contents(value)) for key, value in GLTF_CORE.items()]
    for path in (PROPOSAL / "schema").glob("*.schema.json"):
        contents = json.loads(path.read_text(encoding="utf-8"))
        resources.append((contents["$id"], Resource.from_contents(contents)))
    layout = json.loads((REPO / "vbusd" / "schema" / "layout-metadata.schema.json").read_text(encoding="utf-8"))
    whole = json.loads((REPO / "vbusd" / "schema" / "VBUSD_virtual_bones.schema.json").read_text(encoding="utf-8"))
    resources += [(layout["$id"], Resource.from_contents(layout)), (whole["$id"], Resource.from_contents(whole))]
    registry = Registry().with_resources(resources)

    def make(schema):
        return jsonschema.Draft202012Validator(schema, registry=registry)

    split = {"root": make({"$ref": "glTF.VBUSD_virtual_bones.schema.json"}),
             "primitive": make({"$ref": "mesh.primitive.VBUSD_virtual_bones.schema.json"}),
             "node": make({"$ref": "node.VBUSD_virtual_bones.schema.json"}),
             # The split animation schema leaves `layout` an object (it names the layout schema in
             # its description, as Khronos schemas do for external formats); checked here too.
             "layout": make({"$ref": layout["$id"]})}
    full = {"root": make(whole), "primitive": make({"$ref": whole["$id"] + "#/$defs/primitive"}),
            "node": make({"$ref": whole["$id"] + "#/$defs/node"})}
    return split, full


def _split_accepts(split, kind: str, value) -> bool:
    if not split[kind].is_valid(value):
        return False
    if kind == "root":
        return all(split["layout"].is_valid(a["layout"]) for a in value["animations"])
    return True


def _documents():
    """(kind, object) pairs: the sample's and the example's objects."""
    out = []
    for gltf in (_glb_json(MODEL), json.loads((REPO / "vbusd" / "schema" / "VBUSD_virtual_bones.example.gltf").read_text())):
        out.append(("root", gltf["extensions"][NAME]))
        out += [("primitive", p["extensions"][NAME]) for m in gltf["meshes"] for p in m["primitives"]
                if NAME in p.get("extensions", {})]
    # A crowd node's time samples (runtime-package.md 5.1), as vbusd export writes a --fade-window crowd.
    out.append(("node", {"samples": {"_VB_FADE_WEIGHT": {"times": [0.5, 1.5], "values": 17},
                                     "_VB_LAYER_WEIGHT_1": {"times": [0.0], "values": 18}}}))
    return out


def _broken(kind: str, value) -> list:
    """Variants both schemas must refuse."""
    variants = []

    def variant(change):
        copied = copy.deepcopy(value)
        change(copied)
        variants.append(copied)

    if kind == "root":
        variant(lambda v: v.update(version=2))
        variant(lambda v: v.pop("animations"))
        variant(lambda v: v.update(animations=[]))
        variant(lambda v: v["animations"][0]["texture"].update(mimeType="image/png"))
        variant(lambda v: v["animations"][0]["texture"].update(bufferView=-1))
        variant(lambda v: v["animations"][0].pop("layout"))
        variant(lambda v: v["animations"][0].update(name=""))
        variant(lambda v: v["animations"][0].update(clipExtents=[[[0, 0], [1, 1, 1]]]))
        variant(lambda v: v["animations"][0].update(unknown=1))
        variant(lambda v: v["animations"][0]["layout"].update(encoding="eulerAngles"))
        variant(lambda v: v.update(unknown=True))
    elif kind == "node":
        variant(lambda v: v.pop("samples"))
        variant(lambda v: v.update(samples={}))
        variant(lambda v: v["samples"].update(_VB_CLIP={"times": [0.0], "values": 1}))
        variant(lambda v: v["samples"].update(_VB_LAYER_WEIGHT_01={"times": [0.0], "values": 1}))
        variant(lambda v: v["samples"]["_VB_FADE_WEIGHT"].update(times=[]))
        variant(lambda v: v["samples"]["_VB_FADE_WEIGHT"].update(values=-1))
        variant(lambda v: v["samples"]["_VB_FADE_WEIGHT"].pop("values"))
        variant(lambda v: v.update(unknown=1))
    else:
        variant(lambda v: v.update(influences=0))
        variant(lambda v: v.update(animation=-1))
        variant(lambda v: v.pop("animation"))
        variant(lambda v: v.update(unknown="x"))
    return variants


def test_readme_has_the_sections_of_a_khronos_extension_and_its_links_resolve():
    text = (PROPOSAL / "README.md").read_text(encoding="utf-8")
    headings = re.findall(r"^##+ (.+)$", text, flags=re.M)
    for section in ("Contributors", "Status", "Dependencies", "Overview", "Properties", "JSON Schema",
                    "Texture", "Accessors", "Implementation Notes", "Known Implementations", "Resources"):
        assert section in headings, section
    assert text.startswith(f"# {NAME}\n")
    for folder, document in ((PROPOSAL, text), (SAMPLE, (SAMPLE / "README.md").read_text(encoding="utf-8"))):
        for link in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", document):
            if not link.startswith("http"):
                assert (folder / link).exists(), link


def test_split_schemas_agree_with_the_self_contained_schema():
    split, full = _validators()
    for kind, value in _documents():
        assert _split_accepts(split, kind, value), (kind, list(split[kind].iter_errors(value)))
        assert full[kind].is_valid(value), kind
        for bad in _broken(kind, value):
            assert not full[kind].is_valid(bad), (kind, bad)
            assert not _split_accepts(split, kind, bad), (kind, bad)


def test_sample_folder_has_model_readme_screenshot_and_license():
    readme = (SAMPLE / "README.md").read_text(encoding="utf-8")
    assert "![screenshot](screenshot/screenshot.png)" in readme
    assert (SAMPLE / "screenshot" / "screenshot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Apache License, Version 2.0" in (SAMPLE / "LICENSE.md").read_text(encoding="utf-8")
    gltf = _glb_json(MODEL)
    assert NAME in gltf["extensionsUsed"] and NAME not in gltf.get("extensionsRequired", [])
    crowd = next(n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    instances = gltf["accessors"][crowd["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["_VB_CLIP"]]["count"]
    assert instances == 1200


def test_sample_model_is_what_vbusd_export_writes(tmp_path):
    script = scripts.load("scripts/make_extension_sample.py")
    fresh = script.export_model(tmp_path / "StadiumCrowd.glb")
    assert fresh.read_bytes() == MODEL.read_bytes(), "run python scripts/make_extension_sample.py"


@pytest.mark.node
def test_sample_model_passes_the_gltf_validator():
    result = node_tools.run_json("gltf_check.mjs", MODEL, packages=("three", "gltf-validator"))
    issues = result["validator"]["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    assert {m["code"] for m in issues["messages"]} <= {"UNSUPPORTED_EXTENSION", "UNUSED_OBJECT"}


@pytest.mark.parametrize("path", sorted((PROPOSAL / "schema").glob("*.schema.json")), ids=lambda p: p.name)
def test_split_schemas_are_valid_draft_2020_12(path):
    import jsonschema

    schema = json.loads(path.read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$id"] == path.name
