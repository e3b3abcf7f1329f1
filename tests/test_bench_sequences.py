"""``proxpose bench --sequences``: the tracker and chained estimates on the same sequences."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.test_bench import proxpose


def test_bench_sequences_rejects_an_unknown_motion(tmp_path: Path) -> None:
    out = proxpose("bench", "--sequences", "approach,spiral", "--output", str(tmp_path))
    assert out.returncode == 2
    assert "spiral" in out.stderr and "approach" in out.stderr


@pytest.mark.slow
def test_bench_sequences_pairs_the_tracker_with_chained_estimates(tmp_path: Path) -> None:
    out = proxpose(
        "bench", "--sequences", "approach", "--models", "demo", "--frames", "4", "--size", "128",
        "--references", "tone", "--output", str(tmp_path), timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "sequences.json").read_text())
    assert [(r["model"], r["motion"], r["reference"], r["method"]) for r in rows] == [
        ("demo", "approach", "tone", "track"),
        ("demo", "approach", "tone", "chained"),
    ]
    track, chained = rows
    assert track["frames"] == chained["frames"] == 4
    # every chained frame is a full estimate; one that fails (at 128 px the demo satellite far
    # down the approach can show too few features) is recorded lost, the bench goes on
    assert chained["reinitialised"] + chained["lost"] == 4 and chained["reinitialised"] >= 1
    assert track["tracked"] >= 1
    assert track["render_cost_per_frame"] < chained["render_cost_per_frame"]
    assert "| demo | approach | tone | track |" in (tmp_path / "sequences.md").read_text()
