"""The Blender add-on imports a varied crowd (format 1.3, spec virtual-bones.md 22) with its variety:
read back from Blender's own objects and materials and compared with the crowd's USD primvars read
with pxr: each instance's object colour is its tint, its material's base colour (the node the
add-on multiplies with the object colour) its variant's UsdPreviewSurface colour, and its hat and its
flag (a prop at the right hand's socket) are hidden exactly when its parts mask leaves them out."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.capabilities import require

pytestmark = pytest.mark.blender
require("blender", allow_module_level=True)

import bpy  # noqa: E402

from tests.helpers.variety import varied_crowd  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "dcc" / "blender"))
import vbusd_blender  # noqa: E402,F401
from vbusd_blender.importer import ImportSettings, import_virtual_bones  # noqa: E402


def test_import_keeps_tints_variants_and_parts(tmp_path):
    from pxr import Usd, UsdGeom, UsdShade

    crowd = varied_crowd(tmp_path, count=12, parts={"Hat": 0.4, "Flag": 0.5})
    stage = Usd.Stage.Open(str(crowd))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    primvars = UsdGeom.PrimvarsAPI(prim)
    tints = np.asarray(primvars.GetPrimvar("vb:tint").Get(), dtype=np.float64)
    variants = np.asarray(primvars.GetPrimvar("vb:variant").Get())
    parts = np.asarray(primvars.GetPrimvar("vb:parts").Get())
    colours = [np.asarray(UsdShade.Material(stage.GetPrimAtPath(t)).ComputeSurfaceSource()[0]
                          .GetInput("diffuseColor").Get()) for t in prim.GetRelationship("vb:variantMaterials").GetTargets()]
    assert set(parts & 1) == {0, 1} and set(parts >> 1 & 1) == {0, 1} and set(variants) == {0, 1}

    bpy.ops.wm.read_factory_settings(use_empty=True)
    report = import_virtual_bones(bpy.context, str(crowd), ImportSettings())
    (instances,) = report.instances
    assert len(instances) == len(tints)
    for i, (_, objects) in enumerate(instances):
        by_name = {name.rsplit(".", 1)[0]: bpy.data.objects[name] for name in objects}
        body, hat, flag = by_name["Body"], by_name["Hat"], by_name["Flag"]
        for obj in (body, hat, flag):
            np.testing.assert_allclose(obj.color[:3], tints[i], rtol=1e-6)
            material = obj.material_slots[0].material
            assert obj.material_slots[0].link == "OBJECT"
            multiply = next(node for node in material.node_tree.nodes if node.type == "VECT_MATH")
            np.testing.assert_allclose(multiply.inputs[0].default_value[:], colours[variants[i]], rtol=1e-6)
            assert multiply.operation == "MULTIPLY"
            assert multiply.inputs[1].links[0].from_node.type == "OBJECT_INFO"
        assert body.hide_get() is False and not body.hide_render
        assert hat.hide_viewport == hat.hide_render == (not parts[i] & 1), i
        assert flag.hide_viewport == flag.hide_render == (not parts[i] >> 1 & 1), i
