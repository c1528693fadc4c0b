"""A small chain character with a mask, the primvars of a crowd file, and an instance skinned by
hand from them: what the crowd tests and the browser parity tests share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import vbusd

__all__ = ["chain_character", "additive_chain", "primvars", "by_hand"]


def chain_character(folder: Path, *, masks=(("upper", "b1"),)) -> Path:
    """A three-bone chain (b0 root, b1, b2) with three clips that move differently in time, a mesh
    skinned to all three bones, bind transforms the identity, bone masks (format 1.2)."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh, VirtualBonesAsset

    def local(angle, y):
        c, s = np.cos(angle), np.sin(angle)
        m = np.eye(4)
        m[:2, :2] = [[c, -s], [s, c]]
        m[1, 3] = y
        return m

    def clip(name, amplitudes, frequency, lift):
        def sample(times):
            out = []
            for t in np.atleast_1d(times):
                j0 = local(amplitudes[0] * np.sin(frequency * t), lift * np.sin(2 * frequency * t))
                j1 = j0 @ local(amplitudes[1] * np.sin(frequency * t + 1.0), 1.0)
                j2 = j1 @ local(amplitudes[2] * np.cos(frequency * t), 1.0)
                out.append(np.stack([j0, j1, j2]))
            return np.asarray(out)
        return AnimationClip(name, 0.0, 2.0, sample, native_rate=30, loop=False)

    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.3, 0.3, 30), np.linspace(0.0, 2.4, 30), rng.uniform(-0.3, 0.3, 30)])
    indices = np.array([[0, 1], [1, 2], [0, 2]] * 10)
    weights = np.repeat(rng.uniform(0.2, 0.8, (30, 1)), 2, axis=1) * [1, -1] + [0, 1]
    mesh = SkinnedMesh("/Chain/Mesh", points, np.array([3] * 10), np.arange(30), indices, weights,
                       normals=np.tile([1.0, 0.0, 0.0], (30, 1)))
    animation = SkinnedAnimation("Chain", "/Chain/Anim", ("b0", "b1", "b2"),
                                 (clip("walk", (0.2, 0.3, 0.1), 2.0, 0.1), clip("run", (0.5, 0.8, 0.6), 5.0, 0.3),
                                  clip("wave", (0.0, 1.2, 1.5), 3.0, 0.0)), (mesh,),
                                 bind_transforms=np.stack([np.eye(4)] * 3), bone_parents=(-1, 0, 1))
    vb = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32", masks=masks))
    path = folder / "chain.usda"
    vbusd.write_asset(VirtualBonesAsset(animations=(vb,), default_prim="Chain"), path)
    return path


def primvars(crowd_file: Path) -> dict:
    """The instancer's primvars as USD itself reads them (pxr, not vbusd's reader): defaults, the
    fade weight's time samples, the layer arrays as (instances, layers)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(crowd_file))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    tcps = stage.GetTimeCodesPerSecond()
    out = {"positions": np.array(prim.GetAttribute("positions").Get(), dtype=np.float64)}
    for name in ("clip", "timeOffset", "playbackRate", "fadeClip", "fadeTimeOffset", "fadePlaybackRate",
                 "fadeWeight", "layerClip", "layerTimeOffset", "layerPlaybackRate", "layerWeight", "layerMask"):
        primvar = UsdGeom.Primvar(prim.GetAttribute(f"primvars:vb:{name}"))
        if not primvar.GetAttr().IsValid() or not primvar.GetAttr().HasAuthoredValue():
            continue  # the schema declares every primvar; only the authored ones are the crowd's
        values = np.array(primvar.GetAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
        size = primvar.GetElementSize()
        out[name] = values.reshape(-1, size) if name.startswith("layer") else values
        samples = primvar.GetAttr().GetTimeSamples()
        if samples:
            out[name + ".samples"] = {code / tcps: np.array(primvar.GetAttr().Get(code), dtype=np.float64)
                                      for code in samples}
    masks = stage.GetPrimAtPath(str(prim.GetRelationship("vb:animation").GetTargets()[0])).GetAttribute("vb:maskNames")
    out["maskNames"] = list(masks.Get() or [])
    return out


def by_hand(character: Path, values: dict, i: int, t: float, weight_at) -> np.ndarray:
    """Instance i's world points at stage time t: vbusd.skin of the character with the instance's
    clip, crossfade and layers given by hand (spec "Instancing": tau = offset + rate * t), plus its
    position (the test's instances are neither turned nor scaled)."""
    tau = values["timeOffset"][i] + values["playbackRate"][i] * t
    fade = {}
    if "fadeClip" in values:
        fade = dict(fade_clip=int(values["fadeClip"][i]),
                    fade_time=values["fadeTimeOffset"][i] + values["fadePlaybackRate"][i] * t,
                    fade_weight=float(weight_at(i, t)))
    layers = [{"clip": int(values["layerClip"][i, j]),
               "time": values["layerTimeOffset"][i, j] + values["layerPlaybackRate"][i, j] * t,
               "weight": float(values["layerWeight"][i, j]), "mask": values["maskNames"][int(values["layerMask"][i, j])]}
              for j in range(values["layerClip"].shape[1])] if "layerClip" in values else None
    (pose,) = vbusd.skin(character, int(values["clip"][i]), tau, layers=layers, **fade)
    return pose.points + values["positions"][i]


ADDITIVE_ROWS = (  # base clip, offset, rate; per layer: clip, offset, rate, weight, mask, mode, reference clip, time
    ("walk", 0.3, 1.0, (("wave", 0.4, 1.0, 0.6, "upper", 1, "wave", 0.0), ("run", 0.0, 0.0, 0.0, "all", 0, "run", 0.0))),
    ("run", 0.1, 0.5, (("wave", 0.7, 1.0, 1.0, "all", 1, "walk", 0.25), ("walk", 0.2, 0.0, 0.5, "upper", 0, "walk", 0.0))),
    ("walk", 0.55, 1.0, (("run", 0.3, 0.0, 0.6, "upper", 0, "run", 0.0), ("wave", 1.1, 0.5, 0.8, "all", 1, "wave", 1.5))),
    ("wave", 1.0, 1.0, (("walk", 0.1, 1.0, 0.0, "all", 1, "walk", 0.0), ("run", 0.6, 0.0, 0.0, "upper", 1, "run", 0.0))),
)
"""The additive crowd's instances (format 1.3, spec 23.4): override and additive layers mixed, masked and
not, references of the layer's own clip and of another, instance 3 with every weight 0."""


def additive_chain(folder: Path, rows=ADDITIVE_ROWS, blends: bool = False) -> Path:
    """The chain character (masks ``upper`` = b1 and ``all`` = b0) with a crowd whose instances play
    :data:`ADDITIVE_ROWS`: two layers each, override and additive, written as the instancer's layer
    primvars and its additive ones (primvars:vb:layerMode, layerReferenceClip, layerReferenceTime).
    With ``blends``, the animation also stores the 1D space ``speed = walk@0, run@1`` synced on the
    marker ``step`` and the last instance (whose layers weigh 0) plays it at x 0.3, phase 0.2."""
    import dataclasses

    from vbusd.format.model import Crowd

    asset = vbusd.read_asset(chain_character(folder, masks=(("upper", "b1"), ("all", "b0"))))
    vb = asset.animations[0]
    clips = [c.name for c in vb.clips]
    masks = [name for name, _ in vb.masks]
    n = len(rows)

    def field(k, dtype, convert=lambda v: v):
        return np.array([[convert(layer[k]) for layer in row[3]] for row in rows], dtype)

    crowd = Crowd("/Chain/Crowd", np.column_stack([np.arange(n) * 1.5, np.zeros(n), np.zeros(n)]).astype(np.float32),
                  np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.array([clips.index(r[0]) for r in rows], np.int32), np.array([r[1] for r in rows], np.float32),
                  np.array([r[2] for r in rows], np.float32),
                  layer_clip=field(0, np.int32, clips.index), layer_time_offset=field(1, np.float32),
                  layer_playback_rate=field(2, np.float32), layer_weight=field(3, np.float32),
                  layer_mask=field(4, np.int32, masks.index), layer_mode=field(5, np.int32),
                  layer_reference_clip=field(6, np.int32, clips.index), layer_reference_time=field(7, np.float32))
    if blends:
        from vbusd.format.motion import parse_blend_space, parse_marker

        space = dataclasses.replace(parse_blend_space("speed=walk@0,run@1"), sync_marker="step")
        vb = dataclasses.replace(vb, blend_spaces=(space,),
                                 markers=(parse_marker("walk:step@0.5"), parse_marker("run:step@0.25")))
        crowd = dataclasses.replace(crowd, blend_space=np.array([-1] * (n - 1) + [0], np.int32),
                                    blend_x=np.array([0.0] * (n - 1) + [0.3], np.float32),
                                    blend_y=np.zeros(n, np.float32),
                                    blend_phase=np.array([0.0] * (n - 1) + [0.2], np.float32))
    path = folder / "additive" / "additive.usda"
    vbusd.write_asset(dataclasses.replace(asset, animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), path)
    return path
