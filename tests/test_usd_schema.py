"""The codeless USD schema plugin: generated files up to date, registration on import, schema behaviour.

Checks against OpenUSD itself (usdGenSchema's output, Usd.SchemaRegistry, UsdPrim.CanApplyAPI), not
against vbusd's own code.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pxr

import vbusd  # noqa: E402  (registers the plugin)
from vbusd.io import usd_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SCHEMA_DIR = REPO / "vbusd" / "schema" / "usd"

# usdGenSchema writes these placeholders into a new plugInfo.json; the committed file replaces them
# with relative paths (a codeless plugin has no library). Nothing else may differ.
PLUGINFO_PLACEHOLDERS = {
    '"LibraryPath": "@PLUG_INFO_LIBRARY_PATH@"': '"LibraryPath": ""',
    '"ResourcePath": "@PLUG_INFO_RESOURCE_PATH@"': '"ResourcePath": "."',
    '"Root": "@PLUG_INFO_ROOT@"': '"Root": "."',
}


def _clean_env() -> dict:
    env = dict(os.environ)
    env.pop("PXR_PLUGINPATH_NAME", None)
    return env


@pytest.mark.cli
def test_generated_files_match_usdgenschema(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "pxr.Usd.usdGenSchema", "-q", str(SCHEMA_DIR / "schema.usda"), str(tmp_path)],
        capture_output=True, text=True, env=_clean_env(), timeout=120)
    assert result.returncode == 0, result.stderr
    generated = (tmp_path / "generatedSchema.usda").read_text()
    assert generated == (SCHEMA_DIR / "generatedSchema.usda").read_text(), \
        "generatedSchema.usda is stale: run python -m pxr.Usd.usdGenSchema vbusd/schema/usd/schema.usda schema/usd"
    pluginfo = (tmp_path / "plugInfo.json").read_text()
    for placeholder, committed in PLUGINFO_PLACEHOLDERS.items():
        assert placeholder in pluginfo, f"usdGenSchema no longer writes {placeholder}"
        pluginfo = pluginfo.replace(placeholder, committed)
    assert pluginfo == (SCHEMA_DIR / "plugInfo.json").read_text(), "plugInfo.json is stale"


def test_pluginfo_is_relative_and_codeless():
    text = (SCHEMA_DIR / "plugInfo.json").read_text()
    body = json.loads("\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#")))
    (plugin,) = body["Plugins"]
    assert plugin["Type"] == "resource"
    assert plugin["Root"] == "." and plugin["ResourcePath"] == "." and plugin["LibraryPath"] == ""
    assert plugin["Name"] == usd_plugin.PLUGIN_NAME
    types = plugin["Info"]["Types"]
    assert types["VirtualBonesAnimation"]["schemaKind"] == "concreteTyped"
    assert types["VirtualBonesBindingAPI"]["apiSchemaCanOnlyApplyTo"] == ["Mesh"]
    assert types["VirtualBonesInstancingAPI"]["apiSchemaCanOnlyApplyTo"] == ["PointInstancer"]


def test_schema_registry_knows_the_types():
    from pxr import Tf, Usd

    tf_type = Usd.SchemaRegistry.GetTypeFromName("VirtualBonesAnimation")
    assert tf_type == Tf.Type.FindByName("VirtualBonesAnimation")
    assert not tf_type.isUnknown
    assert tf_type.IsA(Tf.Type.FindByName("UsdTyped"))
    assert Usd.SchemaRegistry.IsConcrete(tf_type)
    for api in ("VirtualBonesBindingAPI", "VirtualBonesInstancingAPI"):
        api_type = Tf.Type.FindByName(api)
        assert not api_type.isUnknown
        assert Usd.SchemaRegistry.GetSchemaKind(api_type) == Usd.SchemaKind.SingleApplyAPI
    definition = Usd.SchemaRegistry().FindConcretePrimDefinition("VirtualBonesAnimation")
    names = set(definition.GetPropertyNames())
    expected = {
        "vb:formatVersion", "vb:formatMinorVersion", "vb:texture", "vb:encoding", "vb:texelFormat", "vb:boneCount",
        "vb:texelsPerBone", "vb:rowCount", "vb:textureWidth", "vb:textureHeight",
        "vb:horizontalPadding", "vb:verticalPadding", "vb:bones", "vb:clipNames", "vb:clipFirstRows",
        "vb:clipRowCounts", "vb:clipRowsPerSecond", "vb:clipLoops", "vb:clipStartTimes",
        "vb:clipExtents", "vb:unormRangeMin", "vb:unormRangeMax", "vb:contentDigest",
        "vb:bindTransforms", "vb:clipRootMotion", "vb:rootMotionUpAxis",  # format 1.1 (sockets, root motion)
        "vb:boneParents", "vb:maskNames", "vb:maskWeights",  # format 1.2 (layers and bone masks)
        "vb:compactRangeMin", "vb:compactRangeMax",  # format 1.2 (compact encoding)
        "vb:blendSpaceNames", "vb:blendSpaceDimensions", "vb:blendSpacePointCounts", "vb:blendSpaceClips",
        "vb:blendSpacePoints", "vb:blendSpaceSyncMarkers",  # format 1.3 (blend spaces)
        "vb:markerClips", "vb:markerNames", "vb:markerTimes"}  # format 1.3 (clip markers)
    assert names == expected


def test_attribute_types_and_allowed_tokens():
    from pxr import Sdf, Usd

    definition = Usd.SchemaRegistry().FindConcretePrimDefinition("VirtualBonesAnimation")
    types = {
        "vb:formatVersion": Sdf.ValueTypeNames.Int, "vb:texture": Sdf.ValueTypeNames.Asset,
        "vb:encoding": Sdf.ValueTypeNames.Token, "vb:bones": Sdf.ValueTypeNames.TokenArray,
        "vb:clipRowsPerSecond": Sdf.ValueTypeNames.DoubleArray, "vb:clipLoops": Sdf.ValueTypeNames.BoolArray,
        "vb:clipExtents": Sdf.ValueTypeNames.Float3Array, "vb:unormRangeMin": Sdf.ValueTypeNames.Float4Array,
        "vb:contentDigest": Sdf.ValueTypeNames.String, "vb:clipFirstRows": Sdf.ValueTypeNames.IntArray}
    for name, type_name in types.items():
        spec = definition.GetAttributeDefinition(name)
        assert spec.GetTypeName() == type_name, name
        assert spec.GetVariability() == Sdf.VariabilityUniform, name
    allowed = {
        "vb:encoding": ["crossMatrix", "affineMatrix", "quatTranslation", "dualQuat",
                        "compactQuatTranslation"],  # format 1.2
        "vb:texelFormat": ["float16", "float32", "unorm16", "uint32"],
        "vb:horizontalPadding": ["powerOfTwo", "none"], "vb:verticalPadding": ["none", "powerOfTwo"]}
    for name, tokens in allowed.items():
        assert list(definition.GetPropertyMetadata(name, "allowedTokens")) == tokens


def test_every_property_is_documented():
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(SCHEMA_DIR / "schema.usda"))
    for name in ("VirtualBonesAnimation", "VirtualBonesBindingAPI", "VirtualBonesInstancingAPI"):
        prim = layer.GetPrimAtPath("/" + name)
        assert prim.documentation.strip(), name
        for prop in prim.properties:
            assert prop.documentation.strip(), f"{name}.{prop.name} has no doc"


def test_fallbacks_come_from_the_schema():
    from pxr import Usd

    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Anim", "VirtualBonesAnimation")
    assert prim.IsA("VirtualBonesAnimation")
    assert prim.GetAttribute("vb:encoding").Get() == "crossMatrix"
    assert prim.GetAttribute("vb:texelFormat").Get() == "float16"
    assert prim.GetAttribute("vb:formatVersion").Get() == 1
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 0
    assert prim.GetAttribute("vb:horizontalPadding").Get() == "powerOfTwo"
    assert prim.GetAttribute("vb:verticalPadding").Get() == "none"
    assert not prim.GetAttribute("vb:encoding").HasAuthoredValue()
    assert prim.GetAttribute("vb:boneCount").Get() is None  # required, no fallback
    # Nothing of the above was written to the layer.
    assert len(stage.GetRootLayer().GetPrimAtPath("/Anim").properties) == 0


def test_binding_api_applies_only_to_meshes():
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    mesh = UsdGeom.Mesh.Define(stage, "/Mesh").GetPrim()
    ok, _ = mesh.CanApplyAPI("VirtualBonesBindingAPI")
    assert ok
    assert mesh.ApplyAPI("VirtualBonesBindingAPI")
    assert mesh.HasAPI("VirtualBonesBindingAPI")
    assert "VirtualBonesBindingAPI" in mesh.GetAppliedSchemas()
    # The API's properties (with their vertex interpolation) come from the schema.
    assert mesh.GetRelationship("vb:animation")
    indices = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("vb:boneIndices")
    assert indices and indices.GetInterpolation() == UsdGeom.Tokens.vertex

    xform = UsdGeom.Xform.Define(stage, "/Xform").GetPrim()
    ok, why = xform.CanApplyAPI("VirtualBonesBindingAPI")
    assert not ok and "Mesh" in why
    instancer = UsdGeom.PointInstancer.Define(stage, "/Crowd").GetPrim()
    assert not instancer.CanApplyAPI("VirtualBonesBindingAPI")[0]


def test_instancing_api_applies_only_to_point_instancers():
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    instancer = UsdGeom.PointInstancer.Define(stage, "/Crowd").GetPrim()
    assert instancer.CanApplyAPI("VirtualBonesInstancingAPI")[0]
    assert instancer.ApplyAPI("VirtualBonesInstancingAPI")
    assert instancer.HasAPI("VirtualBonesInstancingAPI")
    for name in ("vb:clip", "vb:timeOffset", "vb:playbackRate"):
        primvar = UsdGeom.PrimvarsAPI(instancer).GetPrimvar(name)
        assert primvar and primvar.GetInterpolation() == UsdGeom.Tokens.vertex, name
    mesh = UsdGeom.Mesh.Define(stage, "/Mesh").GetPrim()
    ok, why = mesh.CanApplyAPI("VirtualBonesInstancingAPI")
    assert not ok and "PointInstancer" in why


def test_plugin_dir_is_the_package_data_folder():
    import importlib.util

    folder = usd_plugin.plugin_dir()
    # Editable installs map vbusd.schema.usd onto schema/usd, regular ones copy it: either way the
    # folder is the package's own and holds the committed files.
    spec = importlib.util.find_spec(usd_plugin.PLUGIN_PACKAGE)
    assert folder == Path(spec.origin).resolve().parent
    for name in ("plugInfo.json", "generatedSchema.usda"):
        assert (folder / name).read_bytes() == (SCHEMA_DIR / name).read_bytes(), name
    from pxr import Plug

    plugin = Plug.Registry().GetPluginWithName("vbusd")
    assert plugin is not None
    assert Path(plugin.resourcePath).resolve() == folder


_PROBE = r"""
import json, os, sys
environment = dict(os.environ)
import vbusd
from vbusd.io import usd_plugin
state = {"pxr_loaded_by_import": any(m.startswith("pxr.") for m in sys.modules),
         "environment_unchanged": dict(os.environ) == environment,
         "environment_added": sorted(set(os.environ) - set(environment)),
         "plugin_path": os.environ.get("PXR_PLUGINPATH_NAME", ""),
         "vbusd_file": vbusd.__file__, "plugin_dir": str(usd_plugin.plugin_dir())}
from pxr import Usd
stage = Usd.Stage.CreateInMemory()
prim = stage.DefinePrim("/A", "VirtualBonesAnimation")
state["known"] = not Usd.SchemaRegistry.GetTypeFromName("VirtualBonesAnimation").isUnknown
state["encoding"] = prim.GetAttribute("vb:encoding").Get()
print(json.dumps(state))
"""


def _run_probe(code: str, cwd: Path, env=None, *flags) -> dict:
    # -P and a neutral cwd: the checkout's vbusd/ folder must not shadow the installed package.
    result = subprocess.run([sys.executable, "-P", *flags, "-c", code], capture_output=True,
                            text=True, env=env or _clean_env(), timeout=60, cwd=cwd)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


@pytest.mark.cli
def test_import_vbusd_registers_without_importing_pxr(tmp_path):
    state = _run_probe(_PROBE, tmp_path)
    # pxr is not imported by `import vbusd`: the plugin folder goes on PXR_PLUGINPATH_NAME, which pxr
    # reads when its plugin registry starts (the probe's own `from pxr import Usd`); nothing else set.
    assert state["pxr_loaded_by_import"] is False
    assert state["environment_added"] == ["PXR_PLUGINPATH_NAME"]
    assert state["plugin_path"].split(os.pathsep)[0] == state["plugin_dir"]
    assert state["known"] and state["encoding"] == "crossMatrix"


@pytest.mark.cli
@pytest.mark.parametrize("first_import", ["from pxr import Tf", "from pxr import UsdGeom", "import pxr.Sdf"])
def test_registration_holds_whichever_pxr_module_comes_first(tmp_path, first_import):
    # pxr reads the plugin path as its registry starts, whichever pxr module is imported first; the
    # host's own entries stay on the path after vbusd's; no import hook is installed.
    probe = ("import json, os, sys\nos.environ['PXR_PLUGINPATH_NAME'] = '/nonexistent-host-plugins'\n"
             "import vbusd\n" + first_import + "\n"
             "from pxr import Plug, Usd\n"
             "hooks = [f for f in sys.meta_path if type(f).__module__.startswith('vbusd')]\n"
             "print(json.dumps({'plugin': Plug.Registry().GetPluginWithName('vbusd') is not None, 'hooks': len(hooks),\n"
             "  'known': not Usd.SchemaRegistry.GetTypeFromName('VirtualBonesAnimation').isUnknown,\n"
             "  'host_entry_kept': os.environ['PXR_PLUGINPATH_NAME'].endswith('/nonexistent-host-plugins')}))\n")
    state = _run_probe(probe, tmp_path)
    assert state == {"plugin": True, "hooks": 0, "known": True, "host_entry_kept": True}


@pytest.mark.cli
def test_import_vbusd_after_pxr_registers_directly(tmp_path):
    state = _run_probe("from pxr import Usd\n" + _PROBE, tmp_path)
    assert state["environment_unchanged"] is True  # registered through Plug
    assert state["known"] and state["encoding"] == "crossMatrix"


_LATE_PROBE = r"""
import json, os, sys, warnings
from pxr import Usd
# A user script that opened a stage before importing vbusd: USD's schema registry is built now.
Usd.Stage.Open(sys.argv[1])
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    import vbusd
from vbusd.io import usd as usd_io, usd_plugin
from vbusd.format.errors import VbusdError
sample = Usd.Stage.Open(sys.argv[2])
body = sample.GetPrimAtPath("/StadiumCrowd/Body")
state = {"warnings": [(w.category.__name__, str(w.message), os.path.basename(w.filename)) for w in caught],
         "known": usd_plugin.schema_types_known(),
         "usd_has_api": body.HasAPI("VirtualBonesBindingAPI"),
         "authored_api": [str(n) for n in body.GetMetadata("apiSchemas").ApplyOperations([])]}
asset = usd_io.read_asset(sys.argv[2])
state["meshes"] = [len(vb.meshes) for vb in asset.animations]
state["instances"] = [c.instance_count for c in asset.crowds]
try:
    usd_io.write_asset(asset, os.path.join(sys.argv[3], "copy.usda"))
    state["write_error"] = None
except VbusdError as error:
    state["write_error"] = [error.code, str(error)]
state["written"] = sorted(os.listdir(sys.argv[3]))
print(json.dumps(state))
"""


@pytest.mark.cli
def test_import_vbusd_after_usd_built_its_schema_registry(tmp_path):
    # OpenUSD builds Usd.SchemaRegistry once; a plugin registered afterwards gets no prim
    # definitions. vbusd must say so on import, still read assets from authored data (the spec's
    # reader rule) and refuse to write, rather than silently find no bound meshes or crowds.
    sample = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    unrelated = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
    out = tmp_path / "out"
    out.mkdir()
    result = subprocess.run([sys.executable, "-P", "-c", _LATE_PROBE, str(unrelated), str(sample), str(out)],
                            capture_output=True, text=True, env=_clean_env(), timeout=120, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    state = json.loads(result.stdout)
    assert state["known"] is False and state["usd_has_api"] is False  # USD's own behaviour
    assert state["authored_api"] == ["VirtualBonesBindingAPI"]
    (warning,) = state["warnings"]
    assert warning[0] == "RuntimeWarning" and "PXR_PLUGINPATH_NAME" in warning[1]
    assert warning[2] == "<string>", "the warning should point at the user's import line"
    # The sample has one bound mesh and a crowd of 1,200 (checked with plain pxr in test_samples).
    assert state["meshes"] == [1] and state["instances"] == [1200]
    assert state["write_error"][0] == "usd.plugin" and "import vbusd before" in state["write_error"][1].lower()
    assert state["written"] == []  # nothing half-written


@pytest.mark.cli
def test_late_import_with_plugin_path_set_is_fine(tmp_path):
    # The documented remedy: PXR_PLUGINPATH_NAME set before the process starts.
    env = _clean_env()
    env["PXR_PLUGINPATH_NAME"] = str(usd_plugin.plugin_dir())
    state = _run_probe("from pxr import Usd\nUsd.SchemaRegistry()\n" + _PROBE, tmp_path, env)
    assert state["known"] and state["encoding"] == "crossMatrix"


def _install_like_a_wheel(target: Path) -> None:
    """Lay the package out as the wheel does: the vbusd/ tree as it is, with its package-data."""
    import tomllib
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "package-dir" not in config, "the tree is the package: no folder is remapped"
    package_data = config.get("package-data", {})
    for init in (REPO / "vbusd").rglob("__init__.py"):
        source = init.parent
        package = ".".join(source.relative_to(REPO).parts)
        dest = target.joinpath(*package.split("."))
        dest.mkdir(parents=True, exist_ok=True)
        for pattern in ["*.py"] + list(package_data.get(package, [])):
            for file in source.glob(pattern):
                shutil.copy2(file, dest / file.name)


@pytest.mark.cli
def test_installed_layout_resolves_the_plugin(tmp_path):
    site = tmp_path / "site"
    _install_like_a_wheel(site)
    assert (site / "vbusd" / "schema" / "usd" / "plugInfo.json").is_file()
    # -S skips site (and an editable install's path hook), so only the copied tree provides vbusd;
    # pxr comes from wherever it is installed.
    env = _clean_env()
    env["PYTHONPATH"] = os.pathsep.join([str(site), str(Path(pxr.__file__).resolve().parents[1])])
    state = _run_probe(_PROBE, tmp_path, env, "-S")
    assert Path(state["vbusd_file"]).resolve().is_relative_to(site.resolve())
    assert Path(state["plugin_dir"]) == (site / "vbusd" / "schema" / "usd").resolve()
    assert state["known"] and state["encoding"] == "crossMatrix"
