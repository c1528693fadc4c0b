"""The UsdSkel converter's all-frames skinning transforms against UsdSkel's own, frame by frame.

``vbusd.converters.usdskel.AllFramesSkinning`` computes the skinning transforms of every time code
of a clip at once (issue 17 item 5): in numpy, or for many frames in its compiled twin
(``vbusd.kernels.bake.skinning_transforms``); every test here runs on both. The yardstick is
``UsdSkel.SkeletonQuery.ComputeSkinningTransforms`` called at each time code: on every skeleton of
every shared UsdSkel asset (../shared/assets or $VBUSD_SHARED_ASSETS; skipped when absent), at every
authored time code and half-way between them (USD's interpolation, slerp for rotations), and on a
generated rig whose animation covers only some of the skeleton's joints (the rest keep their rest
transforms).
"""

from __future__ import annotations

import numpy as np
import pytest

import vbusd  # noqa: F401  (registers the schema before pxr builds its registry)
from vbusd.converters import usdskel

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("both_bake_paths")]  # numpy, then compiled (vbusd.kernels.bake)

TOLERANCE = 1e-9
"""Largest difference allowed, relative to the largest matrix entry (UsdSkel works in double too)."""


def _skeleton_queries(path):
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    queries = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdSkel.Root):
            cache.Populate(UsdSkel.Root(prim), Usd.TraverseInstanceProxies())
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdSkel.Skeleton):
            query = cache.GetSkelQuery(UsdSkel.Skeleton(prim))
            if query:
                queries.append((str(prim.GetPath()), query))
    return stage, queries


def _codes(query, stage) -> np.ndarray:
    anim = query.GetAnimQuery()
    samples = sorted(float(t) for t in anim.GetJointTransformTimeSamples()) if anim else []
    if not samples:
        samples = [float(stage.GetStartTimeCode())]
    codes = np.asarray(samples)
    if codes.size > 1:  # half-way too: USD's own interpolation between samples
        codes = np.sort(np.concatenate([codes, 0.5 * (codes[1:] + codes[:-1])]))
    return codes


def _usdskel_per_frame(query, codes) -> np.ndarray:
    from pxr import Usd

    frames = []
    for code in codes:
        transforms = query.ComputeSkinningTransforms(Usd.TimeCode(float(code)))
        frames.append(np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4))
    return np.stack(frames)


class _Reader:
    def __init__(self):
        from pxr import Usd, UsdSkel

        self.Usd, self.UsdSkel = Usd, UsdSkel


def _check(path) -> int:
    """Compare every skeleton of one file; returns how many were computed all frames at once."""
    stage, queries = _skeleton_queries(path)
    checked = 0
    for location, query in queries:
        fast = usdskel.AllFramesSkinning.build(_Reader(), query)
        if fast is None:
            continue
        codes = _codes(query, stage)
        expected = _usdskel_per_frame(query, codes)  # row-vector, skeleton space
        got = fast.compute(codes)  # column-vector
        if got is None:  # some value missing at some code (blend shapes only): UsdSkel answers
            continue
        got = np.swapaxes(got, -1, -2)
        scale = max(1.0, float(np.abs(expected).max()))
        worst = float(np.abs(got - expected).max())
        assert worst <= TOLERANCE * scale, f"{path}:{location}: {worst:.3g} (scale {scale:.3g})"
        checked += 1
    return checked


def test_every_shared_usdskel_asset(shared_assets):
    files = sorted(p for p in (shared_assets / "usdskel").rglob("*") if p.suffix in (".usda", ".usdc", ".usdz")
                   and ".baked" not in p.name and "bakedInterval" not in p.name)
    assert files, f"no UsdSkel assets under the shared assets {shared_assets}"
    checked = {str(p.relative_to(shared_assets)): _check(p) for p in files}
    # The real characters (BrainStem, CesiumMan, RiggedFigure, the elephant) must take the fast path.
    for name in ("BrainStem", "CesiumMan", "RiggedFigure", "ElephantWithMonochord"):
        assert any(name in key and count > 0 for key, count in checked.items()), checked


def test_partial_animation_keeps_rest_transforms(tmp_path):
    """Joints the animation does not drive keep their rest transforms (UsdSkel's sparse remap)."""
    from pxr import Gf, Sdf, Usd, UsdSkel, Vt

    path = tmp_path / "partial.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdSkel.Root.Define(stage, "/Root")
    skel = UsdSkel.Skeleton.Define(stage, "/Root/Skel")
    joints = ["a", "a/b", "a/b/c", "a/d"]
    skel.CreateJointsAttr(Vt.TokenArray(joints))
    rest = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(0, 1 + i, 0.5 * i)) for i in range(4)]
    rest[3] = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 0, 1), 30)) * Gf.Matrix4d().SetTranslate(Gf.Vec3d(1, 0, 0))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    bind = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(0.1 * i, i, 0)) for i in range(4)]
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    anim = UsdSkel.Animation.Define(stage, "/Root/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(["a/b/c", "a"]))  # another order, "a/b" and "a/d" missing
    rng = np.random.default_rng(3)
    for frame in range(5):
        quats = rng.normal(size=(2, 4)).astype(np.float32)
        quats /= np.linalg.norm(quats, axis=1, keepdims=True)
        anim.CreateRotationsAttr().Set(Vt.QuatfArray.FromNumpy(quats), frame)
        anim.CreateTranslationsAttr().Set(Vt.Vec3fArray.FromNumpy(rng.normal(size=(2, 3)).astype(np.float32)), frame)
        anim.CreateScalesAttr().Set(Vt.Vec3hArray.FromNumpy((1 + 0.2 * rng.random((2, 3))).astype(np.float16)), frame)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([Sdf.Path("/Root/Skel/Anim")])
    stage.GetRootLayer().Save()
    assert _check(path) == 1


def test_no_animation_is_the_rest_pose(tmp_path):
    from pxr import Gf, Usd, UsdSkel, Vt

    path = tmp_path / "rest.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdSkel.Root.Define(stage, "/Root")
    skel = UsdSkel.Skeleton.Define(stage, "/Root/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(["a", "a/b"]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d().SetTranslate(Gf.Vec3d(0, 1, 0)),
                                                     Gf.Matrix4d().SetScale(Gf.Vec3d(1, 2, 3))]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1), Gf.Matrix4d().SetTranslate(Gf.Vec3d(0, 2, 0))]))
    stage.GetRootLayer().Save()
    assert _check(path) == 1


def test_sampler_uses_it_and_matches_usdskel_in_world_space(repo_root):
    """The converter's sampler (bake input) takes the all-frames path on the stadium sample and
    returns UsdSkel's world-space matrices."""
    from vbusd.format.model import ReadOptions

    scene = usdskel.read(repo_root / "samples" / "stadium_crowd" / "stadium_crowd.usda", ReadOptions())
    clip = scene.animations[0].clips[0]
    sampler = clip.sample
    assert sampler._all_frames is not None
    times = clip.start_time + np.linspace(0.0, clip.end_time - clip.start_time, 97)
    fast = sampler(times)
    sampler._all_frames = None  # UsdSkel, frame by frame
    slow = sampler(times)
    assert np.abs(fast - slow).max() <= TOLERANCE * max(1.0, float(np.abs(slow).max()))


def test_sampler_on_every_shared_asset_in_world_space(shared_assets):
    """Through the converter: every clip of every shared UsdSkel asset that converts, sampled at its
    keys and half-way, all frames at once against UsdSkel frame by frame (world placement included)."""
    from vbusd.format.errors import VbusdError
    from vbusd.format.model import ReadOptions

    compared = 0
    for path in sorted(p for p in (shared_assets / "usdskel").rglob("*") if p.suffix in (".usda", ".usdc", ".usdz")
                       and ".baked" not in p.name and "bakedInterval" not in p.name):
        try:
            scene = usdskel.read(path, ReadOptions())
        except VbusdError:
            continue  # refused by the converter (its own tests cover why)
        for animation in scene.animations:
            for clip in animation.clips:
                sampler = clip.sample
                if getattr(sampler, "_all_frames", None) is None:
                    continue
                keys = np.asarray(clip.key_times, dtype=np.float64)
                times = np.sort(np.concatenate([keys, 0.5 * (keys[1:] + keys[:-1])])) if keys.size > 1 else keys
                fast = sampler(times)
                sampler._all_frames = None
                slow = sampler(times)
                scale = max(1.0, float(np.abs(slow).max()))
                assert np.abs(fast - slow).max() <= TOLERANCE * scale, f"{path}:{animation.path}"
                compared += 1
    assert compared, "no shared UsdSkel asset took the all-frames path"
