"""docs/api.md's examples run as written, in order, from a folder that holds the repository's
samples: the public API page cannot drift from the library (issue 10 item 5)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "api.md"


def _examples() -> list[str]:
    return re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), flags=re.S)


def test_the_page_shows_every_main_job():
    text = "\n".join(_examples())
    for job in ("convert", "read_asset", "write_asset", "validate", "skin", "decode", "Decoder", "shader",
                "build_crowd", "bone_transform"):
        assert f"vbusd.{job}(" in text, f"docs/api.md has no example of vbusd.{job}"


@pytest.mark.slow
def test_every_example_runs(tmp_path, monkeypatch):
    (tmp_path / "samples").symlink_to(ROOT / "samples", target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    # What an earlier run, or the README's commands (out/crowd.usda), left: the examples replace it.
    (tmp_path / "out").mkdir()
    for name in ("crowd.usda", "crowd_vb.usda", "crowd_cache.usda"):
        (tmp_path / "out" / name).write_text("#usda 1.0\n", encoding="utf-8")
    namespace: dict = {"__name__": "api_docs"}
    for number, code in enumerate(_examples(), 1):
        try:
            exec(compile(code, f"docs/api.md example {number}", "exec"), namespace)
        except Exception as error:  # name the example that broke
            raise AssertionError(f"docs/api.md example {number} failed: {error!r}\n{code}") from error
    # What the examples wrote, checked independently of the examples' own asserts.
    assert (tmp_path / "out" / "crowd_vb.usda").is_file() and (tmp_path / "out" / "crowd_cache.usda").is_file()
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "out" / "crowd.usda"))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert sum(len(UsdGeom.PointInstancer(p).GetPositionsAttr().Get()) for p in instancers) == 500
    assert os.listdir(tmp_path / "out" / "copy")
