"""Accuracy of every encoding x texel format on the stadium-crowd sample.

This file is the command line (usage: benchmarks/README.md); the harness itself, with its full
description, is tests/helpers/accuracy.py, importable by the tests that check its logic
(tests/test_samples_accuracy.py).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: tests.helpers and vbusd

from tests.helpers.accuracy import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
