"""Shared scene for the mapping tests: a small table-top world with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.camera import PinholeCamera
from semloc_core.mapping.synthetic import SyntheticObject, look_at, orbit_poses

CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")


@pytest.fixture(scope="session")
def camera() -> PinholeCamera:
    # Kinect-like intrinsics at a quarter of 640x480 keeps the tests fast; the kernel does not care.
    K = np.array([[131.25, 0.0, 79.625], [0.0, 131.25, 59.625], [0.0, 0.0, 1.0]])
    return PinholeCamera(160, 120, K)


@pytest.fixture(scope="session")
def objects() -> list[SyntheticObject]:
    centres = [(0.35, 0.40, 0.08), (0.75, 0.30, 0.10), (0.55, 0.75, 0.15), (0.30, 0.85, 0.07), (0.80, 0.80, 0.09)]
    sizes = [(0.16, 0.16, 0.08), (0.18, 0.18, 0.12), (0.08, 0.20, 0.30), (0.10, 0.10, 0.12), (0.07, 0.07, 0.12)]
    return [SyntheticObject(c, np.array(p), np.array(s)) for c, (p, s) in enumerate(zip(centres, sizes))]


@pytest.fixture(scope="session")
def poses() -> list[np.ndarray]:
    """Twelve views around the table, at two heights, plus a close tilted one."""
    target = np.array([0.55, 0.6, 0.1])
    views = orbit_poses(target, 0.9, 0.5, 8) + orbit_poses(target, 0.7, 0.8, 4, start_angle=0.4)
    views.append(look_at([0.5, 0.1, 0.45], [0.6, 0.7, 0.0], up=(0.2, 0.0, 1.0)))
    return views
