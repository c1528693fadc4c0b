"""``vbusd crowd CHARACTER... -o CROWD.usda``: place instances of converted characters on a point instancer.

See :mod:`vbusd.jobs.crowd` for the layout of the file it writes.
"""

from __future__ import annotations

import json

import click

from vbusd.cli.common import force_option, format_option, human_bytes, quiet_option
from vbusd.format.errors import OptionsError
from vbusd.jobs.crowd import CrowdLayer, CrowdOptions, build_crowd, parse_assignments, parse_weights

__all__ = ["command"]


def _pair(values, option: str):
    if values is None:
        return None
    low, high = values
    return float(low), float(high)


def _weights(text, option: str):
    if text is None:
        return None
    try:
        return tuple(float(w) for w in text.split(","))
    except ValueError:
        raise OptionsError(f"{option} must be numbers separated by commas, got {text!r}", file="crowd") from None


def _layers(specs, weights, offsets, rates) -> tuple:
    """``--layer MASK CLIPS`` (repeatable) with its ranges: each of ``--layer-weight``,
    ``--layer-time-offset`` and ``--layer-rate`` is given once for every layer, or once per
    ``--layer`` (in order), or not at all (the defaults)."""
    count = len(specs)
    per_layer = {}
    for option, values in (("--layer-weight", weights), ("--layer-time-offset", offsets), ("--layer-rate", rates)):
        if values and not count:
            raise OptionsError(f"{option} needs --layer MASK CLIPS", file="crowd")
        if len(values) not in (0, 1, count):
            raise OptionsError(f"{option} is given {len(values)} times for {count} layers: give it once (every "
                               "layer) or once per --layer, in order", file="crowd")
        per_layer[option] = [None] * count if not values else list(values) * (count if len(values) == 1 else 1)
    layers = []
    for j, (mask, clips) in enumerate(specs):
        fields = {"mask": mask, "clips": {} if clips.strip() == "*" else parse_weights(clips, option=f"--layer {mask}")}
        for option, attribute in (("--layer-weight", "weight"), ("--layer-time-offset", "time_offset"),
                                  ("--layer-rate", "playback_rate")):
            if per_layer[option][j] is not None:
                fields[attribute] = tuple(float(v) for v in per_layer[option][j])
        layers.append(CrowdLayer(**fields))
    return tuple(layers)


class _CrowdCommand(click.Command):
    """``--layout points FILE`` (the form the issue and the docs give) as ``--layout points --points FILE``."""

    def parse_args(self, ctx, args):
        args = list(args)
        given = any(a == "--points" or a.startswith("--points=") for a in args)
        for i, arg in enumerate(args[:-1]):
            spelled = (arg == "--layout" and args[i + 1] == "points" and i + 2 < len(args)) or arg == "--layout=points"
            following = i + 2 if arg == "--layout" else i + 1
            if spelled and following < len(args) and not args[following].startswith("-") and not given:
                # With --points given too, the word after `points` is a character, as before.
                args.insert(following, "--points")
                break
        return super().parse_args(ctx, args)


@click.command("crowd", cls=_CrowdCommand)
@click.argument("characters", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str), help="Crowd layer to write (.usda, .usdc).")
@click.option("--layout", default="grid", show_default=True, metavar="[grid|disc|points]",
              help="Placement: a grid, a disc of even density, or the points of FILE (also --points FILE).")
@click.option("--points", "points_file", metavar="FILE", help="CSV (x,y,z rows) or USD points prim for --layout points.")
@click.option("--count", default=100, show_default=True, type=int, help="Instances (grid and disc).")
@click.option("--spacing", default=None, type=float,
              help="Distance between neighbours, scene units (default: from the characters' size, twice their "
                   "largest reach from the up axis times the largest --scale, so turned instances never overlap).")
@click.option("--clips", default=None, metavar="NAME[:W],...", help="Clips to play, with relative weights (default: all, equal).")
@click.option("--character-weights", default=None, metavar="W,...", help="Relative share of each character.")
@click.option("--time-offset", nargs=2, type=float, default=None, metavar="MIN MAX",
              help="Range of time offsets in seconds (default: anywhere in the instance's clip).")
@click.option("--rate", nargs=2, type=float, default=(1.0, 1.0), show_default=True, metavar="MIN MAX",
              help="Range of playback rates.")
@click.option("--yaw", nargs=2, type=float, default=(0.0, 360.0), show_default=True, metavar="MIN MAX",
              help="Range of turns about the up axis, degrees.")
@click.option("--scale", nargs=2, type=float, default=(1.0, 1.0), show_default=True, metavar="MIN MAX",
              help="Range of uniform scales.")
@click.option("--fade-clips", default=None, metavar="NAME[:W],...",
              help="Crossfade (format 1.1): each instance also plays one of these clips (relative weights), blended "
                   "in by its fade weight. The characters must be format 1.1 or later (vbusd convert writes 1.1).")
@click.option("--fade-weight", nargs=2, type=float, default=None, metavar="MIN MAX",
              help="Range of fade weights in 0..1 (0: the instance's clip alone, 1: the fade clip alone; default 0 1).")
@click.option("--fade-window", nargs=2, type=float, default=None, metavar="START END",
              help="Instead of --fade-weight: every instance fades from its clip to its fade clip between these stage "
                   "seconds (the fade weight time-sampled, 0 at START, 1 at END).")
@click.option("--fade-time-offset", nargs=2, type=float, default=None, metavar="MIN MAX",
              help="Range of the fade clip's time offsets in seconds (default: anywhere in the fade clip).")
@click.option("--fade-rate", nargs=2, type=float, default=None, metavar="MIN MAX",
              help="Range of the fade clip's playback rates (default 1 1).")
@click.option("--layer", "layer_specs", nargs=2, multiple=True, metavar="MASK CLIPS",
              help="A layer (format 1.2): one of CLIPS (NAME[:W],..., or '*' for any) plays over the bones of the "
                   "characters' mask MASK (vbusd convert --mask). Repeatable; layers apply in order.")
@click.option("--layer-weight", "layer_weights", nargs=2, type=float, multiple=True, metavar="MIN MAX",
              help="Range of layer weights in 0..1 (default 1 1): once for every layer, or once per --layer.")
@click.option("--layer-time-offset", "layer_offsets", nargs=2, type=float, multiple=True, metavar="MIN MAX",
              help="Range of a layer clip's time offsets in seconds (default: anywhere in its clip): once, or once per --layer.")
@click.option("--layer-rate", "layer_rates", nargs=2, type=float, multiple=True, metavar="MIN MAX",
              help="Range of a layer clip's playback rates (default 1 1): once, or once per --layer.")
@click.option("--tints", default=None, metavar="COLOR,...",
              help="Crowd variety (format 1.3): a palette of #rrggbb colours; each instance picks one as its tint, "
                   "which multiplies its base colour.")
@click.option("--variants", default=None, metavar="NAME=WEIGHT,...",
              help="Material variants (format 1.3) with relative weights; each instance gets one, each variant a "
                   "material.")
@click.option("--parts", default=None, metavar="PART=PROBABILITY,...",
              help="Optional parts (format 1.3): meshes of the characters, by name, each shown on an instance with "
                   "that probability.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed: the same seed gives the same file, byte for byte.")
@format_option
@force_option
@click.option("--allow-outside-paths", is_flag=True, help="Let the crowd reference characters outside its folder.")
@quiet_option
def command(characters, output, layout, points_file, count, spacing, clips, character_weights, time_offset, rate,
            yaw, scale, fade_clips, fade_weight, fade_window, fade_time_offset, fade_rate, layer_specs, layer_weights,
            layer_offsets, layer_rates, tints, variants, parts, seed, output_format, force, allow_outside_paths,
            quiet):
    """Build a USD crowd (PointInstancer + VirtualBonesInstancingAPI) from converted characters."""

    options = CrowdOptions(layout=layout, count=count, spacing=spacing, points=points_file,
                           clips=parse_weights(clips) if clips else {},
                           characters=_weights(character_weights, "--character-weights"),
                           time_offset=_pair(time_offset, "--time-offset"), playback_rate=_pair(rate, "--rate"),
                           yaw=_pair(yaw, "--yaw"), scale=_pair(scale, "--scale"),
                           fade_clips=parse_weights(fade_clips, option="--fade-clips") if fade_clips else {},
                           fade_weight=_pair(fade_weight, "--fade-weight"), fade_window=_pair(fade_window, "--fade-window"),
                           fade_time_offset=_pair(fade_time_offset, "--fade-time-offset"),
                           fade_playback_rate=_pair(fade_rate, "--fade-rate") or (1.0, 1.0),
                           layers=_layers(layer_specs, layer_weights, layer_offsets, layer_rates),
                           tints=tuple(c.strip() for c in tints.split(",") if c.strip()) if tints else (),
                           variants=parse_assignments(variants, option="--variants") if variants else {},
                           parts=parse_assignments(parts, option="--parts") if parts else {},
                           seed=seed, force=force, allow_outside_paths=allow_outside_paths)
    report = build_crowd(characters, output, options)
    if quiet:
        return 0
    if output_format == "json":
        click.echo(json.dumps(report.to_dict(), indent=2))
        return 0
    total = sum(report.instances)
    origin = "" if spacing is not None else " (from the characters' size)"
    spaced = "" if report.spacing is None else f", spacing {report.spacing:.4g}{origin}"
    click.echo(f"{report.output}: {total} instances of {len(report.instances)} character(s){spaced}, "
               f"{human_bytes(report.bytes)} ({report.seconds:.2f} s)")
    fades = report.fade_clips or [None] * len(report.instances)
    for path, n, clip_counts, animations, fade_counts in zip(characters, report.instances, report.clips,
                                                             report.animations, fades):
        shown = ", ".join(f"{name} {k}" for name, k in clip_counts.items())
        together = f", {animations} animations each" if animations > 1 else ""
        fading = "" if fade_counts is None else "; fading into " + ", ".join(
            f"{name} {k}" for name, k in fade_counts.items() if k)
        click.echo(f"  {path}: {n} instances ({shown}){together}{fading}")
    if report.layers:
        click.echo(f"  {report.layers} layer(s) per instance: {', '.join(layer.mask for layer in options.layers)}")
    for path, variety in zip(characters, report.variety):  # format 1.3 crowd variety
        said = []
        if variety["tints"]:
            said.append("tints " + ", ".join(f"{colour} {k}" for colour, k in zip(tints.split(","), variety["tints"])))
        if variety["variants"]:
            said.append("variants " + ", ".join(f"{name} {k}" for name, k in variety["variants"].items()))
        if variety["parts"]:
            said.append("showing " + ", ".join(f"{name} {k}" for name, k in variety["parts"].items()))
        click.echo(f"  {path}: {'; '.join(said)}")
    return 0
