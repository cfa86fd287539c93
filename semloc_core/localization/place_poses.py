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
a stretch without judging it: it is no evidence against the stretch. So does a new run of the estimates
(``restart``: a session replayed again), which also drops the estimates not yet committed.

With ``backfill``, a stretch's first committed pose is also carried back along the odometry to the estimates just
before it that hold no pose and were not ``localized`` (lost, uncertain: the filter searching there while the robot
was where the odometry says; a smoother's backward pass with the odometry as the only edge). The chain passes over
the localized estimates of a withdrawn stretch (or pending ones dropped) without giving them a pose: the localizer
judged them, and a withdrawal does not tell a wrong hypothesis from a kidnapping before which the track was right.
Its uncertainty grows by the localizer's motion noise (``increment_std`` of its motion model: alpha1..4 per
increment, as the filter spreads its particles) from the committed estimate's own spread, linearised (the
covariance of x_{k-1} = x_k ⊖ u_k); the walk stops where the position std would exceed the converged spread (a third
of ``same_track_xy``, ``same_track_theta``: a back-filled pose is no less certain than one the monitor calls
localized), at a frame holding a pose, at an increment of unknown odometry and at a restart (an operator restarts a
robot after carrying it). Back-filled poses join the stretch: withdrawn with it. The odometry does not see a robot
carried away, so lost frames before a kidnapping within that reach get the poses after it (measured in
docs/results).

Pure bookkeeping on keys (frame indices in the evaluation, capture stamps in the loop-closure worker): the caller
applies what ``update`` returns to its own per-frame poses, so the evaluation and the worker keep the same poses.
``commit_after=0`` without ``retract`` records every localized estimate at once (the earlier rule).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Hashable
from dataclasses import asdict

import numpy as np
from pydantic import Field

from semloc_core.geometry import wrap_angle
from semloc_core.localization.filter import compose_motion, uncompose_motion
from semloc_core.settings import settings

MAX_TRACK_KEYS = 100_000  # keys of a track remembered for withdrawal (about 3 h of estimates at 10 Hz): older stay
MAX_BACKFILL = 2048  # estimates a committed pose may be carried back over (the motion noise stops it sooner)


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
                                        "the filter's converged_xy_std, as the localizer's estimates carry it)")
    same_track_theta: float | None = Field(None, gt=0, description="... or turned more than this (rad; default "
                                           "three of the filter's converged_theta_std)")
    backfill: bool = Field(True, description="a stretch's first committed pose is carried back along the odometry "
                           "to the estimates before it that hold no pose, while the motion noise keeps it within a "
                           "third of same_track_xy / same_track_theta (the converged spread)")

    def to_dict(self) -> dict:
        return asdict(self)


class PoseRecorder:
    """See the module docstring; ``rival_frames``, ``elsewhere_xy``, ``elsewhere_theta``: the monitor's (its
    defaults when None), the defaults of ``commit_after``, ``same_track_xy`` and ``same_track_theta`` (the worker
    follows the localizer's own: ``follow_scale``).
    ``update(key, pose, localized, initialising, moved, spread, dt, motion_std)`` per estimate, in the localizer's
    order, ``moved`` the odometry (dx, dy, dθ in the body frame) since the previous estimate (None: unknown),
    ``spread`` its hypothesis's (position std m, heading std rad; ``health.hypothesis_spreads``), ``dt`` the seconds
    ``moved`` covers (None: unknown, and no pose is carried back over it), ``motion_std`` the noise the localizer's
    motion model gave that increment (translation std per axis m, rotation std rad: ``increment_std``; None: the
    localizer worker's default model's, ``DifferentialDriveModel()``); returns ``(committed, retracted)``: the (key,
    pose) pairs a place may now keep (back-filled ones too; ``last_backfilled`` their keys), and the keys whose pose
    it must forget."""

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
        self.pending: list[tuple[Hashable, np.ndarray, np.ndarray]] = []  # localized estimates (key, pose, spread) not
        # yet followed far enough
        self.stretch: list[Hashable] = []  # keys committed since the current localized stretch began
        self.localized = False  # the last estimate was
        self.ended: list[Hashable] = []  # keys the last ended stretch committed, judged when the next one begins
        self.carried: np.ndarray | None = None  # that stretch's last estimate carried along the odometry since
        self.last_spread = self.ended_spread = np.zeros(2)  # hypothesis spreads (xy m, theta rad) of those estimates
        # the last MAX_BACKFILL estimates: [key, odometry from the one before (dx, dy, dθ, dt, its translation and
        # rotation noise std) or None, holds a pose, was localized]
        self.recent: deque[list] = deque()
        self.recent_of: dict[Hashable, list] = {}
        self.stretch_anchored = False  # the current stretch has committed (and carried back) its first pose
        self.last_backfilled: list = []
        self.initialising = False  # the last estimate was

    def follow_scale(self, converged_std) -> None:
        """The localizer's converged spread (position std m, heading std rad), as its estimates carry it: the same
        track reaches three of it, as the monitor's 'elsewhere', unless the configuration sets ``same_track_*``."""
        xy, theta = (float(v) for v in converged_std)
        self.same_track_xy = self.config.same_track_xy or 3 * xy
        self.same_track_theta = self.config.same_track_theta or 3 * theta

    def update(self, key: Hashable, pose, localized: bool, initialising: bool = False, moved=None,
               spread=None, dt: float | None = None, motion_std=None) -> tuple[list, list]:
        pose = np.asarray(pose, dtype=np.float64).reshape(3)
        spread = np.zeros(2) if spread is None else np.asarray(spread, dtype=np.float64).reshape(2)
        if self.carried is not None:
            self.carried = None if moved is None else compose_motion(self.carried, np.asarray(moved, np.float64))
        restarted = initialising and not self.initialising
        self.initialising = initialising
        if moved is not None and dt is not None and motion_std is None:
            motion_std = _default_noise(*np.asarray(moved, np.float64).reshape(3), float(dt))
        self._remember(key, None if moved is None or dt is None or restarted else
                       [*(float(v) for v in np.asarray(moved, np.float64).reshape(3)), float(dt),
                        *(float(v) for v in motion_std)], localized)
        self.last_backfilled = []
        retracted: list = []
        if not localized:
            if self.localized and not initialising:  # a stretch ends: judged when the next begins
                # its last estimate carried along from there: this estimate's odometry counts too
                self.ended, self.ended_spread = self.stretch, self.last_spread
                self.carried = None if moved is None else compose_motion(self.last_pose, np.asarray(moved, np.float64))
            elif initialising:
                self.ended, self.carried = [], None
            self.pending, self.stretch, self.localized, self.stretch_anchored = [], [], False, False
            return [], []
        if not self.localized:  # a stretch begins: on the ended one's track (one hypothesis), or another
            if self.retract and self.ended and self.carried is not None:
                if self._elsewhere(pose, self.carried, np.maximum(spread, self.ended_spread)):
                    retracted = self.ended
                else:  # the same track goes on: withdrawn with this stretch if that is abandoned later
                    self.stretch = self.ended
            self.ended, self.carried = [], None
        for k in retracted:
            self._mark(k, False)
        self.localized, self.last_pose, self.last_spread = True, pose, spread
        self.pending.append((key, pose.copy(), spread.copy()))
        due = max(len(self.pending) - self.commit_after, 0)  # followed by commit_after localized estimates
        due_now, self.pending = self.pending[:due], self.pending[due:]
        committed = [(k, p) for k, p, _ in due_now]
        if committed and not self.stretch_anchored:
            self.stretch_anchored = True
            if self.config.backfill:
                first, first_pose, first_spread = due_now[0]
                filled = self._carried_back(first, first_pose, first_spread)
                self.last_backfilled = [k for k, _ in filled]
                self.stretch.extend(self.last_backfilled)
                committed = filled + committed
        for k, _ in committed:
            self._mark(k, True)
        self.stretch.extend(k for k, _, _ in due_now)
        if len(self.stretch) > MAX_TRACK_KEYS:
            del self.stretch[:len(self.stretch) - MAX_TRACK_KEYS]
        return committed, retracted

    def restart(self) -> None:
        """A new run of the estimates (a session replayed again, the localizer's source restarted: its keys may be
        those of the old run again). The current stretch ends unjudged, as at a restart without the pose: the new
        run is no evidence for or against it; the estimates not yet committed are dropped (no run of the old one
        follows them any more), and nothing is carried back, or filled by a backward pass, across it. What was
        committed stays: the caller's poses are the map."""
        self.pending, self.stretch, self.ended, self.carried = [], [], [], None
        self.localized = self.stretch_anchored = self.initialising = False
        self.recent.clear()
        self.recent_of.clear()
        self.last_backfilled = []

    def fill(self, anchor: Hashable, keys) -> tuple[list, dict[str, int]]:
        """Poses for ``keys`` from a backward filter pass (``smoothing.BackwardPass``) started at ``anchor``, the
        first estimate of a committed stretch: kept as back-filled ones, they join the anchor's stretch and are
        withdrawn with it. Returns the keys a place may keep and the refused ones counted by reason: ``unknown``
        (not among the last MAX_BACKFILL estimates), ``posed`` (holds a pose already), ``anchor`` (the anchor's
        stretch was never committed or was withdrawn)."""
        refused: dict[str, int] = {}
        keys = list(keys)
        anchor_entry = self.recent_of.get(anchor)
        if anchor_entry is None or not anchor_entry[2]:
            return [], {"anchor": len(keys)} if keys else {}
        track = self.stretch if anchor in self.stretch else self.ended if anchor in self.ended else None
        accepted = []
        for key in keys:
            entry = self.recent_of.get(key)
            reason = "unknown" if entry is None else "posed" if entry[2] else None
            if reason is not None:
                refused[reason] = refused.get(reason, 0) + 1
                continue
            entry[2] = True
            accepted.append(key)
        if track is not None:  # else the anchor's stretch is kept and judged no more: so are these
            track.extend(accepted)
        return accepted, refused

    def _remember(self, key: Hashable, moved: list | None, localized: bool) -> None:
        entry = [key, moved, False, bool(localized)]
        self.recent.append(entry)
        self.recent_of[key] = entry
        while len(self.recent) > MAX_BACKFILL:
            old = self.recent.popleft()
            if self.recent_of.get(old[0]) is old:
                del self.recent_of[old[0]]

    def _mark(self, key: Hashable, posed: bool) -> None:
        entry = self.recent_of.get(key)
        if entry is not None:
            entry[2] = posed

    def _carried_back(self, key: Hashable, pose: np.ndarray, spread: np.ndarray) -> list:
        """(key, pose) of the estimates before ``key`` that hold no pose, ``pose`` carried back along the odometry
        while its linearised covariance stays within the converged spread (the module docstring)."""
        limit_xy, limit_theta = self.same_track_xy / 3, self.same_track_theta / 3
        covariance = np.diag([spread[0] ** 2, spread[0] ** 2, spread[1] ** 2])
        entries = list(self.recent)
        at = next((i for i in range(len(entries) - 1, -1, -1) if entries[i][0] == key), None)
        filled: list = []
        if at is None:
            return filled
        for i in range(at, 0, -1):
            moved, before = entries[i][1], entries[i - 1]
            if moved is None or before[2]:
                break
            pose, covariance = _backward_step(pose, covariance, moved[:3], moved[4:6])
            if (np.linalg.eigvalsh(covariance[:2, :2])[-1] > limit_xy ** 2
                    or covariance[2, 2] > limit_theta ** 2):
                break
            if not before[3]:  # a frame the localizer judged (withdrawn or dropped) keeps no pose: the chain passes
                filled.append((before[0], pose.copy()))
        return filled

    def _elsewhere(self, pose: np.ndarray, track: np.ndarray, spread: np.ndarray) -> bool:
        """Beyond three spreads of either hypothesis (at least ``same_track_*``), as the monitor's rivals count."""
        reach_xy, reach_theta = max(self.same_track_xy, 3 * spread[0]), max(self.same_track_theta, 3 * spread[1])
        return bool(math.hypot(pose[0] - track[0], pose[1] - track[1]) > reach_xy
                    or abs(float(wrap_angle(pose[2] - track[2]))) > reach_theta)

    def snapshot(self) -> dict:
        return {"pending": [[k, p.tolist(), s.tolist()] for k, p, s in self.pending], "stretch": list(self.stretch),
                "localized": self.localized, "last_pose": None if not self.localized else self.last_pose.tolist(),
                "ended": list(self.ended), "carried": None if self.carried is None else self.carried.tolist(),
                "spreads": [self.last_spread.tolist(), self.ended_spread.tolist()],
                "recent": [list(entry) for entry in self.recent], "anchored": self.stretch_anchored,
                "initialising": self.initialising}

    def restore(self, snapshot: dict) -> None:
        pending = [(item[0], np.asarray(item[1], dtype=np.float64).reshape(3),
                    np.asarray(item[2] if len(item) > 2 else np.zeros(2), dtype=np.float64).reshape(2))
                   for item in snapshot.get("pending", [])]
        poses = [p for _, p, _ in pending] + [np.asarray(snapshot[name], dtype=np.float64).reshape(3)
                                               for name in ("last_pose", "carried") if snapshot.get(name) is not None]
        if not all(np.isfinite(p).all() for p in poses):
            raise ValueError("pose recorder snapshot: poses must be finite")
        recent = [[entry[0], None if entry[1] is None else _with_noise([float(v) for v in entry[1]]),
                   bool(entry[2]), bool(entry[3:4] and entry[3])] for entry in snapshot.get("recent", [])[-MAX_BACKFILL:]]
        moves = [entry[1] for entry in recent if entry[1] is not None]
        if any(len(m) != 6 or not all(math.isfinite(v) for v in m) or min(m[3:]) < 0 for m in moves) or not all(
                np.isfinite(s).all() and (s >= 0).all() for _, _, s in pending):
            raise ValueError("pose recorder snapshot: odometry and spreads must be finite (dt, noise, spreads >= 0)")
        self.recent = deque(recent)
        self.recent_of = {entry[0]: entry for entry in recent}
        self.stretch_anchored = bool(snapshot.get("anchored", False))
        self.initialising = bool(snapshot.get("initialising", False))
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


def _with_noise(moved: list) -> list:
    """An odometry entry (dx, dy, dθ, dt) of a snapshot written before entries carried their noise: the default
    model's, as ``update`` gives an estimate without it."""
    if len(moved) != 4 or not all(math.isfinite(v) for v in moved) or moved[3] < 0:
        return moved  # refused below (or complete)
    return [*moved, *_default_noise(*moved)]


def _default_noise(dx: float, dy: float, dtheta: float, dt: float) -> tuple[float, float]:
    """The noise the localizer worker's default motion model gives an increment (a localizer not sending its own)."""
    from semloc_core.localization.motion import DifferentialDriveModel, Odometry
    return DifferentialDriveModel().increment_std(Odometry(dx, dy, dtheta, dt))


def _backward_step(pose: np.ndarray, covariance: np.ndarray, moved, increment_std) -> tuple[np.ndarray, np.ndarray]:
    """The pose before body-frame motion ``moved`` (dx, dy, dθ) that led to ``pose``, x_{k-1} = x_k ⊖ u, and its
    covariance F Σ Fᵀ + G Q Gᵀ (F, G the Jacobians in x_k and u; Q the increment's noise: ``increment_std`` =
    (translation std per axis, rotation std))."""
    dx, dy, _ = (float(v) for v in moved)
    before = uncompose_motion(np.asarray(pose, np.float64)[None], np.asarray(moved, np.float64))[0]
    c, s = math.cos(before[2]), math.sin(before[2])
    lever = (s * dx + c * dy, -(c * dx - s * dy))  # d(x, y)_{k-1} / d(heading)
    jacobian_pose = np.array([[1.0, 0.0, lever[0]], [0.0, 1.0, lever[1]], [0.0, 0.0, 1.0]])
    jacobian_motion = np.array([[-c, s, -lever[0]], [-s, -c, -lever[1]], [0.0, 0.0, -1.0]])
    translation_std, rotation_std = increment_std
    noise = np.diag([translation_std ** 2, translation_std ** 2, rotation_std ** 2])
    return before, jacobian_pose @ covariance @ jacobian_pose.T + jacobian_motion @ noise @ jacobian_motion.T
