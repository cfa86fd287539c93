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
