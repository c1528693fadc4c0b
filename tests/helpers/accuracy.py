"""Accuracy of every encoding x texel format on the stadium-crowd sample.

For each of the 4 encodings and 3 texel formats the script bakes the sample's 10 s cheer exactly as
the sample does (power-of-two width and height: 512 rows, looping), decodes it with vbusd's numpy
reference decoder, and measures the largest vertex position error against *exact* linear blend
skinning in float64 of the generator's own matrices, ``p' = sum_i w_i M_i(t) p``: the generator's
``skin`` (which owes nothing to vbusd, and which tests/test_samples.py checks against UsdSkel's own
skinning).

Three columns of errors:

* **row times** (t = row / 51.2 s, all 512 rows): quantization and encoding error only;
* **mid-row times** (t = (row + 0.5) / 51.2 s): the decoder blends two rows, the reference uses the
  generator's exact pose at that time, so the error also holds the interpolation error of the
  format (linear blending of stored channel values between rows);
* **mid-row, texel format only**: the same mid-row times against the spec's row blend applied to
  the exact float64 matrices of the two rows (encoded, blended and decoded in float64, no texel
  format): what storing the rows in float16, float32 or unorm16 costs between rows, with the
  interpolation method itself taken out.

Errors are given in scene units (metres) and as a fraction of the rest mesh's bounding-box
diagonal. ``dualQuat`` is decoded with dual-quaternion skinning (DQS), so its error against LBS
also holds the difference between the two skinning methods.

Run: ``python benchmarks/accuracy.py`` (rich table) or ``python benchmarks/accuracy.py --format
markdown`` (the table in benchmarks/README.md) or ``--format json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

REPO = Path(__file__).resolve().parents[2]
GENERATOR = REPO / "samples" / "stadium_crowd.py"

ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
TEXEL_FORMATS = ("float16", "float32", "unorm16")


def load_generator():
    """Import samples/stadium_crowd.py by path (samples/ is not an installed package)."""
    name = "vbusd_samples_stadium_crowd"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, GENERATOR)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


# The quaternion helpers below are written out here rather than taken from vbusd.format.encoding on
# purpose: exact_dqs is the oracle dualQuat is measured against, so it must not share vbusd's code.


def _matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations to (..., 4) unit quaternions (x, y, z, w), Shepperd's method."""
    r = rotation
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    candidates = np.stack([trace, r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]], axis=-1)
    pick = np.argmax(candidates, axis=-1)
    q = np.empty(r.shape[:-2] + (4,))
    for case in range(4):
        m = pick == case
        if not m.any():
            continue
        a = r[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + a[:, 0, 0] + a[:, 1, 1] + a[:, 2, 2])
            q[m] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                             (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], axis=-1)
        else:
            i = case - 1
            j, k = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(1.0 + a[:, i, i] - a[:, j, j] - a[:, k, k])
            out = np.empty((a.shape[0], 4))
            out[:, i] = 0.25 * s
            out[:, j] = (a[:, j, i] + a[:, i, j]) / s
            out[:, k] = (a[:, k, i] + a[:, i, k]) / s
            out[:, 3] = (a[:, k, j] - a[:, j, k]) / s
            q[m] = out
    return q


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], -1)


def exact_dqs(points: np.ndarray, indices: np.ndarray, weights: np.ndarray,
              matrices: np.ndarray) -> np.ndarray:
    """Dual-quaternion skinning in float64 from rigid skinning matrices, written out here.

    Each bone's dual quaternion is (q_r, q_d = 0.5 (t, 0) q_r); the blend flips every influence
    into the hemisphere of the vertex's first influence, normalizes by the real part's length and
    applies ``p' = R(q_r) p + 2 (q_d conj(q_r)).xyz`` (Kavan et al. 2008; the spec's "Skinning").
    """
    q_r = _matrix_to_quaternion(matrices[..., :3, :3])  # (n, B, 4)
    t = np.concatenate([matrices[..., :3, 3], np.zeros(matrices.shape[:-2] + (1,))], axis=-1)
    q_d = 0.5 * _hamilton(t, q_r)
    real, dual = q_r[:, indices], q_d[:, indices]  # (n, V, K, 4)
    sign = np.where(np.einsum("nvkc,nvc->nvk", real, real[:, :, 0]) < 0, -1.0, 1.0)
    blend = weights[None, :, :, None] * sign[..., None]
    real, dual = (blend * real).sum(axis=2), (blend * dual).sum(axis=2)
    norm = np.linalg.norm(real, axis=-1, keepdims=True)
    real, dual = real / norm, dual / norm
    x, y, z, w = np.moveaxis(real, -1, 0)
    rotation = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
    conjugate = real * np.array([-1.0, -1.0, -1.0, 1.0])
    translation = 2.0 * _hamilton(dual, conjugate)[..., :3]
    return np.einsum("nvij,vj->nvi", rotation, points) + translation


@dataclass(frozen=True)
class Result:
    """One encoding x texel format measurement."""

    encoding: str
    texel_format: str
    used_width: int
    width: int
    height: int
    texel_bytes: int
    row_error: float
    row_fraction: float
    mid_error: float
    mid_fraction: float
    method_row_fraction: float
    mid_format_fraction: float
    seconds: float


def measure(encoding: str, texel_format: str, gen=None, rig=None) -> Result:
    """Bake the sample with one encoding and texel format and measure its largest errors.

    Args:
        encoding: Encoding token.
        texel_format: Texel format token.
        gen: The loaded generator module (loaded when None).
        rig: The generator's rig (built when None).

    Returns:
        The :class:`Result`.
    """
    from vbusd.decoders import reference

    gen = gen or load_generator()
    rig = rig or gen.build_rig()
    start = time.perf_counter()
    vb = gen.bake_reference(rig, encoding=encoding, texel_format=texel_format)
    (mesh,) = vb.meshes
    (clip,) = vb.clips
    rows = np.arange(clip.row_count, dtype=np.float64)
    diagonal = float(np.linalg.norm(rig.points.max(axis=0) - rig.points.min(axis=0)))
    errors = []
    for offset in (0.0, 0.5):
        tau = (rows + offset) / clip.rows_per_second  # clip-local seconds; the clip starts at 0 s
        decoded, _ = reference.skin_mesh(vb, mesh, 0, tau)
        matrices = gen.skinning_matrices(clip.start_time + tau)
        exact = gen.skin(rig, matrices)
        errors.append(float(np.linalg.norm(decoded - exact, axis=-1).max()))
        if offset == 0.0:
            if encoding == "dualQuat":
                # Against its own method: exact DQS, with the bound mesh's influence order (the
                # hemisphere of each vertex's first influence decides the blend's signs).
                exact = exact_dqs(rig.points, np.asarray(mesh.bone_indices),
                                  np.asarray(mesh.bone_weights, dtype=np.float64), matrices)
            method_error = float(np.linalg.norm(decoded - exact, axis=-1).max())
        else:
            format_error = _mid_row_format_error(encoding, clip, mesh, decoded, gen)
    seconds = time.perf_counter() - start
    layout = vb.layout
    return Result(encoding, texel_format, layout.used_width, layout.width, layout.height,
                  layout.texel_bytes, errors[0], errors[0] / diagonal, errors[1], errors[1] / diagonal,
                  method_error / diagonal, format_error / diagonal, seconds)


def _mid_row_format_error(encoding: str, clip, mesh, decoded: np.ndarray, gen) -> float:
    """Largest distance between ``decoded`` (mid-row times, from the stored texels) and the same
    row blend computed from the exact float64 matrices of the rows (no texel format involved)."""
    from vbusd.decoders import reference
    from vbusd.format.encoding import decode_bones, encode_bones, make_hemispheres_continuous

    assert clip.loop, "the cheer loops: the last row blends into row 0"
    times = clip.start_time + np.arange(clip.row_count) / clip.rows_per_second
    values = make_hemispheres_continuous(encode_bones(gen.skinning_matrices(times), encoding), encoding)
    blended = 0.5 * values + 0.5 * np.roll(values, -1, axis=0)  # row i with row i + 1 (wrapping)
    expected, _ = reference.skin(decode_bones(blended, encoding), encoding, mesh.points,
                                 mesh.bone_indices, mesh.bone_weights)
    return float(np.linalg.norm(decoded - expected, axis=-1).max())


def measure_all(encodings: Sequence[str] = ENCODINGS, texel_formats: Sequence[str] = TEXEL_FORMATS) -> list:
    """Measure every combination, encodings outermost."""
    gen = load_generator()
    rig = gen.build_rig()
    return [measure(e, f, gen, rig) for e in encodings for f in texel_formats]


HEADERS = ("encoding", "texel format", "texture", "texel bytes", "max error at rows (m)",
           "fraction of diagonal", "max error mid-row (m)", "fraction of diagonal",
           "mid-row, texel format only (fraction)")


def _cells(r: Result) -> tuple:
    return (r.encoding, r.texel_format, f"{r.width}x{r.height} ({r.used_width} used)", f"{r.texel_bytes:,}",
            f"{r.row_error:.3g}", f"{r.row_fraction:.3g}", f"{r.mid_error:.3g}", f"{r.mid_fraction:.3g}",
            f"{r.mid_format_fraction:.3g}")


def dqs_note(results: list) -> str:
    """One line: dualQuat's row-time error against exact float64 DQS, per texel format."""
    parts = [f"{r.texel_format} {r.method_row_fraction:.3g}" for r in results if r.encoding == "dualQuat"]
    return ("dualQuat against exact float64 dual-quaternion skinning at row times (fraction of the "
            "diagonal): " + ", ".join(parts)) if parts else ""


def markdown(results: list) -> str:
    """The results as a GitHub markdown table, followed by the dualQuat-vs-DQS line."""
    lines = ["| " + " | ".join(HEADERS) + " |",
             "|" + "|".join(["---"] * 2 + ["--:"] * (len(HEADERS) - 2)) + "|"]
    lines += ["| " + " | ".join(_cells(r)) + " |" for r in results]
    note = dqs_note(results)
    return "\n".join(lines + ([f"\n{note}."] if note else []))


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command line: print the accuracy table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--format", choices=("table", "markdown", "json"), default="table")
    parser.add_argument("--encoding", action="append", choices=ENCODINGS,
                        help="measure only this encoding (repeatable)")
    parser.add_argument("--texel-format", action="append", choices=TEXEL_FORMATS,
                        help="measure only this texel format (repeatable)")
    args = parser.parse_args(argv)
    results = measure_all(args.encoding or ENCODINGS, args.texel_format or TEXEL_FORMATS)
    if args.format == "markdown":
        print(markdown(results))
    elif args.format == "json":
        print(json.dumps([asdict(r) for r in results], indent=2))
    else:
        from rich.console import Console
        from rich.table import Table

        table = Table(title="Stadium crowd (18 bones, 202 vertices, 10 s loop, 512 rows): decode vs "
                            "exact float64 LBS")
        for i, header in enumerate(HEADERS):
            table.add_column(header, justify="left" if i < 2 else "right")
        for r in results:
            table.add_row(*_cells(r))
        # Rich assumes 80 columns when stdout is not a terminal, which wraps every cell.
        console = Console(width=None if sys.stdout.isatty() else 200)
        console.print(table)
        note = dqs_note(results)
        if note:
            console.print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
