"""Which shading normals explain the image: the model file's, or each triangle's own.

A model tessellated differently from the surface that made the image (a real spacecraft, or a
renderer that shades each facet flat) shades differently from our render, and a feature's place
in the image moves with its shading: on references rendered with flat facets, renders with the
file's smooth normals drifted twice as far from the true pose as renders shaded flat, and the
other way round. Near the answer (after the coarse stage) the current pose is rendered both
ways and the refinement goes on with the render that explains the reference better (alignment
score). A model without vertex normals renders flat either way: nothing to choose.
"""

from __future__ import annotations

from collections.abc import Callable

from worker.align.session import Session
from worker.engine.photometry import alignment_score
from worker.engine.renderer import Renderer

#: Shading normals a renderer can be built with, from a ``shading`` name.
RendererFor = Callable[[str], Renderer]


def choose_shading(session: Session, renderer_for: RendererFor) -> str:
    """Keep the session's renderer, or switch it to the other shading normals if their render
    at the current pose aligns better with the reference; returns the shading in use."""
    current = session.renderer
    if not current.model.has_vertex_normals:
        return current.shading
    other = renderer_for("faceted" if current.shading == "file" else "file")
    with session.timed("match"):
        score_now = alignment_score(session.ref_grey, session.current_view().grey)
    here = session.current_view()
    session.use_renderer(other)
    candidate = session.current_view()
    with session.timed("match"):
        score_other = alignment_score(session.ref_grey, candidate.grey)
    if score_other <= score_now:
        session.use_renderer(current)
        session.current = here
    return session.renderer.shading
