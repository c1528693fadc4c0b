"""Atomic writes (single file, texture + sidecar, multi-file transactions) and safe path resolution."""

from __future__ import annotations

import os
import stat
import time

import numpy as np
import pytest

from vbusd.io import files as fileio, textures
from vbusd.format.errors import InputError
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, VirtualBones


def small_vb(value: float) -> VirtualBones:
    layout = Layout("crossMatrix", "float16", 2, 3)
    texels = np.zeros(layout.shape, "<f2")
    texels[:, :6] = value
    return VirtualBones(layout, texels, ("a", "b"), (Clip("c", 0, 3, 30.0, True),))


class Boom(Exception):
    pass


def names(folder):
    return sorted(p.name for p in folder.iterdir())


def test_atomic_write_replaces_on_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with fileio.atomic_write(target, "w") as stream:
        stream.write("new")
        assert target.read_text() == "old"  # nothing visible until the block ends
    assert target.read_text() == "new"
    assert names(tmp_path) == ["out.txt"]


def test_failure_mid_write_leaves_target_untouched_and_no_temporaries(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"precious")
    with pytest.raises(Boom):
        with fileio.atomic_write(target) as stream:
            stream.write(b"half a fi")
            raise Boom()
    assert target.read_bytes() == b"precious"
    assert names(tmp_path) == ["out.bin"]
    # A new file is not created either.
    with pytest.raises(Boom):
        with fileio.atomic_write(tmp_path / "new.bin") as stream:
            stream.write(b"x")
            raise Boom()
    assert names(tmp_path) == ["out.bin"]


def test_permissions_follow_umask_or_existing_file(tmp_path):
    old = os.umask(0o022)
    try:
        with fileio.atomic_write(tmp_path / "a") as stream:
            stream.write(b"1")
        assert stat.S_IMODE((tmp_path / "a").stat().st_mode) == 0o644  # not mkstemp's 0600
        os.chmod(tmp_path / "a", 0o640)
        with fileio.atomic_write(tmp_path / "a") as stream:
            stream.write(b"2")
        assert stat.S_IMODE((tmp_path / "a").stat().st_mode) == 0o640
    finally:
        os.umask(old)


def test_temporary_keeps_the_suffix(tmp_path):
    with fileio.AtomicTransaction() as tx:
        temporary = tx.temp_path(tmp_path / "scene.usda")
        assert temporary.parent == tmp_path and temporary.suffix == ".usda"
        assert temporary.name.startswith(".scene.usda.")
        temporary.write_text("#usda 1.0\n")
    assert names(tmp_path) == ["scene.usda"]


def test_next_write_sweeps_stale_temporaries_of_its_own_target_only(tmp_path):
    # A writer killed by SIGKILL leaves its hidden temporary; the next write of the same target
    # removes it once it is older than STALE_TEMPORARY_AGE_S, and touches nothing else.
    old = time.time() - fileio.STALE_TEMPORARY_AGE_S - 60
    stale = tmp_path / ".scene.usda.vbusd-tmp-0123abcd.usda"
    kept = {
        ".scene.usda.vbusd-tmp-89abcdef.usda": time.time(),  # fresh: maybe another live writer
        ".other.usda.vbusd-tmp-0123abcd.usda": old,  # another target's
        ".scene.usda.vbusd-bak-0123abcd.usda": old,  # a backup may be the only old copy
        ".scene.usda.vbusd-tmp-0123abcd.usda.keep": old,  # not the exact pattern
        "scene.usda.vbusd-tmp-0123abcd.usda": old,  # not hidden: not ours
    }
    for path, mtime in [(stale, old)] + [(tmp_path / n, t) for n, t in kept.items()]:
        path.write_text("x")
        os.utime(path, (mtime, mtime))
    with fileio.atomic_write(tmp_path / "scene.usda", "w") as stream:
        stream.write("#usda 1.0\n")
    assert names(tmp_path) == sorted(["scene.usda", *kept])


def test_transaction_writes_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    with pytest.raises(Boom):
        with fileio.atomic_write_many() as tx:
            with tx.open(a, "w") as stream:
                stream.write("new a")
            with tx.open(b, "w") as stream:
                stream.write("new b")
            raise Boom()
    assert a.read_text() == "old a" and names(tmp_path) == ["a.txt"]
    with fileio.atomic_write_many() as tx:
        with tx.open(a, "w") as stream:
            stream.write("new a")
        tx.temp_path(b).write_text("new b")
    assert a.read_text() == "new a" and b.read_text() == "new b"
    assert names(tmp_path) == ["a.txt", "b.txt"]


def test_failed_rename_rolls_back_earlier_renames(tmp_path, monkeypatch):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    a.write_text("old a")
    b.write_text("old b")
    real_replace = os.replace
    calls = []

    def flaky_replace(source, target):
        calls.append(target)
        if len(calls) == 3:  # the third rename (c) fails after a and b were replaced
            raise OSError(28, "No space left on device")
        return real_replace(source, target)

    monkeypatch.setattr(fileio.os, "replace", flaky_replace)
    with pytest.raises(OSError):
        with fileio.AtomicTransaction() as tx:
            for path in (a, b, c):
                with tx.open(path, "w") as stream:
                    stream.write("new")
    monkeypatch.setattr(fileio.os, "replace", real_replace)
    assert a.read_text() == "old a" and b.read_text() == "old b"
    assert names(tmp_path) == ["a", "b"]  # c never appeared; no temporaries or backups left


def test_write_texture_failure_keeps_old_texture_and_sidecar(tmp_path, monkeypatch):
    path = tmp_path / "anim.exr"
    textures.write_texture(path, small_vb(1.0))
    before = {name: (tmp_path / name).read_bytes() for name in names(tmp_path)}
    assert sorted(before) == ["anim.exr", "anim.exr.json"]

    # The sidecar fails after the new EXR was fully written to its temporary.
    original_open = fileio.AtomicTransaction.open

    def open_failing_for_json(self, target, mode="wb", **kwargs):
        if str(target).endswith(".json"):
            raise Boom()
        return original_open(self, target, mode, **kwargs)

    monkeypatch.setattr(fileio.AtomicTransaction, "open", open_failing_for_json)
    with pytest.raises(Boom):
        textures.write_texture(path, small_vb(2.0))
    monkeypatch.undo()
    after = {name: (tmp_path / name).read_bytes() for name in names(tmp_path)}
    assert after == before
    assert textures.read_texture(path).texels[0, 0, 0] == 1.0


def test_write_texture_into_a_callers_transaction(tmp_path):
    with fileio.AtomicTransaction() as tx:
        textures.write_texture(tmp_path / "t.exr", small_vb(3.0), transaction=tx)
        with tx.open(tmp_path / "scene.usda", "w") as stream:
            stream.write("#usda 1.0\n")
        # Before the commit only hidden temporaries exist.
        assert len(names(tmp_path)) == 3 and all(n.startswith(".") for n in names(tmp_path))
    assert names(tmp_path) == ["scene.usda", "t.exr", "t.exr.json"]
    assert textures.read_texture(tmp_path / "t.exr").texels[0, 0, 0] == 3.0


# --- resolve_inside ----------------------------------------------------------------------------


def test_resolve_inside_accepts_relative_paths(tmp_path):
    (tmp_path / "tex").mkdir()
    assert fileio.resolve_inside(tmp_path, "tex/a.exr") == (tmp_path / "tex" / "a.exr").resolve()
    assert fileio.resolve_inside(tmp_path, "tex/../a.exr") == (tmp_path / "a.exr").resolve()
    assert fileio.resolve_inside(tmp_path, "./a.exr") == (tmp_path / "a.exr").resolve()
    assert fileio.resolve_inside(tmp_path, "tex\\a.exr") == (tmp_path / "tex" / "a.exr").resolve()


@pytest.mark.parametrize("reference, why", [
    ("../secret.exr", "'..'"),
    ("tex/../../secret.exr", "'..'"),
    ("..\\secret.exr", "'..'"),
    ("/etc/passwd", "absolute"),
    ("C:/Windows/a.exr", "absolute"),
    ("file:///etc/passwd", "scheme 'file'"),
    ("http://example.com/a.exr", "scheme 'http'"),
    ("data:application/octet-stream;base64,AAAA", "scheme 'data'"),
    ("", "empty"),
    ("a\0b", "NUL"),
])
def test_resolve_inside_refuses_escapes(tmp_path, reference, why):
    with pytest.raises(InputError) as caught:
        fileio.resolve_inside(tmp_path, reference, file="scene.usda", location="/Anim.vb:texture")
    error = caught.value
    assert why in error.message and error.code == "path.unsafe"
    assert (error.file, error.location) == ("scene.usda", "/Anim.vb:texture")


def test_resolve_inside_refuses_symlinks_leaving_the_folder(tmp_path):
    inside, outside = tmp_path / "asset", tmp_path / "elsewhere"
    inside.mkdir()
    outside.mkdir()
    (outside / "t.exr").write_bytes(b"x")
    (inside / "link.exr").symlink_to(outside / "t.exr")
    (inside / "dir").symlink_to(outside)
    for reference in ("link.exr", "dir/t.exr"):
        with pytest.raises(InputError, match="symbolic link"):
            fileio.resolve_inside(inside, reference)
    # A link that stays inside is fine.
    (inside / "real.exr").write_bytes(b"y")
    (inside / "alias.exr").symlink_to(inside / "real.exr")
    assert fileio.resolve_inside(inside, "alias.exr") == (inside / "real.exr").resolve()


def test_outside_hint_is_the_callers_and_only_for_outside_paths(tmp_path):
    # The helper cannot know whether its caller offers a way to allow outside paths (validate does
    # not): without a hint the message suggests nothing; with one, every outside refusal carries it.
    inside = tmp_path / "asset"
    inside.mkdir()
    (inside / "link.exr").symlink_to(tmp_path / "t.exr")
    for reference in ("../x.exr", "/etc/passwd", "link.exr"):
        with pytest.raises(InputError) as caught:
            fileio.resolve_inside(inside, reference)
        assert "--" not in caught.value.message and "allow outside" not in caught.value.message
        with pytest.raises(InputError) as caught:
            fileio.resolve_inside(inside, reference, outside_hint="use --let-me")
        assert caught.value.message.endswith(" (use --let-me)"), caught.value.message
    with pytest.raises(InputError) as caught:  # a URI is refused whatever the caller allows
        fileio.resolve_inside(inside, "http://example.com/a.exr", outside_hint="use --let-me")
    assert "--let-me" not in caught.value.message


def test_allow_outside_accepts_paths_but_never_uris(tmp_path):
    inside = tmp_path / "asset"
    inside.mkdir()
    assert fileio.resolve_inside(inside, "../x.exr", allow_outside=True) == (tmp_path / "x.exr").resolve()
    assert fileio.resolve_inside(inside, str(tmp_path / "y.exr"), allow_outside=True) == \
        (tmp_path / "y.exr").resolve()
    with pytest.raises(InputError, match="scheme"):
        fileio.resolve_inside(inside, "https://example.com/x.exr", allow_outside=True)
