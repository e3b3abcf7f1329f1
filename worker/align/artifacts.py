"""Images that show the fit, as the paper's figures do.

- ``final_render``: the render at the final pose (display-encoded colour).
- ``difference``: |reference − final render| after mapping the reference's tone curve onto the
  render's, colour-mapped; what remains is pose error, lighting mismatch and noise.
- ``overlay_1``, ``overlay_2``, ``overlay_final``: the reference in red and the render in blue
  at iteration 1 (the initial guess), 2 and the final one; aligned structure turns magenta.
- ``convergence``: rotation error, translation error (when the truth is known) and log cost per
  iteration.
"""

from __future__ import annotations

import io

import cv2
import numpy as np

from schemas.estimate import EstimateResult
from worker.align.session import RenderedView
from worker.engine.images import FloatImage, encode_png, to_display, to_grey
from worker.engine.photometry import reference_on_render_scale

#: Artifact names, in display order.
ARTIFACT_NAMES = (
    "overlay_1",
    "overlay_2",
    "overlay_final",
    "difference",
    "final_render",
    "convergence",
)


#: zlib level of the artifact PNGs: the fastest. An overlay of a noisy 1920×1200 reference
#: took 0.58 s at PIL's default (6) and 0.19 s at 1, for 1.18 → 1.54 MB (lossless either way);
#: the four full-size images were a second of every 1920×1200 job's time.
PNG_LEVEL = 1
#: Pixels above this fraction of a render's brightest show the target (the rest is sky).
SKY_LEVEL = 0.02


def _stretch(grey: FloatImage) -> FloatImage:
    top = float(np.percentile(grey, 99.8)) or 1.0
    return np.clip(grey / top, 0.0, 1.0)


def _to_size(image: FloatImage, shape: tuple[int, ...]) -> FloatImage:
    """``image`` resampled to the reference's (H, W): a view rendered at a coarse level."""
    if image.shape[:2] == shape[:2]:
        return image
    return cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def shows_sky(render_grey: FloatImage) -> bool:
    """Whether most of a render is background (an isolated target on the sky), rather than the
    target filling the frame (terrain, docking range)."""
    return float(np.mean(render_grey > SKY_LEVEL * float(render_grey.max()))) < 0.5


def overlay(reference: FloatImage, view: RenderedView) -> bytes:
    """Reference in red, render in blue (RGB PNG), each stretched black to white.

    The reference's black is its median when the render shows mostly sky (the noisy sky then
    turns black), else its darkest percentile: a frame full of ground has no sky to take it
    from, and its median would crush half the image to black."""
    reference_grey = to_grey(reference)
    render_grey = _to_size(view.grey, reference_grey.shape)
    sky = shows_sky(render_grey)
    black = float(np.percentile(reference_grey, 50.0 if sky else 1.0))
    ref = _stretch(np.clip(reference_grey - black, 0.0, None))
    floor = 0.0 if sky else float(np.percentile(render_grey, 1.0))
    ren = _stretch(np.clip(render_grey - floor, 0.0, None))
    rgb = np.stack([ref, np.zeros_like(ref), ren], axis=-1)
    return encode_png(rgb, compress_level=PNG_LEVEL)


def difference(reference: FloatImage, view: RenderedView) -> bytes:
    """|reference − render| on the render's tone scale, colour-mapped (inferno)."""
    diff = np.abs(reference_on_render_scale(reference, view.linear) - view.grey)
    top = max(float(np.percentile(view.grey, 99.8)), 1e-6)
    u8 = (np.clip(diff / top, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    bgr = cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO)
    return encode_png(np.ascontiguousarray(bgr[..., ::-1]), compress_level=PNG_LEVEL)


#: Convergence plot: one panel's width and the figure's height, and the margins, in inches.
#: Fixed margins, not ``tight_layout`` (which lays every tick label out twice: 0.3 s a plot).
PLOT_PANEL_IN, PLOT_HEIGHT_IN = 4.2, 3.2
PLOT_MARGINS_IN = {"left": 0.75, "right": 0.15, "bottom": 0.55, "top": 0.35, "between": 0.85}


def convergence_plot(result: EstimateResult) -> bytes:
    """Per-iteration rotation and translation error (when known) and log cost, PNG.

    Drawn on a bare matplotlib Figure (no pyplot: no global figure state in a worker, and
    faster to import)."""
    from matplotlib.figure import Figure

    hist = result.history
    it = [h.iteration for h in hist]
    known = result.errors is not None and result.initial_errors is not None
    panels = 3 if known else 1
    width, m = PLOT_PANEL_IN * panels, PLOT_MARGINS_IN
    fig = Figure(figsize=(width, PLOT_HEIGHT_IN), dpi=100)
    ax = fig.subplots(1, panels, squeeze=False)[0]
    fig.subplots_adjust(
        left=m["left"] / width,
        right=1.0 - m["right"] / width,
        bottom=m["bottom"] / PLOT_HEIGHT_IN,
        top=1.0 - m["top"] / PLOT_HEIGHT_IN,
        wspace=m["between"] / (PLOT_PANEL_IN - m["between"]),
    )
    if known:
        init = result.initial_errors
        assert init is not None
        rot = [init.rotation_deg] + [h.rotation_error_deg or 0.0 for h in hist]
        tra = [init.translation] + [h.translation_error or 0.0 for h in hist]
        ax[0].semilogy([0, *it], [max(v, 1e-5) for v in rot], "o-")
        ax[0].set(title="Rotation error", xlabel="iteration (0: initial guess)", ylabel="∠ΔR (deg)")
        ax[1].semilogy([0, *it], [max(v, 1e-9) for v in tra], "o-", color="tab:orange")
        ax[1].set(
            title="Translation error",
            xlabel="iteration (0: initial guess)",
            ylabel="‖Δt‖ (scene units)",
        )
    c = ax[-1]
    c.semilogy(it, [max(h.cost, 1e-9) for h in hist], "o-", color="tab:green")
    for h in hist:
        if not h.accepted:
            c.plot(h.iteration, max(h.cost, 1e-9), "x", color="tab:red")
    c.set(title="Cost (x: rejected step)", xlabel="iteration", ylabel="mean squared residual (px²)")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")  # a bare Figure draws with Agg
    return buf.getvalue()


def make_artifacts(
    result: EstimateResult, reference: FloatImage, views: dict[str, RenderedView]
) -> dict[str, bytes]:
    """All artifacts as PNG bytes, keyed by name (see ARTIFACT_NAMES)."""
    final = views["final"]
    return {
        "overlay_1": overlay(reference, views["first"]),
        "overlay_2": overlay(reference, views.get("second", final)),
        "overlay_final": overlay(reference, final),
        "difference": difference(reference, final),
        "final_render": encode_png(to_display(final.linear), compress_level=PNG_LEVEL),
        "convergence": convergence_plot(result),
    }
