"""``python -m vbusd.cli``: the same command line as ``vbusd`` and ``python -m vbusd``."""

import sys

from vbusd.cli import main

sys.exit(main())
