"""Choose the compact encoding's rotation representation, bit allocation and ranges by measured error.

For the stadium-crowd sample (its exact float64 matrices, 512 rows as the sample bakes them) and
every animation of the shared glTF characters (``$VBUSD_SHARED_ASSETS/gltf`` or
``../shared/assets/gltf``; their converter's matrices at the rows the default bake plans), the
script quantizes every row's rigid transform into a 96-bit texel under several candidate layouts,
decodes it and measures the largest vertex position error of linear blend skinning against exact
float64 LBS of the source matrices (``_lbs`` below, written here, not vbusd's decoder):

* at row times (quantization alone);
* at mid-row times, decoding both rows and blending them as spec 5.6 says (quantization plus the
  format's interpolation between rows), against the source's exact pose there.

Candidates (all at most 96 bits, 12 bytes, one R32G32B32_UINT texel):

* ``st16/t15``: smallest-three quaternion, 2-bit index + 3 x 16 bits; translation 3 x 15 bits (the
  format's choice: the only split within both targets on every subject, and the most exact at rows
  on the stadium spectator, Fox and RiggedFigure);
* ``st15/t16``, ``st14/t17`` and ``st17/t14``: the same 95 bits split the other ways;
* range modes: ``bone`` (ranges per bone: the chosen format), ``bone+clip`` (per bone and clip),
  ``global`` (no range reduction: quaternion components in [-1/sqrt2, 1/sqrt2], translation per
  component over all bones: what a fixed layout without per-bone ranges reaches).

Errors are printed in metres (scene units) and as fractions of the rest meshes' bounding-box
diagonal. Run: ``python benchmarks/compact_encoding.py`` (markdown) or ``--format json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

CANDIDATES = (("st16/t15 (chosen)", 16, 15), ("st15/t16", 15, 16), ("st14/t17", 14, 17), ("st17/t14", 17, 14))
RANGE_MODES = ("bone", "bone+clip", "global")


def shared_assets() -> Path:
    """The shared assets folder: $VBUSD_SHARED_ASSETS, else ../shared/assets beside the repo."""
    env = os.environ.get("VBUSD_SHARED_ASSETS")
    return Path(env) if env else REPO.parent / "shared" / "assets"


def _lbs(points: np.ndarray, idx: np.ndarray, w: np.ndarray, matrices: np.ndarray) -> np.ndarray:
    """(n, V, 3) exact LBS in float64: the yardstick, independent of vbusd's decoders."""
    m = matrices[:, idx]
    moved = np.einsum("nvkij,vj->nvki", m[..., :3, :3], points) + m[..., :3, 3]
    return np.einsum("vk,nvki->nvi", w, moved)


def _stadium():
    name = "vbusd_samples_stadium_crowd"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "samples" / "stadium_crowd.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    gen = sys.modules[name]
    return gen.make_skinned_animation(), gen.reference_bake_options(encoding="quatTranslation")


def subjects() -> list:
    """(label, SkinnedAnimation, BakeOptions) of the stadium sample and every shared glTF animation."""
    from vbusd.baking.baker import BakeOptions
    from vbusd.converters import gltf

    out = [("stadium spectator", *_stadium())]
    folder = shared_assets() / "gltf"
    for path in sorted(folder.glob("*/*.gl*")) if folder.is_dir() else ():
        scene = gltf.read(path)
        for i, animation in enumerate(scene.animations):
            label = path.stem + (f" skin {i}" if len(scene.animations) > 1 else "")
            out.append((label, animation, BakeOptions(encoding="quatTranslation")))
    return out


def _rows(animation, options):
    """Per clip: (row times, mid-row times, matrices at rows, matrices at mid-rows, loop)."""
    from vbusd.baking.baker import decide_loop, plan_rows

    loops = [decide_loop(c, options) for c in animation.clips]
    plans = plan_rows(animation.clips, loops, options)
    out = []
    for clip, plan in zip(animation.clips, plans):
        taus = np.arange(plan.row_count) / plan.rows_per_second
        out.append((clip, plan, clip.sample(clip.start_time + taus)))
    return out


def _rigid(matrices: np.ndarray):
    from vbusd.format.quaternion import matrix_to_quat

    u, _, vt = np.linalg.svd(matrices[..., :3, :3])
    rot = u @ vt
    return matrix_to_quat(rot), matrices[..., :3, 3]


def _global_ranges(q, t, bones):
    from vbusd.format.compact import _widen_to_float32

    low = np.concatenate([np.full(4, -np.sqrt(0.5)), t.reshape(-1, 3).min(axis=0)])
    high = np.concatenate([np.full(4, np.sqrt(0.5)), t.reshape(-1, 3).max(axis=0)])
    r = _widen_to_float32(low, high)
    return np.broadcast_to(r, (bones, 7, 2)).copy()


def measure(animation, options, bits, mode: str) -> dict:
    """Largest errors (metres and of the diagonal) of one animation under one candidate."""
    from vbusd.format.compact import (CompactBits, blend_compact, choose_dropped, compact_ranges,
                                      decode_compact_fields, encode_compact)
    from vbusd.format.quaternion import quat_to_matrix

    cb = CompactBits(*bits)
    per_clip = _rows(animation, options)
    allq = np.concatenate([_rigid(m)[0] for _, _, m in per_clip])
    allt = np.concatenate([_rigid(m)[1] for _, _, m in per_clip])
    bones = allq.shape[1]
    if mode == "global":
        ranges_all = _global_ranges(allq, allt, bones)
        dropped_all = np.argmax(np.abs(allq), axis=-1)
    else:
        dropped_all = choose_dropped(allq)
        ranges_all = compact_ranges(allq, allt, dropped_all)
    worst = {"rows_m": 0.0, "mid_m": 0.0, "rows_diag": 0.0, "mid_diag": 0.0}
    first = 0
    for clip, plan, matrices in per_clip:
        n = plan.row_count
        q, t = _rigid(matrices)
        if mode == "bone+clip":
            dropped = choose_dropped(q)
            ranges = compact_ranges(q, t, dropped)
        else:
            dropped, ranges = dropped_all[first:first + n], ranges_all
        first += n
        words, _ = encode_compact(q, t, ranges=ranges, dropped=dropped, bits=cb)
        dq, dt = decode_compact_fields(words, ranges, cb)
        f = 0.5
        nxt = (np.arange(n) + 1) % n if plan.loop else np.minimum(np.arange(n) + 1, n - 1)
        count_mid = n if plan.loop else max(n - 1, 1)
        bq, bt = blend_compact(dq[:count_mid], dt[:count_mid], dq[nxt[:count_mid]], dt[nxt[:count_mid]], f)
        mid_taus = (np.arange(count_mid) + (0.5 if n > 1 else 0.0)) / plan.rows_per_second
        exact_mid = clip.sample(clip.start_time + mid_taus)
        for decoded_q, decoded_t, exact, slot in ((dq, dt, matrices, "rows"), (bq, bt, exact_mid, "mid")):
            m = np.zeros(decoded_q.shape[:-1] + (4, 4))
            m[..., :3, :3] = quat_to_matrix(decoded_q)
            m[..., :3, 3] = decoded_t
            m[..., 3, 3] = 1
            for mesh in animation.meshes:
                p = np.asarray(mesh.points, float)
                idx, w = np.asarray(mesh.bone_indices), np.asarray(mesh.bone_weights, float)
                w = w / w.sum(axis=1, keepdims=True)
                err = float(np.linalg.norm(_lbs(p, idx, w, m) - _lbs(p, idx, w, exact), axis=-1).max())
                diag = float(np.linalg.norm(np.ptp(p, axis=0))) or 1.0
                worst[f"{slot}_m"] = max(worst[f"{slot}_m"], err)
                worst[f"{slot}_diag"] = max(worst[f"{slot}_diag"], err / diag)
    return worst


def _exact_blend_error(animation, options) -> dict:
    """Mid-row error of the row blend itself on exact (unquantized) rows: what interpolation costs."""
    from vbusd.format.compact import blend_compact
    from vbusd.format.quaternion import quat_to_matrix

    worst = {"mid_m": 0.0, "mid_diag": 0.0}
    for clip, plan, matrices in _rows(animation, options):
        n = plan.row_count
        q, t = _rigid(matrices)
        nxt = (np.arange(n) + 1) % n if plan.loop else np.minimum(np.arange(n) + 1, n - 1)
        count_mid = n if plan.loop else max(n - 1, 1)
        bq, bt = blend_compact(q[:count_mid], t[:count_mid], q[nxt[:count_mid]], t[nxt[:count_mid]], 0.5)
        mid_taus = (np.arange(count_mid) + (0.5 if n > 1 else 0.0)) / plan.rows_per_second
        exact = clip.sample(clip.start_time + mid_taus)
        m = np.zeros(bq.shape[:-1] + (4, 4))
        m[..., :3, :3], m[..., :3, 3], m[..., 3, 3] = quat_to_matrix(bq), bt, 1
        for mesh in animation.meshes:
            p = np.asarray(mesh.points, float)
            idx, w = np.asarray(mesh.bone_indices), np.asarray(mesh.bone_weights, float)
            w = w / w.sum(axis=1, keepdims=True)
            err = float(np.linalg.norm(_lbs(p, idx, w, m) - _lbs(p, idx, w, exact), axis=-1).max())
            diag = float(np.linalg.norm(np.ptp(p, axis=0))) or 1.0
            worst["mid_m"] = max(worst["mid_m"], err)
            worst["mid_diag"] = max(worst["mid_diag"], err / diag)
    return worst


def run() -> list:
    """Every subject x candidate x range mode."""
    results = []
    from vbusd.format.encoding import NonRigidError, encode_bones

    for label, animation, options in subjects():
        try:  # the compact encoding holds rigid transforms only, as crossMatrix does
            for _, _, m in _rows(animation, options):
                encode_bones(m, "crossMatrix")
        except NonRigidError as error:
            results.append({"subject": label, "bones": animation.bone_count, "refused": error.message})
            continue
        diag = max(float(np.linalg.norm(np.ptp(np.asarray(m.points, float), axis=0))) for m in animation.meshes)
        entry = {"subject": label, "bones": animation.bone_count, "diagonal_m": diag,
                 "blend_only": _exact_blend_error(animation, options), "runs": {}}
        for name, rb, tb in CANDIDATES:
            for mode in RANGE_MODES:
                entry["runs"][f"{name} {mode}"] = measure(animation, options, (rb, tb), mode)
        results.append(entry)
    return results


def markdown(results: list) -> str:
    """One row per subject and candidate: errors at rows and mid-row, metres and of the diagonal."""
    lines = ["| subject (diagonal) | layout, ranges | max error at rows (m) | of diagonal | max error mid-row (m) | of diagonal |",
             "|---|---|--:|--:|--:|--:|"]
    for r in results:
        if "refused" in r:
            lines.append(f"| {r['subject']} | refused: {r['refused']} | | | | |")
            continue
        b = r["blend_only"]
        lines.append(f"| {r['subject']} ({r['diagonal_m']:.3g} m) | exact rows, blend only | 0 | 0 | "
                     f"{b['mid_m']:.3g} | {b['mid_diag']:.3g} |")
        for key, w in r["runs"].items():
            lines.append(f"| {r['subject']} | {key} | {w['rows_m']:.3g} | {w['rows_diag']:.3g} | "
                         f"{w['mid_m']:.3g} | {w['mid_diag']:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Command line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--format", choices=("markdown", "json"), default="markdown")
    args = parser.parse_args(argv)
    results = run()
    print(json.dumps(results, indent=1) if args.format == "json" else markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
