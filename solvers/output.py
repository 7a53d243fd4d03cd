"""The one stdout silencer: C-level writes to file descriptor 1 go to ``/dev/null``.

Several solver libraries print from C or C++ straight to file descriptor 1, past Python's
``sys.stdout`` and ignoring their own log levels: qpOASES prints a banner whenever a solver is
constructed, HiGHS one on its first construction in a process, IPOPT and Bonmin their banners
and node logs, SoPlex (inside SCIP) tolerance warnings. Redirecting ``sys.stdout`` does not
catch them; duplicating the descriptor does.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def quiet_stdout() -> Iterator[None]:
    """Silence C-level writes to file descriptor 1 inside the block.

    Python's buffered ``sys.stdout`` is flushed before and after, so nothing printed from
    Python before the block is lost or lands inside it. Where descriptor 1 cannot be
    duplicated (a closed or replaced stdout, e.g. under some test runners) the block runs
    unchanged.
    """
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        with open(os.devnull, "w") as sink:
            os.dup2(sink.fileno(), 1)
            try:
                yield
            finally:
                with contextlib.suppress(OSError, ValueError, AttributeError):
                    sys.stdout.flush()
                os.dup2(saved, 1)
    finally:
        os.close(saved)
