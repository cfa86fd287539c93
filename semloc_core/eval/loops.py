"""Loop-closure ground truth from poses (thesis §3.6: pairs closer than a distance threshold).

Matrices are (N, N) bool and symmetric, with a False diagonal. ``hard`` marks true loop closures; ``soft`` marks the
pairs that are not wrong to report (a superset of ``hard``): the evaluation counts ``hard`` as positives, ignores
``soft & ~hard``, and counts the rest as negatives (see ``pr.loop_pairs``).
"""

from __future__ import annotations

import numpy as np


def loop_ground_truth(positions, optical_axes=None, distance: float = 3.0, soft_distance: float | None = None,
                      max_angle: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(hard, soft) loop matrices from camera positions (N, 3) and optical axes (N, 3).

    hard: centres within ``distance`` and, when ``max_angle`` (radians) is given, horizontal viewing directions
    within ``max_angle`` of each other (a limited field of view sees nothing in common when facing away).
    soft: centres within ``soft_distance`` (default ``distance``) whatever the direction.
    """
    positions = np.asarray(positions, float)
    if positions.ndim != 2 or positions.shape[1] not in (2, 3):
        raise ValueError(f"positions must be (N, 2) or (N, 3), got {positions.shape}")
    if distance <= 0:
        raise ValueError("the loop distance threshold must be positive")
    soft_distance = distance if soft_distance is None else float(soft_distance)
    if soft_distance < distance:
        raise ValueError("soft_distance must not be smaller than distance")
    diff = positions[:, None, :] - positions[None, :, :]
    d2 = np.einsum("ijk,ijk->ij", diff, diff)
    hard = d2 <= distance ** 2
    soft = d2 <= soft_distance ** 2
    if max_angle is not None:
        if optical_axes is None:
            raise ValueError("max_angle needs the optical axes")
        axes = np.asarray(optical_axes, float)[:, :2]
        norm = np.linalg.norm(axes, axis=1, keepdims=True)
        axes = axes / np.maximum(norm, 1e-12)
        cos = np.clip(axes @ axes.T, -1.0, 1.0)
        # A camera looking straight up or down has no horizontal direction: it agrees with any.
        vertical = norm[:, 0] < 1e-6
        aligned = (cos >= np.cos(max_angle)) | vertical[:, None] | vertical[None, :]
        hard &= aligned
    np.fill_diagonal(hard, False)
    np.fill_diagonal(soft, False)
    return hard, soft | hard


def frame_decisions(decided, hard, soft, evaluated) -> dict:
    """Loop decisions per later frame, (n, n) bool matrices [earlier, later]: a frame (column) *revisits* when it
    has a ``hard`` partner among the ``evaluated`` pairs, and is *recognised* when one of its decided partners there
    is ``hard`` or ``soft`` (not wrong to report). Frame precision: frames with a decided partner that are
    recognised; frame recall: revisiting frames that are recognised (None without any)."""
    decided, hard, soft, evaluated = (np.asarray(m, bool) for m in (decided, hard, soft, evaluated))
    if not decided.shape == hard.shape == soft.shape == evaluated.shape or decided.ndim != 2:
        raise ValueError("decided, hard, soft and evaluated must be matrices of one shape")
    revisits = (hard & evaluated).any(axis=0)
    reported = (decided & evaluated).any(axis=0)
    correct = (decided & evaluated & (hard | soft)).any(axis=0)
    return {"revisit_frames": int(revisits.sum()), "frames_with_loop": int(reported.sum()),
            "frames_with_correct_loop": int(correct.sum()),
            "revisit_frames_recognised": int((correct & revisits).sum()),
            "frame_precision": float(correct.sum() / reported.sum()) if reported.any() else None,
            "frame_recall": float((correct & revisits).sum() / revisits.sum()) if revisits.any() else None}


def pair_distances(pairs, positions) -> dict:
    """How far apart the camera centres (``positions`` (n, 2 or 3)) of the ``pairs`` ((n, n) bool) are: count and
    quartiles in metres (None without pairs). For the false loop decisions: near misses lie just beyond the ground
    truth's radius, aliased places anywhere."""
    pairs = np.asarray(pairs, bool)
    positions = np.asarray(positions, float)
    if pairs.ndim != 2 or pairs.shape[0] != pairs.shape[1] or positions.shape[0] != pairs.shape[0]:
        raise ValueError("pairs must be (n, n) and positions (n, 2 or 3)")
    a, b = np.nonzero(pairs)
    d = np.linalg.norm(positions[a] - positions[b], axis=1)
    return {"count": int(d.size),
            "quartiles_m": [float(v) for v in np.percentile(d, [25, 50, 75])] if d.size else None}
