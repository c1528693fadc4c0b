"""Culling bounds (vb:clipExtents, spec 13): every decoded vertex, at every row and between rows.

Real third-party rigs (the shared assets: glTF Fox with its three clips and CesiumMan, UsdSkel
TwoBends and SkinnedArm) are converted with ``vbusd.convert`` in every encoding the rig holds, the
extents read back from the written USD (float3, as a renderer reads them), and every vertex of
every bound mesh decoded by the numpy reference at every row, at 16 times inside every row
interval (the looping wrap included) and at 400 random clip times must lie inside its clip's box.
Between rows crossMatrix (cross of blended axes) and the quaternion encodings (normalized
quaternions) leave the box of the rows' points, which is what this checks. Every case runs with the
bake's numpy code and with its compiled twins (``vbusd.kernels.bake``).
"""

from __future__ import annotations

import numpy as np
import pytest

import vbusd
from vbusd.decoders.reference import bone_transforms, skin
from vbusd.format.errors import UnsupportedError
from tests.helpers.capabilities import shared_asset

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("both_bake_paths")]  # numpy, then compiled (vbusd.kernels.bake)

CASES = [
    ("gltf/Fox/Fox.glb", ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")),
    ("gltf/CesiumMan/CesiumMan.glb", ("crossMatrix", "dualQuat")),
    ("usdskel/TwoBends/twoBends.usda", ("crossMatrix", "quatTranslation", "dualQuat")),
    ("usdskel/SkinnedArm/skinnedArm.usda", ("crossMatrix", "affineMatrix")),
]


def _times(clip, substeps: int, rng) -> np.ndarray:
    intervals = clip.row_count if clip.loop else max(clip.row_count - 1, 0)
    fine = np.arange(intervals * substeps + 1) / substeps / clip.rows_per_second
    span = (intervals or 1) / clip.rows_per_second
    return np.concatenate([fine, rng.uniform(-0.5 * span, 1.5 * span, 400)])


@pytest.mark.parametrize("source,encodings", CASES, ids=[c[0].split("/")[1] for c in CASES])
def test_clip_extents_hold_every_vertex_at_and_between_rows(shared_assets, tmp_path, source, encodings):
    path = shared_asset(*source.split("/"))
    rng = np.random.default_rng(15)
    checked = 0
    for encoding in encodings:
        output = tmp_path / encoding / "asset.usda"
        output.parent.mkdir()
        try:
            vbusd.convert(path, output, vbusd.ConvertOptions(encoding=encoding, texel_format="float16", check_rows=0))
        except UnsupportedError:
            continue  # the rig needs more than this encoding holds (the converter says so)
        asset = vbusd.read_asset(output)
        for vb in asset.animations:
            assert vb.clip_extents is not None, f"{source} {encoding}: no vb:clipExtents written"
            for index, clip in enumerate(vb.clips):
                low, high = vb.clip_extents[index].astype(np.float64)
                taus = _times(clip, 16, rng)
                outside = np.full(len(vb.meshes), -np.inf)
                for start in range(0, len(taus), 64):  # 64 times at once: the same numbers, less memory
                    transforms = bone_transforms(vb, index, taus[start:start + 64])  # once for every mesh
                    for m, mesh in enumerate(vb.meshes):
                        # The reference's skinning of the points alone (the extents bound points, not normals).
                        points, _ = skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices,
                                         mesh.bone_weights)
                        outside[m] = max(outside[m], np.maximum(low - points, points - high).max())
                for mesh, worst in zip(vb.meshes, outside):
                    assert worst <= 0, (f"{source} {encoding} clip {clip.name!r} mesh {mesh.path}: a vertex is "
                                        f"{worst:.3g} outside vb:clipExtents")
                    checked += 1
    assert checked, f"{source}: no encoding converted"
