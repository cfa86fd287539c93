"""Motion (prediction) models: move every particle by the odometry since the last update, plus noise.

Interchangeable parts with one method, ``model.sample(states, odometry, dt, rng) -> new states`` (``states`` (N, 3)
[x, y, theta] in the world frame; ``odometry`` an ``Odometry`` or None):

* ``DifferentialDriveModel`` - eq. 4.5 of the thesis: velocities (v, ω) over Δt with normally distributed noise
  ΔV, ΔΩ, moving along the mid-step heading. Noise standard deviations follow nav2 AMCL's ``alpha1..alpha4``.
* ``OmniDriveModel`` - body-frame increments (dx, dy, dθ) with noise, for holonomic bases and hand-held cameras
  (which move sideways, something eq. 4.5 cannot express).
* ``RandomWalkModel`` - no odometry: Gaussian diffusion growing with √Δt.

A model given ``odometry=None`` falls back to its random-walk noise, so a filter keeps working when odometry drops
out. ``model.increment_std(odometry)``: the standard deviations (translation, rotation) of the noise it adds to one
increment, for whatever carries a pose along the odometry outside the filter (``place_poses``' back-fill).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from semloc_core.geometry import wrap_angle
from semloc_core.localization import _kernels


@dataclass(frozen=True)
class Odometry:
    """Motion since the previous update, in the body frame at the previous pose: dx forward, dy left, dtheta
    counter-clockwise (metres, radians), over ``dt`` seconds."""

    dx: float
    dy: float
    dtheta: float
    dt: float

    def __post_init__(self) -> None:
        values = (self.dx, self.dy, self.dtheta, self.dt)
        if not all(math.isfinite(float(v)) for v in values):
            raise ValueError(f"odometry must be finite, got {values}")
        if self.dt < 0:
            raise ValueError(f"odometry dt must be >= 0, got {self.dt}")

    @classmethod
    def from_velocity(cls, v: float, omega: float, dt: float) -> "Odometry":
        """Increment of eq. 4.5 without noise: v·Δt along the mid-step heading, ω·Δt of turn."""
        turn = omega * dt
        return cls(v * dt * math.cos(turn / 2), v * dt * math.sin(turn / 2), turn, dt)

    @classmethod
    def from_twist(cls, v: float, v_lateral: float, omega: float, dt: float) -> "Odometry":
        """Increment of a constant body twist (v forward, v_lateral left, omega) held for dt (SE(2) exponential).

        With v_lateral = 0 it is eq. 4.5's displacement along the mid-step heading, with the chord 2 v sin(ωΔt/2)/ω
        for v Δt."""
        turn = omega * dt
        if abs(turn) < 1e-9:
            along, across = 1.0 - turn * turn / 6.0, turn / 2.0
        else:
            along, across = math.sin(turn) / turn, (1.0 - math.cos(turn)) / turn
        forward, left = v * dt, v_lateral * dt
        return cls(along * forward - across * left, across * forward + along * left, turn, dt)

    @classmethod
    def between(cls, pose_from, pose_to, dt: float) -> "Odometry":
        """Increment between two planar poses (x, y, theta) of an odometry frame."""
        x0, y0, t0 = (float(v) for v in pose_from)
        x1, y1, t1 = (float(v) for v in pose_to)
        c, s = math.cos(t0), math.sin(t0)
        dx, dy = x1 - x0, y1 - y0
        return cls(c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(t1 - t0)), dt)

    @property
    def velocity(self) -> tuple[float, float]:
        """(v, ω) of eq. 4.5 that reproduce this increment (the lateral part a differential drive cannot make is
        dropped: v·Δt is the projection on the mid-step heading)."""
        if self.dt <= 0:
            return 0.0, 0.0
        half = self.dtheta / 2
        return (self.dx * math.cos(half) + self.dy * math.sin(half)) / self.dt, self.dtheta / self.dt


def compose(a: Odometry | None, b: Odometry) -> Odometry:
    """Increment ``a`` followed by increment ``b`` (each in the body frame at its start); ``a`` may be None."""
    if a is None:
        return b
    c, s = math.cos(a.dtheta), math.sin(a.dtheta)
    return Odometry(a.dx + c * b.dx - s * b.dy, a.dy + s * b.dx + c * b.dy, a.dtheta + b.dtheta, a.dt + b.dt)


class OdometryBuffer:
    """Odometry messages kept by time, so that a correction moves the particles exactly up to the observation's
    capture stamp - not by motion that happened after it (odometry usually arrives faster and later than heatlines).

    ``add(stamp_ns, v, v_lateral, omega, dt)``: a constant body twist over (stamp - dt, stamp]. ``integrate_until(
    stamp_ns)``: the composed increment from the previous call's stamp up to ``stamp_ns`` (an interval straddling it
    is split; the rest stays buffered), or None when no odometry covers that span; a stamp not after the previous
    one yields None. ``uncovered_until(stamp_ns)``: the seconds of that span no message covers (a rebooted robot, a
    link gap longer than the publishers' cache, a refused message): motion the increment leaves out, which the
    caller accounts for (the localizer diffuses its particles over it). Odometry arriving after a later observation
    was integrated only counts from that observation's stamp on; a message with the stamp of one still buffered
    replaces it (delivered twice, it counts once). ``reset(stamp_ns)``: forget everything up to it (a new initial
    pose). At most ``max_intervals`` are kept (oldest dropped). ``restart_after_ns``: a message ending further
    back than this before the latest time covered is a new run of the stream (a recorded session replayed again, a
    source restarted), and the buffer starts over from it; without it, such a message is dropped as already applied
    (so would the whole new run be, until its stamps passed the old run's).
    """

    def __init__(self, max_intervals: int = 100_000, restart_after_ns: int | None = None):
        self.max_intervals = int(max_intervals)
        self.restart_after_ns = restart_after_ns
        self._intervals: list[tuple[int, int, float, float, float]] = []  # (start_ns, end_ns, v, v_lateral, omega)
        self.consumed_ns: int | None = None

    def __len__(self) -> int:
        return len(self._intervals)

    def add(self, stamp_ns: int, v: float, v_lateral: float, omega: float, dt: float) -> None:
        values = (v, v_lateral, omega, dt)
        if not all(math.isfinite(float(x)) for x in values) or dt <= 0:
            raise ValueError(f"odometry needs finite values and dt > 0, got {values}")
        end = int(stamp_ns)
        start = end - int(round(dt * 1e9))
        latest = self.covered_until_ns
        if self.restart_after_ns is not None and latest is not None and latest - end > self.restart_after_ns:
            self._intervals, self.consumed_ns = [], None  # a new run of the stream: its motion from its start
        if self.consumed_ns is not None:
            start = max(start, self.consumed_ns)
            if end <= start:
                return  # entirely before motion already applied
        for index, interval in enumerate(self._intervals):
            if interval[1] == end:  # the same message again (a re-delivery): it replaces the one buffered
                self._intervals[index] = (start, end, float(v), float(v_lateral), float(omega))
                return
        self._intervals.append((start, end, float(v), float(v_lateral), float(omega)))
        if len(self._intervals) > 1 and self._intervals[-2][0] > start:
            self._intervals.sort()
        if len(self._intervals) > self.max_intervals:
            del self._intervals[: len(self._intervals) - self.max_intervals]

    @property
    def covered_until_ns(self) -> int | None:
        """The latest time the buffered (or already applied) odometry reaches; None before any."""
        return max((end for _, end, *_ in self._intervals), default=self.consumed_ns)

    def integrate_until(self, stamp_ns: int) -> Odometry | None:
        stamp = int(stamp_ns)
        if self.consumed_ns is not None and stamp <= self.consumed_ns:
            return None
        total: Odometry | None = None
        kept = []
        for start, end, v, v_lateral, omega in self._intervals:
            if start >= stamp:
                kept.append((start, end, v, v_lateral, omega))
                continue
            until = min(end, stamp)
            total = compose(total, Odometry.from_twist(v, v_lateral, omega, (until - start) * 1e-9))
            if end > stamp:
                kept.append((stamp, end, v, v_lateral, omega))
        self._intervals = kept
        self.consumed_ns = stamp
        return total

    def uncovered_until(self, stamp_ns: int) -> float:
        """Seconds of the span ``integrate_until(stamp_ns)`` would integrate that no buffered message covers: from
        the previous call's stamp (before any, from the first message's start) to ``stamp_ns``. Exactly 0 when the
        messages are contiguous: each covers (stamp - dt, stamp] in whole nanoseconds, and a source that sets dt to
        the time since its previous stamp meets it to the nanosecond (a float64 dt rounds back to the integer)."""
        stamp = int(stamp_ns)
        spans = sorted((start, end) for start, end, *_ in self._intervals if start < stamp)
        reached = self.consumed_ns if self.consumed_ns is not None else (spans[0][0] if spans else stamp)
        if stamp <= reached:
            return 0.0
        uncovered = 0
        for start, end in spans:
            uncovered += max(start - reached, 0)
            reached = max(reached, min(end, stamp))
        return (uncovered + stamp - reached) / 1e9

    def reset(self, stamp_ns: int | None = None) -> None:
        """Drop the motion up to ``stamp_ns`` (all buffered motion when None) and apply later motion only."""
        if stamp_ns is None:
            stamp_ns = max((end for _, end, *_ in self._intervals), default=self.consumed_ns)
        if stamp_ns is None:
            return
        self._intervals = [(max(start, int(stamp_ns)), end, *rest) for start, end, *rest in self._intervals
                           if end > int(stamp_ns)]
        self.consumed_ns = int(stamp_ns)

    def snapshot(self) -> dict:
        """The buffered motion as arrays: ``spans`` (k, 2) start/end stamps, ``twists`` (k, 3) v, v_lateral, omega,
        and ``consumed_ns`` (None before any motion was applied)."""
        return {"spans": np.array([i[:2] for i in self._intervals], np.int64).reshape(-1, 2),
                "twists": np.array([i[2:] for i in self._intervals], np.float64).reshape(-1, 3),
                "consumed_ns": None if self.consumed_ns is None else int(self.consumed_ns)}

    def restore(self, snapshot: dict) -> None:
        spans = np.asarray(snapshot["spans"], np.int64).reshape(-1, 2)
        twists = np.asarray(snapshot["twists"], np.float64).reshape(-1, 3)
        if spans.shape[0] != twists.shape[0] or not np.all(np.isfinite(twists)) or np.any(spans[:, 1] < spans[:, 0]):
            raise ValueError("odometry buffer: one finite twist per time span")
        consumed = snapshot.get("consumed_ns")
        self._intervals = [(int(a), int(b), float(v), float(w), float(o))
                           for (a, b), (v, w, o) in zip(spans.tolist(), twists.tolist())]
        self.consumed_ns = None if consumed is None else int(consumed)


def _check(states) -> np.ndarray:
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 2 or states.shape[1] != 3:
        raise ValueError(f"particle states must be (N, 3), got {states.shape}")
    return states


def _check_positive(**values) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class RandomWalkModel:
    """Gaussian diffusion without odometry: per second, ``translation_std`` metres (per axis) and ``rotation_std``
    radians; over Δt the standard deviations scale with √Δt."""

    translation_std: float = 0.2
    rotation_std: float = 0.2

    def __post_init__(self) -> None:
        _check_positive(translation_std=self.translation_std, rotation_std=self.rotation_std)

    def sample(self, states, odometry: Odometry | None, dt: float, rng: np.random.Generator) -> np.ndarray:
        states = _check(states)
        if odometry is not None:
            dt = odometry.dt
        scale = math.sqrt(max(float(dt), 0.0))
        out = states.copy()
        n = states.shape[0]
        out[:, :2] += rng.normal(0.0, self.translation_std * scale, (n, 2))
        out[:, 2] = wrap_angle(out[:, 2] + rng.normal(0.0, self.rotation_std * scale, n))
        return out

    def increment_std(self, odometry: Odometry) -> tuple[float, float]:
        """Standard deviations (translation per axis m, rotation rad) of the noise ``sample`` adds over
        ``odometry.dt``."""
        scale = math.sqrt(max(float(odometry.dt), 0.0))
        return self.translation_std * scale, self.rotation_std * scale


@dataclass(frozen=True)
class DifferentialDriveModel:
    """Eq. 4.5: x += (v + ΔV)Δt cos(θ + Δθ/2), y += (v + ΔV)Δt sin(θ + Δθ/2), θ += Δθ, Δθ = (ω + ΔΩ)Δt.

    ΔV ~ N(0, σ_V), ΔΩ ~ N(0, σ_Ω) with, as nav2 AMCL's ``alpha1..alpha4`` (on velocities here):
    σ_Ω = sqrt(alpha1 ω² + alpha2 v²) + min_rotation_std, σ_V = sqrt(alpha3 v² + alpha4 ω²) + min_speed_std.
    Without odometry it diffuses like ``fallback`` (a RandomWalkModel).
    """

    alpha1: float = 0.2
    alpha2: float = 0.2
    alpha3: float = 0.2
    alpha4: float = 0.2
    min_speed_std: float = 0.01
    min_rotation_std: float = 0.01
    fallback: RandomWalkModel = RandomWalkModel()

    def __post_init__(self) -> None:
        _check_positive(alpha1=self.alpha1, alpha2=self.alpha2, alpha3=self.alpha3, alpha4=self.alpha4,
                        min_speed_std=self.min_speed_std, min_rotation_std=self.min_rotation_std)

    def sample(self, states, odometry: Odometry | None, dt: float, rng: np.random.Generator) -> np.ndarray:
        if odometry is None:
            return self.fallback.sample(states, None, dt, rng)
        states = _check(states)
        n = states.shape[0]
        v, omega = odometry.velocity
        dt = odometry.dt
        speed_std, turn_std = self._velocity_std(v, omega)
        speed_noise = rng.normal(0.0, speed_std, n)  # ΔV
        turn_noise = rng.normal(0.0, turn_std, n)  # ΔΩ
        out = np.empty((n, 3))
        # eq. 4.5 with v + ΔV and Δθ = (ω + ΔΩ) Δt, one pass over the particles
        _kernels.differential_drive(states, speed_noise, turn_noise, float(v), float(omega), float(dt), out)
        return out

    def _velocity_std(self, v: float, omega: float) -> tuple[float, float]:
        """σ_V, σ_Ω of eq. 4.5's noise at (v, ω)."""
        return (math.sqrt(self.alpha3 * v * v + self.alpha4 * omega * omega) + self.min_speed_std,
                math.sqrt(self.alpha1 * omega * omega + self.alpha2 * v * v) + self.min_rotation_std)

    def increment_std(self, odometry: Odometry) -> tuple[float, float]:
        """Standard deviations (translation along the heading m, rotation rad) of the noise ``sample`` adds to
        one increment: σ_V Δt and σ_Ω Δt."""
        speed_std, turn_std = self._velocity_std(*odometry.velocity)
        return speed_std * odometry.dt, turn_std * odometry.dt


@dataclass(frozen=True)
class OmniDriveModel:
    """Body-frame increments with noise: each of dx, dy gets N(0, σ_t), dθ gets N(0, σ_r), where
    σ_t = sqrt(alpha3 t² + alpha4 r²) + min_translation_std, σ_r = sqrt(alpha1 r² + alpha2 t²) + min_rotation_std,
    t = |(dx, dy)|, r = |dθ| (nav2 AMCL's omni model, per update). Without odometry it diffuses like ``fallback``."""

    alpha1: float = 0.2
    alpha2: float = 0.2
    alpha3: float = 0.2
    alpha4: float = 0.2
    min_translation_std: float = 0.005
    min_rotation_std: float = 0.005
    fallback: RandomWalkModel = RandomWalkModel()

    def __post_init__(self) -> None:
        _check_positive(alpha1=self.alpha1, alpha2=self.alpha2, alpha3=self.alpha3, alpha4=self.alpha4,
                        min_translation_std=self.min_translation_std, min_rotation_std=self.min_rotation_std)

    def sample(self, states, odometry: Odometry | None, dt: float, rng: np.random.Generator) -> np.ndarray:
        if odometry is None:
            return self.fallback.sample(states, None, dt, rng)
        states = _check(states)
        n = states.shape[0]
        t_std, r_std = self.increment_std(odometry)
        dx_noise = rng.normal(0.0, t_std, n)
        dy_noise = rng.normal(0.0, t_std, n)
        dtheta_noise = rng.normal(0.0, r_std, n)
        out = np.empty((n, 3))
        _kernels.omni_drive(states, float(odometry.dx), float(odometry.dy), float(odometry.dtheta), dx_noise, dy_noise,
                            dtheta_noise, out)
        return out

    def increment_std(self, odometry: Odometry) -> tuple[float, float]:
        """σ_t (each of dx, dy; m) and σ_r (rad) of the noise ``sample`` adds to one increment."""
        t, r = math.hypot(odometry.dx, odometry.dy), abs(odometry.dtheta)
        return (math.sqrt(self.alpha3 * t * t + self.alpha4 * r * r) + self.min_translation_std,
                math.sqrt(self.alpha1 * r * r + self.alpha2 * t * t) + self.min_rotation_std)
