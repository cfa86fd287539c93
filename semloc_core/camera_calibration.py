"""Camera calibration from views of a chessboard (OpenCV): a pinhole camera with OpenCV's distortion (plumb_bob,
5 coefficients) or a fisheye camera (equidistant, k1..k4). Arrays in, a camera model and its reprojection error
out; reading frames and writing the calibration file is the command's (``semloc calibrate-camera``).

Pixel convention: pixel centres at integer coordinates, as everywhere in semloc and in OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from semloc_core.camera import FisheyeCamera, PinholeCamera

MIN_VIEWS = 3  # fewer views leave the intrinsics under-determined
CameraKind = Literal["pinhole", "fisheye"]


@dataclass(frozen=True)
class Chessboard:
    """A chessboard of ``columns`` x ``rows`` inner corners (OpenCV's pattern size) and ``square_m`` squares."""

    columns: int = 9
    rows: int = 6
    square_m: float = 0.025

    def __post_init__(self) -> None:
        if self.columns < 3 or self.rows < 3 or self.columns == self.rows:
            raise ValueError(f"a chessboard needs at least 3x3 inner corners and columns != rows (its orientation), "
                             f"got {self.columns}x{self.rows}")
        if not self.square_m > 0:
            raise ValueError(f"the square size must be positive, got {self.square_m}")

    def object_points(self) -> np.ndarray:
        """The inner corners in the board frame (N, 3), row by row as OpenCV finds them: (i s, j s, 0)."""
        j, i = np.mgrid[0 : self.rows, 0 : self.columns]
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_m


@dataclass(frozen=True)
class Calibration:
    camera: PinholeCamera | FisheyeCamera
    rms_px: float                   # reprojection error over every corner of every view (pixels, RMS)
    views: int


def find_corners(image: np.ndarray, board: Chessboard) -> np.ndarray | None:
    """The board's inner corners in ``image`` (N, 2) to sub-pixel accuracy (``cv2.findChessboardCornersSB``), or
    None when the whole board is not seen."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found, corners = cv2.findChessboardCornersSB(grey, (board.columns, board.rows),
                                                 flags=cv2.CALIB_CB_ACCURACY)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def new_view(corners: np.ndarray, kept: list[np.ndarray], min_move_px: float) -> bool:
    """Whether a view's corners (N, 2) moved on average at least ``min_move_px`` from those of every view ``kept``
    (either corner order: the board's two 180-degree orientations). Why: the frames of a video are seconds of nearly
    one pose; forty of them fit a lens that reprojects them well and is wrong elsewhere (docs/camera.md)."""
    for view in kept:
        move = min(np.mean(np.linalg.norm(corners - view, axis=1)),
                   np.mean(np.linalg.norm(corners - view[::-1], axis=1)))
        if move < min_move_px:
            return False
    return True


def calibrate(corners: list[np.ndarray], board: Chessboard, width: int, height: int,
              model: CameraKind = "pinhole") -> Calibration:
    """Intrinsics and distortion from the corners of several views (each (N, 2), :func:`find_corners`) of
    ``width`` x ``height`` images. Raises ValueError with fewer than ``MIN_VIEWS`` views or when OpenCV fails."""
    if len(corners) < MIN_VIEWS:
        raise ValueError(f"{len(corners)} view(s) of the chessboard, at least {MIN_VIEWS} are needed: show the board "
                         f"whole, at several angles and distances")
    points = board.object_points()
    count = len(points)
    for k, view in enumerate(corners):
        if np.shape(view) != (count, 2):
            raise ValueError(f"view {k}: {np.shape(view)} corners, the {board.columns}x{board.rows} board has "
                             f"({count}, 2)")
    image_points = [np.asarray(c, np.float64).reshape(-1, 1, 2) for c in corners]
    object_points = [points.reshape(-1, 1, 3).astype(np.float64)] * len(corners)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        if model == "fisheye":
            flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
            _, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(object_points, image_points, (width, height), None,
                                                             None, flags=flags, criteria=criteria)
            camera = FisheyeCamera(width, height, K, dist.ravel())
        elif model == "pinhole":
            _, K, dist, rvecs, tvecs = cv2.calibrateCamera([p.astype(np.float32) for p in object_points],
                                                           [p.astype(np.float32) for p in image_points],
                                                           (width, height), None, None, criteria=criteria)
            camera = PinholeCamera(width, height, K, dist.ravel()[:5])
        else:
            raise ValueError(f"unknown camera model {model!r} (pinhole or fisheye)")
    except cv2.error as error:
        raise ValueError(f"OpenCV could not calibrate from these views: {' '.join(str(error).split())[-200:]}") \
            from None
    view_rms = np.array([_view_rms(camera, points, view, rvec, tvec)
                         for view, rvec, tvec in zip(corners, rvecs, tvecs)])
    rms = float(np.sqrt(np.mean(view_rms**2)))
    return Calibration(camera, rms, len(corners))


def _view_rms(camera, points: np.ndarray, corners: np.ndarray, rvec, tvec) -> float:
    """RMS distance (px) between the corners found and the board's corners projected with the calibration."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    projected, _ = camera.project_cam(points @ R.T + np.asarray(tvec, np.float64).reshape(1, 3))
    return float(np.sqrt(np.mean(np.sum((projected - np.asarray(corners).reshape(-1, 2)) ** 2, axis=1))))
