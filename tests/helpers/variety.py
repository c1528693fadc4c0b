"""Crowd variety (format 1.3) test material: the modular stadium spectator (body + optional ``Hat``, from
samples/stadium_crowd.py) and a varied crowd of it, made once per folder."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import scripts

TINTS = ("#ffffff", "#ff8000", "#2060ff")
# The three palette entries in linear RGB, by hand from the sRGB transfer function (IEC 61966-2-1):
# 0x80 = 128/255 = 0.50196 -> ((0.50196 + 0.055) / 1.055) ** 2.4 = 0.2158605; 0x20 = 32/255 -> 0.0144438;
# 0x60 = 96/255 -> 0.1169707.
TINTS_LINEAR = ((1.0, 1.0, 1.0), (1.0, 0.2158605, 0.0), (0.0144438, 0.1169707, 1.0))
VARIANTS = {"home": 3.0, "away": 1.0}
PARTS = {"Hat": 0.4}


def modular_character(folder: Path) -> Path:
    """The spectator with a hat part, converted (texture beside it) into ``folder``."""
    path = folder / "spectator.usda"
    if not path.exists():
        scripts.load("samples/stadium_crowd.py").write_modular(path)
    return path


def varied_crowd(folder: Path, count: int = 60, seed: int = 7, name: str = "crowd.usda", **overrides) -> Path:
    """A crowd of the modular spectator with the palette, two variants and the hat (Python API)."""
    import vbusd
    from vbusd.jobs.crowd import CrowdOptions

    options = dict(layout="grid", count=count, tints=TINTS, variants=VARIANTS, parts=PARTS, seed=seed, force=True)
    options.update(overrides)
    output = folder / name
    vbusd.build_crowd([modular_character(folder)], output, CrowdOptions(**options))
    return output
