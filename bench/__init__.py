"""The benchmark (``c3bench.bench``), one job per module.

* :mod:`~c3bench.bench.cli`, :mod:`~c3bench.bench.cli_options`,
  :mod:`~c3bench.bench.cli_closed_loop`: the ``c3bench`` command line (one parser);
* :mod:`~c3bench.bench.runner`: the run loop, over :mod:`~c3bench.bench.planning` (cells,
  options), :mod:`~c3bench.bench.rows` (one cell's solve and row),
  :mod:`~c3bench.bench.executors` (local pool, Dask) and :mod:`~c3bench.bench.machine`;
* :mod:`~c3bench.bench.reference`: reference optima; :mod:`~c3bench.bench.metrics`: success
  and aggregates; :mod:`~c3bench.bench.store`: every stored table, its schema and version;
* :mod:`~c3bench.bench.report`, :mod:`~c3bench.bench.plots`, :mod:`~c3bench.bench.compare`:
  what the results say, with :mod:`~c3bench.bench.accuracy` (accuracy profiles, Pareto
  front, claimed-but-wrong cells), :mod:`~c3bench.bench.budgets` (control budget),
  :mod:`~c3bench.bench.report_accuracy` and :mod:`~c3bench.bench.tables` (report sections and
  tables), :mod:`~c3bench.bench.palette` and :mod:`~c3bench.bench.figure_base` (figure
  conventions), :mod:`~c3bench.bench.plots_time`, :mod:`~c3bench.bench.plots_accuracy` and
  :mod:`~c3bench.bench.plots_solver` (the figures);
* :mod:`~c3bench.bench.perf`: control-step timing, :mod:`~c3bench.bench.perf_store` its
  history; :mod:`~c3bench.bench.closed_loop`,
  :mod:`~c3bench.bench.closed_loop_suite`: the controllers driving the MuJoCo cube.
"""
