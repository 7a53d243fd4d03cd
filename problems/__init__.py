"""The cube-tipping problem generator: scene, LCS, MPC, subproblem families and suites.

Two layers:

* the **plant-free core** (:data:`CORE_MODULES`): names and errors, the task constants, the LCS
  types and formulas, the MPC cost and horizon layout, the ``Problem`` contract and its storage,
  the family builders and the capture types. It imports neither MuJoCo nor CasADi, nor any
  module outside the core, so solvers and forked solves can load it without the plant;
* the **plant side**: the MuJoCo scene (:mod:`~c3bench.problems.scene`), the linearisation
  (:mod:`~c3bench.problems.linearize`, :mod:`~c3bench.problems.linearize_batch`) and the suite
  generator (:mod:`~c3bench.problems.suites`).

``tests/test_layers.py`` checks the boundary (and that nothing in ``c3bench.problems`` imports
``c3bench.solvers`` or ``c3bench.bench``).
"""

import ctypes.util
import os

CORE_MODULES: tuple[str, ...] = (
    "c3bench.problems",
    "c3bench.problems.names",
    "c3bench.problems.errors",
    "c3bench.problems.config",
    "c3bench.problems.limits",
    "c3bench.problems.lcs",
    "c3bench.problems.mpc",
    "c3bench.problems.instance_contract",
    "c3bench.problems.instance",
    "c3bench.problems.families",
    "c3bench.problems.capture",
    "c3bench.problems.jit",
)
"""The plant-free core: these modules import only each other, the standard library, numpy and
(:mod:`~c3bench.problems.jit`, the compiled kernels' one decorator) numba; never MuJoCo, CasADi
or a plant-side module."""

# Off-screen rendering: prefer EGL (headless; works with Mesa's software driver) when libEGL is
# installed and the user chose no backend. MuJoCo reads this when it is first imported, so it is
# set here, before any submodule imports mujoco.
if "MUJOCO_GL" not in os.environ and ctypes.util.find_library("EGL"):
    os.environ["MUJOCO_GL"] = "egl"
