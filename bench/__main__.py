"""``python -m bench``: the ``c3bench`` command line."""

import sys

from bench.cli import main

sys.exit(main())
