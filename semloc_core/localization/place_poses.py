"""Which of the localizer's estimates a place keeps as its recorded pose (issue 34's hybrid map).

The places record the pose at which their frames were seen while the localizer says ``localized``. But the monitor's
evidence against an estimate arrives late: its rivals weigh a pose elsewhere over ``rival_frames`` frames, so a
wrong estimate is called ``localized`` until the frames after it show a pose elsewhere explaining them better (or
the estimate jumps, or widens). ``PoseRecorder`` therefore commits an estimate only once the localizer has stayed
``localized`` for ``commit_after`` further estimates (the monitor's ``rival_frames``: the window in which its
rivals could still have spoken against it), drops the estimates still pending when the state leaves ``localized``,
and, with ``retract``, withdraws every pose committed since that stretch began: a stretch that ends in a jump, an
``uncertain`` or ``lost`` verdict may have been on the wrong pose for longer than the window (the evidence against
it is summed over the last frames only).

Pure bookkeeping on keys (frame indices in the evaluation, capture stamps in the loop-closure worker): the caller
applies what ``update`` returns to its own per-frame poses, so the evaluation and the worker keep the same poses.
``commit_after=0`` without ``retract`` records every localized estimate at once (the earlier rule). A restart
without the pose (the localizer initialising again) ends a stretch without withdrawing it.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import asdict

import numpy as np
from pydantic import Field

from semloc_core.settings import settings


@settings
class PlacePoseConfig:
    """Which localized estimates the places keep (``PoseRecorder``)."""

    commit_after: int | None = Field(None, ge=0, description="an estimate is recorded once the localizer has "
                                     "stayed localized for this many further estimates (default: the health "
                                     "monitor's rival_frames, the window its rivals weigh an estimate over); 0: at "
                                     "once")
    retract: bool = Field(True, description="a localized stretch that ends (uncertain, lost, a jump) withdraws the "
                          "poses it recorded: the evidence against a wrong pose may come later than the window")

    def to_dict(self) -> dict:
        return asdict(self)


class PoseRecorder:
    """See the module docstring; ``rival_frames``: the monitor's (its default when None), the default
    ``commit_after``. ``update(key, pose, localized)`` per estimate, in the localizer's order; returns
    ``(committed, retracted)``: the (key, pose) pairs a place may now keep, and the keys whose pose it must forget."""

    def __init__(self, config: PlacePoseConfig | None = None, rival_frames: int | None = None):
        self.config = config or PlacePoseConfig()
        if self.config.commit_after is None:
            from semloc_core.localization.health import HealthConfig

            rival_frames = HealthConfig().rival_frames if rival_frames is None else rival_frames
        self.commit_after = int(self.config.commit_after if self.config.commit_after is not None else rival_frames)
        self.retract = self.config.retract
        self.pending: list[tuple[Hashable, np.ndarray]] = []  # localized estimates not yet followed far enough
        self.stretch: list[Hashable] = []  # keys committed since the current localized stretch began

    def update(self, key: Hashable, pose, localized: bool, initialising: bool = False) -> tuple[list, list]:
        """``initialising``: the localizer restarted without its pose (a global initialisation): the stretch ends,
        what it left pending is dropped, and what it committed stays - a restart is no evidence against it."""
        if not localized:
            self.pending = []
            retracted = self.stretch if self.retract and not initialising else []
            self.stretch = []
            return [], retracted
        self.pending.append((key, np.asarray(pose, dtype=np.float64).reshape(3).copy()))
        due = max(len(self.pending) - self.commit_after, 0)  # followed by commit_after localized estimates
        committed, self.pending = self.pending[:due], self.pending[due:]
        self.stretch.extend(k for k, _ in committed)
        return committed, []

    def snapshot(self) -> dict:
        return {"pending": [[k, p.tolist()] for k, p in self.pending], "stretch": list(self.stretch)}

    def restore(self, snapshot: dict) -> None:
        pending = [(k, np.asarray(p, dtype=np.float64).reshape(3)) for k, p in snapshot.get("pending", [])]
        if not all(np.isfinite(p).all() for _, p in pending):
            raise ValueError("pose recorder snapshot: pending poses must be finite")
        self.pending, self.stretch = pending, list(snapshot.get("stretch", []))
