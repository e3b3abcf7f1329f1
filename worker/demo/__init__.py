"""The procedural demo satellite, the quick-start target registered as ``demo-sat``.

:mod:`~worker.demo.satellite` assembles it from a table of parts and writes the GLB,
:mod:`~worker.demo.geometry` holds the mesh primitives and :mod:`~worker.demo.textures` the
seeded procedural textures.
"""
