"""The worker side of proxpose: the estimation engine, the command line and the RQ worker.

Subpackages by concern: :mod:`worker.engine` (pose math, camera, images, photometry, model
loading, Mitsuba rendering, metrics, the named errors), :mod:`worker.align` (the alignment
pipeline: features, the learned Jacobian, Levenberg–Marquardt, PnP, the sun fit, the coarse
and refinement stages, the estimator and its artifacts), :mod:`worker.jobs` (the worker
process: the RQ job functions, lease keeping, the model file cache, ``proxpose worker``),
:mod:`worker.bench` (``proxpose bench``) and :mod:`worker.demo` (the procedural demo
satellite). :mod:`worker.entry` holds the entry points the CLI and the jobs share (bytes and
JSON in, result out) and :mod:`worker.cli` the ``proxpose`` command.
"""
