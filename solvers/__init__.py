"""Solvers of the C3 / C3+ subproblems and the registry that runs them.

* :mod:`~c3bench.solvers.base`: the contract (``Settings``, ``Result``, ``Backend``);
* :mod:`~c3bench.solvers.registry`: backend discovery and the guarded, in-process ``solve``;
* :mod:`~c3bench.solvers.isolation`: the benchmark's solve (warm-up, repeats, a child process
  killed on overrun) and ``IsolatedBackend`` for control loops; the child's plumbing is
  :mod:`~c3bench.solvers.child_process`;
* :mod:`~c3bench.solvers.backends`: the registry adapters, one module per solver family;
* algorithms of our own: :mod:`~c3bench.solvers.equilibrated` (equilibrated Schur
  complement), :mod:`~c3bench.solvers.lcp` (Lemke, projected Gauss-Seidel),
  :mod:`~c3bench.solvers.projection` (C3+'s closed-form projection),
  :mod:`~c3bench.solvers.modes` (complementarity modes, brute-force reference),
  :mod:`~c3bench.solvers.c3` (the C3 / C3+ ADMM controller), :mod:`~c3bench.solvers.fast`
  and :mod:`~c3bench.solvers.fast_jax` (batched C3+ with a Riccati QP step);
* measurement: :mod:`~c3bench.solvers.residuals`, :mod:`~c3bench.solvers.conditioning`,
  :mod:`~c3bench.solvers.timing`, :mod:`~c3bench.solvers.output` (stdout silencer).
"""
