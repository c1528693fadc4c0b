"""Convert every shared UsdSkel asset and print the table of errors in docs/converters/usdskel.md.

For each asset: ``vbusd.jobs.conversion.convert`` with default options (encoding auto, float16, one row per
time code, every row compared with ``UsdSkel.SkinningQuery.ComputeSkinnedPoints`` in world space),
then the same with float32 texels to show what is quantization. Assets the format cannot hold are
listed with the one-line message ``vbusd convert`` prints.

    python benchmarks/usdskel_assets.py [--assets ../shared/assets/usdskel] [--check-rows N]

Writes a Markdown table on stdout. Not part of the test suite (tests/test_usdskel_assets.py checks
the same assets with a bound).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


def _assets_folder(given: str | None) -> Path:
    import os

    shared = os.environ.get("VBUSD_SHARED_ASSETS")
    candidates = [given, shared and str(Path(shared) / "usdskel"),
                  str(Path(__file__).resolve().parents[2] / "shared" / "assets" / "usdskel")]
    for candidate in candidates:
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    sys.exit("usdskel assets folder not found; pass --assets")


def _row(folder: Path, path: Path, check_rows) -> list:
    from vbusd.jobs.conversion import ConvertOptions, convert
    from vbusd.format.errors import VbusdError

    name = str(path.relative_to(folder))
    with tempfile.TemporaryDirectory() as temp:
        started = time.perf_counter()
        try:
            report = convert(path, Path(temp) / "out.usda", ConvertOptions(check_rows=check_rows))
            exact = convert(path, Path(temp) / "exact.usda",
                            ConvertOptions(check_rows=check_rows, texel_format="float32"))
        except VbusdError as error:
            message = f"`{error.code}`: {error.location}: {error.message}"
            return [f"| {name} | - | - | - | - | - | - | - | refused: {message} |"]
        seconds = time.perf_counter() - started
    rows = []
    for animation, exact_animation in zip(report.animations, exact.animations):
        meshes = animation.meshes
        points = sum(m.points for m in meshes)
        worst = max(meshes, key=lambda m: m.max_error_fraction or 0.0)
        worst_exact = max(exact_animation.meshes, key=lambda m: m.max_error_fraction or 0.0)
        normals = [m.max_normal_error_degrees for m in meshes if m.max_normal_error_degrees is not None]
        texture = f"{animation.width}x{animation.height}"
        rows.append(
            f"| {name} | {animation.path} | {animation.bones} | {len(meshes)} / {points} | "
            f"{animation.rows} @ {animation.clips[0]['rows_per_second']:.4g}/s | {animation.encoding} {texture} | "
            f"{worst.max_error:.3g} ({worst.max_error_fraction:.2e}) | "
            f"{worst_exact.max_error:.2g} ({worst_exact.max_error_fraction:.1e}) | "
            f"{f'{max(normals):.3f}' if normals else '-'}; {seconds:.1f} s |")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", default=None)
    parser.add_argument("--check-rows", default="all", help="rows per clip compared (default all)")
    args = parser.parse_args(argv)
    folder = _assets_folder(args.assets)
    check_rows = None if args.check_rows == "all" else int(args.check_rows)
    files = sorted(p for p in folder.rglob("*") if p.suffix in (".usda", ".usdc", ".usdz", ".usd")
                   and ".baked" not in p.name)
    print("| asset | animation prim | bones | meshes / points | rows | encoding, texture | "
          "max error float16 (of bbox diagonal) | float32 | normals (deg); time of both runs |")
    print("|---|---|---|---|---|---|---|---|---|")
    for path in files:
        for row in _row(folder, path, check_rows):
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
