"""c3bench: which solver should sit inside a contact-implicit MPC controller, and why does it fail?

The installed package maps three folders of the repository:

* ``c3bench.problems`` (``problems/``): the plant-free core (``Problem``, ``LCS``, MPC cost and
  horizon layout, family builders, capture types, names, errors; listed in
  ``c3bench.problems.CORE_MODULES``) and, beside it, the MuJoCo scene, linearisers and suites;
* ``c3bench.solvers`` (``solvers/``): the solver contract, residuals, registry and backends;
* ``c3bench.bench`` (``bench/``): runner, metrics, results store, report, plots and the CLI.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("c3bench")
except PackageNotFoundError:  # pragma: no cover - running from a tree that is not installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
