"""c3bench: which solver should sit inside a contact-implicit MPC controller, and why does it fail?

The installed package maps three folders of the repository:

* ``c3bench.problems`` (``problems/``): the plant-free core (``Problem``, ``LCS``, layouts,
  names, errors) and, beside it, the MuJoCo scene, linearisers, MPC, families and suites;
* ``c3bench.solvers`` (``solvers/``): the solver contract, residuals, registry and backends;
* ``c3bench.bench`` (``bench/``): runner, metrics, results store, report, plots and the CLI.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("c3bench")
except PackageNotFoundError:  # pragma: no cover - running from a tree that is not installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
