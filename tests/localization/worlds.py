"""Small worlds built from arrays for the filter tests: a table top with five classes, a camera circling it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import Odometry, field_of_view_mask, synthetic_scores_heatlines, visible_objects

CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")


@dataclass
class World:
    semantic_map: SemanticMap
    poses: np.ndarray  # (T, 3) ground-truth planar poses
    observed: np.ndarray  # field-of-view mask
    dt: float
    teleports: tuple[int, ...] = ()  # frames where the ground truth jumps (odometry sees no motion)

    def odometry(self, k: int, rng: np.random.Generator, noise: float = 1e-3) -> Odometry | None:
        if k == 0:
            return None
        if k in self.teleports:
            return Odometry(0.0, 0.0, 0.0, self.dt)
        step = Odometry.between(self.poses[k - 1], self.poses[k], self.dt)
        return Odometry(step.dx + noise * rng.normal(), step.dy + noise * rng.normal(),
                        step.dtheta + 3 * noise * rng.normal(), self.dt)

    def heatlines(self, k: int):
        return self.heatlines_at(self.poses[k])

    def heatlines_at(self, pose):
        """What a camera at ``pose`` would see (for frames that disagree with the ground truth)."""
        views = visible_objects(np.asarray(pose, float), self.semantic_map, self.observed, CLASSES)
        return synthetic_scores_heatlines(views, self.observed)


def tabletop(frames: int = 300, seed: int = 0, fov_deg: float = 57.0) -> World:
    """Five objects within 0.4 m of the table centre, a camera 1-1.4 m away circling it and facing it (about the
    motion of the RGB-D Scenes trajectories), a 57-degree field of view, 30 frames per second."""
    rng = np.random.default_rng(seed)
    objects = []
    for name in CLASSES:
        angle, radius = rng.uniform(0, 2 * np.pi), rng.uniform(0.05, 0.4)
        objects.append({"class": name, "position": [radius * math.cos(angle), radius * math.sin(angle), 0.8],
                        "size": [0.12, 0.12, 0.15]})
    semantic_map = SemanticMap.from_objects(objects, bounds=[[-2, -2], [2, 2]])
    s = np.linspace(0, 1, frames)
    angle = 2 * np.pi * 0.9 * s + 0.3 * np.sin(6 * s)
    radius = 1.2 + 0.2 * np.sin(9 * s)
    heading = angle + np.pi + 0.2 * np.sin(17 * s)
    poses = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), (heading + np.pi) % (2 * np.pi) - np.pi])
    return World(semantic_map, poses, field_of_view_mask(360, 0.0, math.radians(fov_deg)), 1 / 30)


def kidnapped(world: World, at: int) -> World:
    """The same world, the ground truth teleported half a turn around the table at frame ``at``."""
    frames = world.poses.shape[0]
    order = np.r_[np.arange(at), (np.arange(at, frames) + frames // 2) % frames]
    return World(world.semantic_map, world.poses[order], world.observed, world.dt, (at,))
