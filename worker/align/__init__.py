"""The alignment pipeline: from a reference image and an initial guess to the pose.

Features and how a render measures them (:mod:`~worker.align.features`,
:mod:`~worker.align.edges`, :mod:`~worker.align.tracked`), the learned Jacobian
(:mod:`~worker.align.jacobian`, :mod:`~worker.align.learning`), Levenberg–Marquardt steps and
robust weights (:mod:`~worker.align.lm`), PnP on ray-cast correspondences
(:mod:`~worker.align.pnp`), the sun's tilt as two more unknowns (:mod:`~worker.align.sunfit`),
the state of one estimate (:mod:`~worker.align.session`), the coarse and refinement stages
(:mod:`~worker.align.coarse`, :mod:`~worker.align.refine`), the pipeline that runs them
(:mod:`~worker.align.estimator`) and the images that show the fit
(:mod:`~worker.align.artifacts`). The method is summarised in ``docs/method.md``.
"""
