"""Localization error against ground truth (thesis §4.8.4): position error over time, RMSE, RMSE after
convergence, time to converge from a global initialisation, heading error.

Definitions:

* position error e_t = |p_est(t) - p_gt(t)| (planar, metres); heading error = |wrap(theta_est - theta_gt)|.
* RMSE over time: with several runs (R, N), sqrt(mean over runs of e^2) at each frame; with one run, |e_t|.
* Converged at frame k: the error stays <= ``threshold`` from k for at least ``hold`` seconds (or to the end of
  the sequence if it is shorter). Time to converge = stamp[k] - stamp[0]; None if never.
* RMSE after convergence: sqrt(mean e^2) over the frames from k on (None if never converged).
"""

from __future__ import annotations

import numpy as np

from semloc_core.geometry import wrap_angle


def _poses(a, name: str) -> np.ndarray:
    a = np.asarray(a, float)
    if a.ndim != 2 or a.shape[1] < 2:
        raise ValueError(f"{name} must be (N, 2) or (N, 3), got {a.shape}")
    return a


def position_errors(estimate, truth) -> np.ndarray:
    """Planar position error per frame (N,); frames where the estimate is NaN (no estimate yet) stay NaN."""
    est = _poses(estimate, "estimate")
    gt = _poses(truth, "truth")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"{est.shape[0]} estimates for {gt.shape[0]} ground-truth poses")
    return np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)


def heading_errors(estimate, truth) -> np.ndarray:
    """|wrap(theta_est - theta_gt)| per frame (radians)."""
    est = _poses(estimate, "estimate")
    gt = _poses(truth, "truth")
    if est.shape[1] < 3 or gt.shape[1] < 3:
        raise ValueError("heading errors need (N, 3) poses")
    return np.abs(wrap_angle(est[:, 2] - gt[:, 2]))


def rmse(errors) -> float:
    e = np.asarray(errors, float)
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def convergence_index(errors, stamps_ns, threshold: float = 0.5, hold_s: float = 5.0) -> int | None:
    """First frame from which the error stays <= threshold for ``hold_s`` seconds (or until the end)."""
    e = np.asarray(errors, float)
    t = np.asarray(stamps_ns, np.int64)
    if e.shape != t.shape:
        raise ValueError(f"{e.size} errors for {t.size} stamps")
    good = np.isfinite(e) & (e <= threshold)
    n = e.size
    # Index of the next bad frame after each frame.
    next_bad = np.full(n + 1, n)
    for k in range(n - 1, -1, -1):
        next_bad[k] = k if not good[k] else next_bad[k + 1]
    hold_ns = int(round(hold_s * 1e9))
    for k in range(n):
        if not good[k]:
            continue
        end = next_bad[k]
        if end == n or t[end - 1] - t[k] >= hold_ns:
            return k
    return None


def trajectory_figures(estimate, truth, stamps_ns, threshold: float = 0.5, hold_s: float = 5.0) -> dict:
    """Every localization figure of one run as a JSON-ready dict (see the module docstring)."""
    errors = position_errors(estimate, truth)
    stamps = np.asarray(stamps_ns, np.int64)
    k = convergence_index(errors, stamps, threshold, hold_s)
    est = np.asarray(estimate, float)
    out = {
        "frames": int(errors.size),
        "rmse": rmse(errors),
        "mean_error": float(np.nanmean(errors)),
        "median_error": float(np.nanmedian(errors)),
        "final_error": float(errors[-1]),
        "converged": k is not None,
        "convergence_frame": k,
        "time_to_converge_s": None if k is None else float((stamps[k] - stamps[0]) / 1e9),
        "rmse_after_convergence": None if k is None else rmse(errors[k:]),
        "threshold_m": threshold,
        "hold_s": hold_s,
        "errors": errors.tolist(),
    }
    if est.shape[1] >= 3 and np.asarray(truth).shape[1] >= 3:
        heading = heading_errors(estimate, truth)
        out["heading_rmse_deg"] = float(np.degrees(rmse(heading)))
        out["heading_rmse_after_convergence_deg"] = None if k is None else float(np.degrees(rmse(heading[k:])))
        out["heading_errors_deg"] = np.degrees(heading).tolist()
    return out
