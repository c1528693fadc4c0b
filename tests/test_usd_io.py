"""USD writer and reader of Virtual Bones assets (vbusd.io.usd).

Round trips for every encoding x texel format with random valid data; the written files inspected
with plain pxr (independent of vbusd's reader) against hand-computed values; quaternion order checked
with Gf.Rotation; the write transaction, path safety, prim/texture disagreement and malformed USD.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import math
import hashlib
import re
from pathlib import Path

import numpy as np
import pytest


import vbusd  # noqa: E402,F401  (registers the schema plugin)
from vbusd.format import metadata as md  # noqa: E402
from vbusd.io import usd as usd_io  # noqa: E402
from vbusd.format.errors import InputError, OptionsError  # noqa: E402
from vbusd.format.layout import Encoding, Layout, Padding, TexelFormat  # noqa: E402
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones, VirtualBonesAsset  # noqa: E402

ENCODINGS = [e.value for e in Encoding]
FORMATS = [f.value for f in TexelFormat]
COMBOS = [(e, f) for e in ENCODINGS for f in FORMATS
          if (e == "compactQuatTranslation") == (f == "uint32")]  # format 1.2: uint32 is the compact encoding's


# --------------------------------------------------------------------------------------------
# Random but valid data
# --------------------------------------------------------------------------------------------


def make_mesh(rng, path: str, bone_count: int, *, vertices: int = 12, influences: int = 4,
              face_varying: bool = False) -> BoundMesh:
    faces = vertices - 2
    counts = np.full(faces, 3, dtype=np.int32)
    indices = rng.integers(0, vertices, size=3 * faces).astype(np.int32)
    weights = rng.random((vertices, influences)).astype(np.float32)
    weights /= weights.sum(axis=1, keepdims=True)
    normals_count = 3 * faces if face_varying else vertices
    normals = rng.normal(size=(normals_count, 3)).astype(np.float32)
    return BoundMesh(path=path, points=rng.normal(size=(vertices, 3)).astype(np.float32),
                     face_vertex_counts=counts, face_vertex_indices=indices,
                     bone_indices=rng.integers(0, bone_count, size=(vertices, influences)).astype(np.int32),
                     bone_weights=weights.astype(np.float32), normals=normals,
                     normals_interpolation="faceVarying" if face_varying else "vertex")


def make_animation(rng, encoding: str, texel_format: str, *, bone_count: int = 5,
                   clip_rows=(7, 4), path: str = "/VirtualBones/Fan/Anim", meshes=None,
                   vertical: str = "none", with_extents: bool = True) -> VirtualBones:
    rows = sum(clip_rows)
    layout = Layout(encoding, texel_format, bone_count, rows, Padding.POWER_OF_TWO, vertical)
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    used = (layout.row_count, layout.used_width, 4)
    ranges = None
    if layout.texel_format is TexelFormat.UNORM16:
        texels[:layout.row_count, :layout.used_width] = rng.integers(0, 65536, size=used)
        low = rng.normal(size=(layout.texels_per_bone, 4))
        ranges = np.stack([low, low + rng.random((layout.texels_per_bone, 4)) + 0.01], axis=-1)
    elif layout.texel_format is TexelFormat.UINT32:
        words = rng.integers(0, 1 << 32, size=used[:2] + (3,), dtype=np.uint64).astype(np.uint32)
        words[..., 1] &= np.uint32(0x7FFFFFFF)  # bit 31 of G is reserved (spec 5.6.2)
        texels[:layout.row_count, :layout.used_width, :3] = words
        low = rng.normal(size=(bone_count, 7)).astype(np.float32).astype(np.float64)  # float32 in USD
        ranges = np.stack([low, low + rng.random((bone_count, 7)).astype(np.float32) + 0.01], axis=-1)
    else:
        texels[:layout.row_count, :layout.used_width] = rng.normal(size=used) * 3
    clips, first = [], 0
    for i, count in enumerate(clip_rows):
        clips.append(Clip(f"clip{i}", first, count, float(rng.integers(1, 60)) + 0.5, bool(i % 2 == 0),
                          float(rng.random() * 10)))
        first += count
    if meshes is None:
        meshes = (make_mesh(rng, path.rsplit("/", 1)[0] + "/Body", bone_count),
                  make_mesh(rng, path.rsplit("/", 1)[0] + "/Head", bone_count, vertices=8,
                            influences=2, face_varying=True))
    extents = rng.normal(size=(len(clips), 2, 3)).astype(np.float32) if with_extents else None
    return VirtualBones(layout=layout, texels=texels, bones=tuple(f"Root/b{i}" for i in range(bone_count)),
                        clips=tuple(clips), unorm_ranges=ranges, meshes=tuple(meshes), path=path,
                        clip_extents=extents)


def make_crowd(rng, path: str = "/VirtualBones/Crowd", count: int = 6, clips: int = 2,
               scales: bool = True) -> Crowd:
    quats = rng.normal(size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return Crowd(path=path, positions=rng.normal(size=(count, 3)).astype(np.float32) * 10,
                 orientations=quats.astype(np.float32),
                 clip=rng.integers(0, clips, size=count).astype(np.int32),
                 time_offset=(rng.random(count) * 5).astype(np.float32),
                 playback_rate=(0.5 + rng.random(count)).astype(np.float32),
                 scales=(0.5 + rng.random((count, 3))).astype(np.float32) if scales else None)


def make_asset(rng, encoding="crossMatrix", texel_format="float16", **kwargs) -> VirtualBonesAsset:
    vb = make_animation(rng, encoding, texel_format, **kwargs)
    return VirtualBonesAsset(animations=(vb,), crowds=(make_crowd(rng),), crowd_animation=(0,),
                             up_axis="Z", meters_per_unit=0.01, time_codes_per_second=30.0,
                             default_prim="VirtualBones")


def assert_meshes_equal(ours: BoundMesh, theirs: BoundMesh) -> None:
    assert ours.path == theirs.path
    for field in ("points", "face_vertex_counts", "face_vertex_indices", "bone_indices",
                  "bone_weights", "normals"):
        a, b = getattr(ours, field), getattr(theirs, field)
        assert a.dtype == b.dtype and np.array_equal(a, b), field
    assert ours.normals_interpolation == theirs.normals_interpolation


def assert_crowds_equal(ours: Crowd, theirs: Crowd) -> None:
    assert ours.path == theirs.path
    for field in ("positions", "orientations", "clip", "time_offset", "playback_rate", "scales"):
        a, b = getattr(ours, field), getattr(theirs, field)
        if a is None or b is None:
            assert a is None and b is None, field
            continue
        assert np.array_equal(np.asarray(a, b.dtype), b), field


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("encoding, texel_format", COMBOS)
def test_round_trip_is_exact(tmp_path, encoding, texel_format):
    rng = np.random.default_rng(100 + 10 * ENCODINGS.index(encoding) + FORMATS.index(texel_format))
    suffix = ".usdc" if (ENCODINGS.index(encoding) + FORMATS.index(texel_format)) % 2 else ".usda"
    asset = make_asset(rng, encoding, texel_format)
    target = tmp_path / f"crowd{suffix}"
    written = usd_io.write_asset(asset, target)

    container = "png" if texel_format == "unorm16" else "exr"
    texture = tmp_path / f"crowd.Anim.{container}"
    assert written == [target, texture, tmp_path / f"crowd.Anim.{container}.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in written)

    back = usd_io.read_asset(target)
    (ours,), (theirs,) = asset.animations, back.animations
    assert theirs.layout == ours.layout
    assert theirs.texels.dtype == ours.texels.dtype
    assert theirs.texels.tobytes() == ours.texels.tobytes()  # bit-identical, padding included
    assert theirs.bones == ours.bones and theirs.clips == ours.clips
    assert md.to_dict(theirs, generator=GENERATOR) == md.to_dict(ours, generator=GENERATOR)  # every metadata key, digest included
    assert theirs.path == ours.path and theirs.texture == f"./{texture.name}"
    if texel_format in ("unorm16", "uint32"):
        assert np.array_equal(theirs.unorm_ranges, ours.unorm_ranges)  # float64, from the metadata
    else:
        assert theirs.unorm_ranges is None
    assert np.array_equal(theirs.clip_extents, ours.clip_extents)
    assert len(theirs.meshes) == len(ours.meshes)
    for a, b in zip(ours.meshes, theirs.meshes):
        assert_meshes_equal(a, b)
    assert back.crowd_animation == (0,)
    assert_crowds_equal(asset.crowds[0], back.crowds[0])
    assert (back.up_axis, back.meters_per_unit, back.time_codes_per_second, back.default_prim) == \
        ("Z", 0.01, 30.0, "VirtualBones")


def test_round_trip_several_animations_and_crowds(tmp_path):
    rng = np.random.default_rng(7)
    fan = make_animation(rng, "dualQuat", "float32", path="/Stadium/Fan/Anim", with_extents=False)
    guard = make_animation(rng, "quatTranslation", "unorm16", bone_count=3, clip_rows=(5,),
                           path="/Stadium/Guard/Motion", vertical="powerOfTwo")
    crowds = (make_crowd(rng, "/Stadium/Fans", 20, 2), make_crowd(rng, "/Stadium/Guards", 3, 1, False),
              make_crowd(rng, "/Stadium/MoreFans", 4, 2))
    asset = VirtualBonesAsset(animations=(fan, guard), crowds=crowds, crowd_animation=(0, 1, 0),
                              default_prim="Stadium", extra={"frames_per_second": 60.0})
    usd_io.write_asset(asset, tmp_path / "stadium.usda")
    back = usd_io.read_asset(tmp_path / "stadium.usda")
    assert [vb.path for vb in back.animations] == ["/Stadium/Fan/Anim", "/Stadium/Guard/Motion"]
    assert back.animations[0].clip_extents is None
    assert back.animations[1].layout.height == 8  # 5 rows, vertical powerOfTwo
    assert back.animations[1].texture == "./stadium.Motion.png"
    for a, b in zip(asset.animations, back.animations):
        assert a.texels.tobytes() == b.texels.tobytes()
        assert [m.path for m in a.meshes] == [m.path for m in b.meshes]
    assert back.crowd_animation == (0, 1, 0)
    for a, b in zip(crowds, back.crowds):
        assert_crowds_equal(a, b)
    assert back.default_prim == "Stadium" and back.extra == {"frames_per_second": 60.0}


# --------------------------------------------------------------------------------------------
# What plain pxr sees
# --------------------------------------------------------------------------------------------


def talk_like_asset(rng) -> VirtualBonesAsset:
    """The talk's rig shape: 18 bones crossMatrix float16, 300 rows padded to 512."""
    vb = make_animation(rng, "crossMatrix", "float16", bone_count=18, clip_rows=(300,),
                        vertical="powerOfTwo")
    return VirtualBonesAsset(animations=(vb,), crowds=(make_crowd(rng, count=4, clips=1),),
                             crowd_animation=(0,), up_axis="Y", meters_per_unit=1.0,
                             time_codes_per_second=24.0)


def test_written_usda_read_with_plain_pxr(tmp_path):
    from pxr import Sdf, Tf, Usd, UsdGeom

    rng = np.random.default_rng(1)
    asset = talk_like_asset(rng)
    usd_io.write_asset(asset, tmp_path / "crowd.usda")
    assert (tmp_path / "crowd.usda").read_text().startswith("#usda 1.0")

    stage = Usd.Stage.Open(str(tmp_path / "crowd.usda"))
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/VirtualBones")
    assert stage.GetDefaultPrim().GetTypeName() == "Xform"
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetFramesPerSecond() == 24.0

    anim = stage.GetPrimAtPath("/VirtualBones/Fan/Anim")
    assert anim.IsA(Tf.Type.FindByName("VirtualBonesAnimation"))
    assert stage.GetPrimAtPath("/VirtualBones/Fan").GetTypeName() == "Xform"
    get = lambda name: anim.GetAttribute(name).Get()  # noqa: E731
    # 18 bones x 3 texels = 54 columns -> 64; 300 rows -> 512.
    assert (get("vb:boneCount"), get("vb:texelsPerBone"), get("vb:textureWidth"),
            get("vb:rowCount"), get("vb:textureHeight")) == (18, 3, 64, 300, 512)
    assert (get("vb:encoding"), get("vb:texelFormat"), get("vb:horizontalPadding"),
            get("vb:verticalPadding"), get("vb:formatVersion")) == \
        ("crossMatrix", "float16", "powerOfTwo", "powerOfTwo", 1)
    for name in ("vb:encoding", "vb:texelFormat", "vb:boneCount", "vb:formatVersion"):
        assert anim.GetAttribute(name).HasAuthoredValue(), name  # written, not left to fallbacks
    assert get("vb:texture").path == "./crowd.Anim.exr"
    assert get("vb:texture").resolvedPath == str((tmp_path / "crowd.Anim.exr").resolve())
    assert list(get("vb:bones"))[:2] == ["Root/b0", "Root/b1"]
    assert re.fullmatch(r"sha256:[0-9a-f]{64}", get("vb:contentDigest"))
    assert len(get("vb:clipExtents")) == 2
    assert anim.GetAttribute("vb:unormRangeMin").Get() is None  # float16: no ranges

    body = stage.GetPrimAtPath("/VirtualBones/Fan/Body")
    assert body.IsA(UsdGeom.Mesh)
    assert body.HasAPI(Tf.Type.FindByName("VirtualBonesBindingAPI"))
    assert body.GetRelationship("vb:animation").GetTargets() == [Sdf.Path("/VirtualBones/Fan/Anim")]
    indices = UsdGeom.PrimvarsAPI(body).GetPrimvar("vb:boneIndices")
    assert indices.GetInterpolation() == "vertex" and indices.GetElementSize() == 4
    assert len(indices.Get()) == 12 * 4
    weights = UsdGeom.PrimvarsAPI(body).GetPrimvar("vb:boneWeights")
    assert weights.GetInterpolation() == "vertex" and weights.GetElementSize() == 4
    mesh = UsdGeom.Mesh(body)
    assert mesh.GetNormalsInterpolation() == "vertex"
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
    points = np.asarray(mesh.GetPointsAttr().Get())
    assert np.array_equal(np.asarray(mesh.GetExtentAttr().Get()),
                          np.stack([points.min(axis=0), points.max(axis=0)]))
    head = UsdGeom.Mesh(stage.GetPrimAtPath("/VirtualBones/Fan/Head"))
    assert head.GetNormalsInterpolation() == "faceVarying"

    crowd = stage.GetPrimAtPath("/VirtualBones/Crowd")
    assert crowd.IsA(UsdGeom.PointInstancer)
    assert crowd.HasAPI(Tf.Type.FindByName("VirtualBonesInstancingAPI"))
    assert crowd.GetRelationship("vb:animation").GetTargets() == [Sdf.Path("/VirtualBones/Fan/Anim")]
    for name in ("vb:clip", "vb:timeOffset", "vb:playbackRate"):
        primvar = UsdGeom.PrimvarsAPI(crowd).GetPrimvar(name)
        assert primvar.GetInterpolation() == "vertex" and len(primvar.Get()) == 4, name
    instancer = UsdGeom.PointInstancer(crowd)
    assert list(instancer.GetProtoIndicesAttr().Get()) == [0, 0, 0, 0]
    (prototype,) = instancer.GetPrototypesRel().GetTargets()
    assert prototype.HasPrefix(crowd.GetPath())  # under the instancer: not drawn on its own
    # The prototype holds the bound meshes (by reference), with their binding.
    proto_body = stage.GetPrimAtPath(prototype.AppendChild("Body"))
    assert proto_body.IsA(UsdGeom.Mesh) and proto_body.HasAPI("VirtualBonesBindingAPI")
    assert np.array_equal(np.asarray(UsdGeom.Mesh(proto_body).GetPointsAttr().Get()), points)
    assert proto_body.GetRelationship("vb:animation").GetTargets() == [Sdf.Path("/VirtualBones/Fan/Anim")]

    # Nothing in the file makes USD complain.
    assert stage.GetCompositionErrors() == []


def test_usdc_is_a_crate_file(tmp_path):
    rng = np.random.default_rng(2)
    usd_io.write_asset(make_asset(rng), tmp_path / "crowd.usdc")
    assert (tmp_path / "crowd.usdc").read_bytes()[:8] == b"PXR-USDC"


def _rotate_z_asset(rng, degrees: float) -> VirtualBonesAsset:
    half = math.radians(degrees) / 2
    crowd = Crowd(path="/VirtualBones/Crowd", positions=np.array([[10, 0, 0]], np.float32),
                  orientations=np.array([[0, 0, math.sin(half), math.cos(half)]], np.float32),
                  clip=np.zeros(1, np.int32), time_offset=np.zeros(1, np.float32),
                  playback_rate=np.ones(1, np.float32))
    vb = make_animation(rng, "crossMatrix", "float16")
    return VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,))


def test_quaternion_order_matches_gf(tmp_path):
    from pxr import Gf, Usd, UsdGeom

    usd_io.write_asset(_rotate_z_asset(np.random.default_rng(3), 90), tmp_path / "rot.usda")
    stage = Usd.Stage.Open(str(tmp_path / "rot.usda"))
    instancer = UsdGeom.PointInstancer(stage.GetPrimAtPath("/VirtualBones/Crowd"))
    for attribute, to_double in ((instancer.GetOrientationsAttr(), Gf.Quatd),
                                 (instancer.GetOrientationsfAttr(), Gf.Quatd)):
        (quat,) = attribute.Get()
        rotated = Gf.Rotation(to_double(quat)).TransformDir(Gf.Vec3d(1, 0, 0))
        assert Gf.IsClose(rotated, Gf.Vec3d(0, 1, 0), 1e-3), (attribute.GetName(), rotated)
    # UsdGeom's own instance transform (row vectors): (1, 0, 0) -> (0, 1, 0) + position (10, 0, 0).
    (matrix,) = instancer.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    assert Gf.IsClose(matrix.Transform(Gf.Vec3d(1, 0, 0)), Gf.Vec3d(10, 1, 0), 1e-3)


# --------------------------------------------------------------------------------------------
# Transaction and options
# --------------------------------------------------------------------------------------------


def _listing(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_failed_texture_write_leaves_nothing(tmp_path, monkeypatch):
    import vbusd.io.exr

    rng = np.random.default_rng(4)
    first = make_animation(rng, "crossMatrix", "float16", path="/VirtualBones/A/Anim")
    second = make_animation(rng, "affineMatrix", "float32", path="/VirtualBones/B/Other")
    asset = VirtualBonesAsset(animations=(first, second))
    (tmp_path / "crowd.usda").write_text("#usda 1.0\n# an older asset\n")
    (tmp_path / "crowd.Other.exr").write_bytes(b"old texture")
    before = _listing(tmp_path)

    real_write_exr = vbusd.io.exr.write_exr
    calls = []

    def failing_write_exr(path, *args, **kwargs):
        calls.append(Path(path))
        if len(calls) == 2:  # the first texture is complete (as a temporary) when the second fails
            Path(path).write_bytes(b"partial")
            raise OSError("disk full (injected)")
        return real_write_exr(path, *args, **kwargs)

    monkeypatch.setattr(vbusd.io.exr, "write_exr", failing_write_exr)
    with pytest.raises(OSError, match="injected"):
        usd_io.write_asset(asset, tmp_path / "crowd.usda")
    assert len(calls) == 2 and all(p.parent == tmp_path and p.name != "crowd.A.exr" for p in calls)
    assert _listing(tmp_path) == before  # no new file, no temporary, old files untouched


def test_failed_usd_export_leaves_nothing(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    asset = make_asset(rng)
    real_build = usd_io.build_stage

    class NoExport:  # the real stage, except that its layer's Export fails (returns False)
        def __init__(self, stage):
            self.stage = stage

        def __getattr__(self, name):
            return getattr(self.stage, name)

        def GetRootLayer(self):
            class Layer:
                def __init__(self, real):
                    object.__setattr__(self, "real", real)

                def __getattr__(self, name):
                    return getattr(self.real, name)

                def __setattr__(self, name, value):
                    setattr(self.real, name, value)

                def Export(self, path):
                    return False
            return Layer(self.stage.GetRootLayer())

    monkeypatch.setattr(usd_io, "build_stage", lambda *a: NoExport(real_build(*a)))
    with pytest.raises(OSError):
        usd_io.write_asset(asset, tmp_path / "crowd.usda")
    assert list(tmp_path.iterdir()) == []


def test_second_write_replaces_all_files(tmp_path):
    from pxr import Sdf

    rng = np.random.default_rng(6)
    usd_io.write_asset(make_asset(rng, "crossMatrix", "float16"), tmp_path / "crowd.usda")
    held = Sdf.Layer.FindOrOpen(str(tmp_path / "crowd.usda"))  # keeps the old layer in USD's registry
    newer = make_asset(rng, "crossMatrix", "float16", bone_count=7)
    usd_io.write_asset(newer, tmp_path / "crowd.usda")
    assert held is not None
    back = usd_io.read_asset(tmp_path / "crowd.usda")  # the registry must not serve the old layer
    assert back.animations[0].layout.bone_count == 7
    assert back.animations[0].texels.tobytes() == newer.animations[0].texels.tobytes()


@pytest.mark.parametrize("name, container, message", [
    ("crowd.usdz", None, "usdz"),
    ("crowd.abc", None, "must end in"),
    ("crowd.usda", "png", "float16"),
    ("crowd.usda", "tiff", "texture_container"),
])
def test_bad_options_are_refused_before_writing(tmp_path, name, container, message):
    rng = np.random.default_rng(8)
    with pytest.raises(OptionsError, match=message):
        usd_io.write_asset(make_asset(rng), tmp_path / name, texture_container=container)
    assert list(tmp_path.iterdir()) == []


def test_clashing_prim_paths_are_refused(tmp_path):
    rng = np.random.default_rng(9)
    vb = make_animation(rng, "crossMatrix", "float16")
    crowd = make_crowd(rng, path=vb.meshes[0].path)
    asset = VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,))
    with pytest.raises(OptionsError, match="both use the prim path"):
        usd_io.write_asset(asset, tmp_path / "crowd.usda")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# Reading bad input
# --------------------------------------------------------------------------------------------


@pytest.fixture
def written(tmp_path):
    """A written .usda asset (crossMatrix float16), returned as its path."""
    rng = np.random.default_rng(10)
    path = tmp_path / "asset" / "crowd.usda"
    path.parent.mkdir()
    usd_io.write_asset(make_asset(rng), path)
    return path


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))


def _one_line(error: InputError) -> str:
    text = str(error)
    assert "\n" not in text and "Traceback" not in text
    return text


def test_texture_path_escape_is_refused(written):
    _edit(written, "@./crowd.Anim.exr@", "@../x.exr@")
    (written.parent.parent / "x.exr").write_bytes((written.parent / "crowd.Anim.exr").read_bytes())
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.code == "texture.outside"  # the code vbusd validate reports for it
    assert caught.value.location == "/VirtualBones/Fan/Anim.vb:texture"
    assert caught.value.file == str(written)
    assert caught.value.message.endswith("(pass allow_outside_paths=True to allow it)")  # the caller's words
    _one_line(caught.value)
    # The user may allow it; then the same texture reads fine.
    back = usd_io.read_asset(written, allow_outside_paths=True)
    assert back.animations[0].texture == "../x.exr"


def test_absolute_texture_path_is_refused(written):
    absolute = (written.parent / "crowd.Anim.exr").resolve()
    _edit(written, "@./crowd.Anim.exr@", f"@{absolute}@")
    with pytest.raises(InputError, match="absolute") as caught:
        usd_io.read_asset(written)
    assert caught.value.code == "texture.outside" and "allow_outside_paths=True" in caught.value.message
    assert usd_io.read_asset(written, allow_outside_paths=True).animations[0].texture == str(absolute)


def test_sublayer_outside_the_folder_is_refused(written):
    outside = written.parent.parent / "outside.usda"
    outside.write_text("#usda 1.0\n")
    _edit(written, "#usda 1.0\n(\n", "#usda 1.0\n(\n    subLayers = [@../outside.usda@]\n")
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.code == "asset.outside" and "outside.usda" in caught.value.location
    assert caught.value.file == str(written)


@pytest.mark.parametrize("old, new, attribute, pointer", [
    ("vb:clipRowsPerSecond = [", "vb:clipRowsPerSecond = [99.25, ", "vb:clipRowsPerSecond",
     "/clips/0/rowsPerSecond"),
    ('vb:encoding = "crossMatrix"', 'vb:encoding = "affineMatrix"', "vb:encoding", "/encoding"),
    ('vb:bones = ["Root/b0"', 'vb:bones = ["Root/renamed"', "vb:bones", "/bones"),
    ("vb:clipLoops = [1, 0]", "vb:clipLoops = [0, 0]", "vb:clipLoops", "/clips/0/loop"),
    ('vb:clipNames = ["clip0"', 'vb:clipNames = ["other"', "vb:clipNames", "/clips/0/name"),
    ('vb:contentDigest = "sha256:', 'vb:contentDigest = "sha256:0', "vb:contentDigest", "/contentDigest"),
])
def test_texture_metadata_must_agree_with_the_prim(written, old, new, attribute, pointer):
    if attribute == "vb:clipRowsPerSecond":  # replace the first rate, keep the count
        text = written.read_text()
        text = re.sub(r"vb:clipRowsPerSecond = \[[^,\]]+", "vb:clipRowsPerSecond = [99.25", text)
        written.write_text(text)
    else:
        _edit(written, old, new)
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    # Located where vbusd validate locates it: the metadata value that disagrees, naming the prim's.
    assert caught.value.code == "metadata.mismatch"
    assert (caught.value.file, caught.value.location) == ("crowd.Anim.exr", pointer)
    assert f"/VirtualBones/Fan/Anim.{attribute}" in _one_line(caught.value)


def test_unorm_ranges_must_agree(tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "u.usda"
    usd_io.write_asset(make_asset(rng, "quatTranslation", "unorm16"), path)
    text = re.sub(r"vb:unormRangeMax = \[\(([^,]+)", "vb:unormRangeMax = [(123.5", path.read_text())
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(path)
    assert (caught.value.code, caught.value.location) == ("metadata.mismatch", "/unormRanges")
    assert "vb:unormRangeMin" in caught.value.message


def test_inconsistent_prim_sizes_are_refused(written):
    _edit(written, "vb:textureWidth = 16", "vb:textureWidth = 32")  # 5 bones x 3 -> 16
    with pytest.raises(InputError, match="expected 16") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Anim.vb:textureWidth"
    assert caught.value.code == "layout.width"


def test_syntax_error_is_an_input_error(written):
    written.write_text(written.read_text()[:-40])  # cut the closing braces
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.code == "usd.open" and caught.value.file == str(written)
    _one_line(caught.value)
    # The place USD names (the file ends inside a prim: its last line) becomes the location.
    last_line = written.read_text().count("\n") + 1
    assert re.fullmatch(r"line (\d+) column \d+", caught.value.location)
    assert abs(int(caught.value.location.split()[1]) - last_line) <= 1
    assert str(written) not in caught.value.message  # said once, as the file


def test_syntax_error_at_a_known_place(written):
    text = written.read_text()
    lines = text.splitlines()
    (index,) = [i for i, line in enumerate(lines) if "vb:textureWidth = " in line]
    lines[index] = lines[index].replace("vb:textureWidth = ", "vb:textureWidth = = ")
    written.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.location.startswith(f"line {index + 1} column ")


def test_truncated_usdc_is_an_input_error(tmp_path):
    rng = np.random.default_rng(12)
    path = tmp_path / "crowd.usdc"
    usd_io.write_asset(make_asset(rng), path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated|corrupt") as caught:
        usd_io.read_asset(path)
    _one_line(caught.value)


def test_missing_required_attribute(written):
    text = re.sub(r"\n\s*uniform int vb:boneCount = \d+", "", written.read_text())
    written.write_text(text)
    with pytest.raises(InputError, match="vb:boneCount") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Anim.vb:boneCount"
    assert caught.value.code == "prim.attribute.missing"


def test_wrongly_typed_attribute(written):
    _edit(written, "uniform int vb:boneCount = 5", "uniform float vb:boneCount = 5")
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Anim.vb:boneCount"
    assert caught.value.code == "prim.attribute.missing" and "must be int, found float" in caught.value.message


def test_unknown_token_is_refused(written):
    _edit(written, 'vb:encoding = "crossMatrix"', 'vb:encoding = "fancyMatrix"')
    with pytest.raises(InputError, match="fancyMatrix") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Anim.vb:encoding"


def test_newer_format_version_is_refused(written):
    from vbusd.format.errors import VersionError

    _edit(written, "vb:formatVersion = 1", "vb:formatVersion = 2")
    with pytest.raises(VersionError):
        usd_io.read_asset(written)


def test_binding_without_animation_target(written):
    _edit(written, "rel vb:animation = </VirtualBones/Fan/Anim>\n", "rel vb:animation\n")
    with pytest.raises(InputError, match="exactly one") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Body.vb:animation"


def test_bone_index_out_of_range(written):
    text = re.sub(r"primvars:vb:boneIndices = \[\d+", "primvars:vb:boneIndices = [99", written.read_text(),
                  count=1)
    written.write_text(text)
    with pytest.raises(InputError, match=r"outside 0\.\.4; the first is 99 at vertex 0") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Body.primvars:vb:boneIndices"
    assert caught.value.code == "binding.indices.range"


def _replace_first_array_value(path: Path, attribute: str, value) -> float:
    """Set the first number of ``attribute``'s array in a .usda file; returns the old number."""
    text = path.read_text()
    match = re.search(re.escape(attribute) + r" = \[\(?([-+0-9.e]+)", text)
    assert match, attribute
    path.write_text(text[:match.start(1)] + str(value) + text[match.end(1):])
    return float(match.group(1))


@pytest.mark.parametrize("value, why, code", [
    ("nan", "the first is nan at vertex 0, influence 0", "binding.weights.negative"),
    ("-0.5", "the first is -0.5 at vertex 0, influence 0", "binding.weights.negative"),
    ("+0.25", "not summing to 1 (tolerance 0.001); the first is vertex 0", "binding.weights.sum"),
])
def test_bad_weights_are_refused(written, value, why, code):
    # Spec 14: weights finite, non-negative, summing to 1 within 1e-3 per point; decoders use them
    # as stored, so a reader must not pass them on.
    attribute = "primvars:vb:boneWeights"
    if value == "+0.25":
        old = _replace_first_array_value(written, attribute, 0.0)
        _replace_first_array_value(written, attribute, old + 0.25)
    else:
        _replace_first_array_value(written, attribute, value)
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert why in caught.value.message and caught.value.code == code
    assert caught.value.location == f"/VirtualBones/Fan/Body.{attribute}"
    _one_line(caught.value)


def test_weights_within_the_tolerance_are_accepted(written):
    old = _replace_first_array_value(written, "primvars:vb:boneWeights", 0.0)
    _replace_first_array_value(written, "primvars:vb:boneWeights", old + 0.0009)
    meshes = {m.path: m for m in usd_io.read_asset(written).animations[0].meshes}
    assert meshes["/VirtualBones/Fan/Body"].bone_weights[0].sum() == pytest.approx(1.0009, abs=1e-6)


def test_non_finite_point_is_refused(written):
    _replace_first_array_value(written, "point3f[] points", "inf")
    with pytest.raises(InputError, match="NaN or infinite; the first is point 0 = ") as caught:
        usd_io.read_asset(written)
    assert caught.value.location == "/VirtualBones/Fan/Body.points"
    assert caught.value.code == "binding.points.nonFinite"


def test_missing_texture_and_file(written):
    (written.parent / "crowd.Anim.exr").unlink()
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(written)
    assert caught.value.code == "file.missing"
    with pytest.raises(InputError, match="no such file"):
        usd_io.read_asset(written.parent / "nothing.usda")
    with pytest.raises(InputError, match="usdz"):
        usd_io.read_asset(written.parent / "crowd.usdz")


# --------------------------------------------------------------------------------------------
# Independent checks: OpenUSD's validators, and a hand-written file
# --------------------------------------------------------------------------------------------


def _usd_validation_errors(path: Path) -> list:
    from pxr import Usd, UsdValidation

    validators = [v for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
                  if not v.GetMetadata().name.startswith("vbusd")]  # OpenUSD's own checks only
    stage = Usd.Stage.Open(str(path))
    return [f"{e.GetValidator().GetMetadata().name}: {e.GetMessage()}"
            for e in UsdValidation.ValidationContext(validators).Validate(stage)]


def test_openusd_validators_accept_the_output(tmp_path):
    rng = np.random.default_rng(13)
    path = tmp_path / "crowd.usda"
    usd_io.write_asset(talk_like_asset(rng), path)
    assert _usd_validation_errors(path) == []
    # The same validators do catch a broken file (so the check above can fail).
    _edit(path, "uniform int vb:boneCount = 18", "uniform float vb:boneCount = 18")
    assert any("AttributeTypeMismatch" in e for e in _usd_validation_errors(path))


HAND_WRITTEN = """#usda 1.0
(
    defaultPrim = "Rig"
    upAxis = "Z"
    metersPerUnit = 0.01
)

def Xform "Rig"
{
    def VirtualBonesAnimation "Anim"
    {
        uniform int vb:formatVersion = 1
        uniform asset vb:texture = @textures/rig.exr@
        uniform token vb:encoding = "crossMatrix"
        uniform token vb:texelFormat = "float16"
        uniform int vb:boneCount = 2
        uniform int vb:texelsPerBone = 3
        uniform int vb:rowCount = 3
        uniform int vb:textureWidth = 8
        uniform int vb:textureHeight = 3
        uniform token vb:horizontalPadding = "powerOfTwo"
        uniform token vb:verticalPadding = "none"
        uniform token[] vb:bones = ["hip", "spine"]
        uniform token[] vb:clipNames = ["wave"]
        uniform int[] vb:clipFirstRows = [0]
        uniform int[] vb:clipRowCounts = [3]
        uniform double[] vb:clipRowsPerSecond = [30]
        uniform bool[] vb:clipLoops = [1]
        uniform double[] vb:clipStartTimes = [0]
        uniform string vb:contentDigest = "DIGEST"
    }

    def Mesh "Tri" (
        prepend apiSchemas = ["VirtualBonesBindingAPI"]
    )
    {
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        normal3f[] primvars:normals = [(0, 0, 1), (0, 0, -1)] (interpolation = "faceVarying")
        int[] primvars:normals:indices = [0, 0, 1]
        int[] primvars:vb:boneIndices = [0, 1, 0, 1, 1, 0] (interpolation = "vertex"
            elementSize = 2)
        float[] primvars:vb:boneWeights = [1, 0, 0.5, 0.5, 0.25, 0.75] (interpolation = "vertex"
            elementSize = 2)
        rel vb:animation = </Rig/Anim>
    }

    def PointInstancer "Crowd" (
        prepend apiSchemas = ["VirtualBonesInstancingAPI"]
    )
    {
        point3f[] positions = [(0, 0, 0), (2, 0, 0)]
        int[] protoIndices = [0, 0]
        rel prototypes = </Rig/Crowd/Prototypes/Tri>
        rel vb:animation = </Rig/Anim>

        def Scope "Prototypes"
        {
            def "Tri" (prepend references = </Rig/Tri>)
            {
            }
        }
    }
}
"""


@pytest.fixture
def hand_written(tmp_path):
    """A Virtual Bones asset written by hand (not by vbusd's writer), with its texture."""
    from vbusd.io.textures import write_texture

    layout = Layout("crossMatrix", "float16", 2, 3)  # 6 columns -> 8 (powerOfTwo), 3 rows
    texels = np.zeros(layout.shape, "<f2")
    texels[:, :6] = np.arange(3 * 6 * 4, dtype=np.float32).reshape(3, 6, 4) / 8
    vb = VirtualBones(layout=layout, texels=texels, bones=("hip", "spine"),
                      clips=(Clip("wave", 0, 3, 30.0, True, 0.0),))
    (tmp_path / "textures").mkdir()
    write_texture(tmp_path / "textures" / "rig.exr", vb)
    # Spec 11.4: SHA-256 of the texels, little-endian, C order, padding included (by hand here).
    digest = "sha256:" + hashlib.sha256(texels.astype("<f2").tobytes()).hexdigest()
    (tmp_path / "rig.usda").write_text(HAND_WRITTEN.replace("DIGEST", digest))
    return tmp_path / "rig.usda", texels


def test_hand_written_asset(hand_written):
    path, texels = hand_written
    back = usd_io.read_asset(path)
    (anim,) = back.animations
    assert anim.layout == Layout(Encoding.CROSS_MATRIX, TexelFormat.FLOAT16, 2, 3,
                                 Padding.POWER_OF_TWO, Padding.NONE)
    assert anim.texels.tobytes() == texels.tobytes()
    assert anim.texture == "textures/rig.exr" and anim.clip_extents is None
    (mesh,) = anim.meshes  # the prototype's reference to /Rig/Tri is not a second mesh
    assert mesh.path == "/Rig/Tri"
    assert mesh.normals_interpolation == "faceVarying"  # primvars:normals, indexed, flattened
    assert mesh.normals.tolist() == [[0, 0, 1], [0, 0, 1], [0, 0, -1]]
    assert mesh.bone_indices.tolist() == [[0, 1], [0, 1], [1, 0]]
    assert mesh.bone_weights.tolist() == [[1, 0], [0.5, 0.5], [0.25, 0.75]]
    (crowd,) = back.crowds  # no vb primvars authored: spec defaults clip 0, offset 0, rate 1
    assert crowd.clip.tolist() == [0, 0] and crowd.time_offset.tolist() == [0, 0]
    assert crowd.playback_rate.tolist() == [1, 1] and crowd.scales is None
    assert crowd.orientations.tolist() == [[0, 0, 0, 1], [0, 0, 0, 1]]  # none authored: identity
    assert (back.up_axis, back.meters_per_unit, back.default_prim) == ("Z", 0.01, "Rig")


@pytest.mark.parametrize("attribute", ["vb:encoding", "vb:texelFormat", "vb:formatVersion",
                                       "vb:horizontalPadding", "vb:verticalPadding"])
def test_schema_fallbacks_are_not_relied_on(hand_written, attribute):
    """Spec 13: writers author every attribute; readers must not fill gaps from the fallbacks."""
    path, _ = hand_written
    text = re.sub(rf"\n\s*uniform \w+ {attribute} = [^\n]+", "", path.read_text())
    path.write_text(text)
    with pytest.raises(InputError, match="missing required") as caught:
        usd_io.read_asset(path)
    assert caught.value.location == f"/Rig/Anim.{attribute}"


def test_prims_below_an_instancer_are_not_read_by_either_reader(hand_written):
    # A prototype may reference an animation prim (here a copy of /Rig/Anim); read_asset does not
    # read below point instancers, and info (read_animation_attributes) must list the same prims.
    path, _ = hand_written
    _edit(path, '            def "Tri" (prepend references = </Rig/Tri>)',
          '            def "AnimCopy" (prepend references = </Rig/Anim>)\n            {\n            }\n'
          '            def "Tri" (prepend references = </Rig/Tri>)')
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    assert stage.GetPrimAtPath("/Rig/Crowd/Prototypes/AnimCopy").GetTypeName() == "VirtualBonesAnimation"
    assert [vb.path for vb in usd_io.read_asset(path).animations] == ["/Rig/Anim"]
    assert [a.path for a in usd_io.read_animation_attributes(path)] == ["/Rig/Anim"]


def test_composition_error_is_one_line_and_usd_prints_nothing(written, capfd):
    # USD itself prints an unresolved reference as a warning on stderr; the reader reports it.
    shot = written.parent / "shot.usda"
    shot.write_text('#usda 1.0\ndef "A" (references = @./crowd.usda@</Nope>)\n{\n}\n')
    with pytest.raises(InputError) as caught:
        usd_io.read_asset(shot)
    assert caught.value.code == "asset.composition" and "</Nope>" in _one_line(caught.value)
    assert capfd.readouterr() == ("", "")


def test_pipes_as_layer_or_sublayer_are_refused_without_blocking(written):
    # USD opens whatever it is given; a named pipe would block the reader forever.
    import os
    import signal

    pipe = written.parent / "pipe.usda"
    os.mkfifo(pipe)
    shot = written.parent / "shot.usda"
    shot.write_text("#usda 1.0\n(\n    subLayers = [@./pipe.usda@]\n)\n")
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("reading a named pipe blocked"))
    signal.alarm(10)
    try:
        for path, file, location in ((pipe, str(pipe), None), (shot, str(shot), "@./pipe.usda@")):
            with pytest.raises(InputError) as caught:
                usd_io.read_asset(path)
            assert (caught.value.code, caught.value.file, caught.value.location) == ("file.kind", file, location)
            assert "not a regular file" in _one_line(caught.value)
    finally:
        signal.alarm(0)
