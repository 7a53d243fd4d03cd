"""``python -m c3bench``: the ``c3bench`` command line."""

import sys

from c3bench.bench.cli import main

sys.exit(main())
