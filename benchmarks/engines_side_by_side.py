"""vbusd's three.js and Babylon.js runtimes beside each engine's own way, same character, same browser (issue 27).

This file is the command line (usage: benchmarks/README.md); the harness itself, with its full
description, is tests/helpers/engines_side_by_side.py, importable by the tests that check its logic
(tests/test_engines_side_by_side.py).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: tests.helpers and vbusd

from tests.helpers.engines_side_by_side import main  # noqa: E402

if __name__ == "__main__":
    main()
