"""Real characters convert whole (issue 12) on the shared assets: no mesh an engine shows is dropped.

glTF: every mesh of three.js's scene (GLTFLoader r187 under Node, keyed by glTF node and
primitive) is a converted mesh, and the decoded asset (affineMatrix, float32) matches three.js at a
few rows of every clip. USD: every visible, non-guide gprim of a stage that converts is a converted
mesh, except curves (no surface to bind), which the converter names in a warning. Assets are found
through $VBUSD_SHARED_ASSETS or ../shared/assets; the tests skip without them (and fail where they are required: CI).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vbusd.baking.baker import BakeOptions, bake
from vbusd.decoders.reference import skin_mesh
from vbusd.format.errors import VbusdError
from vbusd.format.model import ReadOptions
from vbusd.io.gltf import load
from tests.helpers import node as node_tools
from tests.helpers.capabilities import shared_asset_params, shared_assets_dir


ASSETS = shared_assets_dir() or Path(__file__).resolve().parents[2] / "shared" / "assets"
GLTF = sorted((ASSETS / "gltf").glob("*/*.gl*")) if (ASSETS / "gltf").is_dir() else []
USD = sorted(p for p in (ASSETS / "usdskel").rglob("*") if p.suffix in (".usda", ".usdc", ".usdz")) \
    if (ASSETS / "usdskel").is_dir() else []

THREE_TOLERANCE = {"SimpleSkin.gltf": 5e-4}
"""SimpleSkin's rotation keys are rounded to 3 decimals: vbusd normalizes them, three.js composes the
matrix from the key as stored (docs/converters/real-characters.md). Every other asset: 1e-6."""

REFUSED = {"usdskel.blendShapesOnly", "usdskel.nothing", "usdskel.joints.empty"}
"""Refusals the shared USD assets may give: blend-shape-only skeletons, UsdSkel's own baked point
caches (no skeleton bound any more) and the deliberately malformed joint-influence cases."""


def _key(mesh) -> str:
    node = int(mesh.source_path.split()[0].split("/")[2])
    return f"{node}:{int(mesh.source_path.rsplit('/', 1)[1])}"


@pytest.mark.node
@pytest.mark.parametrize("path", shared_asset_params(GLTF))
def test_gltf_asset_whole_and_as_three_shows_it(path, shared_assets):
    from vbusd.converters import gltf

    shown = node_tools.run_json("skin_pose.mjs", path, "-", 0, packages=("three",))["poses"][0]["byNode"]
    scene = gltf.read(path, ReadOptions())
    converted = {_key(m): (a, k) for a, animation in enumerate(scene.animations) for k, m in enumerate(animation.meshes)}
    assert set(shown) <= set(converted), sorted(set(shown) - set(converted))
    document, _ = load(path)
    names = [gltf.make_identifier(a.name, f"animation{i}") for i, a in enumerate(document.animations)]
    tolerance = THREE_TOLERANCE.get(path.name, 1e-6)
    vb = bake(scene.animations[0], BakeOptions(encoding="affineMatrix", texel_format="float32"))
    for c, clip in enumerate(vb.clips):
        rows = np.unique(np.linspace(0, clip.row_count - 1, 4).round().astype(int))
        times = clip.start_time + rows / clip.rows_per_second
        poses = node_tools.run_json("skin_pose.mjs", path, f"#{names.index(clip.name)}", *[f"{t:.17g}" for t in times],
                                    packages=("three",))["poses"]
        for key, (a, k) in converted.items():
            if a != 0:
                continue
            ours, _ = skin_mesh(vb, vb.meshes[k], c, rows / clip.rows_per_second)
            theirs = np.array([np.reshape(p["byNode"][key], (-1, 3)) for p in poses])
            diagonal = np.linalg.norm(np.ptp(theirs.reshape(-1, 3), axis=0))
            assert np.linalg.norm(ours - theirs, axis=-1).max() <= tolerance * diagonal, (clip.name, key)


@pytest.mark.slow
@pytest.mark.parametrize("path", shared_asset_params(USD, id=lambda p: str(p.relative_to(ASSETS / "usdskel"))))
def test_usd_asset_whole(path, shared_assets):
    from pxr import Usd, UsdGeom

    from vbusd.converters import usdskel

    try:
        scene = usdskel.read(path, ReadOptions())
    except VbusdError as error:
        assert error.code in REFUSED, str(error)
        return
    stage = Usd.Stage.Open(str(path))
    shown = {str(p.GetPath()): p.GetTypeName() for p in stage.Traverse()
             if p.IsA(UsdGeom.Gprim) and UsdGeom.Imageable(p).ComputeVisibility() != UsdGeom.Tokens.invisible
             and UsdGeom.Imageable(p).ComputePurpose() != UsdGeom.Tokens.guide}
    converted = {m.path for a in scene.animations for m in a.meshes}
    dropped = {p: kind for p, kind in shown.items() if p not in converted}
    assert set(dropped.values()) <= {"BasisCurves"}, dropped
    for prim in dropped:
        assert any(w.startswith(f"{prim}:") for w in scene.warnings), prim
