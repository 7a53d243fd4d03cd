"""Imported once, by the forkserver that starts isolated solves
(:mod:`c3bench.solvers.child_process`): loads the registry, the backend modules and the installed
solver packages, so that every child starts with them in memory.

Only imports: nothing here may start a thread (the forkserver forks its children).
"""

from c3bench.solvers.child_process import preload_solvers

preload_solvers()
