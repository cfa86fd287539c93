"""A chessboard seen by any semloc camera model, rendered by casting each pixel's ray (the model's own
``rays_cam``) onto the board plane: the ground truth of camera calibration (``semloc_core.camera_calibration``)."""

from __future__ import annotations

import numpy as np

from semloc_core.camera import pixel_grid
from semloc_core.camera_calibration import Chessboard

BACKGROUND = 90  # grey around the board's white margin


def chessboard_rays(camera, supersample: int = 3) -> np.ndarray:
    """Camera-frame rays (H, W, S*S, 3) at ``supersample`` x ``supersample`` points per pixel: computed once per
    camera, they serve every board pose."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = (a.ravel() for a in np.meshgrid(offsets, offsets))
    u, v = pixel_grid(camera)
    return camera.rays_cam(u[..., None] + du, v[..., None] + dv)


def render_chessboard(rays: np.ndarray, board: Chessboard, T_cam_board: np.ndarray) -> np.ndarray:
    """A grey uint8 image of ``board`` at pose ``T_cam_board`` (board frame -> camera frame; the board's inner
    corners at (i s, j s, 0)) seen along ``rays`` (:func:`chessboard_rays`): black and white squares, a one-square
    white margin (as printed boards have), grey beyond; anti-aliased by the supersampling."""
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    normal = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (normal @ t) / (rays @ normal)
    hit = np.isfinite(depth) & (depth > 0)
    points = (np.where(hit, depth, 0.0)[..., None] * rays - t) @ R  # board frame
    s = board.square_m
    x, y = points[..., 0] / s, points[..., 1] / s
    on_squares = (x >= -1) & (x < board.columns) & (y >= -1) & (y < board.rows)
    on_margin = (x >= -2) & (x < board.columns + 1) & (y >= -2) & (y < board.rows + 1)
    black = (np.floor(x) + np.floor(y)) % 2 == 0
    value = np.where(on_squares, np.where(black, 0.0, 255.0), np.where(on_margin, 255.0, BACKGROUND))
    value = np.where(hit, value, BACKGROUND)
    return np.clip(np.round(value.mean(axis=-1)), 0, 255).astype(np.uint8)


def board_poses(board: Chessboard, count: int, rng: np.random.Generator, max_off_axis_deg: float,
                distance_m: tuple[float, float], max_tilt_deg: float = 35.0) -> list[np.ndarray]:
    """``count`` poses T_cam_board of a board facing the camera, as a person shows it: its centre up to
    ``max_off_axis_deg`` off the optical axis (uniform over the disc) at ``distance_m`` (min, max), tilted by up to
    ``max_tilt_deg`` about its own axes (a third of it in-plane)."""
    from scipy.spatial.transform import Rotation

    centre = np.array([(board.columns - 1) / 2.0, (board.rows - 1) / 2.0, 0.0]) * board.square_m
    poses = []
    for _ in range(count):
        off_axis = np.radians(max_off_axis_deg) * np.sqrt(rng.uniform())
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        direction = np.array([np.sin(off_axis) * np.cos(azimuth), np.sin(off_axis) * np.sin(azimuth), np.cos(off_axis)])
        x = np.cross([0.0, 1.0, 0.0], direction)
        x /= np.linalg.norm(x)
        facing = np.stack([x, np.cross(direction, x), direction], axis=1)  # board z along the line of sight
        tilt = Rotation.from_euler("xyz", rng.uniform(-max_tilt_deg, max_tilt_deg, 3) * [1.0, 1.0, 1.0 / 3.0],
                                   degrees=True).as_matrix()
        R = facing @ tilt
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = rng.uniform(*distance_m) * direction - R @ centre
        poses.append(T)
    return poses
