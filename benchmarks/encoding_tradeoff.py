"""The measured trade-off of every encoding x texel format (issue 26): bytes, fetches and error.

For every encoding and texel format pair the format allows (the 12 of format 1.0 and format 1.2's
compactQuatTranslation/uint32) and every subject (the stadium-crowd sample's 2.5 m spectator, with
its exact float64 matrices and the 512 rows it bakes; every animation of the shared glTF characters
in ``$VBUSD_SHARED_ASSETS/gltf`` or ``../shared/assets/gltf`` at the rows the default bake plans),
the script bakes with vbusd, decodes with the numpy reference decoder at every row and reports the
largest vertex distance from exact float64 linear blend skinning of the source's own matrices
(``_lbs`` here, not vbusd's decoder), in scene units (metres) and as a fraction of the rest mesh's
bounding-box diagonal. dualQuat is decoded with dual-quaternion skinning, so its error against LBS
also holds the difference between the two skinning methods. A pair that cannot hold the subject
(crossMatrix, dualQuat and compact with scaled joints, say) says "refused".

Columns per pair: bytes per bone-key (texels per bone x channels stored x bytes per channel) and
texel fetches per bone, row and vertex influence (a decoder reads two rows per bone between rows).

RecursiveSkeletons (84 skins, scaled joints) is left out for time; its rigid skins are in
benchmarks/results/compact_encoding.md.

Run: ``python benchmarks/encoding_tradeoff.py`` (markdown) or ``--format json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

PAIRS = [(e, f) for e in ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
         for f in ("float16", "float32", "unorm16")] + [("compactQuatTranslation", "uint32")]
SKIP = ("RecursiveSkeletons",)


def _lbs(points, idx, w, matrices):
    m = matrices[:, idx]
    moved = np.einsum("nvkij,vj->nvki", m[..., :3, :3], points) + m[..., :3, 3]
    return np.einsum("vk,nvki->nvi", w, moved)


def subjects():
    """(label, SkinnedAnimation, base BakeOptions overrides) of every subject."""
    import compact_encoding

    from vbusd.converters import gltf

    out = [("stadium spectator", compact_encoding._stadium()[0],
            dict(horizontal_padding="powerOfTwo", vertical_padding="powerOfTwo", loop=True))]
    folder = compact_encoding.shared_assets() / "gltf"
    for path in sorted(folder.glob("*/*.gl*")) if folder.is_dir() else ():
        if path.parent.name in SKIP:
            continue
        for i, animation in enumerate(gltf.read(path).animations):
            out.append((path.stem + (f" skin {i}" if i else ""), animation, {}))
    return out


def measure(animation, encoding, texel_format, extra) -> dict:
    """Largest error at rows of one bake, or the refusal."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.decoders.reference import skin_mesh
    from vbusd.format.errors import VbusdError

    try:
        vb = bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format, **extra))
    except VbusdError as error:
        return {"refused": error.message.split(";")[0][:80]}
    worst_m = worst_d = 0.0
    for ci, clip in enumerate(vb.clips):
        source = animation.clips[ci]
        taus = np.arange(clip.row_count) / clip.rows_per_second
        matrices = source.sample(source.start_time + taus)
        for mesh, bound in zip(animation.meshes, vb.meshes):
            w = np.asarray(mesh.bone_weights, float)
            expected = _lbs(np.asarray(mesh.points, float), np.asarray(mesh.bone_indices),
                            w / w.sum(axis=1, keepdims=True), matrices)
            decoded, _ = skin_mesh(vb, bound, ci, taus)
            error = float(np.linalg.norm(decoded - expected, axis=-1).max())
            diagonal = float(np.linalg.norm(np.ptp(np.asarray(mesh.points, float), axis=0))) or 1.0
            worst_m, worst_d = max(worst_m, error), max(worst_d, error / diagonal)
    layout = vb.layout
    return {"m": worst_m, "diag": worst_d,
            "bytes": layout.texels_per_bone * layout.texel_format.stored_channels * layout.texel_format.bytes_per_channel,
            "fetches": layout.texels_per_bone}


def run() -> list:
    results = []
    for label, animation, extra in subjects():
        entry = {"subject": label, "runs": {}}
        for encoding, texel_format in PAIRS:
            entry["runs"][f"{encoding}/{texel_format}"] = measure(animation, encoding, texel_format, extra)
        results.append(entry)
    return results


def markdown(results: list) -> str:
    """Rows: encoding x texel format; columns: bytes, fetches and each subject's error."""
    subjects_ = [r["subject"] for r in results]
    head = "| encoding / texels | bytes per bone-key | fetches per bone, row, influence | " + \
        " | ".join(f"{s}: m (of diagonal)" for s in subjects_) + " |"
    lines = [head, "|---|--:|--:|" + "--:|" * len(subjects_)]
    for encoding, texel_format in PAIRS:
        key = f"{encoding}/{texel_format}"
        sizes = next((r["runs"][key] for r in results if "bytes" in r["runs"][key]), {})
        cells = []
        for r in results:
            m = r["runs"][key]
            cells.append("refused" if "refused" in m else f"{m['m']:.2g} ({m['diag']:.2g})")
        lines.append(f"| {key} | {sizes.get('bytes', '')} | {sizes.get('fetches', '')} | " + " | ".join(cells) + " |")
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
