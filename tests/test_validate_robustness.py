"""Robustness corpus: malformed inputs give exit 2 and one clear line (or, where the asset itself
opens, findings), never a traceback, a hang or unbounded memory.

The corpus is made in a temporary folder from a valid golden fixture by truncating, corrupting and
rewriting its files. Every case runs in-process through ``vbusd.cli.main`` (fast), and the whole
corpus runs once more in a subprocess of the installed ``vbusd`` entry point with a timeout and a
peak-memory measurement.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

from vbusd.cli import main

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
EXR_FIXTURE = FIXTURES / "valid" / "crossMatrix_float16"
PNG_FIXTURE = FIXTURES / "valid" / "quatTranslation_unorm16"
EXR = "asset.Animation.exr"
PNG = "asset.Animation.png"


def _copy(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    (target / "expected.json").unlink()
    return target


def _patch_exr_data_window(data: bytes, width: int, height: int) -> bytes:
    marker = b"dataWindow\0box2i\0"
    at = data.index(marker) + len(marker) + 4  # skip the attribute size
    return data[:at] + struct.pack("<iiii", 0, 0, width - 1, height - 1) + data[at + 16:]


def _patch_png_ihdr(data: bytes, width: int, height: int) -> bytes:
    body = struct.pack(">II", width, height) + data[24:29]
    chunk = b"IHDR" + body
    return data[:12] + chunk + struct.pack(">I", zlib.crc32(chunk) & 0xFFFFFFFF) + data[33:]


def build_corpus(root: Path) -> list:
    """Make the corpus; returns (name, path, allowed exit statuses, expected code or None)."""
    cases = []
    exr_dir = _copy(EXR_FIXTURE, root / "exr")
    png_dir = _copy(PNG_FIXTURE, root / "png")
    exr_bytes = (exr_dir / EXR).read_bytes()
    png_bytes = (png_dir / PNG).read_bytes()

    def add(name, data, suffix, statuses, code=None):
        path = root / "alone" / f"{name}{suffix}"
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(data)
        cases.append((name, path, statuses, code))

    # Textures given on their own: unreadable -> exit 2 with one line.
    for cut in (0, 3, 8, 60, 300, len(exr_bytes) // 2, len(exr_bytes) - 1):
        add(f"exr_truncated_{cut}", exr_bytes[:cut], ".exr", {2}, "texture.unreadable")
    corrupt = bytearray(exr_bytes)
    for i in range(len(corrupt) - 200, len(corrupt) - 100):
        corrupt[i] ^= 0x5A  # inside the zip-compressed pixels
    add("exr_corrupt_pixels", bytes(corrupt), ".exr", {1, 2})
    add("exr_huge_declared", _patch_exr_data_window(exr_bytes, 50000, 40000), ".exr", {2}, "texture.unreadable")
    add("exr_garbage", os.urandom(4096), ".exr", {2}, "texture.unreadable")
    for cut in (0, 8, 20, 40, len(png_bytes) // 2, len(png_bytes) - 4):
        add(f"png_truncated_{cut}", png_bytes[:cut], ".png", {2}, "texture.unreadable")
    bad_crc = bytearray(png_bytes)
    bad_crc[-20] ^= 0xFF
    add("png_bad_crc", bytes(bad_crc), ".png", {2}, "texture.unreadable")
    add("png_huge_declared", _patch_png_ihdr(png_bytes, 60000, 30000), ".png", {2}, "texture.unreadable")
    # JSON sidecars given on their own.
    add("json_broken", b'{"format": "vbusd.virtualBones", "boneCount": 4', ".json", {2}, "metadata.json")
    add("json_not_utf8", b'{"generator": "\xff\xfe"}', ".json", {2}, "metadata.json")
    add("json_list", b"[1, 2, 3]", ".json", {2}, "metadata.json")
    add("json_nan", b'{"boneCount": NaN}', ".json", {1, 2})
    typed = json.loads((exr_dir / (EXR + ".json")).read_text(encoding="utf-8"))
    typed.update(boneCount="4", clips={"walk": 1}, width=-16, bones="root")
    add("json_wrongly_typed", json.dumps(typed).encode(), ".json", {1}, "metadata.schema")
    # USD files that do not open.
    add("usd_syntax", b'#usda 1.0\ndef Xform "A" {\n  int x = \n}\n', ".usda", {2}, "usd.open")
    add("usd_garbage", os.urandom(2048), ".usda", {2}, "usd.open")
    add("usd_empty", b"", ".usda", {2}, "usd.open")
    from pxr import Usd

    crate = root / "crate.usdc"
    stage = Usd.Stage.Open(str(exr_dir / "asset.usda"))  # keep the stage alive: it owns the layer
    stage.GetRootLayer().Export(str(crate))
    del stage
    crate_bytes = crate.read_bytes()
    for cut in (10, 100, len(crate_bytes) // 2, len(crate_bytes) - 16):
        add(f"usdc_truncated_{cut}", crate_bytes[:cut], ".usdc", {2}, "usd.open")
    cases.append(("missing_file", root / "nothere.usda", {2}, "file.missing"))
    def declare_huge(folder):
        usda = folder / "asset.usda"
        text = usda.read_text(encoding="utf-8")
        for old, new in (("int vb:boneCount = 4", "int vb:boneCount = 20000"),
                         ("int vb:rowCount = 12", "int vb:rowCount = 50000"),
                         ("int vb:textureWidth = 16", "int vb:textureWidth = 65536")):
            assert old in text
            text = text.replace(old, new)
        usda.write_text(text, encoding="utf-8")

    # Assets that open, with broken textures or huge declarations: findings, exit 1.
    for name, mutate in (
            ("usd_declares_huge", declare_huge),
            ("usd_texture_truncated", lambda d: (d / EXR).write_bytes(exr_bytes[:len(exr_bytes) // 2])),
            ("usd_texture_huge", lambda d: (d / EXR).write_bytes(_patch_exr_data_window(exr_bytes, 40000, 40000))),
            ("usd_sidecar_broken", lambda d: (d / (EXR + ".json")).write_bytes(b'{"a": ')),
            ("usd_texture_escapes", lambda d: (d / "asset.usda").write_text(
                (d / "asset.usda").read_text(encoding="utf-8").replace("@./asset.Animation.exr@",
                                                                      "@../exr/asset.Animation.exr@"),
                encoding="utf-8"))):
        folder = _copy(EXR_FIXTURE, root / name)
        mutate(folder)
        cases.append((name, folder / "asset.usda", {1}, None))
    return cases


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return build_corpus(tmp_path_factory.mktemp("corpus"))


def test_corpus_in_process(corpus, capsys):
    for name, path, statuses, code in corpus:
        status = main(["validate", str(path), "--format", "json"])
        out, err = capsys.readouterr()
        assert status in statuses, f"{name}: exit {status}, expected {statuses}; stderr {err!r}"
        assert "Traceback" not in out + err, name
        if status == 2:
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("vbusd: "), f"{name}: {err!r}"
            assert str(path.name) in lines[0] or path.stem in lines[0], f"{name}: file not named: {err!r}"
            if code:
                assert f": {code}: " in lines[0], f"{name}: {lines[0]!r}"
            assert out == ""
        else:
            report = json.loads(out)
            assert report["counts"]["error"] >= 1 and err == ""
            if code:
                assert code in {f["code"] for f in report["findings"]}, name


def test_usd_cases_name_the_texture_problem(corpus, capsys):
    expected = {"usd_texture_truncated": "texture.unreadable", "usd_texture_huge": "texture.unreadable",
                "usd_declares_huge": "prim.attribute.invalid",
                "usd_sidecar_broken": "metadata.json", "usd_texture_escapes": "texture.outside"}
    for name, path, _, _ in corpus:
        if name in expected:
            assert main(["validate", str(path), "--format", "json"]) == 1
            report = json.loads(capsys.readouterr().out)
            assert expected[name] in {f["code"] for f in report["findings"]}, name


DRIVER = """
import json, os, resource, subprocess, sys, time
cases = json.loads(sys.argv[1])
results = []
for path in cases:
    start = time.monotonic()
    proc = subprocess.Popen([sys.argv[2], "validate", path], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        results.append([path, "timeout", out, err, 0, time.monotonic() - start])
        continue
    results.append([path, proc.returncode, out, err, 0, time.monotonic() - start])
peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print(json.dumps({"results": results, "peak_kib": peak_kib}))
"""


@pytest.mark.cli
def test_corpus_through_the_installed_command(corpus):
    vbusd_exe = shutil.which("vbusd")
    assert vbusd_exe is not None, "the vbusd command is not on PATH: pip install . (the README's set-up does)"
    # One process per input (what a pipeline does); a sample of the corpus keeps the test fast.
    chosen = [c for c in corpus if c[0] in ("exr_truncated_300", "exr_huge_declared", "png_huge_declared",
                                            "png_bad_crc", "json_list", "usd_syntax",
                                            "usdc_truncated_100", "missing_file", "usd_texture_huge",
                                            "usd_declares_huge")]
    paths = [str(c[1]) for c in chosen]
    result = subprocess.run([sys.executable, "-c", DRIVER, json.dumps(paths), vbusd_exe],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    for (name, _, statuses, _), (path, status, out, err, _, seconds) in zip(chosen, data["results"]):
        assert status != "timeout", name
        assert status in statuses, f"{name}: {status} {err!r}"
        assert "Traceback" not in out + err, name
        if status == 2:
            assert len(err.strip().splitlines()) == 1, f"{name}: {err!r}"
    # pxr + numpy + OpenEXR take about 200 MB; a 40000 x 40000 declaration must not allocate.
    assert data["peak_kib"] < 1024 * 1024, f"peak RSS {data['peak_kib']} KiB"


def test_silenced_streams_are_restored_after_overlapping_threads():
    """UsdValidation runs validators on worker threads: overlapping silencing must not leave
    stdout or stderr pointing at /dev/null."""
    import threading
    import time

    from vbusd.process.capture import captured_output as quiet_stderr

    stdout, stderr = sys.stdout, sys.stderr
    fds = [(os.fstat(fd).st_dev, os.fstat(fd).st_ino) for fd in (1, 2)]
    barrier = threading.Barrier(4)

    def work(delay):
        with quiet_stderr():
            barrier.wait(timeout=10)
            time.sleep(delay)
            with quiet_stderr():  # nested
                print("hidden")

    threads = [threading.Thread(target=work, args=(0.01 * i,)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert sys.stdout is stdout and sys.stderr is stderr
    assert [(os.fstat(fd).st_dev, os.fstat(fd).st_ino) for fd in (1, 2)] == fds


def _usda(path: Path, text: str) -> Path:
    path.write_text("#usda 1.0\n" + text, encoding="utf-8")
    return path


def test_more_malformed_inputs(tmp_path, capsys):
    """Inputs a pipeline meets by accident: empty files of every USD flavour, a folder, layers that
    include themselves or are missing or lie outside the folder, a broken texture inside a .usdz
    package, and a texture whose sidecar disagrees with its embedded metadata."""
    from pxr import Sdf, UsdUtils

    for suffix in (".usda", ".usdc", ".usdz", ".usd"):
        (tmp_path / f"zero{suffix}").write_bytes(b"")
    (tmp_path / "folder.usda").mkdir()
    os.mkfifo(tmp_path / "pipe.usda")  # opening it for reading would block forever
    (tmp_path / "notes.txt").write_text("not an asset", encoding="utf-8")
    _usda(tmp_path / "self_sublayer.usda", '(\n    subLayers = [@./self_sublayer.usda@]\n)\ndef Xform "A" {}\n')
    _usda(tmp_path / "cycle_a.usda", "(\n    subLayers = [@./cycle_b.usda@]\n)\n")
    _usda(tmp_path / "cycle_b.usda", "(\n    subLayers = [@./cycle_a.usda@]\n)\n")
    _usda(tmp_path / "target.usda", 'def Xform "T" {}\n')
    (tmp_path / "inner").mkdir()
    _usda(tmp_path / "inner" / "escape.usda", '(\n    subLayers = [@../target.usda@]\n)\n')
    _usda(tmp_path / "missing_reference.usda", 'def Xform "A" (\n    references = @./gone.usda@\n) {}\n')
    _usda(tmp_path / "self_reference.usda", 'def Xform "A" (\n    references = @./self_reference.usda@\n) {}\n')

    package_src = _copy(EXR_FIXTURE, tmp_path / "package_src")
    exr = (package_src / EXR).read_bytes()
    (package_src / EXR).write_bytes(exr[:len(exr) // 2])
    package = tmp_path / "package.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(package_src / "asset.usda")), str(package))

    disagree = _copy(EXR_FIXTURE, tmp_path / "disagree")
    sidecar = disagree / (EXR + ".json")
    meta = json.loads(sidecar.read_text(encoding="utf-8"))
    meta["clips"][0]["rowsPerSecond"] = meta["clips"][0]["rowsPerSecond"] * 2
    sidecar.write_text(json.dumps(meta), encoding="utf-8")

    # name -> (path, exit status, the code on stderr (exit 2) or among the findings)
    cases = {
        "zero_usda": (tmp_path / "zero.usda", 2, "usd.open"),
        "zero_usdc": (tmp_path / "zero.usdc", 2, "usd.open"),
        "zero_usdz": (tmp_path / "zero.usdz", 2, "usd.open"),
        "zero_usd": (tmp_path / "zero.usd", 2, "usd.open"),
        "folder": (tmp_path / "folder.usda", 2, "file.unreadable"),
        "named_pipe": (tmp_path / "pipe.usda", 2, "file.unreadable"),
        "unknown_suffix": (tmp_path / "notes.txt", 2, "usd.open"),
        # USD composes these with a warning; readers refuse them, so they are errors.
        "self_sublayer": (tmp_path / "self_sublayer.usda", 1, "asset.composition"),
        "sublayer_cycle": (tmp_path / "cycle_a.usda", 1, "asset.composition"),
        "self_reference": (tmp_path / "self_reference.usda", 1, "asset.composition"),
        "missing_reference": (tmp_path / "missing_reference.usda", 1, "asset.composition"),
        "sublayer_outside": (tmp_path / "inner" / "escape.usda", 1, "asset.outside"),  # an error, as for info
        "usdz_texture_truncated": (package, 1, "texture.unreadable"),
        "texture_sidecar_disagrees": (disagree / EXR, 1, "metadata.sidecarMismatch"),
    }
    for name, (path, expected, code) in cases.items():
        status = main(["validate", str(path), "--format", "json"])
        out, err = capsys.readouterr()
        assert status == expected, f"{name}: exit {status}; stderr {err!r}"
        assert "Traceback" not in out + err, name
        if status == 2:
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith(f"vbusd: {path}"), f"{name}: {err!r}"
            assert f": {code}: " in lines[0], f"{name}: {lines[0]!r}"
        else:
            findings = json.loads(out)["findings"]
            assert code in {f["code"] for f in findings}, f"{name}: {findings}"
            if name == "usdz_texture_truncated":
                unreadable = [f for f in findings if f["code"] == "texture.unreadable"][0]
                assert unreadable["location"]["file"].startswith("package.usdz[")


def test_interlaced_png_is_refused_like_vbusds_reader_does(tmp_path, capsys):
    """The spec's PNG is non-interlaced; pypng decodes Adam7 happily, so the validator must say so
    itself (vbusd.io.png refuses it)."""
    import png

    import io

    folder = _copy(PNG_FIXTURE, tmp_path / "interlaced")
    original = (folder / PNG).read_bytes()
    width, height, rows, _ = png.Reader(bytes=original).read()
    rows = [list(r) for r in rows]
    plain = io.BytesIO()
    png.Writer(width, height, greyscale=False, alpha=True, bitdepth=16, interlace=True).write(plain, rows)
    chunks = list(png.Reader(bytes=plain.getvalue()).chunks())
    # Keep the metadata chunk, so that interlacing is the one thing wrong.
    chunks.insert(1, next(c for c in png.Reader(bytes=original).chunks() if c[0] == b"iTXt"))
    with open(folder / PNG, "wb") as handle:
        png.write_chunks(handle, chunks)
    assert main(["validate", str(folder / "asset.usda"), "--format", "json"]) == 1
    findings = json.loads(capsys.readouterr().out)["findings"]
    assert [(f["code"], f["location"]) for f in findings] == [
        ("texture.unreadable", {"kind": "file", "file": PNG, "byteOffset": 8, "part": "IHDR"})]


def test_subsampled_exr_channel_is_named(tmp_path, capsys):
    """An EXR channel with 2 x 2 sampling (the spec requires 1 x 1): one finding naming the channel,
    not OpenEXR's generic failure plus a false "channels are none"."""
    folder = _copy(EXR_FIXTURE, tmp_path / "subsampled")
    data = (folder / EXR).read_bytes()
    marker = b"channels\0chlist\0"
    first_name_end = data.index(b"\0", data.index(marker) + len(marker) + 4)  # after "A"
    at = first_name_end + 1 + 4 + 4  # pixel type, pLinear + reserved, then xSampling, ySampling
    (folder / EXR).write_bytes(data[:at] + struct.pack("<ii", 2, 2) + data[at + 8:])
    assert main(["validate", str(folder / "asset.usda"), "--format", "json"]) == 1
    findings = json.loads(capsys.readouterr().out)["findings"]
    assert [f["code"] for f in findings] == ["texture.unreadable"]
    assert "channel A is subsampled 2 x 2" in findings[0]["message"]


def _rewrite_png_chunk(data: bytes, kind: bytes, edit) -> bytes:
    """``data`` with the first chunk of type ``kind`` replaced by ``edit(kind, body)`` (a new type
    and body; the CRC is recomputed)."""
    pos = 8
    while pos < len(data):
        length, found = struct.unpack(">I4s", data[pos:pos + 8])
        if found == kind:
            new_kind, body = edit(found, data[pos + 8:pos + 8 + length])
            chunk = new_kind + body
            return (data[:pos] + struct.pack(">I", len(body)) + chunk
                    + struct.pack(">I", zlib.crc32(chunk) & 0xFFFFFFFF) + data[pos + 12 + length:])
        pos += 12 + length
    raise AssertionError(f"no {kind!r} chunk")


def _as_text_chunk(kind, body):
    keyword, _, rest = body.partition(b"\0")
    _lang, _, rest = rest[2:].partition(b"\0")  # skip compression flag and method (0, 0)
    _translated, _, text = rest.partition(b"\0")
    return b"tEXt", keyword + b"\0" + text


@pytest.mark.parametrize("case", ["png_tEXt", "png_other_keyword", "exr_other_attribute"])
def test_metadata_only_counts_where_the_spec_puts_it(tmp_path, capsys, case):
    """Layout metadata is the EXR string attribute or the PNG iTXt chunk named vbusd.layout, and
    nothing else (spec "Texture files"); vbusd's reader refuses a texture whose metadata sits
    anywhere else, so the validator must not accept it either (it once took any text chunk or
    attribute with "layout" in its name)."""
    from vbusd.format.errors import InputError
    from vbusd.io.textures import read_texture

    if case.startswith("png"):
        folder, name = _copy(PNG_FIXTURE, tmp_path / case), PNG
        data = (folder / name).read_bytes()
        edit = _as_text_chunk if case == "png_tEXt" else (
            lambda kind, body: (kind, body.replace(b"vbusd.layout\0", b"vbusd.layouX\0", 1)))
        (folder / name).write_bytes(_rewrite_png_chunk(data, b"iTXt", edit))
    else:
        folder, name = _copy(EXR_FIXTURE, tmp_path / case), EXR
        data = (folder / name).read_bytes()
        assert data.count(b"vbusd.layout\0string\0") == 1
        (folder / name).write_bytes(data.replace(b"vbusd.layout\0string\0", b"vbusd.layouX\0string\0"))
    (folder / (name + ".json")).unlink()
    with pytest.raises(InputError) as refused:  # the reader's verdict, independent of the validator
        read_texture(folder / name)
    assert refused.value.code == "metadata.missing"
    assert main(["validate", str(folder / "asset.usda"), "--format", "json"]) == 1
    findings = json.loads(capsys.readouterr().out)["findings"]
    missing = [f for f in findings if f["code"] == "metadata.missing"]
    # "part" names the PNG chunk where one holds the wrong keyword; an EXR header has none.
    assert [{k: v for k, v in f["location"].items() if k != "part"} for f in missing] == [
        {"kind": "file", "file": name}]
    assert "vbusd.layou" in missing[0]["message"]  # names what it found instead


def test_undecodable_metadata_chunk_is_named(tmp_path, capsys):
    """An iTXt vbusd.layout chunk whose text is not UTF-8 (vbusd's reader refuses it): the finding
    says the chunk is there but cannot be decoded (metadata.json: not UTF-8 JSON), not merely that
    metadata is missing."""
    folder = _copy(PNG_FIXTURE, tmp_path / "bad_utf8")
    data = (folder / PNG).read_bytes()
    (folder / PNG).write_bytes(_rewrite_png_chunk(data, b"iTXt", lambda kind, body: (kind, body + b"\xff\xfe")))
    (folder / (PNG + ".json")).unlink()
    assert main(["validate", str(folder / "asset.usda"), "--format", "json"]) == 1
    findings = json.loads(capsys.readouterr().out)["findings"]
    [broken] = [f for f in findings if f["code"] == "metadata.json"]
    assert "cannot be decoded" in broken["message"] and broken["location"]["file"] == PNG
    assert "metadata.missing" not in {f["code"] for f in findings}


@pytest.mark.cli
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_a_named_pipe_sublayer_is_refused_not_waited_on(tmp_path):
    # USD blocks forever reading a pipe; validate must refuse it before composing the stage.
    os.mkfifo(tmp_path / "fifo.usda")
    (tmp_path / "asset.usda").write_text('#usda 1.0\n(\n    subLayers = [@./fifo.usda@]\n)\n')
    run = subprocess.run([sys.executable, "-m", "vbusd", "validate", str(tmp_path / "asset.usda")],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert run.returncode == 2
    assert "file.kind" in run.stderr and "fifo.usda" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr
