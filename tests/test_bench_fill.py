"""`proxpose bench --fill`: spacecraft cases at a chosen size, past the frame at docking range."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from test_bench import proxpose


def _border_lit(image: np.ndarray) -> int:
    """How many pixels on the frame's border show something brighter than the black sky."""
    border = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
    return int(np.sum(border.max(axis=1) > 40))


def test_a_docking_range_case_runs_past_the_frame(tmp_path: Path) -> None:
    """With fill 3 the demo satellite's reference runs past the frame's border, which the
    default size leaves black; the truth is drawn at a fifth of the default range."""
    from worker.bench.cases import CaseTask, build_case, parse_method, resolve_models
    from worker.engine.meshes import load_model
    from worker.entry import init_renderer_backend

    init_renderer_backend()
    ((_, path),) = resolve_models(["demo"], tmp_path, tmp_path, False)[0]
    model = load_model(path)
    cases = {}
    for fill in (0.6, 3.0):
        task = CaseTask(
            model="demo",
            model_path=str(path),
            band=3.0,
            band_lo=0.0,
            index=0,
            width_px=64,
            height_px=64,
            seed=1,
            offsets="uniform",
            methods=[parse_method("default")],
            fill=fill,
        )
        cases[fill], _ = build_case(task, model)
    assert _border_lit(cases[0.6].reference) == 0
    assert _border_lit(cases[3.0].reference) > 20
    ranges = {
        f: float(np.linalg.norm(c.R_true @ model.centre + c.t_true)) for f, c in cases.items()
    }
    assert ranges[3.0] == pytest.approx(ranges[0.6] * 0.6 / 3.0, rel=0.05)


def test_bench_config_records_the_fill_and_the_report_names_it() -> None:
    from worker.bench.cli import add_arguments
    from worker.bench.config import make_config
    from worker.bench.report import _fill_text

    parser = argparse.ArgumentParser()
    add_arguments(parser)  # the real options and their defaults
    args = parser.parse_args(["--quick", "--fill", "3"])
    config = make_config(args)
    assert config["fill"] == 3.0
    assert _fill_text(config) == "spacecraft 3 × the image side across (past the frame); "
    assert _fill_text({**config, "fill": 0.6}) == "" == _fill_text({})


@pytest.mark.parametrize("value", ["0", "-1", "20", "x"])
def test_bench_rejects_a_bad_fill(value: str) -> None:
    out = proxpose("bench", "--models", "demo", "--fill", value, "--output", "/nonexistent")
    assert out.returncode == 2
    assert "--fill" in out.stderr
