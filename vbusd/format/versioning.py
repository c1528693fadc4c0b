"""Format versions and the one registry of upgrade functions.

A format version is ``major.minor`` (spec/virtual-bones.md, "Versioning"): ``formatVersion`` and
``formatMinorVersion`` (absent means 0) in layout metadata, ``vb:formatVersion`` and
``vb:formatMinorVersion`` on an animation prim. Both sources are read into a dict with the
metadata keys and brought to :data:`CURRENT` by :func:`upgrade`, which applies the registered
functions of :data:`UPGRADES` one version step at a time; a newer version is refused
(:class:`~vbusd.format.errors.VersionError`, code ``format.version``).

Registering the upgrade of the next minor version::

    @upgrades_from(1, 0)
    def upgrade_1_0_to_1_1(document: dict) -> dict:
        return {**document, "formatMinorVersion": 1}
"""

from __future__ import annotations

import copy
from typing import Callable, Mapping, NamedTuple, Optional

from vbusd.format.errors import InputError, VersionError
from vbusd.format.layout import FORMAT_VERSION

__all__ = ["Version", "CURRENT", "UPGRADES", "FORMAT_MINOR_VERSION", "upgrades_from", "version_of",
           "upgrade"]

FORMAT_MINOR_VERSION = 3
"""The newest minor version this vbusd reads and writes (the major is ``layout.FORMAT_VERSION``).
Writers write the lowest version that holds an asset (spec 16.1, 16.2, 16.3, 20.5): 1.0 unless it uses a
1.1 key, 1.2 for the compact encoding, levels of detail or a 1.2 key (bone parents, masks), 1.3 for a 1.3
key (blend spaces, markers: spec 23) and for crowd variety (on the instancer that uses it, spec 22.4)."""


class Version(NamedTuple):
    """A format version, ordered as versions are."""

    major: int
    minor: int = 0

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}"


CURRENT = Version(FORMAT_VERSION, FORMAT_MINOR_VERSION)
"""The version readers bring every document to."""

UpgradeFunction = Callable[[dict], dict]

UPGRADES: dict = {}
"""Upgrade functions by the :class:`Version` they upgrade *from*. Each returns a new dict at the
next version (``v.m`` to ``v.(m+1)`` or ``(v+1).0``), with ``formatVersion`` and
``formatMinorVersion`` set to it. Version 1.0 is the first version; 1.0 -> 1.1 is registered below."""

KEYS_1_0 = frozenset((
    "format", "formatVersion", "formatMinorVersion", "generator", "encoding", "texelFormat", "boneCount",
    "texelsPerBone", "rowCount", "usedWidth", "width", "height", "horizontalPadding", "verticalPadding",
    "texelBytes", "bones", "clips", "unormRanges", "contentDigest",
    # what a USD reader adds to the dict of an animation prim (spec 13: USD-only attributes)
    "texture", "clipExtents", "unormRangeMin", "unormRangeMax"))
"""The keys a version 1.0 document (or animation prim dict) may hold."""

KEYS_1_1 = KEYS_1_0 | {"bindTransforms", "clipRootMotion", "rootMotionUpAxis"}
KEYS_1_2 = KEYS_1_1 | {"boneParents", "masks", "compactRanges", "compactRangeMin", "compactRangeMax"}
KNOWN_KEYS = {(1, 0): KEYS_1_0, (1, 1): KEYS_1_1,
              # Levels of detail (1.2, spec 20.5) add no key: they live on UsdLod prims.
              (1, 2): KEYS_1_2,
              # Blend spaces and markers (1.3, spec 16.3, 23). Crowd variety (1.3, spec 22) adds no key:
              # it lives on the instancers (their own vb:formatMinorVersion).
              (1, 3): KEYS_1_2 | {"blendSpaces", "markers"}}
"""The keys each version defines, so that a reader refusing a newer document names what it does not
know (spec 16.1: "refused by name")."""

ENCODINGS_1_0 = frozenset(("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"))
KNOWN_VALUES = {
    "encoding": {(1, 0): ENCODINGS_1_0, (1, 1): ENCODINGS_1_0,
                 (1, 2): ENCODINGS_1_0 | {"compactQuatTranslation"},
                 (1, 3): ENCODINGS_1_0 | {"compactQuatTranslation"}},
    "texelFormat": {(1, 0): frozenset(("float16", "float32", "unorm16")),
                    (1, 1): frozenset(("float16", "float32", "unorm16")),
                    (1, 2): frozenset(("float16", "float32", "unorm16", "uint32")),
                    (1, 3): frozenset(("float16", "float32", "unorm16", "uint32"))},
}
"""The encodings and texel formats each version defines: a reader refusing a newer document names
the encoding it cannot decode first (spec 16.2), then any keys it does not know."""


def upgrades_from(major: int, minor: int = 0) -> Callable[[UpgradeFunction], UpgradeFunction]:
    """Register the decorated function as the upgrade from version ``major.minor``."""

    def register(function: UpgradeFunction) -> UpgradeFunction:
        key = Version(major, minor)
        if key in UPGRADES:
            raise ValueError(f"two upgrade functions from version {key}")
        UPGRADES[key] = function
        return function

    return register


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def version_of(d: Mapping, *, file=None, location_prefix: str = "") -> Version:
    """The version a dict says it has.

    Raises:
        InputError: ``formatVersion`` missing, not an integer or below 1; ``formatMinorVersion``
            not an integer or below 0 (code ``format.version``).
    """
    where = location_prefix + "/formatVersion"
    if "formatVersion" not in d:
        raise InputError("formatVersion is missing", file=file, location=where, code="format.version")
    major = d["formatVersion"]
    if not _is_int(major):
        raise InputError(f"formatVersion must be an integer, got {major!r:.60}", file=file,
                         location=where, code="format.version")
    if major < 1:
        raise InputError(f"formatVersion must be 1 or more, got {major}", file=file, location=where,
                         code="format.version")
    minor = d.get("formatMinorVersion", 0)
    if not _is_int(minor) or minor < 0:
        raise InputError(f"formatMinorVersion must be an integer 0 or more, got {minor!r:.60}", file=file,
                         location=location_prefix + "/formatMinorVersion", code="format.version")
    return Version(major, minor)


def _first_defining(table: Mapping, is_defined) -> Optional[tuple]:
    """The first version of ``table`` (version -> what it defines) for which ``is_defined`` holds."""
    return next((v for v in sorted(table) if is_defined(table[v])), None)


def _check_defined(d: Mapping, version: Version, *, file=None, location_prefix: str = "") -> None:
    """Refuse an older document that uses what its version does not define (spec 16: "Versioning").

    A document declaring version 1.1 but using the compact encoding (1.2) is no 1.1 document: an
    upgrade function fills in what the newer version adds, and cannot vouch for a key or value the
    document's own version never had. Versions the tables do not describe are not checked.

    Raises:
        InputError: Naming the first such encoding, texel format or key and the version that
            defines it (code ``format.version``).
    """
    known = KNOWN_KEYS.get(tuple(version))
    if known is None:
        return
    later = [(key, f"{key} {d[key]}", _first_defining(table, lambda values, value=d[key]: value in values))
             for key, table in KNOWN_VALUES.items()
             if tuple(version) in table and isinstance(d.get(key), str) and d[key] not in table[tuple(version)]]
    later += [(key, str(key), _first_defining(KNOWN_KEYS, lambda keys, key=key: key in keys))
              for key in sorted(str(k) for k in d) if key not in known]
    later = [(key, what, newer) for key, what, newer in later if newer is not None]  # unknown: the schema says
    if later:
        key, what, newer = later[0]
        declared = "formatMinorVersion" if "formatMinorVersion" in d else "formatVersion"
        raise InputError(f"{what} needs format version {Version(*newer)}, but the document declares {version}, "
                         "which does not define it", file=file,
                         location=f"{location_prefix}/{declared}", code="format.version")


def upgrade(d: Mapping, *, upgrades: Optional[Mapping] = None, current=None, file=None,
            location_prefix: str = "") -> dict:
    """Bring a dict of an older format version up to the current one.

    The dict is a layout metadata document, or the attributes of an animation prim read into the
    metadata keys (:mod:`vbusd.format.names`): both go through the same functions. A dict already
    at the current version is returned as a copy. A missing or non-integer version is an error,
    never taken as some default version.

    Args:
        d: The dict as read (not modified).
        upgrades: Table of upgrade functions (default :data:`UPGRADES`; tests pass their own). Keys
            are :class:`Version` or, for major-only steps, integers.
        current: The version to reach (default :data:`CURRENT`); an integer means ``major.0``.
        file: File the dict came from, for messages.
        location_prefix: Prefix of the JSON pointers in messages (where the dict sits in the file).

    Returns:
        A new dict at version ``current``.

    Raises:
        InputError: Not an object, a bad version, an older version that uses a key, encoding or
            texel format only a newer version defines, or no upgrade function for some step (code
            ``format.version``).
        VersionError: A version newer than ``current``.
    """
    table = UPGRADES if upgrades is None else {(Version(k) if _is_int(k) else Version(*k)): f
                                               for k, f in upgrades.items()}
    target = CURRENT if current is None else (Version(current) if _is_int(current) else Version(*current))
    if not isinstance(d, Mapping):
        raise InputError(f"layout metadata must be a JSON object, got {type(d).__name__}", file=file,
                         location=location_prefix or "/", code="format.version")
    version = version_of(d, file=file, location_prefix=location_prefix)
    where = location_prefix + "/formatVersion"
    if version.major > target.major:
        raise VersionError(f"formatVersion {version.major} is newer than this reader (version {target}); "
                           "upgrade vbusd to read it", file=file, location=where, code="format.version")
    if version > target:
        known = KNOWN_KEYS.get(tuple(target))
        unknown = [f"{key} {d[key]}" for key, table in KNOWN_VALUES.items()
                   if tuple(target) in table and isinstance(d.get(key), str) and d[key] not in table[tuple(target)]]
        unknown += sorted(str(k) for k in d if known is not None and k not in known)
        uses = (f"; it uses {', '.join(unknown)}, which version {target} does not define" if unknown else "")
        raise VersionError(f"format version {version} is newer than this reader (version {target}){uses}; "
                           "upgrade vbusd to read it", file=file,
                           location=location_prefix + "/formatMinorVersion", code="format.version")
    if version < target:
        _check_defined(d, version, file=file, location_prefix=location_prefix)
    result = copy.deepcopy(dict(d))
    while version < target:
        step = table.get(version)
        if step is None:
            raise InputError(f"no upgrade from formatVersion {version} to a newer version", file=file,
                             location=where, code="format.version")
        result = step(result)
        following = version_of(result, file=file, location_prefix=location_prefix)
        if following <= version:
            raise AssertionError(f"the upgrade from version {version} did not raise the version")
        version = following
    return result


@upgrades_from(1, 0)
def upgrade_1_0_to_1_1(document: dict) -> dict:
    """1.0 -> 1.1 (spec 16.1): every 1.1 key is optional and absent means 1.0 behaviour; nothing to fill in."""
    return {**document, "formatMinorVersion": 1}


@upgrades_from(1, 1)
def upgrade_1_1_to_1_2(document: dict) -> dict:
    """1.1 -> 1.2 (spec 16.2, 20.5): the compact encoding (which no 1.1 document uses), bone parents and
    masks (layers) and levels of detail (UsdLod prims) are all optional; nothing to fill in."""
    return {**document, "formatMinorVersion": 2}


@upgrades_from(1, 2)
def upgrade_1_2_to_1_3(document: dict) -> dict:
    """1.2 -> 1.3 (spec 16.3, 22, 23): blend spaces and clip markers are optional and absent means none
    (additive layers and blend parameters are a decoder's and an instance's); crowd variety lives on
    instancers (their own version): no metadata key or animation attribute to fill in."""
    return {**document, "formatMinorVersion": 3}
