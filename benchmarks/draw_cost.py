"""Draw-time cost of Virtual Bones against the alternatives, in a real OpenGL pipeline (issue 18).

This file is the command line (usage: benchmarks/README.md); the harness itself, with its full
description, is tests/helpers/draw_cost.py, importable by the tests that check its logic
(tests/test_draw_cost.py).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: tests.helpers and vbusd

from tests.helpers.draw_cost import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
