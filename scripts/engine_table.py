"""Render docs/engines.md's feature x engine table from what the browser tests ran.

``pytest tests/test_browser_parity.py tests/test_browser_lod.py tests/test_conformance_browser.py --parity-json
docs/engine-parity.json`` records, for every
test marked ``@pytest.mark.parity(feature)``, the cell (feature, engine) it probed and its outcome
(passed, failed, skipped with the reason). This script renders those cells, together with the
rows other test modules cover (:data:`ELSEWHERE`: each names the test that probes it) and the
cells no test can fill yet (:data:`NOT_YET`, each saying why), into the table between the
``<!-- engine-table:begin -->`` and ``<!-- engine-table:end -->`` markers of docs/engines.md.

    python scripts/engine_table.py          # rewrite the table in docs/engines.md
    python scripts/engine_table.py --check  # exit 1 when the committed table differs

tests/test_engine_table.py runs the check, so the committed table is always the recorded run's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "engines.md"
RECORD = REPO / "docs" / "engine-parity.json"
BEGIN, END = "<!-- engine-table:begin -->", "<!-- engine-table:end -->"
ENGINES = (("three", "three.js WebGL"), ("three-webgpu", "three.js WebGPU"), ("babylon", "Babylon.js"))

# Rows in table order. Cells from the recorded parity run come first; then these.
FEATURES = (
    "float encodings, float16 / float32",
    "compact encoding (uint32)",
    "unorm16",
    "pulled skin binding",
    "crossfade, time-sampled fade (`--fade-window`)",
    "layers with masks",
    "Fox and CesiumMan: compact encoding, pulled binding, crossfade, sockets",
    "Fox and CesiumMan: layers with masks, levels of detail, root motion",
    "sockets",
    "root motion",
    "levels of detail",
    "glTF package through the engine's loader, mesh without normals",
    "glTF package carrying layers and crossfades",
    "conformance vectors (spec/conformance/)",
    "crowd variety",
    "previous pose (motion vectors)",
    "velocity output (motion vectors)",
    "blend spaces",
    "clip events",
    "additive layers",
)

# Cells probed by other modules (each against vbusd's decoder, within the same tolerances).
ELSEWHERE = {
    ("float encodings, float16 / float32", "three"): "test_browser.py",
    ("float encodings, float16 / float32", "three-webgpu"): "test_browser_webgpu.py",
    ("float encodings, float16 / float32", "babylon"): "test_browser_babylon.py",
}

# Cells no test fills yet, with the reason.
NOT_YET: dict = {}

PARITY = "test_browser_parity.py"


def cell_text(feature: str, engine: str, recorded: dict) -> str:
    cell = recorded.get(feature, {}).get(engine)
    if cell is not None:
        test = cell["test"]
        note = f": {cell['note']}" if cell.get("note") else ""
        if cell["outcome"] == "passed":
            return f"{test}{note}"
        if cell["outcome"] == "skipped":
            return f"skipped in the recorded run ({test}{note})"
        return f"FAILED in the recorded run ({test})"
    if (feature, engine) in ELSEWHERE:
        return ELSEWHERE[feature, engine]
    if (feature, engine) in NOT_YET:
        return NOT_YET[feature, engine]
    return "not run: no test probes this cell"


def render(recorded: dict) -> str:
    unknown = sorted(set(recorded) - set(FEATURES))
    if unknown:
        raise SystemExit(f"engine_table: recorded features not in FEATURES: {', '.join(unknown)}")
    lines = ["| feature | " + " | ".join(title for _, title in ENGINES) + " |",
             "|---|" + "---|" * len(ENGINES)]
    for feature in FEATURES:
        lines.append(f"| {feature} | " + " | ".join(cell_text(feature, engine, recorded).replace("|", "\\|")
                                                     for engine, _ in ENGINES) + " |")
    return "\n".join(lines)


def updated(text: str, table: str) -> str:
    if text.count(BEGIN) != 1 or text.count(END) != 1:
        raise SystemExit(f"engine_table: {DOC.name} must hold {BEGIN} and {END} once each")
    head, rest = text.split(BEGIN)
    _, tail = rest.split(END)
    return f"{head}{BEGIN}\n{table}\n{END}{tail}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/engines.md's table differs")
    args = parser.parse_args(argv)
    recorded = json.loads(RECORD.read_text(encoding="utf-8"))
    text = DOC.read_text(encoding="utf-8")
    new = updated(text, render(recorded))
    if args.check:
        if new != text:
            print(f"engine_table: the table in {DOC.relative_to(REPO)} differs from {RECORD.relative_to(REPO)}; "
                  "run python scripts/engine_table.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
