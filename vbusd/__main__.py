"""``python -m vbusd``: the same as the ``vbusd`` command."""

import sys

from vbusd.cli import main

sys.exit(main())
