"""Cases written for replay: the reference and a request per method, which ``proxpose
estimate`` runs again (the bench's failed cases, or all of them with ``--save-cases all``)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

from schemas.options import EstimateOptions
from worker.bench.synth import Case, from_truth

#: Where failed cases are written, under the output directory.
CASES_DIRNAME = "cases"


class _Method(Protocol):
    @property
    def label(self) -> str: ...

    def options(self, **extra: Any) -> EstimateOptions: ...


class _Task(Protocol):
    """What of a worker.bench.cases.CaseTask saving needs (that module imports this one)."""

    @property
    def model_path(self) -> str: ...
    @property
    def output_dir(self) -> str | None: ...
    @property
    def save_cases(self) -> str: ...
    @property
    def methods(self) -> Sequence[_Method]: ...
    @property
    def case_id(self) -> str: ...


def save_case(task: _Task, case: Case, records: list[dict[str, Any]]) -> None:
    """Write the reference and one request per method (``proxpose estimate`` replays them);
    with ``save_cases="failed"`` only cases some method did not solve, and their records get a
    ``reproduce`` command line."""
    from worker.bench.stats import is_success

    chosen = [r for r in records if task.save_cases == "all" or not is_success(r)]
    if not chosen or task.output_dir is None:
        return
    import cv2

    folder = Path(task.output_dir) / CASES_DIRNAME / task.case_id
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "reference.png"), case.reference[..., ::-1])
    specs = {s.label: s for s in task.methods}
    for record in chosen:
        spec = specs[record["method"]]
        # an estimate from the truth replays from the truth, each seed's with its seed
        truth = record.get("start") == "truth"
        tag = ("_truth" if truth else "") + (
            f"_seed{record['seed_index']}" if record.get("seed_index") else ""
        )
        name = "request_" + re.sub(r"[^A-Za-z0-9]+", "_", spec.label) + tag + ".json"
        options = spec.options(seed=record["estimator_seed"])
        started = from_truth(case) if truth else case
        request = started.request.model_copy(update={"options": options})
        (folder / name).write_text(request.model_dump_json(indent=2, exclude_unset=True))
        rel = os.path.relpath(folder, task.output_dir)
        record["reproduce"] = (
            f"proxpose estimate --model {task.model_path} --image {rel}/reference.png "
            f"--request {rel}/{name} --output {rel}/{Path(name).stem.replace('request_', 'out_')}"
        )
