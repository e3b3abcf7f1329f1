"""The terrain band of `proxpose bench` (worker/bench/terrain.py), end to end on the quick suite."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_bench import QUICK_TIMEOUT_S, proxpose


@pytest.mark.slow
def test_quick_bench_with_the_terrain_band(tmp_path: Path) -> None:
    """--terrain adds the terrain and the held-out ridged terrain beside the demo satellite's
    band: their cases in the terrain band, from the guess and from the truth, reported apart."""
    out = proxpose(
        "bench",
        "--quick",
        "--terrain",
        "--methods",
        "default",
        "--output",
        str(tmp_path / "out"),
        env={"PROXPOSE_DATA_DIR": str(tmp_path / "data")},
        timeout=QUICK_TIMEOUT_S,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    data = json.loads((tmp_path / "out" / "bench.json").read_text())
    terrain = [r for r in data["cases"] if r["reference"] == "terrain"]
    assert {(r["model"], r["start"]) for r in terrain} == {
        (m, s) for m in ("terrain", "terrain-ridged") for s in ("offset", "truth")
    }
    assert all(2.0 < r["initial_rotation_deg"] <= 6.0 for r in terrain if r["start"] == "offset")
    assert [g["group"] for g in data["summary"]["by_band"]] == [3.0, 10.0, 20.0]  # demo only
    assert [g["group"] for g in data["summary"]["by_terrain"]] == ["terrain", "terrain-ridged"]
    md = (tmp_path / "out" / "bench.md").read_text()
    assert "### Terrain band" in md and "#### `terrain-ridged`" in md
