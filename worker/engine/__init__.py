"""The engine: pose math and rendering, with no knowledge of features or of the alignment.

Attitude parameterisations and pose composition (:mod:`~worker.engine.posemath`), the pinhole
camera (:mod:`~worker.engine.camera`), image decoding and encoding (:mod:`~worker.engine.images`),
bringing a reference and a render onto one photometric scale
(:mod:`~worker.engine.photometry`), model loading (:mod:`~worker.engine.meshes`), Mitsuba
rendering and ray casting (:mod:`~worker.engine.renderer`, :mod:`~worker.engine.variant`), the
error metrics (:mod:`~worker.engine.metrics`) and the named errors every layer above raises
(:mod:`~worker.engine.exceptions`). Importing any of them neither imports Mitsuba nor picks a
variant.
"""
