"""Which of the localizer's estimates a place keeps as its recorded pose (issue 34's hybrid map).

The places record the pose at which their frames were seen while the localizer says ``localized``. But the monitor's
evidence against an estimate arrives late: its rivals weigh a pose elsewhere over ``rival_frames`` frames, so a
wrong convergence is called ``localized`` until the frames after it show a pose elsewhere explaining them better -
on the shared table tops' mapping laps for 1-69 frames at a time, every such stretch wrong from its first frame.
``PoseRecorder`` therefore

* commits an estimate only once the localizer has stayed ``localized`` for ``commit_after`` further estimates (the
  monitor's ``rival_frames``: the window in which its rivals could still speak against it), and drops the
  estimates still pending when the state leaves ``localized``;
* with ``retract``, judges a localized stretch that ended when the next one begins: carried along the odometry
  from the stretch's last estimate, does the new estimate lie on the same track? A filter that comes back to the
  same track - within three spreads of either hypothesis, at least ``same_track_xy`` / ``same_track_theta``, as the
  monitor counts a rival - (a false alarm: on the table tops a pose elsewhere fits ten frames 9:1 better than a correct estimate
  on 7-26 % of the frames) keeps the stretch, which joins the new one as one track (withdrawn with it if that is
  abandoned later); one that comes back elsewhere - farther than ``same_track_xy`` or turned more than
  ``same_track_theta`` - has abandoned that hypothesis for another, and the stretch's poses are withdrawn (a
  pose graph's outlier rejection, with the odometry as the edge). Without odometry across the gap the stretch is
  kept, and judged no more.

A robot kidnapped, or carried off a track without odometry, looks the same as an abandoned hypothesis: the stretch
before is withdrawn (measured in docs/results). A restart without the pose (the localizer initialising again) ends
a stretch without judging it: it is no evidence against the stretch.

Pure bookkeeping on keys (frame indices in the evaluation, capture stamps in the loop-closure worker): the caller
applies what ``update`` returns to its own per-frame poses, so the evaluation and the worker keep the same poses.
``commit_after=0`` without ``retract`` records every localized estimate at once (the earlier rule).
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import asdict

import numpy as np
from pydantic import Field

from semloc_core.geometry import wrap_angle
from semloc_core.localization.filter import compose_motion
from semloc_core.settings import settings

MAX_TRACK_KEYS = 100_000  # keys of a track remembered for withdrawal (about 3 h of estimates at 10 Hz): older stay


@settings
class PlacePoseConfig:
    """Which localized estimates the places keep (``PoseRecorder``)."""

    commit_after: int | None = Field(None, ge=0, description="an estimate is recorded once the localizer has "
                                     "stayed localized for this many further estimates (default: the health "
                                     "monitor's rival_frames, the window its rivals weigh an estimate over); 0: at "
                                     "once")
    retract: bool = Field(True, description="a localized stretch after which the localizer comes back localized "
                          "off the stretch's track (carried along the odometry) withdraws the poses it recorded")
    same_track_xy: float | None = Field(None, gt=0, description="farther than this (m) from the last stretch's "
                                        "track: another hypothesis (default: the monitor's 'elsewhere', three of "
                                        "the filter's converged_xy_std)")
    same_track_theta: float | None = Field(None, gt=0, description="... or turned more than this (rad; default "
                                           "three of the filter's converged_theta_std)")

    def to_dict(self) -> dict:
        return asdict(self)


class PoseRecorder:
    """See the module docstring; ``rival_frames``, ``elsewhere_xy``, ``elsewhere_theta``: the monitor's (its
    defaults when None), the defaults of ``commit_after``, ``same_track_xy`` and ``same_track_theta``.
    ``update(key, pose, localized, initialising, moved, spread)`` per estimate, in the localizer's order, ``moved``
    the odometry (dx, dy, dθ in the body frame) since the previous estimate (None: unknown), ``spread`` its
    hypothesis's (position std m, heading std rad; ``health.hypothesis_spreads``); returns ``(committed,
    retracted)``: the (key, pose) pairs a place may now keep, and the keys whose pose it must forget."""

    def __init__(self, config: PlacePoseConfig | None = None, rival_frames: int | None = None,
                 elsewhere_xy: float | None = None, elsewhere_theta: float | None = None):
        from semloc_core.localization.filter import FilterConfig
        from semloc_core.localization.health import HealthConfig

        self.config = c = config or PlacePoseConfig()
        self.commit_after = int(c.commit_after if c.commit_after is not None else
                                rival_frames if rival_frames is not None else HealthConfig().rival_frames)
        self.retract = c.retract
        self.same_track_xy = c.same_track_xy or elsewhere_xy or 3 * FilterConfig().converged_xy_std
        self.same_track_theta = c.same_track_theta or elsewhere_theta or 3 * FilterConfig().converged_theta_std
        self.pending: list[tuple[Hashable, np.ndarray]] = []  # localized estimates not yet followed far enough
        self.stretch: list[Hashable] = []  # keys committed since the current localized stretch began
        self.localized = False  # the last estimate was
        self.ended: list[Hashable] = []  # keys the last ended stretch committed, judged when the next one begins
        self.carried: np.ndarray | None = None  # that stretch's last estimate carried along the odometry since
        self.last_spread = self.ended_spread = np.zeros(2)  # hypothesis spreads (xy m, theta rad) of those estimates

    def update(self, key: Hashable, pose, localized: bool, initialising: bool = False, moved=None,
               spread=None) -> tuple[list, list]:
        pose = np.asarray(pose, dtype=np.float64).reshape(3)
        spread = np.zeros(2) if spread is None else np.asarray(spread, dtype=np.float64).reshape(2)
        if self.carried is not None:
            self.carried = None if moved is None else compose_motion(self.carried, np.asarray(moved, np.float64))
        retracted: list = []
        if not localized:
            if self.localized and not initialising:  # a stretch ends: judged when the next begins
                self.ended, self.carried, self.ended_spread = self.stretch, self.last_pose, self.last_spread
            elif initialising:
                self.ended, self.carried = [], None
            self.pending, self.stretch, self.localized = [], [], False
            return [], []
        if not self.localized:  # a stretch begins: on the ended one's track (one hypothesis), or another
            if self.retract and self.ended and self.carried is not None:
                if self._elsewhere(pose, self.carried, np.maximum(spread, self.ended_spread)):
                    retracted = self.ended
                else:  # the same track goes on: withdrawn with this stretch if that is abandoned later
                    self.stretch = self.ended
            self.ended, self.carried = [], None
        self.localized, self.last_pose, self.last_spread = True, pose, spread
        self.pending.append((key, pose.copy()))
        due = max(len(self.pending) - self.commit_after, 0)  # followed by commit_after localized estimates
        committed, self.pending = self.pending[:due], self.pending[due:]
        self.stretch.extend(k for k, _ in committed)
        if len(self.stretch) > MAX_TRACK_KEYS:
            del self.stretch[:len(self.stretch) - MAX_TRACK_KEYS]
        return committed, retracted

    def _elsewhere(self, pose: np.ndarray, track: np.ndarray, spread: np.ndarray) -> bool:
        """Beyond three spreads of either hypothesis (at least ``same_track_*``), as the monitor's rivals count."""
        reach_xy, reach_theta = max(self.same_track_xy, 3 * spread[0]), max(self.same_track_theta, 3 * spread[1])
        return bool(math.hypot(pose[0] - track[0], pose[1] - track[1]) > reach_xy
                    or abs(float(wrap_angle(pose[2] - track[2]))) > reach_theta)

    def snapshot(self) -> dict:
        return {"pending": [[k, p.tolist()] for k, p in self.pending], "stretch": list(self.stretch),
                "localized": self.localized, "last_pose": None if not self.localized else self.last_pose.tolist(),
                "ended": list(self.ended), "carried": None if self.carried is None else self.carried.tolist(),
                "spreads": [self.last_spread.tolist(), self.ended_spread.tolist()]}

    def restore(self, snapshot: dict) -> None:
        pending = [(k, np.asarray(p, dtype=np.float64).reshape(3)) for k, p in snapshot.get("pending", [])]
        poses = [p for _, p in pending] + [np.asarray(snapshot[name], dtype=np.float64).reshape(3)
                                            for name in ("last_pose", "carried") if snapshot.get(name) is not None]
        if not all(np.isfinite(p).all() for p in poses):
            raise ValueError("pose recorder snapshot: poses must be finite")
        self.pending, self.stretch = pending, list(snapshot.get("stretch", []))
        self.localized = bool(snapshot.get("localized", False)) and snapshot.get("last_pose") is not None
        if self.localized:
            self.last_pose = np.asarray(snapshot["last_pose"], dtype=np.float64).reshape(3)
        self.ended = list(snapshot.get("ended", []))
        carried = snapshot.get("carried")
        self.carried = None if carried is None else np.asarray(carried, dtype=np.float64).reshape(3)
        spreads = np.asarray(snapshot.get("spreads", np.zeros((2, 2))), dtype=np.float64).reshape(2, 2)
        if not np.isfinite(spreads).all() or (spreads < 0).any():
            raise ValueError("pose recorder snapshot: spreads must be finite and >= 0")
        self.last_spread, self.ended_spread = spreads[0], spreads[1]
