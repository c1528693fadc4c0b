"""Convert every glTF asset in ../shared/assets/gltf and bake it in every encoding.

For each asset the script reports what the glTF converter makes of it (skins, joints, clips, rows
per second it proposes, warnings, read time) and, for each encoding with float16 texels (the
default) and affineMatrix with float32, whether the bake succeeds or the one-line error it gives
(for example crossMatrix refusing scaled joints), the texture size, and the largest vertex error of
the reference-decoded points:

* **at rows**: against linear blend skinning, in float64, with the converter's own matrices at the
  row's time (encoding + texel format error);
* **mid-row**: against the same at times halfway between rows (adds the error of blending rows
  linearly where glTF interpolates rotations by slerp).

Errors are fractions of the rest meshes' bounding-box diagonal (over all meshes of the animation,
the worst animation of the asset). dualQuat is decoded with dual-quaternion skinning, so its error
against LBS also holds the difference between the two skinning methods.

Run: ``python benchmarks/gltf_assets.py`` (markdown tables, as in docs/converters/gltf.md) or
``--format json``; ``--assets DIR`` to point elsewhere.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ASSETS = REPO.parent / "shared" / "assets" / "gltf"
RUNS = (("crossMatrix", "float16"), ("affineMatrix", "float16"), ("affineMatrix", "float32"),
        ("quatTranslation", "float16"), ("dualQuat", "float16"))


def _lbs(points: np.ndarray, idx: np.ndarray, w: np.ndarray, matrices: np.ndarray) -> np.ndarray:
    """(n, V, 3) LBS of rest points with (n, B, 4, 4) matrices, float64.

    Written here rather than taken from vbusd.decoders.reference: it is the yardstick the reference
    decoder's output is measured against, so it must not be that decoder.
    """
    m = matrices[:, idx]                                   # (n, V, K, 4, 4)
    moved = np.einsum("nvkij,vj->nvki", m[..., :3, :3], points) + m[..., :3, 3]
    return np.einsum("vk,nvki->nvi", w, moved)


def measure(animation, encoding: str, texel_format: str) -> dict:
    """Bake one animation; return sizes and errors, or the error line."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.format.errors import VbusdError
    from vbusd.decoders.reference import skin_mesh

    try:
        vb = bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format))
    except VbusdError as error:
        return {"status": f"{error.code}: {error.message}"}
    worst_rows = worst_mid = 0.0
    for ci, (clip, source) in enumerate(zip(vb.clips, animation.clips)):
        tau_rows = np.arange(clip.row_count) / clip.rows_per_second
        tau_mid = (np.arange(max(clip.row_count - 1, 1)) + 0.5) / clip.rows_per_second
        if clip.row_count == 1:
            tau_mid = tau_rows
        for taus, slot in ((tau_rows, "rows"), (tau_mid, "mid")):
            matrices = source.sample(clip.start_time + taus)
            for mesh, bound in zip(animation.meshes, vb.meshes):
                expected = _lbs(np.asarray(mesh.points, float), np.asarray(mesh.bone_indices),
                                np.asarray(mesh.bone_weights, float), matrices)
                decoded, _ = skin_mesh(vb, bound, ci, taus)
                diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.points, float), axis=0))) or 1.0
                err = float(np.abs(decoded - expected).max()) / diag
                if slot == "rows":
                    worst_rows = max(worst_rows, err)
                else:
                    worst_mid = max(worst_mid, err)
    layout = vb.layout
    return {"status": "ok", "texture": f"{layout.width}x{layout.height}",
            "rows_error": worst_rows, "mid_error": worst_mid}


def survey(folder: Path) -> list:
    """Convert and bake every asset under ``folder``; one dict per asset."""
    from vbusd.converters import gltf
    from vbusd.format.errors import VbusdError

    results = []
    for path in sorted(folder.glob("*/*.gl*")):
        start = time.perf_counter()
        try:
            scene = gltf.read(path)
        except VbusdError as error:
            results.append({"asset": path.name, "read_error": str(error)})
            continue
        seconds = time.perf_counter() - start
        first = scene.animations[0]
        entry = {
            "asset": path.name, "bytes": path.stat().st_size, "read_s": round(seconds, 3),
            "skins": len(scene.animations), "joints": first.bone_count,
            "vertices": sum(len(m.points) for m in first.meshes),
            "clips": [{"name": c.name, "start": round(c.start_time, 4), "end": round(c.end_time, 4),
                       "rate": c.native_rate} for c in first.clips],
            "warnings": list(scene.warnings), "runs": {},
        }
        for encoding, texel_format in RUNS:
            merged = None
            for animation in scene.animations:
                result = measure(animation, encoding, texel_format)
                if result["status"] != "ok":
                    merged = result
                    break
                if merged is None:
                    merged = result
                else:
                    merged["rows_error"] = max(merged["rows_error"], result["rows_error"])
                    merged["mid_error"] = max(merged["mid_error"], result["mid_error"])
            entry["runs"][f"{encoding}/{texel_format}"] = merged
        results.append(entry)
    return results


def markdown(results: list) -> str:
    """The two tables of docs/converters/gltf.md."""
    lines = ["| asset | bytes | read (s) | skins | joints (first skin) | vertices | clips (s, proposed rows/s) | warnings |",
             "|---|--:|--:|--:|--:|--:|---|---|"]
    for r in results:
        if "read_error" in r:
            lines.append(f"| {r['asset']} | | | | | | | **{r['read_error']}** |")
            continue
        clips = "; ".join(f"{c['name']} {c['start']:g}–{c['end']:g} @ {c['rate']:g}" for c in r["clips"])
        warns = "<br>".join(w.replace("|", "\\|") for w in r["warnings"]) or "—"
        lines.append(f"| {r['asset']} | {r['bytes']:,} | {r['read_s']} | {r['skins']} | {r['joints']} | "
                     f"{r['vertices']} | {clips} | {warns} |")
    lines += ["", "| asset | encoding / texels | result | texture | max error at rows (of diagonal) | max error mid-row |",
              "|---|---|---|---|--:|--:|"]
    for r in results:
        for run, m in r.get("runs", {}).items():
            if m["status"] == "ok":
                lines.append(f"| {r['asset']} | {run} | ok | {m['texture']} | {m['rows_error']:.3g} | "
                             f"{m['mid_error']:.3g} |")
            else:
                lines.append(f"| {r['asset']} | {run} | {m['status'].replace('|', '/')} | | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Command line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=Path, default=DEFAULT_ASSETS)
    parser.add_argument("--format", choices=("markdown", "json"), default="markdown")
    args = parser.parse_args(argv)
    if not args.assets.is_dir():
        print(f"no assets at {args.assets}")
        return 1
    results = survey(args.assets)
    print(json.dumps(results, indent=1) if args.format == "json" else markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
