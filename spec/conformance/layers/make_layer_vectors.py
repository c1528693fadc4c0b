"""Write the layer conformance vectors of this folder (format 1.2, spec/virtual-bones.md 8.6).

One vector per encoding, in float16 and float32 (8): the rig, texture, clips and mesh of the
format 1.1 vectors (../make_vectors.py: a 4-bone chain root, spine, arm, hand), plus the bones'
parents, two masks ("upper": spine and every bone below it; "soft": arm 0.5, hand 1, a per-bone
weight no --mask writes) and 6 instances with up to two layers each (clip, time offset, playback
rate, weight, mask) on top of the crossfade, with the expected skinned points, normals and sockets
at three scene times, and the previous-frame pose (spec 21) at three more, computed in float64 by vbusd's numpy reference decoder (itself checked against
three.js' AnimationMixer and UsdSkel's poses, tests/test_layers.py).

Usage (from the repository root): ``python spec/conformance/layers/make_layer_vectors.py`` rewrites
the vectors; ``--check`` compares them with what it would write (exit 1 on a difference).
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import argparse
import dataclasses
import json
import runpy
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BASE = runpy.run_path(str(HERE.parent / "make_vectors.py"))
ENCODINGS = BASE["ENCODINGS"]
TEXEL_FORMATS = ("float16", "float32")
TIMES = BASE["TIMES"]
PREVIOUS_DT = BASE["PREVIOUS_DT"]
PREVIOUS_TIMES = BASE["PREVIOUS_TIMES"]
PARENTS = (-1, 0, 1, 2)
MASKS = (("upper", (0.0, 1.0, 1.0, 1.0)), ("soft", (0.0, 0.0, 0.5, 1.0)))
INSTANCES = (
    # clip, timeOffset, playbackRate, fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight,
    # then per layer (2): clip, timeOffset, playbackRate, weight, mask
    (0, 0.0, 1.0, 0, 0.0, 1.0, 0.0, (1, 0.25, 1.0, 0.5, 0), (0, 0.0, 1.0, 0.0, 0)),     # one layer, halfway
    (0, 0.5, 1.0, 0, 0.0, 1.0, 0.0, (1, 0.0, 1.0, 1.0, 0), (0, 1.25, 1.0, 0.25, 1)),    # two layers in order
    (1, 0.125, 1.0, 0, 0.5, 1.0, 0.3125, (0, 0.75, 0.5, 0.75, 1), (0, 0.0, 1.0, 0.0, 0)),  # on a crossfade
    (0, 0.25, 1.0, 1, 0.0, 1.0, 0.5, (1, 0.0, 1.0, 0.0, 0), (1, 0.0, 1.0, 0.0, 1)),     # weights 0: unlayered
    (1, 0.875, -1.0, 0, 0.0, 1.0, 0.0, (1, 0.375, 1.0, 0.625, 0), (0, 0.0, 1.0, 0.0, 0)),  # negative rate
    (0, 1.9375, 0.0, 0, 0.0, 1.0, 0.0, (1, 0.5, 2.0, 1.0, 1), (0, 0.0, 1.0, 0.0, 0)),   # frozen base, soft mask
)
TOLERANCES = {"float16": (1e-6, 1e-5), "float32": (1e-6, 1e-5)}


def _crowd(vb):
    from vbusd.format.model import Crowd

    n = len(INSTANCES)
    base = np.array([row[:7] for row in INSTANCES], dtype=np.float64)
    layers = np.array([[layer for layer in row[7:]] for row in INSTANCES], dtype=np.float64)  # (n, 2, 5)
    return Crowd("/Conformance/Crowd", positions=np.zeros((n, 3), np.float32),
                 orientations=np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (n, 1)),
                 clip=base[:, 0].astype(np.int32), time_offset=base[:, 1].astype(np.float32),
                 playback_rate=base[:, 2].astype(np.float32), fade_clip=base[:, 3].astype(np.int32),
                 fade_time_offset=base[:, 4].astype(np.float32), fade_playback_rate=base[:, 5].astype(np.float32),
                 fade_weight=base[:, 6].astype(np.float32), layer_clip=layers[..., 0].astype(np.int32),
                 layer_time_offset=layers[..., 1].astype(np.float32),
                 layer_playback_rate=layers[..., 2].astype(np.float32),
                 layer_weight=layers[..., 3].astype(np.float32), layer_mask=layers[..., 4].astype(np.int32))


def build(encoding: str, texel_format: str, folder: Path) -> dict:
    """Bake one vector, write its texture into ``folder`` and return its JSON document."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.decoders.reference import crowd_joint_transforms, skin_crowd, skin_crowd_previous
    from vbusd.format import metadata as md
    from vbusd.io.textures import write_texture

    animation = dataclasses.replace(BASE["_animation"](encoding), bone_parents=PARENTS)
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format, max_influences=4,
                                     masks=(("upper", "spine"),)))
    masks = tuple((name, np.array(weights)) for name, weights in MASKS)
    assert np.array_equal(vb.masks[0][1], masks[0][1])  # --mask upper=spine gives the same weights
    vb = dataclasses.replace(vb, masks=masks)
    mesh = vb.meshes[0]
    texture = f"layers-{encoding}-{texel_format}.exr"
    write_texture(folder / texture, vb, sidecar=False)
    crowd = _crowd(vb)
    expected = []
    for time in TIMES:
        points, normals = skin_crowd(vb, mesh, crowd, time)
        sockets = np.stack([crowd_joint_transforms(vb, crowd, bone, time) for bone in range(len(vb.bones))], axis=1)
        expected.append({"time": time, "positions": points.tolist(), "normals": normals.tolist(),
                         "sockets": sockets.tolist()})
    frames = []  # the previous-frame pose (spec 21), as in ../make_vectors.py: layers at t - dt too
    for time in PREVIOUS_TIMES:
        points, normals = skin_crowd(vb, mesh, crowd, time)
        previous_points, previous_normals = skin_crowd_previous(vb, mesh, crowd, time, PREVIOUS_DT)
        frames.append({"time": time, "positions": points.tolist(), "normals": normals.tolist(),
                       "previousPositions": previous_points.tolist(), "previousNormals": previous_normals.tolist()})
    every_point = np.array([e["positions"] for e in expected]).reshape(-1, 3)
    diagonal = float(np.linalg.norm(every_point.max(axis=0) - every_point.min(axis=0)))
    position_fraction, normal_tolerance = TOLERANCES[texel_format]
    keys = ("clip", "timeOffset", "playbackRate", "fadeClip", "fadeTimeOffset", "fadePlaybackRate", "fadeWeight")
    layer_keys = ("clip", "timeOffset", "playbackRate", "weight", "mask")
    instances = []
    for row in INSTANCES:
        instance = dict(zip(keys, [int(row[0]), *row[1:3], int(row[3]), *row[4:7]]))
        instance["layers"] = [dict(zip(layer_keys, [int(layer[0]), *layer[1:4], int(layer[4])])) for layer in row[7:]]
        instances.append(instance)
    return {
        "vector": f"layers-{encoding}-{texel_format}",
        "formatVersion": 1,
        "formatMinorVersion": 2,
        "description": f"the 4-bone chain of the 1.1 vectors ({encoding}, {texel_format}) with bone parents, masks "
                       "'upper' and 'soft', and 6 instances with up to 2 layers on top of the crossfade",
        "layout": md.to_dict(vb, generator=GENERATOR),
        "texture": texture,
        "texels": np.ascontiguousarray(vb.texels).astype(np.float64).reshape(-1).tolist(),
        "bindTransforms": vb.bind_transforms.tolist(),
        "boneParents": list(PARENTS),
        "masks": [{"name": name, "weights": list(weights)} for name, weights in MASKS],
        "mesh": {"points": mesh.points.tolist(), "normals": mesh.normals.tolist(),
                 "influences": int(mesh.bone_indices.shape[1]), "boneIndices": mesh.bone_indices.tolist(),
                 "boneWeights": mesh.bone_weights.tolist()},
        "instances": instances,
        "expected": expected,
        "previous": {"dt": PREVIOUS_DT, "frames": frames},
        "tolerance": {"position": position_fraction * diagonal, "positionFractionOfDiagonal": position_fraction,
                      "diagonal": diagonal, "normal": normal_tolerance,
                      "socket": position_fraction * max(diagonal, 1.0)},
    }


def write_all(folder: Path) -> list[Path]:
    """Write every vector (JSON and texture) into ``folder``; returns the written paths."""
    written = []
    for encoding in ENCODINGS:
        for texel_format in TEXEL_FORMATS:
            document = build(encoding, texel_format, folder)
            path = folder / f"layers-{encoding}-{texel_format}.json"
            lines = [f"  {json.dumps(key)}: {json.dumps(value, separators=(',', ':'))}" for key, value in document.items()]
            path.write_text("{\n" + ",\n".join(lines) + "\n}\n", encoding="utf-8")
            written += [path, folder / document["texture"]]
    return written


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
                where = BASE["differences"](fresh, old) if old is not None else ["(missing)"]
                if where:
                    stale.append(f"{path.name} at {', '.join(where[:5])}{' ...' if len(where) > 5 else ''}")
        for name in stale:
            print(f"stale: {name}")
        return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
