"""Mutation run: thousands of corrupted inputs through convert, validate, info and decode.

Every mutant is a copy of a valid seed (a Virtual Bones asset in .usda or .usdc with its EXR or PNG
texture and sidecar, a UsdSkel source, a glTF or GLB source) with one file corrupted: bytes
flipped, cut short, spans inserted, deleted or duplicated, PNG chunks altered with a valid CRC,
numbers in text replaced by extremes (NaN, 1e308, 2**32 + 5...), strings replaced by hostile ones
(paths leaving the folder, control bytes, non-UTF-8), lines deleted or duplicated. Each command
runs in a long-lived worker process (``vbusd.cli.main`` in-process, stdout and stderr captured at
the file-descriptor level so USD's C++ messages are seen too), watched by the parent:

* traceback: an exception escaped ``main``, or "Traceback" reached stdout or stderr;
* hang: no answer within ``--timeout`` seconds (the worker is killed and replaced);
* memory: the worker's peak resident set passed ``--max-rss-mb`` while handling the input (the
  worker is replaced after such an input, so every input is measured from a fresh baseline);
* partial: a failed convert or decode left a file in its output folder;
* clobbered: an existing output (written before the run, ``--force`` given) or an input file
  changed although the command failed;
* raw: a line on stderr that is not vbusd's own (``vbusd...`` or the command name), e.g. a raw
  USD warning.

Usage::

    python benchmarks/mutation_run.py --mutants 5000 --jobs 2 --json benchmarks/results/mutation.json

``--surfaces compact,package,lod,mask`` runs the format 1.2 seeds instead (made at the start of the
run: compact assets in EXR and KTX2, runtime packages, levels of detail, masks and a layered crowd),
with structure-aware mutators beside the byte-level ones, the Python API and ``view``'s check
beside the commands, and the accepted-bad oracle (:func:`agreement`): the readers of one file must
accept and refuse it alike. benchmarks/README.md has both runs' figures.

The suite runs small slices of both (tests/test_mutation_smoke.py).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import resource
import select
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
VALID = ROOT / "tests" / "fixtures" / "validate" / "valid"
GLTF = ROOT / "tests" / "fixtures" / "gltf"
SAMPLE = ROOT / "samples" / "stadium_crowd"

NUMBERS = [b"-1e308", b"1e308", b"nan", b"inf", b"-inf", b"-1", b"0", b"4294967301", b"99999999",
           b"1e-320", b"65536", b"2147483648", b"0.5", b"-0"]
STRINGS = [b"../../../../etc/passwd", b"/etc/hostname", b"http://example.invalid/x", b"", b"\xff\xfe\x00",
           b"\x1b[31mred", b"a" * 5000, b"con", b"nul:", b"x.exr", b"//?/c:/x"]


# --------------------------------------------------------------------------------------------
# seeds and mutants
# --------------------------------------------------------------------------------------------


def _usdc_copy(folder: Path) -> None:
    """Add asset.usdc (a binary copy of asset.usda) to a seed folder."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(folder / "asset.usda"))
    layer.Export(str(folder / "asset.usdc"))


def make_seeds(root: Path) -> list:
    """Copy the seeds into ``root``; returns ``(name, folder, entry file, kind)`` per seed.

    ``kind`` is ``asset`` (a Virtual Bones asset: decode/info/validate succeed on the seed) or
    ``source`` (UsdSkel or glTF: convert succeeds on the seed).
    """
    seeds = []
    for name in sorted(p.name for p in VALID.iterdir() if (VALID / p.name / "asset.usda").exists()):
        folder = root / "seeds" / name
        shutil.copytree(VALID / name, folder)
        (folder / "expected.json").unlink(missing_ok=True)
        seeds.append((name, folder, "asset.usda", "asset"))
        if name.startswith("crossMatrix") or name.startswith("quatTranslation"):
            usdc = root / "seeds" / f"{name}_usdc"
            shutil.copytree(folder, usdc)
            _usdc_copy(usdc)
            (usdc / "asset.usda").unlink()
            seeds.append((f"{name}_usdc", usdc, "asset.usdc", "asset"))
    source = root / "seeds" / "stadium_source"
    source.mkdir(parents=True)
    shutil.copy(SAMPLE / "stadium_crowd.usda", source / "stadium_crowd.usda")
    seeds.append(("stadium_source", source, "stadium_crowd.usda", "source"))
    for name in ("bar.gltf", "bar.glb", "bar_sparse.gltf", "two_skins.gltf"):
        folder = root / "seeds" / name.replace(".", "_")
        folder.mkdir(parents=True)
        shutil.copy(GLTF / name, folder / name)
        seeds.append((name.replace(".", "_"), folder, name, "source"))
    return seeds


def _fix_png_crcs(data: bytearray) -> bytearray:
    """Recompute every chunk CRC so a mutation inside a chunk reaches the chunk's parser."""
    at = 8
    while at + 12 <= len(data):
        length = struct.unpack(">I", data[at:at + 4])[0]
        end = at + 12 + length
        if end > len(data):
            break
        data[end - 4:end] = struct.pack(">I", zlib.crc32(bytes(data[at + 4:end - 4])) & 0xFFFFFFFF)
        at = end
    return data


def mutate(data: bytes, suffix: str, rng: random.Random) -> tuple:
    """One corrupted version of ``data``; returns ``(bytes, operation name)``."""
    text_like = suffix in (".usda", ".json", ".gltf")
    ops = ["flip", "truncate", "insert", "delete", "duplicate"]
    if text_like:
        ops += ["number", "number", "number", "string", "line_delete", "line_duplicate"]
    if suffix == ".png":
        ops += ["png_chunk", "png_chunk"]
    if suffix in (".exr", ".usdc", ".glb", ".ktx2", ".bin"):
        ops += ["word", "word"]
    op = rng.choice(ops)
    out = bytearray(data)
    n = max(len(out), 1)
    if op == "flip":
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(n)
            if i < len(out):
                out[i] ^= 1 << rng.randrange(8)
    elif op == "truncate":
        out = out[:rng.randrange(n)]
    elif op == "insert":
        i = rng.randrange(n)
        out[i:i] = bytes(rng.randrange(256) for _ in range(rng.choice((1, 4, 16, 300))))
    elif op == "delete":
        i = rng.randrange(n)
        del out[i:i + rng.choice((1, 4, 16, 300))]
    elif op == "duplicate":
        i = rng.randrange(n)
        span = out[i:i + rng.choice((4, 16, 300, 4000))]
        out[i:i] = span
    elif op == "word":  # a 32-bit little-endian word (sizes, offsets, counts) set to an extreme
        i = rng.randrange(max(n - 4, 1)) & ~3
        out[i:i + 4] = struct.pack("<I", rng.choice((0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 65536, 1 << 24)))
    elif op == "number":
        matches = list(re.finditer(rb"-?\d+(\.\d+)?(e[-+]?\d+)?", bytes(out)))
        if matches:
            m = rng.choice(matches)
            out[m.start():m.end()] = rng.choice(NUMBERS)
    elif op == "string":
        matches = list(re.finditer(rb'"([^"\\\n]{0,200})"', bytes(out)))
        if matches:
            m = rng.choice(matches)
            out[m.start() + 1:m.end() - 1] = rng.choice(STRINGS)
    elif op in ("line_delete", "line_duplicate"):
        lines = bytes(out).split(b"\n")
        i = rng.randrange(len(lines))
        if op == "line_delete":
            del lines[i]
        else:
            lines.insert(i, lines[i])
        out = bytearray(b"\n".join(lines))
    elif op == "png_chunk":
        if len(out) > 40:
            i = rng.randrange(8, len(out))
            for _ in range(rng.randint(1, 4)):
                j = min(len(out) - 1, i + rng.randrange(16))
                out[j] = rng.randrange(256)
            out = _fix_png_crcs(out)
    return bytes(out), op


def _peak_rss_mb() -> float:
    """This worker's peak resident set, in MB: VmHWM of its own address space. (``ru_maxrss`` is
    preserved across execve, so a worker started by a large process, pytest after a long session
    say, would report its parent's peak.)"""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def make_mutants(root: Path, count: int, seed: int) -> list:
    """Write ``count`` mutant folders under ``root``; returns one job description per mutant."""
    rng = random.Random(seed)
    seeds = make_seeds(root)
    jobs = []
    for i in range(count):
        name, folder, entry, kind = seeds[i % len(seeds)]
        files = sorted(p.name for p in folder.iterdir() if p.is_file())
        target_name = entry if rng.random() < 0.4 else rng.choice(files)
        mutant = root / "mutants" / f"{i:05d}"
        shutil.copytree(folder, mutant)
        data = (mutant / target_name).read_bytes()
        new, op = mutate(data, Path(target_name).suffix, rng)
        (mutant / target_name).write_bytes(new)
        jobs.append({"id": i, "seed": name, "kind": kind, "folder": str(mutant), "entry": entry,
                     "mutated": target_name, "op": op})
    return jobs


# --------------------------------------------------------------------------------------------
# format 1.2 surfaces: compact encoding, runtime packages, levels of detail, masks and layers
# --------------------------------------------------------------------------------------------

SURFACES = ("old", "compact", "package", "lod", "mask")
EXTENSION = "VBUSD_virtual_bones"
STADIUM = SAMPLE / "stadium_crowd.usda"
BAR = GLTF / "bar.gltf"

# KTX2 header fields (spec/ktx2.md): name -> (byte offset, struct format)
KTX2_FIELDS = {"vkFormat": (12, "<I"), "typeSize": (16, "<I"), "pixelWidth": (20, "<I"),
               "pixelHeight": (24, "<I"), "pixelDepth": (28, "<I"), "layerCount": (32, "<I"),
               "faceCount": (36, "<I"), "levelCount": (40, "<I"), "supercompressionScheme": (44, "<I"),
               "dfdByteOffset": (48, "<I"), "dfdByteLength": (52, "<I"), "kvdByteOffset": (56, "<I"),
               "kvdByteLength": (60, "<I"), "sgdByteOffset": (64, "<Q"), "sgdByteLength": (72, "<Q"),
               "level0.byteOffset": (80, "<Q"), "level0.byteLength": (88, "<Q"),
               "level0.uncompressedByteLength": (96, "<Q")}
HOSTILE_JSON = [None, True, False, -1, 0, 1, 2, 3, 1.5, -0.0, 1e308, -1e308, 1e39, 2 ** 31, 2 ** 32 + 5,
                2 ** 53 + 1, 10 ** 30, float("nan"), float("inf"), "", "x", "../../etc/passwd", "\u0000", [], {},
                [[]], [0] * 3, {"a": 1}]


def _cli(argv: list) -> None:
    """Run one vbusd command in-process for a seed; a failure stops the run (the seeds must be valid)."""
    from vbusd.cli import main as vbusd_main

    status = vbusd_main(argv + ["-q"])
    if status != 0:
        raise SystemExit(f"seed command failed ({status}): vbusd {' '.join(argv)}")


def make_seeds_1_2(root: Path, surfaces) -> list:
    """Make the format 1.2 seeds under ``root/seeds`` with vbusd's own commands; returns one dict
    per seed: name, folder, entry, kind (asset, crowd or package), surface, textures (the names of
    its texture files) and, for each, the cached texels and metadata text (``root/cache``)."""
    import numpy as np

    from vbusd.io.textures import read_texture

    base = root / "seeds"
    base.mkdir(parents=True, exist_ok=True)
    short = ["--frame-range", "0", "10"]
    seeds = []

    def add(name, folder, entry, kind, surface):
        seeds.append({"name": name, "folder": folder, "entry": entry, "kind": kind, "surface": surface})

    def convert(name, source, extra, surface):
        folder = base / name
        stem = "bar" if source == BAR else "st"
        _cli(["convert", str(source), "-o", str(folder / f"{stem}.usda"), "--check-rows", "0"] + extra)
        add(name, folder, f"{stem}.usda", "asset", surface)
        return folder

    def export(name, source: Path, suffix, surface):
        folder = base / name
        shutil.copytree(source.parent, folder)
        _cli(["export", str(folder / source.name), "-o", str(folder / f"pkg{suffix}")])
        for p in list(folder.iterdir()):  # the package alone (a .gltf keeps its .bin and .ktx2)
            if not p.name.startswith("pkg"):
                p.unlink()
        add(name, folder, f"pkg{suffix}", "package", surface)

    compact = ["--encoding", "compactQuatTranslation", "--on-bad-clip", "skip"]
    if "compact" in surfaces or "package" in surfaces:
        c_exr = convert("compact_exr", BAR, compact, "compact")
        c_ktx2 = convert("compact_ktx2", BAR, compact + ["--container", "ktx2"], "compact")
        usdc = base / "compact_ktx2_usdc"
        shutil.copytree(c_ktx2, usdc)
        from pxr import Sdf
        Sdf.Layer.FindOrOpen(str(usdc / "bar.usda")).Export(str(usdc / "bar.usdc"))
        (usdc / "bar.usda").unlink()
        add("compact_ktx2_usdc", usdc, "bar.usdc", "asset", "compact")
        golden = base / "compact_golden"
        shutil.copytree(VALID / "compactQuatTranslation_uint32", golden)
        (golden / "expected.json").unlink(missing_ok=True)
        add("compact_golden", golden, "asset.usda", "asset", "compact")
    if "lod" in surfaces or "package" in surfaces:
        lod = convert("lod_exr", STADIUM, ["--lod-ratios", "0.5"] + short, "lod")
        convert("lod_compact_ktx2", BAR, compact + ["--container", "ktx2", "--lod-ratios", "0.5"], "lod")
        golden = base / "lod_golden"
        shutil.copytree(VALID / "crossMatrix_float16_lods", golden)
        (golden / "expected.json").unlink(missing_ok=True)
        add("lod_golden", golden, "asset.usda", "asset", "lod")
    if "mask" in surfaces or "package" in surfaces:
        mask = convert("mask_exr", STADIUM, ["--mask", "upper=chest", "--mask", "arm=L_shoulder"] + short, "mask")
        mask_c = convert("mask_compact_ktx2", STADIUM, ["--mask", "upper=chest"] + compact + ["--container", "ktx2"]
                         + short, "mask")
        crowd = base / "layered_crowd"
        shutil.copytree(mask, crowd)
        _cli(["crowd", str(crowd / "st.usda"), "-o", str(crowd / "crowd.usda"), "--count", "3", "--seed", "1",
              "--layer", "upper", "*", "--layer", "arm", "Skeleton", "--layer-weight", "0.25", "0.75"])
        add("layered_crowd", crowd, "crowd.usda", "crowd", "mask")
    if "package" in surfaces:
        export("package_compact_glb", c_ktx2 / "bar.usda", ".glb", "package")
        export("package_compact_gltf", c_exr / "bar.usda", ".gltf", "package")
        export("package_lod_glb", lod / "st.usda", ".glb", "package")
        export("package_mask_gltf", mask_c / "st.usda", ".gltf", "package")
        plain = base / "plain_crowd_src"
        shutil.copytree(lod, plain)
        _cli(["crowd", str(plain / "st.usda"), "-o", str(plain / "crowd.usda"), "--count", "3", "--seed", "2"])
        export("package_crowd_glb", plain / "crowd.usda", ".glb", "package")
        export("package_crowd_gltf", plain / "crowd.usda", ".gltf", "package")
        shutil.rmtree(plain)
        golden = base / "package_golden"
        shutil.copytree(VALID / "runtime_package", golden)
        (golden / "expected.json").unlink(missing_ok=True)
        add("package_golden", golden, "asset.gltf", "package", "package")
    chosen = [s for s in seeds if s["surface"] in surfaces]
    cache = root / "cache"
    cache.mkdir(exist_ok=True)
    for seed in chosen:
        folder = seed["folder"]
        seed["textures"] = sorted(p.name for p in folder.iterdir() if p.suffix in (".exr", ".ktx2", ".png"))
        seed["cache"] = {}
        for name in seed["textures"]:
            data = read_texture(folder / name)
            npy = cache / f"{seed['name']}.{name}.npy"
            np.save(npy, np.asarray(data.texels))
            text = (folder / f"{name}.json").read_text(encoding="utf-8") if (folder / f"{name}.json").exists() \
                else None
            seed["cache"][name] = {"texels": str(npy), "metadata": text,
                                   "encoding": data.info.layout.encoding.value}
        seed["folder"] = str(folder)
    return chosen


# ---- small file helpers -------------------------------------------------------------------------


def _glb_split(data: bytes) -> tuple:
    """(JSON document, BIN chunk bytes, offset of the BIN chunk's data in the file) of a GLB."""
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    at = 20 + length
    if at + 8 <= len(data):
        size = struct.unpack_from("<I", data, at)[0]
        return document, data[at + 8:at + 8 + size], at + 8
    return document, b"", at + 8


def _glb_join(document: dict, binary: bytes) -> bytes:
    from vbusd.io.gltf_package import glb_bytes

    return glb_bytes(document, binary)


def _package_document(path: Path) -> dict:
    if path.suffix == ".gltf":
        return json.loads(path.read_text(encoding="utf-8"))
    return _glb_split(path.read_bytes())[0]


def _write_package_document(path: Path, document: dict) -> None:
    if path.suffix == ".gltf":
        path.write_text(json.dumps(document), encoding="utf-8")
    else:
        _, binary, _ = _glb_split(path.read_bytes())
        path.write_bytes(_glb_join(document, binary))


def _ktx2_places(folder: Path, seed: dict) -> list:
    """Where the KTX2 files of a mutant are: ``(file name, byte offset of the KTX2 in it)``."""
    if seed["kind"] != "package":
        return [(n, 0) for n in seed["textures"] if n.endswith(".ktx2")]
    entry = folder / seed["entry"]
    document = _package_document(entry)
    places = []
    for animation in document["extensions"][EXTENSION]["animations"]:
        view = document["bufferViews"][animation["texture"]["bufferView"]]
        if entry.suffix == ".glb":
            places.append((seed["entry"], _glb_split(entry.read_bytes())[2] + view.get("byteOffset", 0)))
        else:
            places.append((document["buffers"][view["buffer"]]["uri"], view.get("byteOffset", 0)))
    return places


def _kvd_layout_span(data: bytes, base: int) -> tuple:
    """(start, end) of the vbusd.layout value text (without its NUL) in a KTX2 file at ``base``."""
    offset, length = struct.unpack_from("<II", data, base + 56)
    at, end = base + offset, base + offset + length
    while at + 4 <= end:
        size = struct.unpack_from("<I", data, at)[0]
        entry = data[at + 4:at + 4 + size]
        key, _, value = entry.partition(b"\0")
        if key == b"vbusd.layout":
            start = at + 4 + len(key) + 1
            return start, start + len(value.rstrip(b"\0"))
        at += 4 + size + (-size % 4)
    raise ValueError("no vbusd.layout")


def _dumps(value, indent=None) -> str:
    return json.dumps(value, indent=indent, allow_nan=True)


def _json_paths(value, prefix=()) -> list:
    """Every path (tuple of keys and indices) inside a JSON value, itself included."""
    out = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _json_paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value[:64]):
            out += _json_paths(v, prefix + (i,))
    return out


def _json_edit(document, rng: random.Random, under=()) -> str:
    """Change one value of a JSON document in place; returns what was done."""
    base = document
    for k in under:
        base = base[k]
    paths = [p for p in _json_paths(base) if p]
    if not paths:
        return "none"
    path = rng.choice(paths)
    parent = base
    for k in path[:-1]:
        parent = parent[k]
    key = path[-1]
    old = parent[key]
    how = rng.choice(["hostile", "hostile", "hostile", "numeric", "delete", "duplicate", "swap", "type"])
    if how == "numeric" and isinstance(old, (int, float)) and not isinstance(old, bool):
        parent[key] = rng.choice([old + 1, old - 1, old * 2, -old, old / 2 if isinstance(old, float) else old // 2,
                                  old * 1e10])
    elif how == "delete":
        del parent[key]
    elif how == "duplicate" and isinstance(parent, list):
        parent.insert(key, old)
    elif how == "swap" and isinstance(old, list) and len(old) >= 2:
        i, j = rng.sample(range(len(old)), 2)
        old[i], old[j] = old[j], old[i]
    elif how == "type":
        parent[key] = [old] if not isinstance(old, list) else (old[0] if old else None)
    else:
        how = "hostile"
        parent[key] = rng.choice(HOSTILE_JSON)
    return f"{how}:{'/'.join(map(str, under + path))}"


# ---- metadata copies (embedded, sidecar, package extension) --------------------------------------


def _write_metadata(folder: Path, seed: dict, texture: str, text: str, where: str) -> str:
    """Write layout metadata ``text`` into the texture (``where`` in texture/both) and its sidecar
    (sidecar/both). EXR and PNG are rewritten with vbusd's writer (texels kept); a KTX2 gets the
    text in place, padded with spaces, when it fits. Returns the name changed last, or None."""
    import numpy as np

    changed = None
    if where in ("sidecar", "both") and (folder / f"{texture}.json").exists():
        (folder / f"{texture}.json").write_text(text, encoding="utf-8")
        changed = f"{texture}.json"
    if where in ("texture", "both"):
        path = folder / texture
        if texture.endswith(".ktx2"):
            data = bytearray(path.read_bytes())
            start, end = _kvd_layout_span(data, 0)
            raw = json.dumps(json.loads(text), allow_nan=True, separators=(",", ":")).encode()
            if len(raw) > end - start:
                return changed
            data[start:end] = raw + b" " * (end - start - len(raw))
            path.write_bytes(bytes(data))
        elif texture.endswith(".exr"):
            from vbusd.io import exr

            exr.write_exr(path, np.load(seed["cache"][texture]["texels"]), text, compression="zip")
        else:
            return changed
        changed = texture
    return changed


def _package_layouts(document: dict) -> list:
    return [a.get("layout") for a in document["extensions"][EXTENSION]["animations"]]


def _edit_package_layout(folder: Path, seed: dict, edit, where: str) -> str:
    """Apply ``edit(layout dict)`` to the package extension's layout (``where`` in extension/both)
    and to the KTX2's vbusd.layout (kvd/both), the KTX2 edited in place when the text fits."""
    entry = folder / seed["entry"]
    document = _package_document(entry)
    layout = document["extensions"][EXTENSION]["animations"][0]["layout"]
    copy = json.loads(json.dumps(layout))
    if edit(copy) is False:
        return None
    changed = None
    if where in ("kvd", "both"):
        name, base = _ktx2_places(folder, seed)[0]
        data = bytearray((folder / name).read_bytes())
        start, end = _kvd_layout_span(data, base)
        raw = json.dumps(copy, allow_nan=True, separators=(",", ":")).encode()
        if len(raw) > end - start:
            return None
        data[start:end] = raw + b" " * (end - start - len(raw))
        (folder / name).write_bytes(bytes(data))  # a GLB's BIN chunk keeps its length
        changed = name
    if where in ("extension", "both"):
        document["extensions"][EXTENSION]["animations"][0]["layout"] = copy
        _write_package_document(entry, document)
        changed = seed["entry"]
    return changed


def _edit_metadata(folder: Path, seed: dict, edit, rng: random.Random):
    """``edit(metadata dict)`` on one copy or all copies of the metadata; returns (where, changed
    file) or None when ``edit`` says it does not apply (returns False)."""
    if seed["kind"] == "package":
        where = rng.choice(["both", "both", "extension", "kvd"])
        changed = _edit_package_layout(folder, seed, edit, where)
        return (where, changed) if changed else None
    texture = rng.choice(seed["textures"])
    text = seed["cache"][texture]["metadata"]
    document = json.loads(text)
    if edit(document) is False:
        return None
    where = rng.choice(["both", "both", "both", "texture", "sidecar"])
    changed = _write_metadata(folder, seed, texture, _dumps(document, indent=2), where)
    return (where, changed) if changed else None


# ---- USD text (.usda) edits ---------------------------------------------------------------------


def _usda_files(folder: Path, seed: dict) -> list:
    return sorted(p.name for p in folder.iterdir() if p.suffix == ".usda")


def _usda_value(text: str, name: str):
    """(start, end) of the value of the first attribute ``name`` (one line) in a .usda text."""
    m = re.search(rf"^[ \t]*(?:uniform )?[\w\[\]]+ {re.escape(name)} = ([^\n]*)$", text, re.M)
    return (m.start(1), m.end(1)) if m else None


def _usda_set(path: Path, name: str, change) -> bool:
    """Replace attribute ``name``'s value text by ``change(old text)``; False when absent."""
    text = path.read_text(encoding="utf-8")
    span = _usda_value(text, name)
    if span is None:
        return False
    old = text[span[0]:span[1]]
    trailer = ""
    if old.endswith("("):  # a primvar with metadata: "[...] ("
        old, trailer = old[:-1].rstrip(), " ("
    new = change(old)
    if new is None:
        return False
    path.write_text(text[:span[0]] + new + trailer + text[span[1]:], encoding="utf-8")
    return True


def _items(value: str) -> list:
    return [v.strip() for v in value.strip()[1:-1].split(",")] if value.strip() not in ("[]", "") else []


def _array(items) -> str:
    return "[" + ", ".join(items) + "]"


def _usd_number(x) -> str:
    if isinstance(x, float) and x != x:
        return "nan"
    if x in (float("inf"), float("-inf")):
        return "inf" if x > 0 else "-inf"
    return repr(x)


# ---- the structure-aware mutators: each returns (op, file changed, expectation) or None ---------


def m_minor_version(folder: Path, seed: dict, rng: random.Random):
    value = rng.choice([0, 1, 1, -1, 3, 99, 2 ** 31])
    needs_1_2_metadata = any(c["encoding"] == "compactQuatTranslation" for c in seed["cache"].values()) \
        or seed["surface"] == "mask" or (seed["kind"] == "package" and seed["name"] in
                                         ("package_compact_glb", "package_compact_gltf", "package_mask_gltf"))
    place = rng.choice(["prim", "metadata"]) if seed["kind"] != "package" else "metadata"
    if place == "prim":
        usda = [n for n in _usda_files(folder, seed) if _usda_value((folder / n).read_text(), "vb:formatMinorVersion")]
        if not usda:
            return None
        name = usda[0]
        _usda_set(folder / name, "vb:formatMinorVersion", lambda old: str(value))
        # A compact encoding or masks on a prim below 1.2 are refused by rule (spec 16); levels of
        # detail are a structure of other prims, which the spec has writers mark 1.2 (20.5) but
        # does not have readers refuse below it.
        expect = "all" if value == -1 or (value in (0, 1) and needs_1_2_metadata) else None
        return f"minor_version:prim={value}", name, expect

    def edit(doc):
        if doc.get("formatMinorVersion") == value:
            return False
        doc["formatMinorVersion"] = value

    done = _edit_metadata(folder, seed, edit, rng)
    if done is None:
        return None
    where, changed = done
    expect = "all" if value == -1 or (value in (0, 1) and needs_1_2_metadata) else None
    return f"minor_version:{where}={value}", changed, expect


def m_compact_range(folder: Path, seed: dict, rng: random.Random):
    if not any(c["encoding"] == "compactQuatTranslation" for c in seed["cache"].values()) and \
            seed["name"] not in ("package_compact_glb", "package_compact_gltf", "package_mask_gltf"):
        return None
    how = rng.choice(["inf", "-inf", "nan", "swap", "huge", "overflow32"])

    def new_pair(lo, hi):
        if how == "inf":
            return lo, float("inf")
        if how == "-inf":
            return float("-inf"), hi
        if how == "nan":
            return (float("nan"), hi) if rng.random() < 0.5 else (lo, float("nan"))
        if how == "swap":
            return (hi, lo) if lo < hi else None
        if how == "huge":
            return -3e38, 3e38
        return lo, 1e39

    place = "metadata" if seed["kind"] == "package" else rng.choice(["prim", "metadata", "all"])
    if seed["kind"] == "package":
        layouts = _package_layouts(_package_document(folder / seed["entry"]))
        ranges = layouts[0]["compactRanges"]
    else:
        texture = next(n for n, c in seed["cache"].items() if c["encoding"] == "compactQuatTranslation")
        ranges = json.loads(seed["cache"][texture]["metadata"])["compactRanges"]
    candidates = [(b, k) for b in range(len(ranges)) for k in range(7)
                  if how != "swap" or ranges[b][k][0] < ranges[b][k][1]]
    if not candidates:
        return None
    b, k = rng.choice(candidates)
    pair = new_pair(*ranges[b][k])
    if pair is None:
        return None
    changed = None
    if place in ("prim", "all"):
        usda = [n for n in _usda_files(folder, seed) if _usda_value((folder / n).read_text(), "vb:compactRangeMin")]
        if not usda:
            return None
        for attr, v in (("vb:compactRangeMin", pair[0]), ("vb:compactRangeMax", pair[1])):
            def change(old, v=v):
                items = _items(old)
                items[7 * b + k] = _usd_number(v)
                return _array(items)
            _usda_set(folder / usda[0], attr, change)
        changed = usda[0]
    if place in ("metadata", "all"):
        def edit(doc):
            doc["compactRanges"][b][k] = list(pair)
        done = _edit_metadata(folder, seed, edit, rng)
        if done is None and changed is None:
            return None
        changed = done[1] if done else changed
    return f"compact_range:{place}:{how}:{b}/{k}", changed, "all"


def _compact_texture(seed):
    for name, c in seed["cache"].items():
        if c["encoding"] == "compactQuatTranslation":
            return name
    return None


def m_compact_word(folder: Path, seed: dict, rng: random.Random):
    """Change texel words of a compact texture (bit 31 of G, the dropped index, all ones) and,
    mostly, write the content digest of the changed words everywhere it is stored, so that only
    the texel rules can find them."""
    import numpy as np

    from vbusd.format.digest import content_digest

    how = rng.choice(["bit31", "bit31", "dropped", "all_ones"])
    recompute = rng.random() < 0.7
    if seed["kind"] == "package":
        if seed["name"] not in ("package_compact_glb", "package_compact_gltf", "package_mask_gltf"):
            return None
        name, base = _ktx2_places(folder, seed)[0]
        data = bytearray((folder / name).read_bytes())
        offset = struct.unpack_from("<Q", data, base + 80)[0]
        width, height = struct.unpack_from("<II", data, base + 20)
        words = np.frombuffer(bytes(data[base + offset:base + offset + width * height * 12]), "<u4").reshape(
            height, width, 3).copy()
        layout = _package_layouts(_package_document(folder / seed["entry"]))[0]
        used = layout["usedWidth"]
    else:
        texture = _compact_texture(seed)
        if texture is None:
            return None
        texels = np.load(seed["cache"][texture]["texels"]).copy()
        words = texels[..., :3]
        used = json.loads(seed["cache"][texture]["metadata"])["usedWidth"]
    rows = words.shape[0]
    count = rng.choice([1, 1, 5, rows * used])
    cells = [(rng.randrange(rows), rng.randrange(used)) for _ in range(count)] if count < rows * used else \
        [(r, c) for r in range(rows) for c in range(used)]
    before = content_digest(np.concatenate([words, np.zeros(words.shape[:2] + (1,), "<u4")], axis=2))
    for r, c in cells:
        if how == "bit31":
            words[r, c, 1] |= np.uint32(1 << 31)
        elif how == "dropped":
            words[r, c, 2] = (words[r, c, 2] & np.uint32(0x3FFFFFFF)) | np.uint32(rng.randrange(4) << 30)
        else:
            words[r, c] = np.uint32(0xFFFFFFFF)
    after = content_digest(np.concatenate([words, np.zeros(words.shape[:2] + (1,), "<u4")], axis=2))
    if before == after:
        return None
    if seed["kind"] == "package":
        data[base + offset:base + offset + words.nbytes] = words.astype("<u4").tobytes()
        (folder / name).write_bytes(bytes(data))
        changed = name
    else:
        texels[..., :3] = words
        if texture.endswith(".ktx2"):
            path = folder / texture
            data = bytearray(path.read_bytes())
            offset = struct.unpack_from("<Q", data, 80)[0]
            data[offset:offset + words.nbytes] = np.ascontiguousarray(words).astype("<u4").tobytes()
            path.write_bytes(bytes(data))
        else:
            from vbusd.io import exr

            exr.write_exr(folder / texture, texels, seed["cache"][texture]["metadata"], compression="zip")
        changed = texture
    if recompute:  # the digest is the same length: replace it in every file that holds it
        for p in folder.iterdir():
            if p.is_file():
                raw = p.read_bytes()
                if before.encode() in raw:
                    p.write_bytes(raw.replace(before.encode(), after.encode()))
    expect = ("validate" if how in ("bit31", "all_ones") else None) if recompute else "decoders"
    return f"compact_word:{how}:{count}:{'digest' if recompute else 'stale'}", changed, expect


def m_ktx2_header(folder: Path, seed: dict, rng: random.Random):
    places = _ktx2_places(folder, seed)
    if not places:
        return None
    name, base = rng.choice(places)
    field = rng.choice(list(KTX2_FIELDS))
    offset, fmt = KTX2_FIELDS[field]
    data = bytearray((folder / name).read_bytes())
    old = struct.unpack_from(fmt, data, base + offset)[0]
    top = 0xFFFFFFFF if fmt == "<I" else 0xFFFFFFFFFFFFFFFF
    value = rng.choice([0, 1, 2, 4, old + 1, max(old - 1, 0), old * 2, old + 8, 97, 109, 91, 104, 2 ** 31, top,
                        top - 3, 1 << 40 if fmt == "<Q" else 65536])
    value = min(value, top)
    if value == old:
        return None
    struct.pack_into(fmt, data, base + offset, value)
    (folder / name).write_bytes(bytes(data))
    expect = None if field == "sgdByteOffset" else "all"
    return f"ktx2_header:{field}={value}", name, expect


def m_ktx2_kvd(folder: Path, seed: dict, rng: random.Random):
    """One value of the KTX2's vbusd.layout changed in place (package: also in the extension)."""
    edit = lambda doc: None if _json_edit(doc, rng) != "none" else False  # noqa: E731
    done = _edit_metadata(folder, seed, edit, rng)
    return (f"kvd:{done[0]}", done[1], None) if done else None


def m_gltf_json(folder: Path, seed: dict, rng: random.Random):
    entry = folder / seed["entry"]
    document = _package_document(entry)
    under = ()
    if rng.random() < 0.5:
        under = ("extensions", EXTENSION)
    elif rng.random() < 0.3:
        under = rng.choice([("accessors",), ("bufferViews",), ("nodes",), ("meshes",), ("buffers",)])
    if any(k not in document if i == 0 else False for i, k in enumerate(under)):
        under = ()
    op = _json_edit(document, rng, under)
    _write_package_document(entry, document)
    return f"gltf_json:{op}", seed["entry"], None


def m_metadata_json(folder: Path, seed: dict, rng: random.Random):
    op = []

    def edit(doc):
        op.append(_json_edit(doc, rng))
        return False if op[-1] == "none" else None

    done = _edit_metadata(folder, seed, edit, rng)
    return (f"metadata_json:{done[0]}:{op[0]}", done[1], None) if done else None


def m_lod_attr(folder: Path, seed: dict, rng: random.Random):
    usda = [n for n in _usda_files(folder, seed) if "LODRootAPI" in (folder / n).read_text()]
    if not usda:
        return None
    path = folder / usda[0]
    text = path.read_text(encoding="utf-8")
    levels = len(re.findall(r'^\s+def Xform "lod\d+"', text, re.M))
    how = rng.choice(["index", "index", "heuristics", "heuristics", "thresholds", "thresholds", "apischema",
                      "domain"])
    if how == "index":
        value = rng.choice([-1, levels, levels + 1, 99, 2 ** 31 - 1, 1, 0])
        if "lod:default:index" in text:
            text = re.sub(r"int lod:default:index = [^\n]*", f"int lod:default:index = {value}", text, count=1)
        else:
            text = text.replace("rel lod:heuristics", f"int lod:default:index = {value}\n        rel lod:heuristics", 1)
        path.write_text(text, encoding="utf-8")
        return f"lod:index={value}", usda[0], ("all" if not 0 <= value < levels else None)
    if how == "heuristics":
        m = re.search(r"rel lod:heuristics = <([^>]*)>", text)
        if not m:
            return None
        target = m.group(1)
        animation = re.search(r'def VirtualBonesAnimation "(\w+)"', text).group(1)
        root = target.rsplit("/", 1)[0]
        kind = rng.choice(["two", "none", "other", "missing"])
        new = {"two": f"rel lod:heuristics = [<{target}>, <{root}/{animation}>]", "none": "rel lod:heuristics = None",
               "other": f"rel lod:heuristics = <{root}/{animation}>",
               "missing": f"rel lod:heuristics = <{root}/NoSuchPrim>"}[kind]
        path.write_text(text[:m.start()] + new + text[m.end():], encoding="utf-8")
        return f"lod:heuristics={kind}", usda[0], "all"
    if how == "thresholds":
        value = rng.choice(["[2]", "[0]", "[-0.5]", "[nan]", "[inf]", "[]", "[0.01, 0.001]", "[1]", "[0.5]"])
        m = re.search(r"float\[\] thresholds = \[[^\]\n]*\]", text)
        if not m:
            return None
        path.write_text(text[:m.start()] + f"float[] thresholds = {value}" + text[m.end():], encoding="utf-8")
        return f"lod:thresholds={value}", usda[0], (None if value in ("[1]", "[0.5]") else "all")
    if how == "apischema":
        path.write_text(text.replace('prepend apiSchemas = ["LODRootAPI"]', "", 1), encoding="utf-8")
        return "lod:noLODRootAPI", usda[0], None
    path.write_text(text.replace('lod:domain = "imaging"', 'lod:domain = "physics"', 1), encoding="utf-8")
    return "lod:domain", usda[0], None


def m_mask_attr(folder: Path, seed: dict, rng: random.Random):
    usda = [n for n in _usda_files(folder, seed) if _usda_value((folder / n).read_text(), "vb:maskNames")]
    if not usda:
        return None
    path = folder / usda[0]
    how = rng.choice(["names_dup", "names_empty", "names_drop", "names_add", "weights_drop", "weights_add",
                      "weight_value", "weight_value", "parents_cycle", "parents_range", "metadata_weight",
                      "metadata_names"])
    if how.startswith("metadata"):
        value = rng.choice([float("nan"), -1.0, 2.0, 0.5, float("inf")])

        def edit(doc):
            masks = doc.get("masks")
            if not masks:
                return False
            if how == "metadata_weight":
                masks[0]["weights"][rng.randrange(len(masks[0]["weights"]))] = value
            else:
                masks[-1]["name"] = rng.choice(["", masks[0]["name"], "x" * 300])

        done = _edit_metadata(folder, seed, edit, rng)
        if done is None:
            return None
        # Only the metadata changed: the prim's masks now differ from it (metadata.mismatch) if
        # nothing else is wrong, so every reader refuses.
        return f"mask:{how}:{done[0]}", done[1], "all"

    def names(old):
        items = _items(old)
        if how == "names_dup":
            items[-1] = items[0] if len(items) > 1 else items[0]
            if len(items) == 1:
                items.append(items[0])
        elif how == "names_empty":
            items[rng.randrange(len(items))] = '""'
        elif how == "names_drop":
            items.pop()
        else:
            items.append('"extra"')
        return _array(items)

    def weights(old):
        items = _items(old)
        if how == "weights_drop":
            items.pop(rng.randrange(len(items)))
        elif how == "weights_add":
            items.append("1")
        else:
            items[rng.randrange(len(items))] = rng.choice(["nan", "-1", "2", "inf", "0.5"])
        return _array(items)

    def parents(old):
        items = _items(old)
        if how == "parents_cycle":
            child = next(i for i, p in enumerate(items) if p != "-1")
            items[int(items[child])] = str(child)
        else:
            items[rng.randrange(len(items))] = rng.choice(["-2", str(len(items)), "99"])
        return _array(items)

    attr, change = (("vb:maskNames", names) if how.startswith("names") else
                    ("vb:boneParents", parents) if how.startswith("parents") else ("vb:maskWeights", weights))
    if not _usda_set(path, attr, change):
        return None
    return f"mask:{how}", usda[0], "all"


def m_layer_primvar(folder: Path, seed: dict, rng: random.Random):
    if seed["kind"] != "crowd":
        return None
    path = folder / seed["entry"]
    text = path.read_text(encoding="utf-8")
    names = ["primvars:vb:layerClip", "primvars:vb:layerMask", "primvars:vb:layerWeight",
             "primvars:vb:layerTimeOffset", "primvars:vb:layerPlaybackRate"]
    name = rng.choice(names)
    how = rng.choice(["value", "value", "value", "drop", "add", "elementSize", "remove", "interpolation"])
    expect = None
    if how == "elementSize":
        m = re.search(rf"{re.escape(name)} = [^\n]*\n\s*elementSize = (\d+)", text)
        if not m:
            return None
        value = rng.choice([0, 1, 3, -1, 2 ** 31])
        text = text[:m.start(1)] + str(value) + text[m.end(1):]
        expect = "all" if value != int(m.group(1)) else None
    elif how == "remove":
        m = re.search(rf"^[^\n]*{re.escape(name)} = [^\n]*\n(\s+[^\n]*\n)*?\s+\)\n", text, re.M)
        if not m:
            return None
        text = text[:m.start()] + text[m.end():]
    elif how == "interpolation":
        m = re.search(rf"{re.escape(name)} = [^\n]*\n(?:\s*\w+ = [^\n]*\n)*?\s*interpolation = \"(\w+)\"", text)
        if not m:
            return None
        text = text[:m.start(1)] + rng.choice(["constant", "uniform", "faceVarying"]) + text[m.end(1):]
        expect = "all"
    else:
        span = _usda_value(text, name)
        if span is None:
            return None
        old = text[span[0]:span[1]]
        trailer = " (" if old.endswith("(") else ""
        items = _items(old.rstrip(" ("))
        if how == "drop":
            items.pop(rng.randrange(len(items)))
            expect = "all"
        elif how == "add":
            items.append(items[0])
            expect = "all"
        else:
            i = rng.randrange(len(items))
            integer = name.endswith(("Clip", "Mask"))
            value = rng.choice(["-1", "2", "99", "2147483647"] if integer else
                               ["nan", "inf", "-inf", "-1", "2", "1e30", "0"])
            items[i] = value
            if integer and name.endswith("Mask") and int(value) not in (0, 1):
                expect = "all"
            if integer and name.endswith("Clip") and int(value) != 0:
                expect = "all"
        text = text[:span[0]] + _array(items) + trailer + text[span[1]:]
    path.write_text(text, encoding="utf-8")
    return f"layer:{name.rsplit(':', 1)[1]}:{how}", seed["entry"], expect


MUTATORS_1_2 = {
    "minor_version": m_minor_version, "compact_range": m_compact_range, "compact_word": m_compact_word,
    "ktx2_header": m_ktx2_header, "ktx2_kvd": m_ktx2_kvd, "gltf_json": m_gltf_json,
    "metadata_json": m_metadata_json, "lod_attr": m_lod_attr, "mask_attr": m_mask_attr,
    "layer_primvar": m_layer_primvar,
}


def _mutator_weights(seed: dict) -> dict:
    """Which structure-aware mutators apply to a seed, with relative weights (the rest of the
    mutants are byte-level, :func:`mutate`)."""
    kind, surface = seed["kind"], seed["surface"]
    compact = any(c["encoding"] == "compactQuatTranslation" for c in seed["cache"].values()) or \
        seed["name"] in ("package_compact_glb", "package_compact_gltf", "package_mask_gltf")
    ktx2 = any(n.endswith(".ktx2") for n in seed["textures"]) or kind == "package"
    weights = {"minor_version": 2, "metadata_json": 3}
    if compact:
        weights.update(compact_range=3, compact_word=3)
    if ktx2:
        weights.update(ktx2_header=3, ktx2_kvd=2)
    if kind == "package":
        weights.update(gltf_json=6)
    if surface == "lod" or seed["name"] == "package_lod_glb":
        weights.update(lod_attr=5 if kind != "package" else 0)
    if surface == "mask":
        weights.update(mask_attr=5)
    if kind == "crowd":
        weights.update(layer_primvar=8)
    return {k: v for k, v in weights.items() if v}


def make_mutants_1_2(root: Path, count: int, seed: int, surfaces) -> list:
    """``count`` mutants of the format 1.2 seeds: 60 % structure-aware, 40 % byte-level."""
    rng = random.Random(seed)
    seeds = make_seeds_1_2(root, surfaces)
    jobs = []
    for i in range(count):
        s = seeds[i % len(seeds)]
        folder = Path(s["folder"])
        mutant = root / "mutants" / f"{i:05d}"
        shutil.copytree(folder, mutant)
        done = None
        weights = _mutator_weights(s)
        if weights and rng.random() < 0.6 and not s["entry"].endswith(".usdc"):
            name = rng.choices(list(weights), weights=list(weights.values()))[0]
            try:
                done = MUTATORS_1_2[name](mutant, s, rng)
            except (ValueError, KeyError, IndexError, TypeError, StopIteration, AttributeError):
                done = None  # the mutator does not apply to this seed (or an earlier change)
        if done is None:
            files = sorted(p.name for p in mutant.iterdir() if p.is_file())
            target = s["entry"] if rng.random() < 0.4 else rng.choice(files)
            data = (mutant / target).read_bytes()
            new, op = mutate(data, Path(target).suffix, rng)
            (mutant / target).write_bytes(new)
            done = (op, target, None)
        op, mutated, expect = done
        jobs.append({"id": i, "seed": s["name"], "kind": s["kind"], "surface": s["surface"], "folder": str(mutant),
                     "entry": s["entry"], "mutated": mutated or s["entry"], "op": op, "expect": expect})
    return jobs


def commands_for(job: dict, out: Path) -> list:
    """The command lines one mutant runs, each ``(argv, output path or None, group)``: the runs of
    one group read the same file, and the readers of a group must agree (format 1.2 surfaces).

    ``api`` and ``view`` are not commands of vbusd but in-process calls of the worker: the Python
    API (``vbusd.read_asset`` and ``vbusd.skin`` of clip 0 at 0.25 s; ``vbusd.read_texture`` for a
    texture) and the check ``vbusd view`` makes before it serves (``ViewerServer``: a package's
    ``check_package``, a USD asset's scene)."""
    entry = str(Path(job["folder"]) / job["entry"])
    mutated = str(Path(job["folder"]) / job["mutated"])
    if job.get("surface", "old") == "old":
        runs = [(["validate", entry], None), (["info", entry], None),
                (["decode", entry, "-o", str(out / "decode" / "cache.usda")], out / "decode" / "cache.usda"),
                (["convert", entry, "-o", str(out / "convert" / "asset.usda"), "--check-rows", "4"],
                 out / "convert" / "asset.usda")]
        if mutated != entry and Path(mutated).suffix in (".exr", ".png", ".json"):
            runs += [(["validate", mutated], None), (["info", mutated], None)]
        return [(argv, output, None) for argv, output in runs]
    runs = [(["validate", entry, "--format", "json"], None, "entry"), (["info", entry], None, "entry")]
    if job["kind"] == "package":
        runs += [(["view", entry], None, "entry")]
    else:
        runs += [(["decode", entry, "-o", str(out / "decode" / "cache.usda")], out / "decode" / "cache.usda", "entry"),
                 (["export", entry, "-o", str(out / "export" / "asset.glb")], out / "export" / "asset.glb", "entry"),
                 (["api", entry], None, "entry"), (["view", entry], None, "entry")]
    if mutated != entry and Path(mutated).suffix in (".exr", ".png", ".ktx2", ".json"):
        runs += [(["validate", mutated, "--format", "json"], None, "side"), (["info", mutated], None, "side")]
        if Path(mutated).suffix != ".json":
            runs += [(["api", mutated], None, "side")]
    return runs


# --------------------------------------------------------------------------------------------
# worker: runs vbusd.cli.main in-process, one command at a time
# --------------------------------------------------------------------------------------------


def _digest_folder(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def _in_process(argv: list) -> int:
    """The worker's ``api`` and ``view`` runs (:func:`commands_for`): 0, or the exit status of the
    vbusd error raised, printed as the command line prints it (an exception of another class
    escapes: a traceback)."""
    from vbusd.format.errors import VbusdError

    path = Path(argv[1])
    try:
        if argv[0] == "api":
            import vbusd

            if path.suffix.lower() in (".exr", ".png", ".ktx2"):
                vbusd.read_texture(path)
            else:
                vbusd.skin(vbusd.read_asset(path), 0, 0.25)
        else:
            from vbusd.web.server import ViewerServer

            ViewerServer(path).stop()
    except VbusdError as error:
        print(f"vbusd: {error}", file=sys.stderr)  # a message of several lines shows as a raw line
        return error.exit_status
    return 0


CODE_IN_LINE = re.compile(r": ([a-z][A-Za-z0-9]*(?:\.[A-Za-z0-9]+)+): ")


def _codes(argv: list, status, capture, first: str) -> tuple:
    """(error codes, internal) of one run: a JSON validate report's error codes, else the code of
    the one error line; internal when the run ended in command.internal or a finding says a
    check failed unexpectedly (asset.internal)."""
    codes = []
    if argv[0] == "validate" and "json" in argv and status in (0, 1):
        capture.seek(0)
        try:
            report = json.loads(capture.read().decode("utf-8", "replace"))
            codes = sorted({f["code"] for f in report.get("findings", []) if f.get("severity") == "error"})
        except (ValueError, AttributeError, TypeError):
            codes = ["<no JSON report>"]
    elif status not in (0, None):
        m = CODE_IN_LINE.search(first)
        codes = [m.group(1) if m else "<no code>"]
    internal = status == 3 or "command.internal" in codes or "asset.internal" in codes
    return codes, internal


def worker() -> int:
    """Read jobs (JSON lines) on stdin; answer each with one JSON line on the saved stdout."""
    import traceback

    answer = os.fdopen(os.dup(1), "w", buffering=1)
    from vbusd.cli import main

    capture, errors = tempfile.TemporaryFile(), tempfile.TemporaryFile()
    for line in sys.stdin:
        job = json.loads(line)
        argv, output = job["argv"], job.get("output")
        folder = Path(job["folder"])
        before = _digest_folder(folder)
        sentinel = None
        if output:
            Path(output).parent.mkdir(parents=True, exist_ok=True)
            if job.get("existing"):
                Path(output).write_bytes(b"old output\n")
                sentinel = hashlib.sha256(b"old output\n").hexdigest()
                argv = argv + ["--force"]
        for f in (capture, errors):
            f.seek(0)
            f.truncate()
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(capture.fileno(), 1)
        os.dup2(errors.fileno(), 2)
        escaped = None
        start = time.perf_counter()
        try:
            status = _in_process(argv) if argv[0] in ("api", "view") else main(argv)
        except SystemExit as done:
            status = done.code if isinstance(done.code, int) else 2
        except BaseException:  # noqa: BLE001 - what escapes main is what this run looks for
            escaped = traceback.format_exc()
            status = None
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        seconds = time.perf_counter() - start
        capture.seek(0)
        errors.seek(0)
        stderr = errors.read().decode("utf-8", "replace")
        text = capture.read().decode("utf-8", "replace") + stderr
        left = []
        clobbered = before != _digest_folder(folder)
        if output:
            out_dir = Path(output).parent
            names = sorted(p.name for p in out_dir.iterdir())
            if status != 0:
                if sentinel:
                    ok = Path(output).exists() and hashlib.sha256(Path(output).read_bytes()).hexdigest() == sentinel
                    clobbered = clobbered or not ok
                    left = [n for n in names if n != Path(output).name]
                else:
                    left = names
            shutil.rmtree(out_dir, ignore_errors=True)
        command = argv[0]
        raw = [l for l in stderr.splitlines() if l.strip() and not l.startswith(("vbusd", f"{command}:"))]
        rss_mb = _peak_rss_mb()
        first = stderr.strip().splitlines()[0][:300] if stderr.strip() else ""
        codes, internal = _codes(argv, status, capture, first)
        answer.write(json.dumps({"status": status, "escaped": escaped, "traceback": "Traceback (most recent" in text,
                                 "left": left, "clobbered": clobbered, "raw": raw[:3], "rss_mb": rss_mb,
                                 "seconds": seconds, "first_line": first, "codes": codes, "internal": internal})
                     + "\n")
    return 0


class Worker:
    """One worker process and its pipes."""

    def __init__(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "mutation_run.py"), "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
        self.baseline_mb = None

    def ask(self, job: dict, timeout: float):
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not ready:
            return None
        line = self.proc.stdout.readline()
        return json.loads(line) if line else {"status": None, "escaped": "worker died", "traceback": True,
                                              "left": [], "clobbered": False, "raw": [], "rss_mb": 0,
                                              "seconds": 0, "first_line": "worker died"}

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()


def run(jobs: list, out_root: Path, *, workers: int = 2, timeout: float = 60.0, max_rss_mb: float = 500.0,
        progress=None) -> dict:
    """Run every command of every mutant; returns counts and the failing cases."""
    import threading

    tasks = []
    for job in jobs:
        for k, (argv, output, group) in enumerate(commands_for(job, out_root / f"m{job['id']:05d}")):
            tasks.append({"job": job, "argv": argv, "folder": job["folder"], "group": group,
                          "output": None if output is None else str(output),
                          "existing": (job["id"] + k) % 2 == 1})
    results = [None] * len(tasks)
    lock = threading.Lock()
    cursor = {"next": 0, "done": 0}

    def loop():
        w = Worker()
        while True:
            with lock:
                i = cursor["next"]
                cursor["next"] += 1
            if i >= len(tasks):
                break
            task = tasks[i]
            answer = w.ask({k: task[k] for k in ("argv", "folder", "output", "existing")}, timeout)
            if answer is None:
                w.kill()
                answer = {"status": None, "hang": True}
                w = Worker()
            elif answer.get("escaped") == "worker died":
                w = Worker()
            elif answer["rss_mb"] > max_rss_mb:
                answer["memory"] = True
                w.kill()
                w = Worker()
            results[i] = answer
            with lock:
                cursor["done"] += 1
                if progress:
                    progress(cursor["done"], len(tasks))
        w.kill()

    threads = [threading.Thread(target=loop) for _ in range(workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    counts = Counter()
    failures = []
    by_command = Counter()
    statuses = Counter()
    for task, answer in zip(tasks, results):
        command = task["argv"][0]
        by_command[command] += 1
        statuses[f"{command}:{answer.get('status')}"] += 1
        problems = []
        if answer.get("hang"):
            problems.append("hang")
        if answer.get("escaped") or answer.get("traceback"):
            problems.append("traceback")
        if answer.get("memory"):
            problems.append("memory")
        if answer.get("left"):
            problems.append("partial")
        if answer.get("clobbered"):
            problems.append("clobbered")
        if answer.get("raw"):
            problems.append("raw")
        if answer.get("internal"):
            problems.append("internal")
        for p in problems:
            counts[p] += 1
        if problems:
            failures.append({"problems": problems, "argv": task["argv"], "seed": task["job"]["seed"],
                             "mutated": task["job"]["mutated"], "op": task["job"]["op"],
                             "detail": (answer.get("escaped") or "")[-1500:] or answer.get("first_line", ""),
                             "raw": answer.get("raw"), "left": answer.get("left")})
    disagreements = agreement(tasks, results)
    for d in disagreements:
        counts[d["category"]] += 1
        counts["accepted_bad"] += 1
        failures.append({"problems": ["accepted_bad", d["category"]], "argv": d["argv"], "seed": d["seed"],
                         "mutated": d["mutated"], "op": d["op"], "detail": d["detail"], "raw": None, "left": None})
    peak = max((a.get("rss_mb", 0) for a in results if a), default=0)
    names = ("traceback", "internal", "hang", "memory", "partial", "clobbered", "raw", "accepted_bad")
    return {"mutants": len(jobs), "runs": len(tasks), "by_command": dict(by_command),
            "statuses": dict(sorted(statuses.items())),
            "problems": {k: counts.get(k, 0) for k in names},
            "accepted_bad": {k: counts.get(k, 0) for k in ACCEPTED_BAD},
            "ops": dict(sorted(Counter(j["op"].split(":")[0] for j in jobs).items())),
            "expected_refusals": dict(Counter(j.get("expect") or "none" for j in jobs)),
            "peak_rss_mb": round(peak, 1), "failures": failures}


# --------------------------------------------------------------------------------------------
# the accepted-bad oracle: the readers of one file must accept and refuse alike
# --------------------------------------------------------------------------------------------

ACCEPTED_BAD = ("validate_missed", "reader_accepted", "expected_refusal")
"""validate_missed: validate found no error but another reader refused the file; reader_accepted:
validate found an error every reader must refuse, and a reader read the file; expected_refusal: a
targeted mutant whose rule is known (spec) was accepted by a reader that must refuse it."""

DECODING = {"decode", "export", "api"}
"""Readers that read the texels (and so must check the content digest); ``view`` of a USD asset
too. ``info`` and ``view`` of a package read the metadata and headers only (spec: "every check
vbusd validate makes but the texels")."""

LIMITATIONS = {"export": {"layers.unsupported", "export.noMeshes", "export.mesh"},
               "decode": set(), "api": set(), "view": set(), "info": set()}
"""Refusals that are no verdict on the file: what a reader does not implement (the runtime
package holds no layers yet) or cannot write."""

NOT_READ = {"info": ("binding.", "texture.unreadable")}
"""What a reader does not read, by its documentation: ``info`` describes the animation prims,
their texture headers and metadata, and the crowds; it reads neither the bound meshes
(``binding.*``) nor the pixels (a texture whose header reads but whose pixels do not is
``texture.unreadable`` for validate only)."""


def _texel_codes() -> set:
    """Findings about texel values: validate's checks of the texels, which readers that decode
    follow the spec in decoding anyway (bit 31 ignored, crossMatrix axes renormalized...)."""
    from vbusd.format.codes import _FINDINGS

    return {c.code for c in _FINDINGS if c.location == "texel"}


def agreement(tasks: list, results: list) -> list:
    """The disagreements of the readers of each file of each format 1.2 mutant (see ACCEPTED_BAD)."""
    texel = _texel_codes()
    groups = {}
    for task, answer in zip(tasks, results):
        if task.get("group") is None or answer is None or answer.get("status") not in (0, 1, 2):
            continue
        groups.setdefault((task["job"]["id"], task["group"]), []).append((task, answer))
    out = []
    for (_, group), runs in sorted(groups.items()):
        validate = next(((t, a) for t, a in runs if t["argv"][0] == "validate"), None)
        if validate is None:
            continue
        job = validate[0]["job"]
        v_status, v_codes = validate[1]["status"], validate[1].get("codes") or []
        structural = [c for c in v_codes if c not in texel and c != "texture.digest"]
        digest = "texture.digest" in v_codes
        expect = job.get("expect") if group == "entry" else None

        def report(category, task, answer, why):
            out.append({"category": category, "argv": task["argv"], "seed": job["seed"], "mutated": job["mutated"],
                        "op": job["op"], "detail": f"{why}; validate {v_status} {v_codes[:4]}; "
                                                   f"{task['argv'][0]} {answer['status']} {answer.get('first_line', '')[:240]}"})

        if expect in ("all", "validate", "decoders") and v_status == 0:
            report("expected_refusal", *validate, f"expected refusal ({expect})")
        for task, answer in runs:
            reader = task["argv"][0]
            if reader == "validate":
                continue
            status = answer["status"]
            codes = answer.get("codes") or []
            decodes = reader in DECODING or (reader == "view" and job["kind"] != "package")
            read = [c for c in structural if not c.startswith(NOT_READ.get(reader, ("<none>",)))]
            if status == 2 and v_status == 0 and not set(codes) & LIMITATIONS.get(reader, set()):
                report("validate_missed", task, answer, "validate found no error")
            elif status == 0 and v_status in (1, 2) and (read or (digest and decodes)):
                report("reader_accepted", task, answer, "validate found an error")
            elif status == 0 and (expect == "all" or (expect == "decoders" and decodes)):
                report("expected_refusal", task, answer, f"expected refusal ({expect})")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--mutants", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds before a run counts as a hang")
    parser.add_argument("--max-rss-mb", type=float, default=500.0)
    parser.add_argument("--json", type=Path, help="write the summary and failures here")
    parser.add_argument("--keep", type=Path, help="build the mutants here and keep them")
    parser.add_argument("--surfaces", default="old",
                        help="comma-separated: old (the 1.0/1.1 assets and sources), compact, package, lod, "
                             "mask (format 1.2); --mutants mutants of the old seeds and as many of the 1.2 ones")
    args = parser.parse_args(argv)
    if args.worker:
        return worker()
    surfaces = [s.strip() for s in args.surfaces.split(",") if s.strip()]
    unknown = sorted(set(surfaces) - set(SURFACES))
    if unknown or not surfaces:
        parser.error(f"--surfaces: unknown {', '.join(unknown) or 'empty'} (known: {', '.join(SURFACES)})")
    root = Path(tempfile.mkdtemp(prefix="vbusd-mutants-")) if args.keep is None else args.keep
    start = time.perf_counter()
    jobs = make_mutants(root / "old", args.mutants, args.seed) if "old" in surfaces else []
    if set(surfaces) - {"old"}:
        new = make_mutants_1_2(root / "new", args.mutants, args.seed, set(surfaces) - {"old"})
        jobs += [dict(j, id=j["id"] + len(jobs)) for j in new]
    last = [0.0]

    def progress(done, total):
        now = time.perf_counter()
        if now - last[0] > 5 or done == total:
            last[0] = now
            print(f"\r{done}/{total} runs, {now - start:.0f} s", end="", file=sys.stderr, flush=True)

    summary = run(jobs, root / "out", workers=args.jobs, timeout=args.timeout, max_rss_mb=args.max_rss_mb,
                  progress=progress)
    summary["seconds"] = round(time.perf_counter() - start, 1)
    summary["command"] = "python benchmarks/mutation_run.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(file=sys.stderr)
    shown = {k: v for k, v in summary.items() if k != "failures"}
    print(json.dumps(shown, indent=2))
    for failure in summary["failures"][:40]:
        print(f"{'/'.join(failure['problems'])}: {' '.join(failure['argv'][:2])} [{failure['seed']}: "
              f"{failure['mutated']} {failure['op']}]: {failure['detail'][-300:]} {failure['raw'] or ''}")
    if args.json:  # no machine paths: the mutants' folder, the tree and Python's are named for what they are
        text = json.dumps(summary, indent=2).replace(str(root), "<mutants>").replace(f"{ROOT}{os.sep}", "")
        for prefix, name in ((sys.prefix, "<python>"), (sys.base_prefix, "<python>")):
            text = text.replace(prefix, name)
        args.json.write_text(text + "\n")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if not any(summary["problems"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
