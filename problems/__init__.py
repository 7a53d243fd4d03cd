"""The cube-tipping problem generator: scene, LCS, MPC, subproblem families and suites."""

import ctypes.util
import os

# Off-screen rendering: prefer EGL (headless; works with Mesa's software driver) when libEGL is
# installed and the user chose no backend. MuJoCo reads this when it is first imported, so it is
# set here, before any submodule imports mujoco.
if "MUJOCO_GL" not in os.environ and ctypes.util.find_library("EGL"):
    os.environ["MUJOCO_GL"] = "egl"
