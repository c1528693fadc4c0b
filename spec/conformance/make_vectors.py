"""Write the Virtual Bones conformance vectors of this folder (spec/conformance/README.md).

One vector per encoding and texel format (12): a small texture (4 bones, a looping clip of 8 rows
and a clamped clip of 5 rows, both at 4 rows per second), a mesh of 8 vertices with 4 influences,
8 instances (clip, time offset, playback rate and the format 1.1 crossfade: fade clip, its offset
and rate, fade weight) and the expected skinned points and normals of every instance at three
scene times, with every joint's socket transform (format 1.1), and the previous-frame pose (spec 21) of
every instance for a frame interval at three more times, computed in float64 by vbusd's numpy reference decoder from the stored texels.

Every time, offset and rate is a multiple of 1/64 with few significant bits, so a decoder that
computes ``tau = timeOffset + playbackRate * time`` in binary32 gets the same clip times as the
reference, and the tolerances measure only the decoder's arithmetic.

Usage (from the repository root): ``python spec/conformance/make_vectors.py`` rewrites the
vectors; ``--check`` only compares them with what it would write (exit 1 on a difference): as
numbers, floats within :data:`CHECK_TOLERANCE`, not as text.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
TEXEL_FORMATS = ("float16", "float32", "unorm16")
VECTORS = tuple((e, f) for e in ENCODINGS for f in TEXEL_FORMATS) + (("compactQuatTranslation", "uint32"),)
"""Every vector: each 1.0 encoding in each 1.0 texel format, and the compact encoding of format 1.2."""
TIMES = (0.0, 0.375, 1.875)
PREVIOUS_DT = 0.25
"""The frame interval of the previous-frame pose (spec 21): one row of the vectors' clips, so that
previous times fall on rows: instance 0 at t = 0 wraps back across the loop to row 7."""
PREVIOUS_TIMES = (0.0, 0.875, 1.875)
"""Scene times of the previous-pose frames: the loop boundary (instance 0 at t = 0, instance 4's
fade clip), the clamped clip's end (instance 2 at 0.875 s: 1.125 s held at the last row, 0.875 s a
frame before it) and both times past the end (1.875 s: zero velocity)."""
INSTANCES = (
    # clip, timeOffset, playbackRate, fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight
    (0, 0.0, 1.0, 0, 0.0, 1.0, 0.0),          # rows, mid-row, the loop's wrap (row 7 into row 0)
    (0, -0.5, 1.25, 0, 0.0, 1.0, 0.0),        # negative clip time: floored modulo
    (1, 0.25, 1.0, 0, 0.0, 1.0, 0.0),         # clamped clip, held last row past its end
    (0, 0.0625, 1.0, 1, 0.5, 0.5, 0.3125),    # crossfade into the clamped clip
    (1, 0.125, -1.0, 0, 1.0, 2.0, 1.0),       # weight 1: the fade clip alone; negative rate
    (0, 0.75, 0.5, 0, 1.5, 1.0, 0.5),         # fading a clip into itself at another time
    (1, 0.0, 1.0, 1, 3.0, 1.0, 0.0),          # weight 0: the fade clip is not read
    (0, 1.9375, 0.0, 1, 0.875, 0.0, 0.75),    # frozen (rate 0) in the wrap interval, fading
)
# Largest difference allowed from the float64 expectation, as a fraction of the diagonal of the
# bounding box of all expected points (positions) and per unit-normal component (normals): binary32
# arithmetic, and for unorm16 the binary32 dequantization min + (max - min) * u / 65535.
TOLERANCES = {"float16": (1e-6, 1e-5), "float32": (1e-6, 1e-5), "unorm16": (2e-6, 2e-5), "uint32": (2e-6, 2e-5)}
"""uint32 (compactQuatTranslation): binary32 dequantization of the fields, the square root of the
dropped component and the normalization, as for unorm16."""


def _rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                     [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                     [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]])


AXES = ((0.2, 0.1, 1.0), (1.0, 0.3, -0.2), (-0.4, 1.0, 0.5), (0.6, -0.5, 1.0))


def _animation(encoding: str):
    """A 4-bone chain, 1 unit between joints; scale where the encoding holds it; a twist for dualQuat."""
    from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh

    def sampler(speed: float, duration: float, loop: bool):
        def sample(times):
            times = np.atleast_1d(np.asarray(times, dtype=np.float64))
            out = np.tile(np.eye(4), (len(times), 4, 1, 1))
            for k, time in enumerate(times):
                phase = 2 * math.pi * time / duration if loop else math.pi * time / duration
                world = np.eye(4)
                for bone in range(4):
                    local = np.eye(4)
                    local[:3, :3] = _rotation(AXES[bone], 0.8 * speed * math.sin(phase + bone))
                    if encoding == "affineMatrix":  # non-uniform scale and shear
                        local[:3, :3] = local[:3, :3] @ np.diag([1.0 + 0.2 * math.sin(phase + bone), 1.0, 0.9])
                        local[0, 1] += 0.05 * bone
                    elif encoding == "quatTranslation":  # uniform scale
                        local[:3, :3] *= 1.0 + 0.15 * math.sin(phase + 2 * bone)
                    local[:3, 3] = (0.1 * math.sin(phase), 1.0 if bone else 0.25 * math.cos(phase), 0.0)
                    world = world @ local
                    bind = np.eye(4)
                    bind[1, 3] = -float(bone)
                    out[k, bone] = world @ bind
                if encoding == "dualQuat":  # quaternions of opposite hemispheres in one vertex
                    twist = np.eye(4)
                    twist[:3, :3] = _rotation((0.3, 0.2, 1.0), 1.1 * math.pi)
                    out[k, 2:] = out[k, 2:] @ twist
            return out
        return sample

    rng = np.random.default_rng(2026)
    points = np.column_stack([rng.uniform(-0.4, 0.4, 8), np.linspace(0.1, 3.6, 8), rng.uniform(-0.4, 0.4, 8)])
    normals = rng.normal(size=(8, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[5] = 0.0  # a degenerate normal: the spec's normalize(0) is 0
    indices = np.array([[0, 1, 2, 3], [1, 0, 2, 3], [1, 2, 0, 0], [2, 1, 3, 0],
                        [2, 3, 1, 0], [3, 2, 0, 0], [3, 2, 1, 0], [3, 0, 0, 0]])
    weights = np.array([[0.7, 0.2, 0.1, 0.0], [0.5, 0.25, 0.25, 0.0], [0.6, 0.4, 0.0, 0.0], [0.4, 0.3, 0.2, 0.1],
                        [0.55, 0.45, 0.0, 0.0], [0.8, 0.2, 0.0, 0.0], [0.5, 0.3, 0.2, 0.0], [1.0, 0.0, 0.0, 0.0]])
    mesh = SkinnedMesh("/Conformance/Mesh", points, np.array([3, 3]), np.array([0, 1, 2, 3, 4, 5]), indices, weights,
                       normals=normals)
    clips = (AnimationClip("sway", 0.0, 2.0, sampler(1.0, 2.0, True), native_rate=4, loop=True),
             AnimationClip("reach", 0.0, 1.0, sampler(1.3, 1.0, False), native_rate=4, loop=False))
    binds = np.tile(np.eye(4), (4, 1, 1))
    binds[:, 1, 3] = np.arange(4.0)  # joint b sits at (0, b, 0) in the bind pose
    return SkinnedAnimation("Conformance", "/Conformance/Anim", ("root", "spine", "arm", "hand"), clips, (mesh,),
                            bind_transforms=binds)


def build(encoding: str, texel_format: str, folder: Path) -> dict:
    """Bake one vector, write its texture into ``folder`` and return its JSON document."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.decoders.reference import crowd_joint_transforms, skin_crowd, skin_crowd_previous
    from vbusd.format import metadata as md
    from vbusd.format.model import Crowd
    from vbusd.io.textures import write_texture

    vb = bake(_animation(encoding), BakeOptions(encoding=encoding, texel_format=texel_format, max_influences=4))
    mesh = vb.meshes[0]
    suffix = "png" if texel_format == "unorm16" else "exr"  # uint32: three UINT channels in EXR
    texture = f"{encoding}-{texel_format}.{suffix}"
    write_texture(folder / texture, vb, sidecar=False)
    table = np.array(INSTANCES, dtype=np.float64)
    n = len(INSTANCES)
    identity = np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (n, 1))
    crowd = Crowd("/Conformance/Crowd", positions=np.zeros((n, 3), np.float32), orientations=identity,
                  clip=table[:, 0].astype(np.int32), time_offset=table[:, 1].astype(np.float32),
                  playback_rate=table[:, 2].astype(np.float32), fade_clip=table[:, 3].astype(np.int32),
                  fade_time_offset=table[:, 4].astype(np.float32), fade_playback_rate=table[:, 5].astype(np.float32),
                  fade_weight=table[:, 6].astype(np.float32))
    expected = []
    for time in TIMES:
        points, normals = skin_crowd(vb, mesh, crowd, time)
        sockets = np.stack([crowd_joint_transforms(vb, crowd, bone, time) for bone in range(len(vb.bones))], axis=1)
        expected.append({"time": time, "positions": points.tolist(), "normals": normals.tolist(),
                         "sockets": sockets.tolist()})
    frames = []
    for time in PREVIOUS_TIMES:
        points, normals = skin_crowd(vb, mesh, crowd, time)
        previous_points, previous_normals = skin_crowd_previous(vb, mesh, crowd, time, PREVIOUS_DT)
        frames.append({"time": time, "positions": points.tolist(), "normals": normals.tolist(),
                       "previousPositions": previous_points.tolist(), "previousNormals": previous_normals.tolist()})
    every_point = np.array([e["positions"] for e in expected]).reshape(-1, 3)
    diagonal = float(np.linalg.norm(every_point.max(axis=0) - every_point.min(axis=0)))
    position_fraction, normal_tolerance = TOLERANCES[texel_format]
    stored = np.ascontiguousarray(vb.texels)
    if texel_format == "uint32":  # the file's three words R, G, B per texel (spec 9.4), as integers
        texels = stored[..., :3].astype(np.int64).reshape(-1).tolist()
    elif texel_format == "unorm16":
        texels = stored.astype(np.int64).reshape(-1).tolist()
    else:
        texels = stored.astype(np.float64).reshape(-1).tolist()
    keys = ("clip", "timeOffset", "playbackRate", "fadeClip", "fadeTimeOffset", "fadePlaybackRate", "fadeWeight")
    return {
        "vector": f"{encoding}-{texel_format}",
        "formatVersion": 1,
        "formatMinorVersion": 2 if texel_format == "uint32" else 1,
        "description": f"4 bones, {encoding}, {texel_format}: a looping clip (8 rows) and a clamped clip (5 rows) "
                       "at 4 rows/s, 8 vertices with 4 influences, 8 instances with crossfades, 3 scene times",
        "layout": md.to_dict(vb, generator=GENERATOR),
        "texture": texture,
        "texels": texels,
        "bindTransforms": vb.bind_transforms.tolist(),
        "mesh": {"points": mesh.points.tolist(), "normals": mesh.normals.tolist(),
                 "influences": int(mesh.bone_indices.shape[1]), "boneIndices": mesh.bone_indices.tolist(),
                 "boneWeights": mesh.bone_weights.tolist()},
        "instances": [dict(zip(keys, [int(row[0]), *row[1:3], int(row[3]), *row[4:]])) for row in INSTANCES],
        "expected": expected,
        "previous": {"dt": PREVIOUS_DT, "frames": frames},
        "tolerance": {"position": position_fraction * diagonal, "positionFractionOfDiagonal": position_fraction,
                      "diagonal": diagonal, "normal": normal_tolerance,
                      "socket": position_fraction * max(diagonal, 1.0)},
    }


def write_all(folder: Path) -> list[Path]:
    """Write every vector (JSON and texture) into ``folder``; returns the written paths."""
    written = []
    for encoding, texel_format in VECTORS:
        document = build(encoding, texel_format, folder)
        path = folder / f"{encoding}-{texel_format}.json"
        lines = [f"  {json.dumps(key)}: {json.dumps(value, separators=(',', ':'))}" for key, value in document.items()]
        path.write_text("{\n" + ",\n".join(lines) + "\n}\n", encoding="utf-8")
        written += [path, folder / document["texture"]]
    return written


CHECK_TOLERANCE = 1e-12
"""``--check`` compares numbers, not their text: two floats agree when they differ by at most this
fraction of the larger magnitude (or of 1 below it). A float64 result may change in its last bits
with the numpy release (a norm, a matrix product summed in another order); 1e-12 is a millionth of
the smallest conformance tolerance, so a vector whose content changed is still stale."""


def differences(fresh, old, pointer: str = "") -> list[str]:
    """JSON pointers where two parsed vectors differ: strings, integers, booleans and shapes
    exactly, floats within :data:`CHECK_TOLERANCE`."""
    if isinstance(fresh, dict) and isinstance(old, dict):
        if fresh.keys() != old.keys():
            return [f"{pointer or '/'} (keys)"]
        return [d for key in fresh for d in differences(fresh[key], old[key], f"{pointer}/{key}")]
    if isinstance(fresh, list) and isinstance(old, list):
        if len(fresh) != len(old):
            return [f"{pointer} (length)"]
        return [d for i, (a, b) in enumerate(zip(fresh, old)) for d in differences(a, b, f"{pointer}/{i}")]
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (fresh, old))
    if numbers and (isinstance(fresh, float) or isinstance(old, float)):
        return [] if abs(fresh - old) <= CHECK_TOLERANCE * max(1.0, abs(fresh), abs(old)) else [pointer]
    return [] if type(fresh) is type(old) and fresh == old else [pointer]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with the committed vectors, write nothing")
    args = parser.parse_args(argv)
    if not args.check:
        for path in write_all(HERE):
            print(f"wrote {path.relative_to(HERE)}")
        return 0
    with tempfile.TemporaryDirectory() as scratch:
        stale = []
        for path in write_all(Path(scratch)):
            committed = HERE / path.name
            if path.suffix == ".json":
                fresh = json.loads(path.read_text())
                old = json.loads(committed.read_text()) if committed.is_file() else None
                for document in (fresh, old or {}):
                    document.get("layout", {}).pop("generator", None)
                where = differences(fresh, old) if old is not None else ["(missing)"]
                if where:
                    stale.append(f"{path.name} at {', '.join(where[:5])}{' ...' if len(where) > 5 else ''}")
        for name in stale:
            print(f"stale: {name}")
        return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
