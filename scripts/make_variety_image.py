"""Make docs/engines.md's picture of crowd variety: the stadium sample with tints, variants, hats and flags.

The sample's 1,200 seats (samples/stadium_crowd.py: positions, orientations, time offsets and rates
of its own crowd) are filled with the modular spectator (``write_modular``: the body, an optional
``Hat`` part and an optional ``Flag`` prop at the right hand's socket, sharing its skeleton and
texture), and each spectator gets, from one seeded generator as ``vbusd crowd --tints ... --variants
home=3,away=1 --parts Hat=0.4,Flag=0.15`` draws them, a tint of a five-colour palette, a material
variant, a hat on two in five and a flag on about one in seven (format 1.3, spec/virtual-bones.md 22). The crowd is written with :func:`vbusd.write_asset` into a temporary folder and drawn by
``vbusd view``'s three.js page in headless Chromium at the README picture's size and time
(scripts/make_readme_image.py), from nearer the front rows, and the canvas is saved as a PNG.

Usage (needs what scripts/install-system-deps.sh installs)::

    python scripts/make_variety_image.py              # writes docs/images/stadium_variety.png
    python scripts/make_variety_image.py -o other.png

Exit status 2 with one line when the browser is missing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUTPUT = REPO / "docs" / "images" / "stadium_variety.png"
PALETTE = ("#f2f2f2", "#ff8000", "#2060ff", "#e02030", "#30b040")
VARIANTS = {"home": 3.0, "away": 1.0}
HAT = 0.4
FLAG = 0.15
SEED = 37
CAMERA = "-7,4.2,33,1,2.0,42"  # nearer the front rows than the README's picture: the hats show


def varied_stadium(folder: Path) -> Path:
    """The stadium's seats filled with varied modular spectators; returns the asset's path."""
    sys.path.insert(0, str(REPO))
    from tests.helpers import scripts

    import vbusd
    from vbusd.format.variety import hex_to_linear

    sample = scripts.load("samples/stadium_crowd.py")
    character = sample.write_modular(folder / "spectator.usda")
    seated = vbusd.read_asset(REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda").crowds[0]
    asset = vbusd.read_asset(character)
    n = seated.instance_count
    rng = np.random.default_rng(SEED)
    palette = np.asarray([hex_to_linear(c) for c in PALETTE], dtype=np.float32)
    weights = np.asarray(list(VARIANTS.values()))
    tint = palette[rng.integers(len(palette), size=n)]
    variant = rng.choice(len(weights), size=n, p=weights / weights.sum()).astype(np.int32)
    parts = (rng.random(n) < HAT).astype(np.int32) | (rng.random(n) < FLAG).astype(np.int32) << 1
    crowd = dataclasses.replace(
        seated, path=f"/{asset.default_prim}/Crowd",
        tint=tint, variant=variant,
        variant_names=tuple(VARIANTS), parts=parts, part_names=("Hat", "Flag"))
    out = folder / "stadium_variety.usda"
    vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,)), out)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", type=Path, default=OUTPUT, help="PNG to write (default: %(default)s)")
    args = parser.parse_args(argv)
    from vbusd.io.files import atomic_write
    from vbusd.web.browser import unavailable_reason

    reason = unavailable_reason()
    if reason:
        print(f"make_variety_image: {reason}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO / "scripts"))
    import make_readme_image

    make_readme_image.CAMERA = CAMERA  # the README picture's size, time and field of view, a nearer eye
    with tempfile.TemporaryDirectory() as folder:
        data = make_readme_image.render_png(varied_stadium(Path(folder)))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.output) as handle:
        handle.write(data)
    print(f"make_variety_image: wrote {args.output} ({len(data):,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
