"""The progress line of one localization run (semloc eval localization): the monitor's flags as frame counts."""

from semloc_core.experiments.localization import run_summary
from semloc_core.localization.evaluation import state_metrics


def test_the_run_line_counts_the_flagged_frames():
    """4 frames far off (3 of them flagged), 4 close (1 flagged): the line says "3 of 4" and "1 of 4", not the
    shares 0.75 and 0.25 written as if they were counts."""
    states = ["lost", "uncertain", "lost", "localized", "localized", "localized", "localized", "uncertain"]
    errors = [3.0, 2.5, 4.0, 2.2, 0.05, 0.02, 0.03, 0.01]
    detection = state_metrics(states, errors, far=2.0, near=0.1)
    assert (detection["flagged_far_frames"], detection["flagged_near_frames"]) == (3, 1)
    metrics = {"time_to_converge_frames": 4, "rmse_after_convergence_m": 0.0277128, "recoveries": [],
               "state_detection": detection}
    line = run_summary("B-soft-detector", metrics, 1.25)
    assert "not localized on 3 of 4 frames > 2 m off, 1 of 4 < 0.1 m" in line, line
    assert "RMSE after 0.028 m" in line, line
    unconverged = run_summary("A-soft-detector", {**metrics, "rmse_after_convergence_m": None}, 1.0)
    assert "RMSE after -," in unconverged, unconverged
