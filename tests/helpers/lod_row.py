"""The LOD row: the stadium spectator with 3 generated levels, instances in a row at chosen
distances in front of a fixed page camera (one behind it), and OpenUSD's own choice of level for
each (tests/test_browser_lod.py, tests/test_browser_parity.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

import vbusd

REPO = Path(__file__).resolve().parents[2]
STADIUM = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
DISTANCES = (3.0, 9.0, 16.0, 40.0, 90.0, -10.0)  # metres in front of the camera (the last: behind it)
FOV, WIDTH, HEIGHT = 40.0, 320, 180
EYE = (0.0, 1.0, 0.0)
PAGE = f"?paused=1&ui=0&silhouette=1&width={WIDTH}&height={HEIGHT}&pixelRatio=1&fov={FOV}&camera=0,1,0,0,1,-100"


PARTS = (3, 0, 1, 2, 3, 1)
"""Parts masks of the modular row (Hat bit 0, Flag bit 1): each part shown and hidden at levels 0 and 1."""
MODULAR_SCREEN_SIZES = (0.06, 0.003)
"""Thresholds of the modular row's levels: its flag widens the clips' extents, so the stadium's defaults
would leave level 2 empty; these give the levels 0, 0, 1, 1, 2 and -1 (behind the camera)."""


def make_row_package(folder: Path, modular: bool = False):
    """(asset, package path) of the row: tests/test_browser_parity.py probes it in every engine. With
    ``modular``, the spectator is the modular one (body, ``Hat`` and ``Flag`` parts, tests/helpers/variety.py)
    with the same 3 generated levels, and the row has the parts masks :data:`PARTS` (spec 22.3, parts
    and levels of detail)."""
    from vbusd.format.model import Crowd
    from vbusd.io.gltf_package import export_gltf

    if modular:
        from vbusd.baking.lod import add_levels

        from tests.helpers.variety import modular_character

        asset = vbusd.read_asset(modular_character(folder))
        asset = dataclasses.replace(asset, animations=(add_levels(asset.animations[0], (0.5, 0.2), screen_sizes=MODULAR_SCREEN_SIZES),))
    else:
        character = folder / "stadium.usda"
        vbusd.convert(STADIUM, character, vbusd.ConvertOptions(lod_ratios=(0.5, 0.2), check_rows=0))
        asset = vbusd.read_asset(character)
    n = len(DISTANCES)
    variety = dict(parts=np.array(PARTS, np.int32), part_names=("Hat", "Flag")) if modular else {}
    crowd = Crowd("/StadiumCrowd/Row", positions=np.array([[0.0, 0.0, -d] for d in DISTANCES], np.float32),
                  orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  clip=np.zeros(n, np.int32), time_offset=np.linspace(0, 4, n).astype(np.float32),
                  playback_rate=np.ones(n, np.float32), **variety)
    asset = dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,))
    package = folder / "row.glb"
    export_gltf(asset, package)
    return asset, package


def usdlod_levels(asset) -> list:
    """OpenUSD's choice for each instance: ComputeLOD of a LODScreenSizeHeuristic with the animation's
    thresholds and extent, seen through a GfFrustum like the page's camera."""
    from pxr import Gf, Usd, UsdLod

    vb = asset.animations[0]
    extents = np.asarray(vb.clip_extents, np.float64)
    box = [tuple(extents[:, 0].min(axis=0)), tuple(extents[:, 1].max(axis=0))]
    stage = Usd.Stage.CreateInMemory()
    heuristic = UsdLod.ScreenSizeHeuristic.Define(stage, "/H")
    heuristic.CreateLodDomainAttr("imaging")
    heuristic.CreateThresholdsAttr(list(vb.lods.screen_sizes))
    heuristic.CreateExtentAttr(box)
    frustum = Gf.Frustum()
    frustum.SetPerspective(FOV, WIDTH / HEIGHT, 0.01, 1000.0)
    frustum.SetPosition(Gf.Vec3d(*EYE))  # looking down -Z, as the page's camera does
    levels = []
    for d in DISTANCES:
        world = Gf.Matrix4d().SetTranslate(Gf.Vec3d(0.0, 0.0, -d))
        # UsdLod gives what lies outside the frustum screen size 0; the runtime culls it (-1).
        levels.append(-1 if heuristic.ComputeScreenSize(frustum, world) == 0 else int(heuristic.ComputeLOD(frustum, world)))
    return levels
