"""Make docs/images/blend_space_strip.png: a crowd of Foxes moving across a 1D blend space.

The Fox (glTF sample model; $VBUSD_SHARED_ASSETS or ../shared/assets) is converted with a blend
space ``speed = Walk@1, Run@3`` synchronized on a marker at each clip's left-front-foot contact
(spec/virtual-bones.md section 23), and skinned by the numpy reference decoder (``vbusd.skin(...,
blend=...)``): one Fox per column at speeds 1 (walk) to 3 (run), one row per time step, every Fox's
phase advancing at ``1 / sum w D`` (spec 23.3) from the same start, so every column puts its left
front foot down together in the first row. The side view is drawn by a small numpy rasterizer
(flat-shaded triangles, a depth buffer) and written with pypng, so the picture needs no browser or GPU.

Usage::

    python scripts/make_blend_space_image.py            # writes docs/images/blend_space_strip.png
    python scripts/make_blend_space_image.py -o other.png
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUTPUT = REPO / "docs" / "images" / "blend_space_strip.png"
SPEEDS = (1.0, 1.5, 2.0, 2.5, 3.0)
STEPS = (0.0, 0.12, 0.24, 0.36)  # seconds after the common footfall
CELL = 190
FOOT = "b_LeftFoot02_018"


def fox_path() -> Path:
    root = Path(os.environ.get("VBUSD_SHARED_ASSETS") or REPO.parent / "shared" / "assets")
    return root / "gltf" / "Fox" / "Fox.glb"


def contact_time(vb, clip: str) -> float:
    """The clip-local time at which the foot bone is lowest (its footfall), at the clip's rows."""
    import vbusd

    c = next(c for c in vb.clips if c.name == clip)
    times = np.arange(c.row_count) / c.rows_per_second
    heights = [vbusd.bone_transform(vb, FOOT, clip, float(t))[1, 3] for t in times]
    return float(times[int(np.argmin(heights))])


def render(points: np.ndarray, faces: np.ndarray, image: np.ndarray, depth: np.ndarray, origin, scale) -> None:
    """Side view (z to the right, y up; x toward the viewer) of one skinned mesh into ``image`` (H, W, 3),
    flat-shaded, with a depth buffer: a small numpy rasterizer, so the picture needs no GPU or browser."""
    tri = points[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    light = np.array([0.6, 0.7, 0.4]) / np.linalg.norm([0.6, 0.7, 0.4])
    shade = 0.3 + 0.7 * np.abs(normals @ light)
    sx = origin[0] + scale * tri[:, :, 2]
    sy = origin[1] - scale * tri[:, :, 1]
    height, width = depth.shape
    for f in range(len(faces)):
        x0, x1 = int(max(np.floor(sx[f].min()), 0)), int(min(np.ceil(sx[f].max()), width - 1))
        y0, y1 = int(max(np.floor(sy[f].min()), 0)), int(min(np.ceil(sy[f].max()), height - 1))
        if x1 < x0 or y1 < y0:
            continue
        gx, gy = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
        (ax, bx, cx), (ay, by, cy) = sx[f], sy[f]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        w0 = ((bx - gx) * (cy - gy) - (by - gy) * (cx - gx)) / area
        w1 = ((cx - gx) * (ay - gy) - (cy - gy) * (ax - gx)) / area
        w2 = 1.0 - w0 - w1
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        z = w0 * tri[f, 0, 0] + w1 * tri[f, 1, 0] + w2 * tri[f, 2, 0]
        block = depth[y0:y1 + 1, x0:x1 + 1]
        nearer = inside & (z > block)
        block[nearer] = z[nearer]
        image[y0:y1 + 1, x0:x1 + 1][nearer] = np.array([215, 120, 60]) * shade[f]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(OUTPUT))
    args = parser.parse_args(argv)
    source = fox_path()
    if not source.is_file():
        print(f"make_blend_space_image: {source}: the Fox sample model is missing (set VBUSD_SHARED_ASSETS)",
              file=sys.stderr)
        return 2
    import png

    import vbusd
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.converters import gltf
    from vbusd.format.motion import BlendSpace, Marker

    animation = gltf.read(source).animations[0]
    plain = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32"))
    markers = tuple(Marker(clip, "footL", contact_time(plain, clip)) for clip in ("Walk", "Run"))
    space = BlendSpace("speed", 1, ("Walk", "Run"), ((1.0,), (3.0,)), "footL")
    vb = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32", blend_spaces=(space,),
                                     markers=markers))
    mesh = vb.meshes[0]
    counts = np.asarray(mesh.face_vertex_counts)
    indices = np.asarray(mesh.face_vertex_indices)
    assert np.all(counts == 3), "the Fox is triangulated"
    faces = indices.reshape(-1, 3)
    durations = {c.name: c.duration for c in vb.clips}
    scale = 0.9
    rows, columns = len(STEPS), len(SPEEDS)
    image = np.empty((rows * CELL // 2 + 10, columns * CELL + 10, 3))
    image[:] = (246, 244, 238)
    depth = np.full(image.shape[:2], -np.inf)
    for column, x in enumerate(SPEEDS):
        w_run = (x - 1.0) / 2.0
        cycle = (1.0 - w_run) * durations["Walk"] + w_run * durations["Run"]
        for row, t in enumerate(STEPS):
            points = vbusd.skin(vb, blend={"space": "speed", "x": x, "phase": t / cycle})[0].points
            origin = (5 + column * CELL + CELL // 2 + 10, 5 + (row + 1) * CELL // 2 - 10)
            depth[:] = -np.inf
            render(points, faces, image, depth, origin, scale)
        image[:, 5 + (column + 1) * CELL - 1] = (200, 200, 200)
    for row in range(1, rows):
        image[5 + row * CELL // 2, :] = (220, 220, 220)
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.clip(np.round(image), 0, 255).astype(np.uint8)
    with tempfile.NamedTemporaryFile(dir=output.parent, suffix=".png", delete=False) as handle:
        png.Writer(pixels.shape[1], pixels.shape[0], greyscale=False).write(handle, pixels.reshape(pixels.shape[0], -1))
    os.replace(handle.name, output)
    print(output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
