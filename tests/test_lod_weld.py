"""Generated levels of an unindexed mesh (spec/virtual-bones.md 20.3): points equal in position,
influences and normal are welded before simplifying, so a mesh stored as three points per triangle
(glTF's Fox) gets simpler levels; a level the simplifier still cannot reduce is one warning line
of the conversion report, not a silent copy."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

import vbusd
from vbusd.decoders.reference import skin_mesh
from vbusd.format.model import BoundMesh

from tests.helpers.capabilities import require, shared_asset

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd"

require("lod", allow_module_level=True)  # generated levels need meshoptimizer


def unindexed_grid(k: int = 8, bone_of_triangle=lambda t: 0) -> BoundMesh:
    """A k x k grid of 2 k^2 triangles stored unindexed (three points per triangle, as glTF's Fox),
    each triangle's points bound with weight 1 to ``bone_of_triangle(t)``."""
    grid = np.array([[x, y, 0.0] for y in range(k + 1) for x in range(k + 1)], dtype=np.float32)
    triangles = []
    for y in range(k):
        for x in range(k):
            a = y * (k + 1) + x
            triangles += [[a, a + 1, a + k + 2], [a, a + k + 2, a + k + 1]]
    triangles = np.array(triangles)
    count = len(triangles)
    bones = np.repeat([bone_of_triangle(t) for t in range(count)], 3).reshape(-1, 1).astype(np.int32)
    return BoundMesh(path="/Grid/grid", points=grid[triangles.reshape(-1)], face_vertex_counts=np.full(count, 3, np.int32),
                     face_vertex_indices=np.arange(3 * count, dtype=np.int32), bone_indices=bones,
                     bone_weights=np.ones((3 * count, 1), np.float32))


def test_weld_points_by_position_influences_and_normal():
    """Hand-made points: equal position and influences weld; another bone, weight or normal does not."""
    from vbusd.baking.lod import weld_points

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0]], np.float32)
    bones = np.array([[0, 1], [0, 1], [0, 1], [2, 1], [0, 1], [0, 1]])
    weights = np.array([[0.5, 0.5], [1, 0], [0.5, 0.5], [0.5, 0.5], [0.25, 0.75], [1, 0]], np.float32)
    assert weld_points(points, bones, weights).tolist() == [0, 1, 0, 3, 4, 1]
    normals = np.array([[0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1]], np.float32)
    assert weld_points(points, bones, weights, normals).tolist() == [0, 1, 2, 3, 4, 1]


def test_unindexed_grid_simplifies_after_welding():
    """The 128-triangle unindexed grid (one bone) at ratio 0.5 keeps at most 64 triangles (meshoptimizer
    kept all 128 before the weld), every level point a grid point."""
    from vbusd.baking.lod import simplify_mesh

    mesh = unindexed_grid()
    level = simplify_mesh(mesh, 0.5, 1, "/Grid/lod1/grid", 1)
    triangles = len(level.face_vertex_counts)
    assert 32 <= triangles <= 64, triangles
    assert len(level.points) < 81  # welded: fewer points than the grid's 9 x 9
    assert {tuple(p) for p in level.points.tolist()} <= {tuple(p) for p in mesh.points.tolist()}


def test_poorly_simplified_hand_values():
    from vbusd.baking.lod import poorly_simplified

    assert poorly_simplified(100, 50, 0.5) is None
    assert poorly_simplified(100, 75, 0.5) is None  # half the asked reduction: still a simpler level
    assert "keeps 76 of 100 triangles, not about 50" in poorly_simplified(100, 76, 0.5)
    assert "keeps 100 of 100" in poorly_simplified(100, 100, 0.2)


def test_a_level_the_simplifier_cannot_reduce_is_a_warning():
    """The grid with each triangle on its own bone (no point welds: every edge a skin seam) cannot be
    simplified: add_levels still writes the level, and reports one line naming it and the counts."""
    from vbusd.baking.lod import add_levels, simplify_mesh

    mesh = unindexed_grid(bone_of_triangle=lambda t: t % 4)
    assert len(simplify_mesh(mesh, 0.5, 1, "/x", 1).face_vertex_counts) > 96  # the premise
    vb = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda").animations[0]  # 18 bones; its texture is not read
    vb = dataclasses.replace(vb, meshes=(mesh,), lods=None)
    warnings = []
    levels = add_levels(vb, (0.5,), warnings=warnings)
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert warnings[0].startswith(f"{levels.lods.item_path(1)}/grid: LOD 1 of /Grid/grid keeps "), warnings
    assert "of 128 triangles, not about 64" in warnings[0], warnings
    assert [m.lod for m in levels.meshes] == [0, 1]
    warnings = []
    add_levels(dataclasses.replace(vb, meshes=(unindexed_grid(),)), (0.5,), warnings=warnings)
    assert warnings == []  # the one-bone grid welds and simplifies


def test_fox_levels_are_simpler_and_follow_the_decoder(tmp_path):
    """The Khronos Fox (unindexed: 1728 points, 576 triangles; affineMatrix float32) with
    --lod-ratios 0.5,0.2: each level has about the asked triangles (at most 5 % above
    ceil(r x 576), at least half of it; before the weld every level kept all 576), no warning in the
    conversion report, and each level skinned by the decoder (``skin_mesh``) equals, within 1e-6 of
    the diagonal, linear blend skinning by hand of the same LOD 0 rest points with their heaviest
    ``4 >> level`` LOD 0 influences renormalized, under the decoder's bone matrices."""
    from vbusd.decoders.reference import skinning_matrices

    source = shared_asset("gltf", "Fox", "Fox.glb")
    out = tmp_path / "fox.usda"
    report = vbusd.convert(source, out, vbusd.ConvertOptions(encoding="affineMatrix", texel_format="float32",
                                                             lod_ratios=(0.5, 0.2), check_rows=0))
    assert not [w for w in report.warnings if "triangles" in w], report.warnings
    vb = vbusd.read_asset(out).animations[0]
    by_level = {m.lod: m for m in vb.meshes}
    base = by_level[0]
    total = len(base.face_vertex_counts)
    assert total == 576 and len(base.points) == 3 * total  # unindexed
    for level, ratio in ((1, 0.5), (2, 0.2)):
        mesh = by_level[level]
        target = math.ceil(ratio * total)
        triangles = len(mesh.face_vertex_counts)
        print("Fox LOD", level, "triangles", triangles, "of", total, "target", target, "points", len(mesh.points))
        assert 0.5 * target <= triangles <= 1.05 * target, (level, triangles, target)
        keep = 4 >> level
        sources = np.array([int(np.flatnonzero((base.points == p).all(axis=1))[0]) for p in mesh.points])
        weights = np.asarray(base.bone_weights, np.float64)[sources]
        order = np.argsort(-weights, axis=1, kind="stable")[:, :keep]
        bones = np.take_along_axis(np.asarray(base.bone_indices)[sources], order, axis=1)
        kept = np.take_along_axis(weights, order, axis=1)
        kept /= kept.sum(axis=1, keepdims=True)
        rest = np.concatenate([np.asarray(base.points, np.float64)[sources], np.ones((len(sources), 1))], axis=1)
        for clip in range(len(vb.clips)):
            for t in (0.3, 1.1):
                matrices = skinning_matrices(vb, clip, np.array([t]))[0]
                by_hand = np.einsum("vk,vkij,vj->vi", kept, matrices[bones], rest)[:, :3]
                got, _ = skin_mesh(vb, mesh, clip, np.array([t]))
                full, _ = skin_mesh(vb, base, clip, np.array([t]))
                diagonal = float(np.linalg.norm(full[0].max(0) - full[0].min(0)))
                error = float(np.abs(got[0] - by_hand).max()) / diagonal
                assert error <= 1e-6, (level, clip, t, error)


def test_the_warning_reaches_the_conversion_report(tmp_path, monkeypatch, capsys):
    """``vbusd convert --lod-ratios`` passes add_levels' lines to its report and prints each as one
    line (a level made poorly simplified on purpose: the stadium sample simplifies well)."""
    from vbusd.baking import lod
    from vbusd.cli import main

    monkeypatch.setattr(lod, "poorly_simplified", lambda total, kept, ratio: f"keeps {kept} of {total} triangles (test)")
    report = vbusd.convert(SAMPLE / "stadium_crowd.usda", tmp_path / "a.usda",
                           vbusd.ConvertOptions(lod_ratios=(0.5,), check_rows=0))
    lines = [w for w in report.warnings if "(test)" in w]
    assert len(lines) == 1 and "/lod1/" in lines[0] and "LOD 1 of " in lines[0], report.warnings
    assert main(["convert", str(SAMPLE / "stadium_crowd.usda"), "-o", str(tmp_path / "b.usda"), "--lod-ratios", "0.5",
                 "--check-rows", "0"]) == 0
    printed = capsys.readouterr()
    assert sum("(test)" in line for line in (printed.out + printed.err).splitlines()) == 1, printed
