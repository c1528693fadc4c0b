"""A large synthetic UsdSkel rig written from code: a branching skeleton over a grid mesh, every
joint moving each frame. The tests' compiled-bake cases and benchmarks/bench_convert.py (and
bench_batch.py) convert it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import vbusd  # noqa: F401  (registers the Virtual Bones USD schema before pxr builds its registry)


def build_rig(path: Path, frames: int, points: int, joints: int, tcps: float = 24.0, normals: bool = False) -> dict:
    """Write the rig: a branching skeleton over a grid mesh; returns what was made.

    ``normals=True`` also authors the grid's vertex normals (those of its surface
    ``y = 0.25 * sqrt(x^2 + z^2)``, computed by hand), so that a conversion checks its skinned
    normals against UsdSkel's; the benchmark's rig has none.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    rng = np.random.default_rng(7)
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(tcps)
    stage.SetFramesPerSecond(tcps)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    UsdGeom.SetStageUpAxis(stage, "Y")
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())

    # Skeleton: 10 chains of joints/10 joints each, fanned out from a root, along +Y.
    chains = 10
    per_chain = max(1, (joints - 1) // chains)
    names, parents, heads = ["root"], [-1], [np.zeros(3)]
    for c in range(chains):
        parent, name = 0, "root"
        angle = 2 * math.pi * c / chains
        for k in range(per_chain):
            name = f"{name}/c{c}_{k}"
            names.append(name)
            parents.append(parent)
            heads.append(np.array([math.cos(angle) * (k + 1), 0.5 * (k + 1), math.sin(angle) * (k + 1)]))
            parent = len(names) - 1
    count = len(names)
    skel = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(names))
    binds = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, h))) for h in heads]
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(binds))
    local = [heads[i] - (heads[parents[i]] if parents[i] >= 0 else 0) for i in range(count)]
    rests = [Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, t))) for t in local]
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rests))

    anim = UsdSkel.Animation.Define(stage, "/Rig/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(names))
    t_attr, r_attr, s_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
    s_attr.Set(Vt.Vec3hArray.FromNumpy(np.ones((count, 3), dtype=np.float16)))
    local = np.array(local, dtype=np.float32)
    phase = rng.uniform(0, 2 * math.pi, count)
    speed = rng.uniform(0.5, 2.0, count)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for frame in range(1, frames + 1):
        t = frame / tcps
        angle = 0.4 * np.sin(speed * t + phase)  # radians, about each joint's own axis
        quats = np.concatenate([np.cos(angle / 2)[:, None], axes * np.sin(angle / 2)[:, None]], axis=1)
        r_attr.Set(Vt.QuatfArray.FromNumpy(quats.astype(np.float32)), frame)
        offset = local + 0.05 * np.sin(t + phase)[:, None]
        t_attr.Set(Vt.Vec3fArray.FromNumpy(offset.astype(np.float32)), frame)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([Sdf.Path("/Rig/Skel/Anim")])

    # Mesh: a square grid of about `points` points spanning the skeleton's footprint.
    side = int(round(math.sqrt(points)))
    xs = np.linspace(-per_chain, per_chain, side)
    gx, gz = np.meshgrid(xs, xs, indexing="ij")
    gy = 0.25 * np.sqrt(gx ** 2 + gz ** 2)
    pts = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    quads = []
    for i in range(side - 1):
        row = np.arange(side - 1) + i * side
        quads.append(np.stack([row, row + side, row + side + 1, row + 1], axis=1))
    fvi = np.concatenate(quads).reshape(-1)
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Grid")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(fvi) // 4, 4, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(fvi.astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr("none")
    if normals:
        # The surface's normal is (-dy/dx, 1, -dy/dz), dy/dx = 0.25 x / r; (0, 1, 0) at the apex.
        r = np.maximum(np.sqrt(gx ** 2 + gz ** 2), 1e-12).reshape(-1)
        slope = np.where(r > 1e-9, 0.25 / r, 0.0)
        n = np.stack([-slope * gx.reshape(-1), np.ones_like(r), -slope * gz.reshape(-1)], axis=-1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(n.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    # Influences: the 4 nearest joint heads, weighted by inverse distance.
    head_array = np.array(heads)
    distance = np.linalg.norm(pts[:, None, :] - head_array[None], axis=-1)
    nearest = np.argsort(distance, axis=1)[:, :4]
    d = np.take_along_axis(distance, nearest, axis=1)
    w = 1.0 / (d + 0.25)
    w /= w.sum(axis=1, keepdims=True)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([Sdf.Path("/Rig/Skel")])
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(nearest.reshape(-1).astype(np.int32)))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(w.reshape(-1).astype(np.float32)))
    stage.GetRootLayer().Save()
    return {"joints": count, "points": int(len(pts)), "frames": frames}
