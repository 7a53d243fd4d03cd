"""Registry adapters, one module per solver family (qpsolvers' grain).

Every public module here registers its backends on import
(:func:`c3bench.solvers.registry.register`); the registry imports them all on first use, found
with :func:`pkgutil.iter_modules` (no hand-kept list). Modules whose name starts with ``_`` are
shared helpers and are not imported by the discovery:

=======================  ===================================================================
``osqp_backend``         ``osqp`` (Stellato et al. 2020)
``clarabel_backend``     ``clarabel`` (Goulart and Chen 2024)
``proxqp_backend``       ``proxqp_dense``, ``proxqp_sparse`` (Bambade et al. 2022)
``qpsolvers_backends``   ``daqp``, ``piqp``, ``highs``, ``quadprog``, ``scs``, ``qpalm``
                         through qpsolvers (Caron et al. 2024)
``casadi_conic``         ``casadi_qpoases`` (Ferreau et al. 2014), ``casadi_hpipm`` (Frison
                         and Diehl 2020)
``kkt``                  ``equilibrated_kkt``, ``equilibrated_kkt_noridge``, ``schur_plain``,
                         ``kkt_ldl``: direct solves of the equality-constrained QPs
``c3plus_riccati``       ``c3plus_riccati``: the C3+ QP step by a Riccati recursion
``lcp``                  ``lemke`` (Lemke 1965), ``pgs`` (Cottle, Pang and Stone 1992)
``c3plus_closed_form``   ``c3plus_closed_form``: C3+'s projection in closed form
``scip_backend``         ``scip`` (SCIP through PySCIPOpt, Maher et al. 2016)
``gurobi_backend``       ``gurobi`` (Gurobi, licence permitting)
``bonmin_backend``       ``bonmin`` (Bonami et al. 2008, through CasADi)
``ipopt_mpcc``           ``ipopt_scholtes`` (Scholtes 2001), ``ipopt_penalty`` (Hu and
                         Ralph 2004), IPOPT (Wächter and Biegler 2006) through CasADi
``c3_admm``              ``c3plus_admm``, ``c3_admm``: the controller as an ``mpcc`` solver
``cvxpy_backend``        ``cvxpy_clarabel``, ``cvxpy_osqp``, ``cvxpy_scip``: through a CVXPY
                         problem compiled once per shape (Diamond and Boyd 2016)
``_qp_forms``            helpers of the convex QP adapters (two-sided and cone forms)
``_miqp``                helpers of the MIQP adapters (polishing, the final check)
=======================  ===================================================================

Full references are in each module's docstring. No module imports a solver package at
module level (CasADi-, Gurobi- and SCIP-based backends import it inside their functions), so
discovery never loads MuJoCo or CasADi.
"""
