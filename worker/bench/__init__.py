"""``proxpose bench``: our estimator and the baselines on the same seeded synthetic cases.

:mod:`~worker.bench.cli` is the command (arguments, serial or parallel runs),
:mod:`~worker.bench.config` the suites, the checked settings and the tasks,
:mod:`~worker.bench.cases` the models, cases and one estimate per method (with
:mod:`~worker.bench.records` and :mod:`~worker.bench.costs`: render-equivalents, memory),
:mod:`~worker.bench.synth` renders the references independently of the estimator,
:mod:`~worker.bench.references` the robustness suite's reference classes (most through the
independent ray tracer :mod:`~worker.bench.raytrace`), :mod:`~worker.bench.stats` the
statistics, :mod:`~worker.bench.report` the tables and the plot, :mod:`~worker.bench.outputs`
writes the files and :mod:`~worker.bench.sensor` compares Mitsuba's batch sensor with separate
renders. Nothing here is imported by the service or the worker process.
"""
