"""A backward filter pass over the frames before a localized stretch (issue 34; a smoother's backward pass).

A filter that has just become ``localized`` was lost over the frames before: the places hold no pose there, and
the odometry back-fill (``place_poses``) carries the stretch's first pose back only as far as the motion noise
allows (table tops: about 40 frames). A second particle filter, run **backwards in time** over those frames' own
heatlines from the forward filter's particles at the stretch's first step, with the odometry inverted (the motion
u_k from frame k-1 to k undone: x_{k-1} = x_k ⊕ u_k⁻¹) and the same motion and perception models, keeps the pose
for longer (table top 05: 155 frames). A fresh ``HealthMonitor`` judges it, and only its **first** localized
stretch counts: the pass stops at its first verdict other than ``localized`` after it was localized (past there
it is lost as the forward filter was, and a stretch it finds again by its own recovery is unvetted), at an
increment of unknown odometry (no pose is carried over it) and at the oldest stored frame (``max_frames`` back, or
the last restart). Its last ``commit_after`` estimates are dropped, as the places drop an estimate not followed by
that many localized ones (the monitor's rivals speak late). It goes on over frames that hold a pose (the live
filter's committed or back-filled ones): whether a frame holds one, and whether its stretch was withdrawn since,
only the places know (``PoseRecorder.fill`` refuses the posed ones), and a withdrawn stretch is just where a pass
helps (06's lap, the prototype: 742-766). Measured on the prototype
(docs/results/2026-12-06-tabletop-backward-pass.md): 05's kidnap recovery with a prior lap 64 -> 43 frames, no
wrong pose; keeping every localized estimate of the pass added wrong ones.

``BackwardSmoother`` is fed every live step (``record``) and decides itself when a pass starts: a localized
stretch's first step keeps the filter's snapshot, and once the stretch has stayed localized for ``commit_after``
further steps (when the places commit its first pose) a ``BackwardPass`` starts from that snapshot over the frames
stored before it. ``advance(steps)`` runs a few steps of the pending passes (a worker does
``steps_per_frame`` per live frame, so the live path never stalls for a whole pass) and returns the (key, pose,
covariance) of the passes that finished. The pass's filter and monitor draw from their own generators: the live
filter's course is the same with or without it. Memory is bounded: at most ``max_frames`` frames are stored (the
oldest dropped: a pass reaches no farther back) and a frame holds its heatlines (classes x bins floats).
Pure: arrays and the filter in, poses out; the evaluation and the localizer worker use it the same way.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Hashable
from dataclasses import asdict, dataclass

import numpy as np
from pydantic import Field

from semloc_core.localization.filter import NonFiniteStepError
from semloc_core.localization.health import HealthMonitor, LocalizationState, judge
from semloc_core.localization.motion import Odometry
from semloc_core.settings import settings


@settings
class SmoothingConfig:
    """The backward pass over the frames before a localized stretch (``BackwardSmoother``)."""

    enabled: bool = Field(True, description="run a backward filter pass from each localized stretch over the "
                          "frames before it (table top 05 with a prior lap: kidnap recovery 64 -> 43 frames)")
    max_frames: int = Field(1200, ge=1, le=100_000, description="the last frames stored, so the farthest a pass "
                            "reaches back (a table-top lap is 600-1,200 frames; each holds "
                            "its heatlines, float32 classes x bins: 20 kB at 14 x 360)")
    steps_per_frame: int = Field(3, ge=1, description="pass steps run per live frame (worker; each costs a filter "
                                 "step, ~15 ms: a pass over 1,000 frames ends within ~330 live frames)")
    max_pending: int = Field(4, ge=1, description="passes waiting; a stretch committing while this many wait "
                             "starts none (a pass is best-effort)")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True, eq=False)
class PastFrame:
    """One live frame as the pass needs it: ``moved`` the odometry (dx, dy, dθ body frame) from the frame before to
    this one over ``dt`` seconds (None: unknown), ``perception`` the model that weighed it (None: the pass filter's
    own)."""

    key: Hashable
    heatlines: object | None
    view: object | None
    moved: tuple[float, float, float] | None
    dt: float
    perception: object | None = None


def inverse_motion(moved) -> Odometry:
    """u⁻¹ of a body-frame increment u = (dx, dy, dθ): the motion that undoes it, in the end pose's body frame
    (x ⊕ u ⊕ u⁻¹ = x), its dt 0 (the caller's)."""
    dx, dy, dtheta = (float(v) for v in moved)
    c, s = math.cos(dtheta), math.sin(dtheta)
    return Odometry(-(c * dx + s * dy), -(-s * dx + c * dy), -dtheta, 0.0)


class BackwardPass:
    """One pass: ``particle_filter`` (restored from the forward filter's snapshot at the anchor frame, its own
    generator) goes back over ``frames`` (oldest first, the anchor last), judged by ``monitor`` with probes from
    ``rng``; ``step()`` one frame, ``done``; ``poses()``: (key, pose, covariance) of its first localized stretch
    (without the last ``commit_after``)."""

    def __init__(self, particle_filter, monitor: HealthMonitor, frames: list[PastFrame], rng: np.random.Generator,
                 commit_after: int):
        self.filter, self.monitor, self.rng = particle_filter, monitor, rng
        self.frames = frames
        self.anchor = frames[-1].key
        self.commit_after = int(commit_after)
        self.at = len(frames) - 2  # the next frame to go back to
        self.stretch: list[tuple[Hashable, np.ndarray, np.ndarray]] = []
        self.verdicts: dict[str, int] = {}  # the pass's verdicts so far, counted by state
        self.done = self.at < 0
        self.stop_reason = "no earlier frame" if self.done else None

    def step(self) -> None:
        if self.done:
            return
        later, frame = self.frames[self.at + 1], self.frames[self.at]
        if later.moved is None:  # the motion between them is unknown: no pose is carried over it
            return self._stop("unknown odometry")
        if frame.perception is not None:
            self.filter.perception = frame.perception
        undo = inverse_motion(later.moved)
        odometry = Odometry(undo.dx, undo.dy, undo.dtheta, float(later.dt))
        try:
            estimate = self.filter.step(frame.heatlines, odometry, float(later.dt), frame.view)
        except NonFiniteStepError:  # the pass is best-effort: it ends, the live filter never sees it
            return self._stop("a non-finite step")
        verdict = judge(self.monitor, self.filter, estimate, frame.heatlines, frame.view, self.rng,
                        (undo.dx, undo.dy, undo.dtheta))
        self.at -= 1
        self.verdicts[verdict.state.value] = self.verdicts.get(verdict.state.value, 0) + 1
        if verdict.state is LocalizationState.LOCALIZED:
            self.stretch.append((frame.key, np.asarray(estimate.pose, float).copy(),
                                 np.asarray(estimate.covariance, float).copy()))
        elif self.stretch:  # the 'first' rule: the first stretch ends here
            return self._stop(f"{verdict.state.value} after its first stretch")
        if self.at < 0:
            self._stop("oldest stored frame")

    def _stop(self, reason: str) -> None:
        self.done = True
        self.stop_reason = f"{reason}; " + ", ".join(f"{n} {state}" for state, n in sorted(self.verdicts.items()))

    def poses(self) -> list[tuple[Hashable, np.ndarray, np.ndarray]]:
        kept = len(self.stretch) - self.commit_after
        return self.stretch[:max(kept, 0)]


class BackwardSmoother:
    """See the module docstring. ``make_filter(rng)``: a new filter like the live one (motion, perception, free
    space, config) drawing from ``rng``; ``make_monitor()``: a fresh monitor like the live one's; ``commit_after``:
    the steps a stretch must stay localized before its first pose commits (the places' ``commit_after``);
    ``rng``: the passes' own generator (their filters and monitors draw from generators spawned from it)."""

    def __init__(self, config: SmoothingConfig, make_filter: Callable[[np.random.Generator], object],
                 make_monitor: Callable[[], HealthMonitor], commit_after: int, rng: np.random.Generator):
        self.config = config
        self.make_filter, self.make_monitor = make_filter, make_monitor
        self.commit_after = int(commit_after)
        self.rng = rng
        self.frames: deque[PastFrame] = deque(maxlen=config.max_frames)  # the last ones, since a restart
        self.anchor: tuple[PastFrame, dict] | None = None  # the current stretch's first frame, the filter there
        self.localized_for = 0  # steps the current stretch has been localized
        self.committed = False  # the current stretch has started its pass
        self.passes: deque[BackwardPass] = deque()
        self.initialising = False  # the live filter was at the last frame
        self.started = self.dropped = 0

    def reset(self) -> None:
        """A restart (a new initial pose, a global relocalization): the stored frames and the passes are dropped."""
        self.frames.clear()
        self.passes.clear()
        self.anchor, self.localized_for, self.committed = None, 0, False

    def record(self, frame: PastFrame, localized: bool, initialising: bool, snapshot: Callable[[], dict]) -> None:
        """After each live step: ``frame``, the live verdict, whether the filter is initialising (its start: a
        restart, no pass crosses it) and ``snapshot()`` the live filter's state after this step (taken at a stretch's first
        step only)."""
        if not self.config.enabled:
            return
        if initialising and not self.initialising:  # a restart: no pass crosses it
            self.reset()
        self.initialising = initialising
        self.frames.append(frame)
        if not localized:
            self.anchor, self.localized_for, self.committed = None, 0, False
            return
        if self.committed:
            return
        if self.anchor is None:
            self.anchor = (frame, _without_generator(snapshot()))
            self.localized_for = 0
            return
        self.localized_for += 1
        if self.localized_for >= self.commit_after:
            self._start()

    def _start(self) -> None:
        first, snapshot = self.anchor
        frames = list(self.frames)
        at = next((i for i, f in enumerate(frames) if f is first), None)  # None: dropped (max_frames)
        self.anchor, self.committed = None, True
        if at is None or len(self.passes) >= self.config.max_pending:
            self.dropped += 1
            return
        seeds = self.rng.spawn(2)
        particle_filter = self.make_filter(seeds[0])
        particle_filter.restore(snapshot)
        self.passes.append(BackwardPass(particle_filter, self.make_monitor(), frames[:at + 1], seeds[1],
                                        self.commit_after))
        self.started += 1

    def advance(self, steps: int | None = None) -> list[tuple[Hashable, Hashable, list]]:
        """Run up to ``steps`` pass steps (default ``steps_per_frame``; a negative count: every pass to its end); returns (anchor key, stop reason, [(key, pose, covariance), ...]) of the passes that ended."""
        budget = self.config.steps_per_frame if steps is None else steps
        ended = []
        while self.passes and (budget < 0 or budget > 0):
            current = self.passes[0]
            current.step()
            budget -= budget > 0
            if current.done:
                self.passes.popleft()
                ended.append((current.anchor, current.stop_reason, current.poses()))
        return ended

    def finish(self) -> list[tuple[Hashable, Hashable, list]]:
        """Every pending pass to its end (the evaluation, after a lap)."""
        return self.advance(-1)


def _without_generator(snapshot: dict) -> dict:
    """The live filter's snapshot without its generator's state: the pass draws from its own."""
    return {k: v for k, v in snapshot.items() if k != "rng"}
