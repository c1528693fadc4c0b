"""The JSON form of vbusd's reports: one key style for every ``--format json``.

Keys are camelCase, as in the spec's layout metadata (``texelFormat``, ``rowsPerSecond``), whatever
the Python attribute is called (``texel_format``). Times are rounded to :data:`TIME_DECIMALS`
decimals, the precision of a time code, so a time stored as float32 prints as ``27.8``, not
``27.799999237060547``. Other numbers (errors, fractions) keep their full precision. Non-finite
numbers become ``null`` so that the output is strict JSON.

Reports (:class:`vbusd.jobs.conversion.ConvertReport`, :class:`vbusd.jobs.pointcache.DecodeReport`)
build their ``to_dict()`` with :func:`json_ready`; ``vbusd info`` passes its dict through it too.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re

__all__ = ["TIME_DECIMALS", "TIME_KEYS", "camel_case", "round_time", "json_ready", "json_text", "is_unicode_text"]

TIME_DECIMALS = 6
"""Decimals kept of a time (seconds or time codes): a microsecond, far below any frame."""

TIME_KEYS = frozenset({"startTime", "duration", "startTimeCode", "endTimeCode", "seconds", "time", "times"})
"""Keys whose numbers (and whose nested numbers) are times, rounded to :data:`TIME_DECIMALS`."""

_SNAKE = re.compile(r"_([a-z0-9])")


def is_unicode_text(text: str) -> bool:
    """Whether ``text`` is Unicode that UTF-8 (a sidecar, a USD layer) can hold: no lone surrogate,
    which is what a byte that is not UTF-8 becomes in a command-line argument or a file name."""
    try:
        str(text).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def camel_case(name: str) -> str:
    """``texel_format`` -> ``texelFormat``; a name without underscores stays as it is."""
    return _SNAKE.sub(lambda match: match.group(1).upper(), name)


def round_time(value: float) -> float:
    """A time rounded to :data:`TIME_DECIMALS` decimals (``-0.0`` printed as ``0.0``)."""
    return round(float(value), TIME_DECIMALS) + 0.0


def json_ready(value, *, time: bool = False):
    """``value`` as plain JSON data: dataclasses become dicts with camelCase keys, numpy values
    become Python numbers and lists, times are rounded.

    Args:
        value: A dataclass, dict, list, tuple, number, string, None or numpy value.
        time: Whether ``value`` is a time (set for the values under :data:`TIME_KEYS`).

    Dict keys are kept as they are (a dict may map file paths to sizes); code that builds a dict for
    a report writes its keys in camelCase.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {camel_case(f.name): _item(camel_case(f.name), getattr(value, f.name), time)
                for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(key): _item(str(key), item, time) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(item, time=time) for item in value]
    if hasattr(value, "tolist") and hasattr(value, "dtype"):  # numpy scalar or array, without importing numpy
        return json_ready(value.tolist(), time=time)
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            return None
        return round_time(value) if time else value
    return str(value)


def _item(key: str, value, time: bool):
    return json_ready(value, time=time or key in TIME_KEYS)


def json_text(value) -> str:
    """``value`` in its JSON form (see :func:`json_ready`), indented, as ``--format json`` prints it."""
    return json.dumps(json_ready(value), indent=2, allow_nan=False)
