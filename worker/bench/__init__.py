"""``proxpose bench``: our estimator and the baselines on the same seeded synthetic cases.

:mod:`~worker.bench.cli` is the command (arguments, the suite, serial or parallel runs),
:mod:`~worker.bench.cases` the models, cases and one estimate per method,
:mod:`~worker.bench.synth` renders the references independently of the estimator,
:mod:`~worker.bench.report` summarises and plots, :mod:`~worker.bench.outputs` writes the files
and :mod:`~worker.bench.sensor` compares Mitsuba's batch sensor with separate renders. Nothing
here is imported by the service or the worker process.
"""
