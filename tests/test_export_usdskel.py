"""The UsdSkel fallback (spec/runtime-package.md, "UsdSkel fallback"): `vbusd export ... --as usdskel`.

Independence: the fallback is skinned by UsdSkel itself (``UsdSkel.Cache`` ->
``SkelQuery.ComputeSkinningTransforms`` -> ``SkinningQuery.ComputeSkinnedPoints``, with the time
mapping of USD's own layer offsets and variant selections and the instance transforms from
``UsdGeom.Xformable.ComputeLocalToWorldTransform``), and compared with vbusd's numpy reference
decode of the asset (:mod:`vbusd.decoders.reference`), which is itself tested against the spec's
hand-computed examples. The bound is the texel format's rounding bound ``tol`` of
spec/validation.md, computed here by hand, times the rest point's length, plus float32 rounding.
The comparison is made at row times, where both sides read stored rows exactly; between rows
UsdSkel interpolates rotations spherically and the spec linearly (spec: "UsdSkel fallback").
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest


import vbusd  # noqa: E402,F401  (registers the schema plugin)
from vbusd.cli import main  # noqa: E402
from vbusd.decoders.reference import skin_crowd, skin_mesh  # noqa: E402
from vbusd.format.model import Clip, Crowd  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "stadium_crowd"
TOLERANCE = {"float16": 4 * 2.0 ** -11, "float32": 4 * 2.0 ** -24 + 1e-6}  # spec/validation.md
FLOAT32 = 2.0 ** -22  # a few float32 roundings in UsdSkel's and USD's arithmetic, relative


def tolerance(vb) -> float:
    name = vb.layout.texel_format.value
    if name in TOLERANCE:
        return TOLERANCE[name]
    ranges = np.asarray(vb.unorm_ranges)
    return 4 * np.sqrt(3) * float(np.max(ranges[..., 1] - ranges[..., 0])) / 65535 / 2 + 1e-7


def usdskel_points(stage, root_path: str, code: float) -> list:
    """World-space skinned points of every mesh under the SkelRoot at ``root_path``, by UsdSkel."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath(root_path))
    assert root, f"{root_path} is not a SkelRoot"
    cache.Populate(root, Usd.PrimDefaultPredicate)
    out = []
    for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
        query = cache.GetSkelQuery(binding.GetSkeleton())
        transforms = query.ComputeSkinningTransforms(code)
        for target in binding.GetSkinningTargets():
            points = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(code)
            assert target.ComputeSkinnedPoints(transforms, points, code)
            world = UsdGeom.Xformable(target.GetPrim()).ComputeLocalToWorldTransform(code)
            out.append(np.array([world.Transform(Gf.Vec3d(p)) for p in points]))
    return out


def copy_sample(tmp_path) -> Path:
    folder = tmp_path / "asset"
    folder.mkdir()
    for path in SAMPLE.glob("stadium_crowd_vb*"):
        shutil.copy(path, folder / path.name)
    return folder / "stadium_crowd_vb.usda"


def export(asset: Path, out: Path, *extra) -> dict:
    import io
    from contextlib import redirect_stdout

    buffer = io.StringIO()
    with redirect_stdout(buffer):
        assert main(["export", str(asset), "-o", str(out), "--as", "usdskel", "--format", "json", *extra]) == 0
    return json.loads(buffer.getvalue())


@pytest.fixture(scope="module")
def encodings(tmp_path_factory):
    """The stadium character in every encoding: the sample's crossMatrix/float16 bake, and the
    UsdSkel source converted to the others (one texel format each)."""
    folder = tmp_path_factory.mktemp("encodings")
    assets = {}
    for encoding, texel_format in (("dualQuat", "float32"), ("quatTranslation", "unorm16"),
                                   ("affineMatrix", "float16")):
        out = folder / f"{encoding}.usda"
        assert main(["convert", str(SAMPLE / "stadium_crowd.usda"), "-o", str(out), "--encoding", encoding,
                     "--texel-format", texel_format, "--quiet"]) == 0
        assets[encoding] = out
    return assets


def character_only(tmp_path, source: Path) -> Path:
    """The asset without its crowd: the fallback then draws the character itself."""
    from vbusd.io.usd import read_asset, write_asset

    asset = read_asset(source)
    out = tmp_path / "character" / "character.usda"
    out.parent.mkdir()
    write_asset(replace(asset, crowds=(), crowd_animation=()), out)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("encoding", ["crossMatrix", "dualQuat", "quatTranslation", "affineMatrix"])
def test_usdskel_skinning_equals_the_reference_decode_at_every_row(tmp_path, encodings, encoding):
    from pxr import Usd, UsdSkel

    source = copy_sample(tmp_path) if encoding == "crossMatrix" else encodings[encoding]
    asset_path = character_only(tmp_path, source)
    report = export(asset_path, tmp_path / "fallback.usda")
    asset = vbusd.read_asset(asset_path)
    vb = asset.animations[0]
    assert vb.layout.encoding.value == encoding
    tol = tolerance(vb)
    assert report["tolerance"] == pytest.approx(tol) and report["maxMatrixDeviation"] <= tol
    assert not report["warnings"]
    stage = Usd.Stage.Open(str(tmp_path / "fallback.usda"))
    # What a Hydra renderer needs: SkelRoot, Skeleton, one SkelAnimation per clip, SkelBindingAPI.
    (root,) = [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]
    animations = [p for p in Usd.PrimRange.AllPrims(stage.GetPrimAtPath("/_VbusdCharacters"))
                  if p.IsA(UsdSkel.Animation)]
    assert len(animations) == len(vb.clips)
    (mesh_prim,) = [p for p in Usd.PrimRange(root) if p.HasAPI(UsdSkel.BindingAPI) and p.GetTypeName() == "Mesh"]
    method = UsdSkel.BindingAPI(mesh_prim).GetSkinningMethodAttr().Get()
    assert method == ("dualQuaternion" if encoding == "dualQuat" else "classicLinear")
    clip = vb.clips[0]
    tcps = asset.time_codes_per_second
    rows = np.arange(0, clip.row_count + 1, 7)  # every 7th row and the wrap (row N = row 0)
    reference, _ = skin_mesh(vb, vb.meshes[0], 0, rows / clip.rows_per_second)
    rest = np.linalg.norm(vb.meshes[0].points, axis=1)
    worst = 0.0
    for k, row in enumerate(rows):
        (points,) = usdskel_points(stage, str(root.GetPath()), (clip.start_time + row / clip.rows_per_second) * tcps)
        error = np.linalg.norm(points - reference[k], axis=1)
        bound = tol * rest + FLOAT32 * (rest + np.linalg.norm(reference[k], axis=1))
        assert np.all(error <= bound), (row, float(np.max(error / bound)))
        worst = max(worst, float(error.max()))
    # The bound discriminates: the pose moves far more than it from one row to the next.
    motion = np.linalg.norm(reference[1:] - reference[:-1], axis=2).max()
    assert worst < motion / 20, (worst, motion)


def crowd_asset(tmp_path) -> Path:
    """The sample split into a looping and a clamped clip, with a crowd whose instances play both,
    forwards, backwards, frozen and at double and half speed; time offsets on whole rows."""
    from vbusd.io.usd import read_asset, write_asset

    asset = read_asset(copy_sample(tmp_path))
    vb = asset.animations[0]
    rate = vb.clips[0].rows_per_second
    vb = replace(vb, clips=(Clip("loop", 0, 200, rate, True), Clip("once", 200, 312, rate, False, 1.0)),
                 clip_extents=None)
    rates = np.array([1, 2, 0.5, -1, 0, 1, -2, 0.5], np.float32)
    clips = np.array([0, 0, 0, 0, 0, 1, 1, 1], np.int32)
    offsets = (np.array([0, 17, 190, 5, 33, 300, 100, -40]) / rate).astype(np.float32)
    n = rates.size
    angle = np.linspace(0, 3, n)
    quats = np.stack([np.zeros(n), np.sin(angle / 2), np.zeros(n), np.cos(angle / 2)], axis=1).astype(np.float32)
    crowd = Crowd(path=asset.crowds[0].path, positions=np.stack([np.arange(n) * 2.0, np.zeros(n), np.ones(n)],
                                                                  axis=1).astype(np.float32),
                  orientations=quats, clip=clips, time_offset=offsets, playback_rate=rates,
                  scales=np.full((n, 3), 1.5, np.float32))
    out = tmp_path / "crowd" / "crowd.usda"
    out.parent.mkdir()
    write_asset(replace(asset, animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), out)
    return out


@pytest.mark.slow
def test_crowd_instances_play_their_clip_offset_and_rate_through_layer_offsets(tmp_path):
    from pxr import Usd

    asset_path = crowd_asset(tmp_path)
    report = export(asset_path, tmp_path / "crowd_fallback.usda", "--duration", "6")
    assert report["instances"] == [8]
    asset = vbusd.read_asset(asset_path)
    vb, crowd = asset.animations[0], asset.crowds[0]
    tcps = asset.time_codes_per_second
    rate = vb.clips[0].rows_per_second
    stage = Usd.Stage.Open(str(tmp_path / "crowd_fallback.usda"))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == pytest.approx(6 * tcps)
    tol = tolerance(vb)
    rest = np.linalg.norm(vb.meshes[0].points, axis=1)
    # Stage times on even rows keep every instance's time on a row (rates 0.5 .. 2); 290 rows is
    # past the looping clip's end (200 rows): it must have wrapped, the clamped one held.
    for row in (0, 2, 64, 150, 290):
        t = row / rate
        reference, _ = skin_crowd(vb, vb.meshes[0], crowd, t)
        for i in range(crowd.instance_count):
            (points,) = usdskel_points(stage, f"/StadiumCrowd/Crowd/i{i}", t * tcps)
            error = np.linalg.norm(points - reference[i], axis=1)
            bound = 1.5 * tol * rest + FLOAT32 * (rest + np.linalg.norm(reference[i], axis=1))
            assert np.all(error <= bound), (row, i, float(np.max(error / bound)))


def test_crowd_built_by_vbusd_crowd_and_the_size_against_a_point_cache(tmp_path):
    from pxr import Usd, UsdSkel

    character = copy_sample(tmp_path)
    crowd = tmp_path / "asset" / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "50", "--rate", "0.8", "1.2",
                 "--seed", "3"]) == 0
    report = export(crowd, tmp_path / "asset" / "crowd_skel.usdc")
    assert report["instances"] == [50]
    stage = Usd.Stage.Open(str(tmp_path / "asset" / "crowd_skel.usdc"))
    roots = [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]
    assert len(roots) == 50  # the characters' class is not drawn
    # One character's joints instead of 50 x 202 points per sample: far below a point cache
    # (50 x 202 x 24 bytes x 301 samples = 73 MB).
    assert report["files"][str(tmp_path / "asset" / "crowd_skel.usdc")] < 50 * 202 * 24 * 301 / 20


def _one_error(capsys, code: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vbusd: ") and f": {code}: " in err[0], err
    return err[0]


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys):
    from vbusd.io.usd import read_asset, write_asset

    character = copy_sample(tmp_path)
    asset = read_asset(character)
    bare = tmp_path / "bare" / "bare.usda"
    bare.parent.mkdir()
    write_asset(replace(asset, animations=(replace(asset.animations[0], meshes=()),), crowds=(),
                        crowd_animation=()), bare)
    out = tmp_path / "out" / "fallback.usda"
    assert main(["export", str(bare), "-o", str(out), "--as", "usdskel"]) == 2
    assert "bare.usda" in _one_error(capsys, "export.noMeshes")
    assert not out.parent.exists()
    # A crowd whose character is gone.
    crowd = tmp_path / "asset" / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "4"]) == 0
    capsys.readouterr()
    for path in character.parent.glob("stadium_crowd_vb*"):
        path.unlink()
    assert main(["export", str(crowd), "-o", str(out), "--as", "usdskel"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not out.parent.exists()
    # Usage: wrong suffix, --duration without usdskel, an existing output without --force.
    assert main(["export", str(crowd), "-o", str(tmp_path / "x.glb"), "--as", "usdskel"]) == 2
    _one_error(capsys, "options.invalid")
    assert main(["export", str(crowd), "-o", str(tmp_path / "x.glb"), "--duration", "3"]) == 2
    _one_error(capsys, "options.invalid")
    out.parent.mkdir()
    out.write_text("keep me")
    assert main(["export", str(crowd), "-o", str(out), "--as", "usdskel"]) == 2
    _one_error(capsys, "options.invalid")
    assert out.read_text() == "keep me"


@pytest.mark.slow
def test_openusd_validators_accept_the_fallback_and_catch_a_missing_binding(tmp_path):
    """OpenUSD's own validators (UsdSkel's SkelBindingAPI checks, composition, stage metadata) find
    nothing in the fallback of the stadium crowd; with SkelBindingAPI removed from the mesh they do."""
    from pxr import Usd, UsdValidation

    validators = [v for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
                  if not v.GetMetadata().name.startswith("vbusd")]
    names = {v.GetMetadata().name for v in validators}
    assert "usdSkelValidators:SkelBindingApiAppliedValidator" in names
    out = tmp_path / "fallback.usda"
    export(copy_sample(tmp_path), out)

    def errors(path):
        return [f"{e.GetValidator().GetMetadata().name}: {e.GetMessage()}"
                for e in UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))]

    assert errors(out) == []
    text = out.read_text()
    start = text.index('def Mesh "Body"')
    schema = text.index('prepend apiSchemas = ["SkelBindingAPI"]', start)
    broken = tmp_path / "broken.usda"
    broken.write_text(text[:schema] + text[schema + len('prepend apiSchemas = ["SkelBindingAPI"]'):])
    found = errors(broken)
    assert found and all("SkelBindingApiAppliedValidator" in e for e in found)


def test_shear_that_usdskel_cannot_hold_is_reported(tmp_path, capsys):
    """An affineMatrix bone with shear (x += 0.5 y): UsdSkel's transforms have none, so the export
    warns with the deviation, and UsdSkel's skinning indeed differs from the reference there."""
    from pxr import Usd

    from vbusd.format.encoding import pack
    from vbusd.format.layout import Layout
    from vbusd.format.model import BoundMesh, VirtualBones, VirtualBonesAsset
    from vbusd.io.usd import write_asset

    layout = Layout("affineMatrix", "float32", 1, 2)
    identity = np.eye(3, 4)
    shear = np.eye(3, 4)
    shear[0, 1] = 0.5
    texels = pack(np.stack([identity, shear])[:, None].astype(np.float32), layout)  # rows of [A | t]
    mesh = BoundMesh(path="/Rig/Tri", points=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32),
                     face_vertex_counts=np.array([3], np.int32), face_vertex_indices=np.array([0, 1, 2], np.int32),
                     bone_indices=np.zeros((3, 1), np.int32), bone_weights=np.ones((3, 1), np.float32))
    vb = VirtualBones(layout=layout, texels=texels, bones=("b",), clips=(Clip("c", 0, 2, 1.0, False),),
                      meshes=(mesh,), path="/Rig/Anim")
    path = tmp_path / "rig" / "rig.usda"
    path.parent.mkdir()
    write_asset(VirtualBonesAsset(animations=(vb,), default_prim="Rig", time_codes_per_second=1.0), path)
    report = export(path, tmp_path / "sheared.usda")
    assert report["maxMatrixDeviation"] > 0.1 > report["tolerance"]
    assert len(report["warnings"]) == 1 and "shear" in report["warnings"][0]
    stage = Usd.Stage.Open(str(tmp_path / "sheared.usda"))
    (points,) = usdskel_points(stage, "/Rig/Anim", 1.0)  # row 1: the sheared one
    reference, _ = skin_mesh(vb, mesh, 0, [1.0])
    assert np.abs(reference[0][2] - [0.5, 1, 0]).max() < 1e-6       # x += 0.5 y, by hand
    assert np.linalg.norm(points[2] - reference[0][2]) > 0.1
