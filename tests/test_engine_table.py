"""docs/engines.md's feature x engine table is the one scripts/engine_table.py renders from the
recorded parity run (docs/engine-parity.json, written by ``pytest tests/test_browser_parity.py
--parity-json docs/engine-parity.json``), and no cell of it is empty or failed."""

from __future__ import annotations

import json
from pathlib import Path

from tests.helpers import scripts

REPO = Path(__file__).resolve().parents[1]
table = vars(scripts.load("scripts/engine_table.py"))


def test_committed_table_is_the_rendered_one():
    assert table["main"](["--check"]) == 0, "run python scripts/engine_table.py"


def test_every_cell_says_something_and_none_failed():
    recorded = json.loads((REPO / "docs" / "engine-parity.json").read_text(encoding="utf-8"))
    rendered = table["render"](recorded)
    for row in rendered.splitlines()[2:]:
        cells = [c.strip() for c in row.strip("|").split(" | ")]
        assert len(cells) == 1 + len(table["ENGINES"]), row
        assert all(cells), row
        assert not any(c.startswith(("FAILED", "not run")) for c in cells), row
