"""The vbusd checks as OpenUSD UsdValidation validators.

:func:`register` adds four prim validators to ``UsdValidation.ValidationRegistry`` (the process-wide
singleton), three limited by ``schemaTypes`` to the TfType of a vbusd schema and one for prims that
carry vbusd primvars without the API schema (which no schema-typed validator visits), and a suite
holding all four:

========================================  ==============================  =========================
validator                                 schemaTypes                     runs
========================================  ==============================  =========================
``vbusd:VirtualBonesAnimationValidator``  ``VirtualBonesAnimation``       prim attributes, clips,
                                                                          texture, metadata, texels,
                                                                          levels of detail
``vbusd:VirtualBonesBindingValidator``    ``VirtualBonesBindingAPI``      mesh bindings
``vbusd:VirtualBonesInstancingValidator`` ``VirtualBonesInstancingAPI``   point instancer primvars
``vbusd:UnappliedApiValidator``           (none: every prim)              vb: primvars without the
                                                                          API schema applied
``vbusd:Suite`` (suite)                   all of the above
========================================  ==============================  =========================

All carry the keyword ``vbusd``. So any of these runs them over a stage::

    import vbusd.validators.usd_validation as vbv
    from pxr import Tf, UsdValidation
    vbv.register()
    context = UsdValidation.ValidationContext(keywords=["vbusd"])
    # or: UsdValidation.ValidationContext([Tf.Type.FindByName("VirtualBonesAnimation")])
    errors = context.Validate(stage)

Each vbusd finding becomes a ``UsdValidation.ValidationError`` whose name is the vbusd code (its
identifier is ``<validator>.<code>``), whose type maps error -> Error, warning -> Warn and info /
hint -> Info (UsdValidation has no hint), and whose site is the prim or property. Findings located
in the texture (a texel or JSON pointer) are sited at the animation's ``vb:texture`` property and
name the exact place at the start of the message.
"""

from __future__ import annotations

import os
import threading

from vbusd.format.names import ANIMATION_TYPE, BINDING_API, INSTANCING_API, TEXTURE
from vbusd.format.diagnostics import UsdSite
from pxr import Sdf, UsdValidation
from vbusd.validators.api import guarded
from vbusd.validators.checks_animation import check_animation_prim
from vbusd.io.usd_lod import check_animation_levels
from vbusd.validators.checks_bindings import check_binding_prim, has_binding
from vbusd.validators.checks_bindings import check_instancer_prim, has_instancing
from vbusd.validators.checks_bindings import applied_schemas
import vbusd.io.usd_plugin as plugin
from vbusd.format.errors import UnsupportedError

__all__ = ["KEYWORD", "ANIMATION_VALIDATOR", "BINDING_VALIDATOR", "INSTANCING_VALIDATOR",
           "PRIMVARS_VALIDATOR", "SUITE", "register"]

KEYWORD = "vbusd"
ANIMATION_VALIDATOR = "vbusd:VirtualBonesAnimationValidator"
BINDING_VALIDATOR = "vbusd:VirtualBonesBindingValidator"
INSTANCING_VALIDATOR = "vbusd:VirtualBonesInstancingValidator"
PRIMVARS_VALIDATOR = "vbusd:UnappliedApiValidator"
SUITE = "vbusd:Suite"

_LOCK = threading.Lock()


def _to_errors(prim, findings):
    kinds = {"error": UsdValidation.ValidationErrorType.Error,
             "warning": UsdValidation.ValidationErrorType.Warn,
             "info": UsdValidation.ValidationErrorType.Info,
             "hint": UsdValidation.ValidationErrorType.Info}
    stage = prim.GetStage()
    errors = []
    for item in findings:
        location = item.location
        if isinstance(location, UsdSite):
            path = Sdf.Path(location.prim_path)
            if location.property:
                path = path.AppendProperty(location.property)
            message = item.message
        else:
            path = prim.GetPath().AppendProperty(TEXTURE) if prim.GetTypeName() == ANIMATION_TYPE \
                else prim.GetPath()
            message = f"{location}: {item.message}"
        site = UsdValidation.ValidationErrorSite(stage, path)
        errors.append(UsdValidation.ValidationError(item.code, kinds[item.severity.value], [site], message))
    return errors


def _asset_dir(stage) -> str:
    real = stage.GetRootLayer().realPath
    return os.path.dirname(real) if real else os.getcwd()


def _animation_task(prim, time_range=None):
    if prim.IsPseudoRoot() or prim.GetTypeName() != ANIMATION_TYPE:
        return []
    findings = guarded(check_animation_prim, prim, _asset_dir(prim.GetStage()),
                       location=UsdSite(str(prim.GetPath())))
    # Levels of detail (format 1.2): the lod.* checks of the animation's bound meshes.

    findings += guarded(check_animation_levels, prim, location=UsdSite(str(prim.GetPath())))
    return _to_errors(prim, findings)


def _binding_task(prim, time_range=None):
    if prim.IsPseudoRoot() or not has_binding(prim):
        return []
    return _to_errors(prim, guarded(check_binding_prim, prim, location=UsdSite(str(prim.GetPath()))))


def _instancing_task(prim, time_range=None):
    if prim.IsPseudoRoot() or not has_instancing(prim):
        return []
    return _to_errors(prim, guarded(check_instancer_prim, prim, location=UsdSite(str(prim.GetPath()))))


def _unapplied_task(prim, time_range=None):
    """Prims carrying vb: binding or instancing primvars without the API schema applied: a
    schema-typed validator never visits them, yet they are findings (``binding.api.missing``) and
    their primvars are checked as for bound meshes (what ``vbusd validate`` does)."""

    if prim.IsPseudoRoot() or prim.GetTypeName() == ANIMATION_TYPE:
        return []
    applied = applied_schemas(prim)
    site = UsdSite(str(prim.GetPath()))
    if INSTANCING_API not in applied and has_instancing(prim):
        return _to_errors(prim, guarded(check_instancer_prim, prim, location=site))
    if BINDING_API not in applied and INSTANCING_API not in applied and has_binding(prim):
        return _to_errors(prim, guarded(check_binding_prim, prim, location=site))
    return []


def register() -> list:
    """Register the vbusd validators and suite with UsdValidation (idempotent, thread-safe).

    Returns:
        The registered ``UsdValidation.Validator`` objects (animation, binding, instancing,
        unapplied API).

    Raises:
        UnsupportedError: The installed usd-core has no ``ValidationRegistry.RegisterPrimValidator``
            in its Python API (older releases cannot register Python validators; usd-core 26.11
            can).
    """

    plugin.register()  # the schema TfTypes must exist for schemaTypes filtering
    try:
        from pxr import UsdValidation
    except ImportError:
        UsdValidation = None
    if UsdValidation is None or not hasattr(UsdValidation.ValidationRegistry, "RegisterPrimValidator"):
        raise UnsupportedError("this usd-core cannot register Python validators with UsdValidation "
                               "(use usd-core 26.11 or newer); `vbusd validate` works without it",
                               file="usd", code="usd.validation")

    registry = UsdValidation.ValidationRegistry()
    specs = (
        (ANIMATION_VALIDATOR, ANIMATION_TYPE, _animation_task,
         "vbusd: VirtualBonesAnimation attributes, clips, texture file, layout metadata and texels."),
        (BINDING_VALIDATOR, BINDING_API, _binding_task,
         "vbusd: meshes bound with VirtualBonesBindingAPI (indices, weights, counts, normals)."),
        (INSTANCING_VALIDATOR, INSTANCING_API, _instancing_task,
         "vbusd: point instancers with VirtualBonesInstancingAPI (clip indices, offsets, rates)."),
        (PRIMVARS_VALIDATOR, None, _unapplied_task,
         "vbusd: prims carrying vb: binding or instancing primvars without the API schema applied."),
    )
    with _LOCK:
        for name, schema_type, task, doc in specs:
            if registry.HasValidator(name):
                continue
            metadata = UsdValidation.ValidatorMetadata(name=name, doc=doc, keywords=[KEYWORD],
                                                       schemaTypes=[schema_type] if schema_type else [],
                                                       isSuite=False)
            registry.RegisterPrimValidator(metadata, task)
        validators = [registry.GetOrLoadValidatorByName(name) for name, *_ in specs]
        if not registry.HasValidatorSuite(SUITE):
            metadata = UsdValidation.ValidatorMetadata(
                name=SUITE, doc="vbusd: every Virtual Bones check.", keywords=[KEYWORD], isSuite=True)
            registry.RegisterValidatorSuite(metadata, validators)
    return validators
