"""The vbusd checks run inside OpenUSD's UsdValidation framework (usd-core's ValidationContext)."""

from __future__ import annotations

from pathlib import Path

import pytest

import vbusd  # noqa: F401  (registers the schema plugin)
from pxr import Sdf, Tf, Usd, UsdGeom, UsdValidation, Vt  # noqa: E402

from vbusd.validators import usd_validation  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures" / "validate"


@pytest.fixture(scope="module")
def validators():
    return usd_validation.register()


def _broken_binding_stage():
    """An in-memory stage written with plain pxr calls: a 2-bone animation and a triangle whose
    second vertex uses bone 5."""
    stage = Usd.Stage.CreateInMemory()
    animation = stage.DefinePrim("/Rig/Anim", "VirtualBonesAnimation")
    animation.GetAttribute("vb:boneCount").Set(2)
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Body")
    mesh.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0), (0, 1, 0)]))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    prim = mesh.GetPrim()
    prim.ApplyAPI("VirtualBonesBindingAPI")
    prim.GetRelationship("vb:animation").SetTargets([Sdf.Path("/Rig/Anim")])
    primvars = UsdGeom.PrimvarsAPI(prim)
    primvars.CreatePrimvar("vb:boneIndices", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex, 1).Set(
        Vt.IntArray([0, 5, 1]))
    primvars.CreatePrimvar("vb:boneWeights", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex, 1).Set(
        Vt.FloatArray([1, 1, 1]))
    return stage


def _named(errors, name):
    return [e for e in errors if e.GetName() == name]


def test_registered_by_schema_type_keyword_and_suite(validators):
    registry = UsdValidation.ValidationRegistry()
    for name, schema_type in ((usd_validation.ANIMATION_VALIDATOR, "VirtualBonesAnimation"),
                              (usd_validation.BINDING_VALIDATOR, "VirtualBonesBindingAPI"),
                              (usd_validation.INSTANCING_VALIDATOR, "VirtualBonesInstancingAPI")):
        assert registry.HasValidator(name)
        assert name in [m.name for m in registry.GetValidatorMetadataForSchemaType(schema_type)]
        assert list(registry.GetValidatorMetadata(name).GetSchemaTypes()) == [schema_type]
    assert {m.name for m in registry.GetValidatorMetadataForKeyword("vbusd")} >= {
        usd_validation.ANIMATION_VALIDATOR, usd_validation.BINDING_VALIDATOR, usd_validation.INSTANCING_VALIDATOR}
    # The fourth runs on every prim (no schemaTypes): vb: primvars without the API schema.
    assert not list(registry.GetValidatorMetadata(usd_validation.PRIMVARS_VALIDATOR).GetSchemaTypes())
    assert len(registry.GetOrLoadValidatorSuiteByName(usd_validation.SUITE).GetContainedValidators()) == 4
    assert usd_validation.register()  # idempotent


def test_context_by_keyword_reports_a_broken_binding(validators):
    stage = _broken_binding_stage()
    errors = UsdValidation.ValidationContext(keywords=["vbusd"]).Validate(stage)
    found = _named(errors, "binding.indices.range")
    assert len(found) == 1
    error = found[0]
    assert error.GetType() == UsdValidation.ValidationErrorType.Error
    assert error.GetIdentifier() == f"{usd_validation.BINDING_VALIDATOR}.binding.indices.range"
    sites = error.GetSites()
    assert len(sites) == 1 and sites[0].IsProperty()
    assert sites[0].GetProperty().GetPath() == Sdf.Path("/Rig/Body.primvars:vb:boneIndices")
    assert "5" in error.GetMessage()


def test_context_by_schema_type_runs_only_that_validator(validators):
    stage = _broken_binding_stage()
    context = UsdValidation.ValidationContext([Tf.Type.FindByName("VirtualBonesBindingAPI")])
    errors = context.Validate(stage)
    assert {e.GetName() for e in errors} == {"binding.indices.range"}
    assert all(e.GetValidator().GetMetadata().name == usd_validation.BINDING_VALIDATOR for e in errors)


def test_animation_findings_in_the_texture_are_sited_at_vb_texture(validators):
    stage = Usd.Stage.Open(str(FIXTURES / "texture.nonFinite" / "asset.usda"))
    errors = UsdValidation.ValidationContext([Tf.Type.FindByName("VirtualBonesAnimation")]).Validate(stage)
    nan = _named(errors, "texture.nonFinite")
    assert len(nan) == 1
    assert nan[0].GetSites()[0].GetProperty().GetPath() == Sdf.Path("/VirtualBones/Animation.vb:texture")
    assert nan[0].GetMessage().startswith("asset.Animation.exr[row 3, column 5, bone 1, texel 2, channel R]")
    info = _named(errors, "texture.padding.fraction")
    assert info and info[0].GetType() == UsdValidation.ValidationErrorType.Info


def test_suite_over_a_valid_stage_reports_no_error(validators):
    stage = Usd.Stage.Open(str(FIXTURES / "valid" / "dualQuat_float16" / "asset.usda"))
    suite = UsdValidation.ValidationRegistry().GetOrLoadValidatorSuiteByName(usd_validation.SUITE)
    errors = UsdValidation.ValidationContext([suite]).Validate(stage)
    assert not [e for e in errors if e.GetType() in (UsdValidation.ValidationErrorType.Error,
                                                     UsdValidation.ValidationErrorType.Warn)]


def test_instancer_error_through_the_suite(validators):
    stage = Usd.Stage.Open(str(FIXTURES / "instancer.clip.range" / "asset.usda"))
    suite = UsdValidation.ValidationRegistry().GetOrLoadValidatorSuiteByName(usd_validation.SUITE)
    errors = _named(UsdValidation.ValidationContext([suite]).Validate(stage), "instancer.clip.range")
    assert len(errors) == 1
    assert errors[0].GetSites()[0].GetProperty().GetPath() == Sdf.Path("/VirtualBones/Crowd.primvars:vb:clip")


def test_registration_survives_a_second_import_of_the_module(validators):
    """Importing the module again (importlib.reload, or the same file under another module name as
    pytest's importlib mode or a plugin loader may do) and registering again must neither fail nor
    register the validators twice: each finding is still reported once."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "vbusd.validators._usd_validation_copy", Path(usd_validation.__file__))
    copy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(copy)
    again = copy.register()
    reloaded = importlib.reload(usd_validation).register()
    names = [v.GetMetadata().name for v in validators]
    assert [v.GetMetadata().name for v in again] == names == [v.GetMetadata().name for v in reloaded]
    registry = UsdValidation.ValidationRegistry()
    for name, schema_type in zip(names, ("VirtualBonesAnimation", "VirtualBonesBindingAPI",
                                         "VirtualBonesInstancingAPI")):
        assert [m.name for m in registry.GetValidatorMetadataForSchemaType(schema_type)
                if m.name.startswith("vbusd:")] == [name]
    errors = UsdValidation.ValidationContext(keywords=["vbusd"]).Validate(_broken_binding_stage())
    assert len(_named(errors, "binding.indices.range")) == 1


STAGE_LEVEL = {"asset.composition", "asset.empty", "asset.outside"}


@pytest.mark.slow
def test_usd_validation_reports_what_vbusd_validate_reports_on_every_fixture(validators):
    """The same checks: over every golden fixture, each finding of `vbusd validate` (except the
    stage-level ones, which are not prim validators) comes out of a UsdValidation context too, with
    the same code, and USD-sited findings at the same prim or property."""
    from vbusd.validators.api import validate

    suite = UsdValidation.ValidationRegistry().GetOrLoadValidatorSuiteByName(usd_validation.SUITE)
    for asset in sorted(FIXTURES.rglob("asset.usda")):
        expected = {(f.code, str(f.location) if f.location.kind == "usd" else None)
                    for f in validate(asset).findings if f.code not in STAGE_LEVEL}
        stage = Usd.Stage.Open(str(asset))  # kept alive: error sites refer to it
        errors = UsdValidation.ValidationContext([suite]).Validate(stage)
        got = set()
        for error in errors:
            site = error.GetSites()[0]
            path = str(site.GetProperty().GetPath() if site.IsProperty() else site.GetPrim().GetPath())
            got |= {(error.GetName(), path), (error.GetName(), None)}
        assert expected <= got, (asset.parent.name, sorted(expected - got, key=str))
