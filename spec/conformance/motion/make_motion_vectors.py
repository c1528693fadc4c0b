"""Write the blend-space, additive-layer and event conformance vectors of this folder (format 1.3,
spec/virtual-bones.md section 23).

One vector per encoding in float32 (4): the rig, texture, clips and mesh of the layer vectors
(../layers/make_layer_vectors.py: the 4-bone chain root, spine, arm, hand with its parents; clips
"sway", looping 2 s, and "reach", clamped 1 s), its masks ("upper", "soft", and "all": every bone),
two blend spaces ("lean", 1D: sway@0, reach@1, sway@2 -- a clip at two points; "fan", 2D: a square
with a fifth point in its middle and the clips at several points, synchronized on the marker "beat")
and four markers, with

* ``blends``: a blend space at a parameter and phase, its weights and each point's clip time, and
  the expected skinned points, normals and joint transforms (``J'``);
* ``additive``: a clip and time with additive (and override) layers and references, expected as above;
* ``weights``: parameters of both spaces (inside, on edges, outside) and the weights they give;
* ``events``: clip-local intervals (forward, backward, across loops, on a clamped clip) and the
  markers crossed;

computed in float64 by vbusd's numpy reference decoder (itself checked against three.js'
AnimationMixer: tests/test_blend_spaces.py). A decoder that layers decodes the blends as layers of
mask "all" with the weights of ``layerWeights`` (spec 23.1, "Decoding a blend as layers").

Usage (from the repository root): ``python spec/conformance/motion/make_motion_vectors.py`` rewrites
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
PARENTS = (-1, 0, 1, 2)
MASKS = (("upper", (0.0, 1.0, 1.0, 1.0)), ("soft", (0.0, 0.0, 0.5, 1.0)), ("all", (1.0, 1.0, 1.0, 1.0)))
SPACES = ("lean=sway@0,reach@1,sway@2", "fan=sway@0:0,reach@1:0,sway@0:1,reach@1:1,reach@0.5:0.5")
SYNCS = ("fan=beat",)
MARKERS = ("sway:beat@0.5", "sway:tick@1.25", "reach:beat@0.25", "reach:end@1")
BLENDS = (
    {"space": "lean", "x": 0.25, "phase": 0.125},
    {"space": "lean", "x": 1.5, "phase": 0.625},
    {"space": "lean", "x": 2.5, "phase": 1.75},      # outside: the last point alone; phase past a loop
    {"space": "fan", "x": 0.25, "y": 0.125, "phase": 0.375},
    {"space": "fan", "x": 0.75, "y": 0.5, "phase": 0.5},
    {"space": "fan", "x": 1.5, "y": 0.25, "phase": -0.25},  # outside the hull: onto its nearest edge
)
ADDITIVE = (
    ("sway", 0.25, [{"clip": "reach", "time": 0.5, "weight": 0.75, "mask": "upper", "mode": "additive",
                     "reference": {"clip": "reach", "time": 0.0}}]),
    ("reach", 0.375, [{"clip": "sway", "time": 1.5, "weight": 1.0, "mask": "soft", "mode": "additive"}]),
    ("sway", 1.125, [{"clip": "reach", "time": 0.75, "weight": 0.5, "mask": "all"},
                     {"clip": "sway", "time": 0.25, "weight": 0.5, "mask": "upper", "mode": "additive",
                      "reference": {"clip": "sway", "time": 1.0}}]),
)
WEIGHTS = (("lean", -1.0, 0.0), ("lean", 0.5, 0.0), ("lean", 1.0, 0.0), ("lean", 1.75, 0.0),
           ("fan", 0.5, 0.5), ("fan", 0.25, 0.75), ("fan", 0.5, 0.0), ("fan", -0.5, 2.0), ("fan", 2.0, 0.5))
EVENTS = (("sway", 0.0, 4.5), ("sway", 0.5, 1.25), ("sway", 3.0, -1.0), ("reach", -1.0, 2.0), ("reach", 0.25, 0.5),
          ("reach", 0.0, 0.25))
TOLERANCE = (1e-6, 1e-5)


def build(encoding: str, folder: Path) -> dict:
    """Bake one vector, write its texture into ``folder`` and return its JSON document."""
    import vbusd
    from vbusd.api import blend_points
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.format import metadata as md
    from vbusd.format.motion import as_layer_weights, blend_weights, parse_blend_space, parse_marker
    from vbusd.jobs.conversion import with_syncs
    from vbusd.io.textures import write_texture

    animation = dataclasses.replace(BASE["_animation"](encoding), bone_parents=PARENTS)
    spaces = with_syncs(tuple(parse_blend_space(s) for s in SPACES), SYNCS)
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32", max_influences=4,
                                     masks=(("upper", "spine"), ("soft", "arm"), ("all", "root")), blend_spaces=spaces,
                                     markers=tuple(parse_marker(m) for m in MARKERS)))
    vb = dataclasses.replace(vb, masks=tuple((name, np.array(weights)) for name, weights in MASKS))
    mesh = vb.meshes[0]
    texture = f"motion-{encoding}-float32.exr"
    write_texture(folder / texture, vb, sidecar=False)
    names = {s.name: s for s in vb.blend_spaces}

    def pose(**kwargs) -> dict:
        skinned = vbusd.skin(vb, **kwargs)[0]
        joints = [vbusd.bone_transform(vb, b, **kwargs).tolist() for b in range(len(vb.bones))]
        return {"positions": skinned.points.tolist(), "normals": skinned.normals.tolist(), "joints": joints}

    blends = []
    for blend in BLENDS:
        space = names[blend["space"]]
        weights = blend_weights(space, blend["x"], blend.get("y", 0.0))
        points = blend_points(vb, dict(blend))
        blends.append({"blend": blend, "weights": [[k, w] for k, w in weights],
                       "layerWeights": [[k, w] for k, w in as_layer_weights(weights)],
                       "clipTimes": [[vb.clips[c].name, float(t[0])] for c, t, _ in points],
                       **pose(blend=dict(blend))})
    additive = [{"clip": clip, "time": time, "layers": layers, **pose(clip=clip, time=time, layers=layers)}
                for clip, time, layers in ADDITIVE]
    every_point = np.array([case["positions"] for case in blends + additive]).reshape(-1, 3)
    diagonal = float(np.linalg.norm(every_point.max(axis=0) - every_point.min(axis=0)))
    position_fraction, normal_tolerance = TOLERANCE
    return {
        "vector": f"motion-{encoding}-float32",
        "formatVersion": 1,
        "formatMinorVersion": 3,
        "description": f"the 4-bone chain of the layer vectors ({encoding}, float32) with masks 'upper', 'soft' "
                       "and 'all', blend spaces 'lean' (1D) and 'fan' (2D, synced on 'beat'), four markers: blends, "
                       "additive layers, weights and events",
        "layout": md.to_dict(vb, generator=GENERATOR),
        "texture": texture,
        "texels": np.ascontiguousarray(vb.texels).astype(np.float64).reshape(-1).tolist(),
        "bindTransforms": vb.bind_transforms.tolist(),
        "boneParents": list(PARENTS),
        "masks": [{"name": name, "weights": list(weights)} for name, weights in MASKS],
        "mesh": {"points": mesh.points.tolist(), "normals": mesh.normals.tolist(),
                 "influences": int(mesh.bone_indices.shape[1]), "boneIndices": mesh.bone_indices.tolist(),
                 "boneWeights": mesh.bone_weights.tolist()},
        "blends": blends,
        "additive": additive,
        "weights": [{"space": s, "x": x, "y": y, "weights": [[k, w] for k, w in blend_weights(names[s], x, y)]}
                    for s, x, y in WEIGHTS],
        "events": [{"clip": clip, "t0": t0, "t1": t1, "events": vbusd.events(vb, clip, t0, t1)}
                   for clip, t0, t1 in EVENTS],
        "tolerance": {"position": position_fraction * diagonal, "positionFractionOfDiagonal": position_fraction,
                      "diagonal": diagonal, "normal": normal_tolerance, "joint": position_fraction * max(diagonal, 1.0)},
    }


def write_all(folder: Path) -> list[Path]:
    """Write every vector (JSON and texture) into ``folder``; returns the written paths."""
    written = []
    for encoding in ENCODINGS:
        document = build(encoding, folder)
        path = folder / f"motion-{encoding}-float32.json"
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
