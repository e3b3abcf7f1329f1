"""What a tracked frame hands to the next (worker.align.tracker), and how its LM judged the
rows it carried."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from worker.align.learning import learn_at_pose
from worker.align.refine import StageState
from worker.align.session import Session
from worker.align.tracked import TrackedFeatures

Array = NDArray[np.float64]
Pose = tuple[Array, Array]


@dataclass
class Memory:
    """What a frame hands to the next."""

    state: StageState
    learned_pose: Pose  # where the Jacobian was learned
    learned_features: int  # how many features it was learned for
    session: Session = field(repr=False)

    @classmethod
    def learned_here(cls, state: StageState, session: Session) -> Memory:
        """``state``, its Jacobian learned at ``session``'s pose."""
        return cls(state, (session.R, session.t), int(state.ok.sum()), session)


def mispredicted(session: Session) -> bool:
    """Whether the frame's LM rejected a trial (recorded unaccepted and without a step): the
    carried rows promised a cost the render did not show. Rows learned where the target looked
    otherwise can fit a pose degrees off along a weakly seen rotation (an Aura tumble at 2° a
    frame: frame 1 ended 1.56° off at a feature cost of 0.0017 px²); rows and features made
    afresh there moved it back to 0.33° (bench/README.md, "A rejected trial learns the rows
    again")."""
    return any(not r.accepted and r.step_norm == 0.0 for r in session.history)


def fresh_state(session: Session) -> StageState:
    """Features made afresh at the session's pose and their Jacobian learned there."""
    view = session.current_view()
    features = TrackedFeatures(session, view)
    h, ok = features.measure(view, None)
    learned = learn_at_pose(session, h, features.feature_normals)
    return StageState(features, h, ok, learned, learned_at=view, level=view.level)
