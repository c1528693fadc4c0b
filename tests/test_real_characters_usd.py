"""Real characters convert whole (issue 12), UsdSkel side: hand-built stages against UsdSkel.

The independent result is UsdSkel's own ``UsdSkel.BakeSkinning`` on a copy of the stage: it writes
the skinned points (and, for rigidly deformed prims, their transforms) and the world positions
are read back with ``UsdGeom.XformCache``. The converted asset is baked in affineMatrix/float32
and decoded by the reference decoder at every row; the largest distance must stay within 1e-6 of
the diagonal of UsdSkel's bounding box; a mesh no binding reaches is placed by its own transform
(``XformCache``), as renderers show it. The stage is Z up in centimetres, which the output keeps
and ``vbusd info`` shows.
"""

from __future__ import annotations

import json

import numpy as np
import pytest


from vbusd.baking.baker import BakeOptions, bake  # noqa: E402
from vbusd.converters import usdskel  # noqa: E402
from vbusd.decoders.reference import skin_mesh_at_rows  # noqa: E402
from vbusd.format.model import ReadOptions  # noqa: E402

from tests.helpers import cli  # noqa: E402

pytestmark = pytest.mark.slow  # seconds each: outside the fast tier (-m unit)

TOLERANCE = 1e-6

_CONSTANT_ONE = '''int[] primvars:skel:jointIndices = [{joint}] (
            interpolation = "constant"
            elementSize = 1
        )
        float[] primvars:skel:jointWeights = [1] (
            interpolation = "constant"
            elementSize = 1
        )'''


def stage_text(spawn_scale: str = "(1, 1, 1)") -> str:
    """A character: Hips -> Head (Z up, cm); Body skinned per vertex; Helmet a Mesh with a rigid
    (constant) binding to Head and its own (ignored) transform; Gear an Xform with a rigid binding
    that its child Mesh Visor inherits; a second skeleton Spawner whose first key scales to
    ``spawn_scale``."""
    return f'''#usda 1.0
(
    defaultPrim = "Root"
    metersPerUnit = 0.01
    upAxis = "Z"
    startTimeCode = 0
    endTimeCode = 12
    timeCodesPerSecond = 24
)

def SkelRoot "Root" (
    prepend apiSchemas = ["SkelBindingAPI"]
)
{{
    rel skel:skeleton = </Root/Skel>
    rel skel:animationSource = </Root/Skel/Anim>

    def Skeleton "Skel" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        uniform token[] joints = ["Hips", "Hips/Head"]
        uniform matrix4d[] bindTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,100,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,150,1))]
        uniform matrix4d[] restTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,100,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,50,1))]
        rel skel:animationSource = </Root/Skel/Anim>

        def SkelAnimation "Anim"
        {{
            uniform token[] joints = ["Hips", "Hips/Head"]
            float3[] translations.timeSamples = {{ 0: [(0,0,100), (0,0,50)], 12: [(20,5,100), (0,0,50)] }}
            quatf[] rotations.timeSamples = {{ 0: [(1,0,0,0), (1,0,0,0)], 6: [(0.9659258,0,0.2588190,0), (0.9238795,0.3826834,0,0)], 12: [(0.9238795,0,0.3826834,0), (0.7071068,0.7071068,0,0)] }}
            half3[] scales = [(1,1,1), (1,1,1)]
        }}
    }}

    def Mesh "Body" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [3, 3, 3, 3]
        int[] faceVertexIndices = [0, 1, 2, 0, 2, 3, 2, 4, 5, 2, 5, 3]
        point3f[] points = [(-10,0,100), (10,0,100), (10,0,150), (-10,0,150), (10,0,190), (-10,0,190)]
        int[] primvars:skel:jointIndices = [0, 0, 0, 0, 0, 1, 0, 1, 1, 0, 1, 0] (
            interpolation = "vertex"
            elementSize = 2
        )
        float[] primvars:skel:jointWeights = [1, 0, 1, 0, 0.5, 0.5, 0.5, 0.5, 1, 0, 1, 0] (
            interpolation = "vertex"
            elementSize = 2
        )
    }}

    def Mesh "Helmet" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [3, 3]
        int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]
        point3f[] points = [(-10,0,190), (10,0,190), (10,0,210), (-10,0,210)]
        {_CONSTANT_ONE.format(joint=1)}
        double3 xformOp:translate = (0, 5, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}

    def Sphere "Ball" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        double radius = 8
        matrix4d primvars:skel:geomBindTransform = ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,200,1))
        {_CONSTANT_ONE.format(joint=1)}
    }}

    def Capsule "Arm" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        double radius = 3
        double height = 20
        uniform token axis = "X"
        matrix4d primvars:skel:geomBindTransform = ((1,0,0,0),(0,1,0,0),(0,0,1,0),(20,0,150,1))
        int[] primvars:skel:jointIndices = [0, 1] (
            interpolation = "constant"
            elementSize = 2
        )
        float[] primvars:skel:jointWeights = [0.25, 0.75] (
            interpolation = "constant"
            elementSize = 2
        )
    }}

    def Mesh "Lantern"
    {{
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,0,0), (4,0,0), (0,0,6)]
        double3 xformOp:translate.timeSamples = {{ 0: (30, 0, 100), 12: (30, 10, 120) }}
        float xformOp:rotateZ.timeSamples = {{ 0: 0, 12: 90 }}
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateZ"]
    }}

    def Xform "Gear" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        {_CONSTANT_ONE.format(joint=1)}

        def Mesh "Visor"
        {{
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            point3f[] points = [(0,-10,195), (0,10,195), (0,0,215)]
        }}
    }}
}}

def SkelRoot "Spawn" (
    prepend apiSchemas = ["SkelBindingAPI"]
)
{{
    rel skel:skeleton = </Spawn/Spawner>

    def Skeleton "Spawner" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        uniform token[] joints = ["Base"]
        uniform matrix4d[] bindTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1))]
        uniform matrix4d[] restTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1))]
        rel skel:animationSource = </Spawn/Spawner/Grow>

        def SkelAnimation "Grow"
        {{
            uniform token[] joints = ["Base"]
            float3[] translations = [(0,0,0)]
            quatf[] rotations = [(1,0,0,0)]
            half3[] scales.timeSamples = {{ 0: [{spawn_scale}], 12: [(1,1,1)] }}
        }}
    }}

    def Mesh "Egg" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,0,0), (10,0,0), (0,10,0)]
        {_CONSTANT_ONE.format(joint=0)}
    }}
}}
'''


@pytest.fixture
def character(tmp_path):
    path = tmp_path / "character.usda"
    path.write_text(stage_text())
    return path


def baked_by_usdskel(path, tmp_path, codes, implicit_points) -> dict:
    """World points of every mesh at ``codes``, after ``UsdSkel.BakeSkinning`` of a copy.

    ``implicit_points``: the points of each Cube, Sphere, ... in its own space (UsdSkel deforms such
    a prim by its transform)."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    copy = tmp_path / "baked_by_usdskel.usda"
    copy.write_text(path.read_text())
    stage = Usd.Stage.Open(str(copy))
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(0, 12))
    result = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Gprim):
            continue
        poses = []
        for code in codes:
            time = Usd.TimeCode(code)
            if prim.IsA(UsdGeom.Mesh):
                points = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(time), dtype=np.float64)
            else:   # UsdSkel moved the prim (its transform); the points are the converted mesh's own
                points = implicit_points[str(prim.GetPath())]
            world = np.array(UsdGeom.XformCache(time).GetLocalToWorldTransform(prim), dtype=np.float64)
            poses.append(points @ world[:3, :3] + world[3, :3])
        result[str(prim.GetPath())] = np.array(poses)
    return result


def test_rigid_and_inherited_bindings_match_usdskel_bake(character, tmp_path):
    scene = usdskel.read(character, ReadOptions(skeletons=("/Root/Skel",)))
    (animation,) = scene.animations
    assert [m.path for m in animation.meshes] == ["/Root/Body", "/Root/Helmet", "/Root/Ball", "/Root/Arm",
                                                  "/Root/Gear/Visor", "/Root/Lantern"]
    assert not [w for w in scene.warnings if "Gear" in w], scene.warnings   # the Xform is no mesh
    # Lantern: no binding reaches it; it follows its own animated transform as an extra bone.
    assert animation.bones == ("Hips", "Hips/Head", "Root/Lantern")
    assert any(w.startswith("/Root/Lantern:") and "own animated transform" in w for w in scene.warnings)
    meshes = {m.path: m for m in animation.meshes}
    # The implicit gprims, by hand: every point of the sphere at distance 8 from its centre (z = 200
    # in bind space), faces wound outwards (positive volume); the capsule's points within its radius
    # of its axis segment.
    ball = meshes["/Root/Ball"]
    np.testing.assert_allclose(np.linalg.norm(ball.points - (0, 0, 200), axis=1), 8.0, atol=1e-9)
    assert _volume(ball) > 0 and _volume(meshes["/Root/Arm"]) > 0
    arm = meshes["/Root/Arm"].points - (20, 0, 150)
    along = np.clip(arm[:, 0], -10, 10)
    np.testing.assert_allclose(np.linalg.norm(arm - np.stack([along, 0 * along, 0 * along], 1), axis=1), 3.0,
                               atol=1e-9)
    vb = bake(animation, BakeOptions(encoding="affineMatrix", texel_format="float32"))
    (clip,) = vb.clips
    codes = (clip.start_time + np.arange(clip.row_count) / clip.rows_per_second) * scene.time_codes_per_second
    # G of the implicit prims is a translation: their own points are the bind points less it.
    implicit = {"/Root/Ball": ball.points - (0, 0, 200), "/Root/Arm": meshes["/Root/Arm"].points - (20, 0, 150)}
    reference = baked_by_usdskel(character, tmp_path, codes, implicit)
    for index, mesh in enumerate(vb.meshes):
        ours, _ = skin_mesh_at_rows(vb, mesh, 0)
        theirs = reference[mesh.path]
        if mesh.path == "/Root/Arm":
            # Two constant influences: UsdSkel's BakeSkinning fits a transform to the blend
            # (UsdSkelSkinTransformLBS), ComputeSkinnedPoints blends per point, as the converter does
            # (spec: Rigid bindings). The reference is the latter, UsdSkel's own.
            theirs, _ = scene.reference(0, index, codes / scene.time_codes_per_second)
            fitted = reference[mesh.path]
            assert np.linalg.norm(fitted - theirs, axis=-1).max() < 1e-3   # the fit's shear, small here
        diagonal = np.linalg.norm(np.ptp(theirs.reshape(-1, 3), axis=0))
        assert np.linalg.norm(ours - theirs, axis=-1).max() <= TOLERANCE * diagonal, mesh.path
    visor = vb.meshes[2]
    assert np.all(visor.bone_indices == 1) and np.all(visor.bone_weights[:, 0] == 1)


def _volume(mesh) -> float:
    """Signed volume of a closed mesh (fan triangulation of each face): positive when faces wind
    counterclockwise seen from outside."""
    total, start = 0.0, 0
    for count in mesh.face_vertex_counts:
        face = mesh.points[mesh.face_vertex_indices[start:start + count]]
        for k in range(1, count - 1):
            total += np.dot(face[0], np.cross(face[k], face[k + 1])) / 6.0
        start += count
    return total


def _convert(capfd, tmp_path, source, *extra):
    """``vbusd convert`` in this process (tests.helpers.cli), its output captured like a child's."""
    out = tmp_path / "out" / "character.usda"
    return cli.run(capfd, "convert", source, "-o", out, "--format", "json", *extra), out


def test_units_and_up_axis_are_kept_and_shown(character, tmp_path, capfd):
    from pxr import Usd, UsdGeom

    result, out = _convert(capfd, tmp_path, character, "--clips", "Skel")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["metersPerUnit"] == 0.01 and report["upAxis"] == "Z"
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    info = cli.run(capfd, "info", out, "--format", "json")
    assert info.returncode == 0, info.stderr
    shown = json.loads(info.stdout)
    assert shown["upAxis"] == "Z" and shown["metersPerUnit"] == 0.01
    text = cli.run(capfd, "info", out).stdout
    assert "Z up, 1 unit = 0.01 m" in text


def test_clips_select_and_unknown_clip_is_one_line(character, tmp_path, capfd):
    result, out = _convert(capfd, tmp_path, character, "--clips", "Skel")
    assert result.returncode == 0, result.stderr
    assert [a["path"] for a in json.loads(result.stdout)["animations"]] == ["/Root/Skel"]
    result, out = _convert(capfd, tmp_path, character, "--clips", "Run", "--force")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "no clip named 'Run'" in lines[0] and "'Skel'" in lines[0] and "'Spawner'" in lines[0]


def test_zero_scale_skeleton_skipped(tmp_path, capfd):
    source = tmp_path / "spawn.usda"
    source.write_text(stage_text(spawn_scale="(0, 0, 0)"))
    result, out = _convert(capfd, tmp_path, source)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "clip 'Spawner'" in lines[0] and "--on-bad-clip skip" in lines[0]
    assert not out.parent.exists()
    result, out = _convert(capfd, tmp_path, source, "--on-bad-clip", "skip")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [a["path"] for a in report["animations"]] == ["/Root/Skel"]
    assert [(s["animation"], s["clip"]) for s in report["skippedClips"]] == [("/Spawn/Spawner", "Spawner")]


BLEND = """#usda 1.0
(
    defaultPrim = "Root"
    startTimeCode = 0
    endTimeCode = 12
    timeCodesPerSecond = 24
    upAxis = "Y"
)

def SkelRoot "Root" (
    prepend apiSchemas = ["SkelBindingAPI"]
)
{
    rel skel:skeleton = </Root/Skel>

    def Skeleton "Skel" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {
        uniform token[] joints = ["Hips"]
        uniform matrix4d[] bindTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1))]
        uniform matrix4d[] restTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1))]
        rel skel:animationSource = </Root/Skel/Anim>

        def SkelAnimation "Anim"
        {
            uniform token[] joints = ["Hips"]
            float3[] translations.timeSamples = { 0: [(0,1,0)], 12: [(0,1,2)] }
            quatf[] rotations = [(1,0,0,0)]
            half3[] scales = [(1,1,1)]
            uniform token[] blendShapes = ["Smile", "Frown"]
            float[] blendShapeWeights.timeSamples = { 0: [0, 0], 6: [1, 0.25], 12: [0.5, 0] }
        }
    }

    def Mesh "Face" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,1,0), (1,1,0), (0,2,0)]
        int[] primvars:skel:jointIndices = [0] (
            interpolation = "constant"
            elementSize = 1
        )
        float[] primvars:skel:jointWeights = [1] (
            interpolation = "constant"
            elementSize = 1
        )
        uniform token[] skel:blendShapes = ["Frown", "Smile"]
        rel skel:blendShapeTargets = [</Root/Face/Frown>, </Root/Face/Smile>]

        def BlendShape "Smile"
        {
            uniform vector3f[] offsets = [(0, 0, 3)]
            uniform int[] pointIndices = [1]
        }

        def BlendShape "Frown"
        {
            uniform vector3f[] offsets = [(0, -4, 0)]
            uniform int[] pointIndices = [2]
        }
    }
}
"""


def test_blend_shape_warning_states_largest_displacement(tmp_path):
    """By hand: at time code 6 Smile (weight 1) moves point 1 by 3 and Frown (0.25) point 2 by 1;
    the largest is 3 (the mesh's own blend shape order differs from the animation's, which the
    mapper resolves). UsdSkel.BakeSkinning, which applies them, differs from the conversion by
    exactly that at that frame."""
    source = tmp_path / "face.usda"
    source.write_text(BLEND)
    scene = usdskel.read(source)
    (warning,) = [w for w in scene.warnings if "blend shapes" in w]
    assert warning.endswith("move a point by up to 3 scene units (point 1, time code 6)"), warning
    vb = bake(scene.animations[0], BakeOptions(encoding="affineMatrix", texel_format="float32"))
    clip = vb.clips[0]
    codes = (clip.start_time + np.arange(clip.row_count) / clip.rows_per_second) * scene.time_codes_per_second
    reference = baked_by_usdskel(source, tmp_path, codes, {})["/Root/Face"]
    ours, _ = skin_mesh_at_rows(vb, vb.meshes[0], 0)
    row = int(np.argmin(np.abs(codes - 6)))
    np.testing.assert_allclose(np.linalg.norm(reference[row] - ours[row], axis=1), [0, 3, 1], atol=1e-5)
