"""A small synthetic feature world for loop-closure tests (no images, no SIFT).

Landmarks are 2-D points with SIFT-like descriptors; a panoramic or limited-field-of-view camera at a planar pose
sees the landmarks within range, each as a feature whose bearing is the landmark's direction in the body frame and
whose descriptor is the landmark's, perturbed. Ground truth loop closures follow from the poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semloc_core.geometry import wrap_angle
from semloc_core.loopclosure.features import FeatureSequence, normalize_descriptors


def sift_like(count: int, rng: np.random.Generator) -> np.ndarray:
    """Non-negative, sparse-ish unit vectors clipped at 0.2 and renormalised, as SIFT's are."""
    raw = rng.gamma(0.6, 1.0, (count, 128))
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    raw = np.minimum(raw, 0.2)
    return raw / np.linalg.norm(raw, axis=1, keepdims=True)


@dataclass
class LandmarkWorld:
    positions: np.ndarray  # (L, 2)
    descriptors: np.ndarray  # (L, 128) unit vectors

    @classmethod
    def random(cls, count: int, extent: float, rng: np.random.Generator, margin: float = 4.0) -> "LandmarkWorld":
        positions = rng.uniform(-margin, extent + margin, (count, 2))
        return cls(positions, sift_like(count, rng))

    def observe(
        self,
        pose,
        rng: np.random.Generator,
        max_range: float = 6.0,
        fov: float = 2 * np.pi,
        noise: float = 0.12,
        keep: float = 0.8,
        clutter: int = 5,
    ) -> FeatureSequence:
        x, y, theta = pose
        rel = self.positions - (x, y)
        distance = np.hypot(rel[:, 0], rel[:, 1])
        bearing = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - theta)
        seen = (distance < max_range) & (np.abs(bearing) <= fov / 2) & (rng.random(distance.size) < keep)
        desc = self.descriptors[seen] + noise * np.abs(rng.normal(0, 1, (int(seen.sum()), 128))) / np.sqrt(128)
        bearings = bearing[seen] + rng.normal(0, 0.01, int(seen.sum()))
        junk_bearing = rng.uniform(-fov / 2, fov / 2, clutter) if fov < 2 * np.pi else rng.uniform(-np.pi, np.pi, clutter)
        descriptors = np.concatenate([desc, sift_like(clutter, rng)])
        return FeatureSequence.from_unsorted(np.concatenate([bearings, junk_bearing]), normalize_descriptors(descriptors))


def polyline_poses(waypoints, spacing: float) -> np.ndarray:
    """Planar poses every ``spacing`` metres along a polyline, heading along the direction of travel."""
    waypoints = np.asarray(waypoints, dtype=float)
    poses = []
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        length = float(np.hypot(*(b - a)))
        heading = float(np.arctan2(*(b - a)[::-1]))
        for s in np.arange(0.0, length, spacing):
            p = a + (b - a) * s / length
            poses.append((p[0], p[1], heading))
    return np.array(poses)


def loop_route(side: float = 10.0, spacing: float = 0.5) -> np.ndarray:
    """A square driven once, half of it again in the same direction, then back the other way (two revisits)."""
    square = [(0, 0), (side, 0), (side, side), (0, side), (0, 0)]
    again = [(0, 0), (side, 0), (side, side)]
    back = [(side, side), (side, 0), (0, 0)]
    return np.concatenate([polyline_poses(square, spacing), polyline_poses(again, spacing),
                           polyline_poses(back, spacing)])


def ground_truth(poses: np.ndarray, threshold: float, window: int) -> np.ndarray:
    """gt[i, j] (i < j - window): the two poses lie within ``threshold`` metres."""
    n = len(poses)
    distance = np.hypot(poses[:, None, 0] - poses[None, :, 0], poses[:, None, 1] - poses[None, :, 1])
    upper = np.triu(np.ones((n, n), bool), window + 1)
    return (distance < threshold) & upper


def synthetic_sequence(seed: int = 0, side: float = 10.0, spacing: float = 0.5, landmarks: int = 400, **observe):
    rng = np.random.default_rng(seed)
    world = LandmarkWorld.random(landmarks, side, rng)
    poses = loop_route(side, spacing)
    frames = [world.observe(p, rng, **observe) for p in poses]
    return poses, frames
