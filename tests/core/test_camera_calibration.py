"""Camera calibration and cameras at another resolution.

`semloc calibrate-camera` on chessboard sequences rendered through the camera models themselves (pinhole with
distortion from an image folder, fisheye from a lossless video) recovers the true intrinsics within 1 % and writes
the file the camera worker reads; a calibration at another resolution is scaled when the aspect ratio matches and
refused otherwise."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from semloc_core.camera import FisheyeCamera, PinholeCamera, resized
from semloc_core.camera_calibration import Chessboard, new_view
from semloc_core.sim.chessboard import board_poses, chessboard_rays, render_chessboard
from semloc_core.io.camera_model import CalibrationError, fit_to_frames, load_camera, save_camera
from services.frames import camera_from_frame, camera_model_frame
from services.cli import main

BOARD = Chessboard(9, 6, 0.03)
PINHOLE = PinholeCamera(640, 480, np.array([[520.0, 0, 318.2], [0, 515.0, 242.7], [0, 0, 1]]),
                        [-0.28, 0.09, 0.001, -0.0008, -0.01])
FISHEYE = FisheyeCamera(400, 300, np.array([[170.0, 0, 200.7], [0, 168.5, 149.1], [0, 0, 1]]),
                        [0.02, -0.01, 0.004, -0.001])


def render_views(camera, count: int, off_axis_deg: float, distance_m: tuple[float, float]) -> list[np.ndarray]:
    rays = chessboard_rays(camera, supersample=2)
    poses = board_poses(BOARD, count, np.random.default_rng(1), off_axis_deg, distance_m)
    return [render_chessboard(rays, BOARD, T) for T in poses]


def intrinsics(camera) -> np.ndarray:
    return camera.K[[0, 1, 0, 1], [0, 1, 2, 2]]


@pytest.mark.parametrize("truth, container", [(PINHOLE, "folder"), (FISHEYE, "video")], ids=["pinhole", "fisheye"])
def test_calibrate_camera_recovers_the_rendered_intrinsics(tmp_path, capsys, truth, container):
    fisheye = isinstance(truth, FisheyeCamera)
    # Boards close enough for large squares, and (wide lens) spread far off axis
    views = render_views(truth, 12, 40.0 if fisheye else 12.0, (0.22, 0.35) if fisheye else (0.4, 0.6))
    if container == "folder":
        source = tmp_path / "board"
        source.mkdir()
        for index, image in enumerate(views):
            cv2.imwrite(str(source / f"{index:03d}.png"), image)
    else:
        source = tmp_path / "board.mkv"
        writer = cv2.VideoWriter(str(source), cv2.VideoWriter_fourcc(*"FFV1"), 5.0, (truth.width, truth.height))
        for image in views:
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        writer.release()
    output = tmp_path / "camera.yml"
    code = main(["calibrate-camera", str(source), "-o", str(output), "--board", "9x6", "--square", "0.03",
                 "--model", "fisheye" if fisheye else "pinhole", "--quiet"])
    assert code == 0, capsys.readouterr().err
    camera = load_camera(output)  # as the camera worker reads it
    assert type(camera) is type(truth) and (camera.width, camera.height) == (truth.width, truth.height)
    np.testing.assert_allclose(intrinsics(camera), intrinsics(truth), rtol=0.01)
    document = yaml.safe_load(output.read_text())
    assert document["views"] >= 10 and 0 < document["reprojection_error_px"] < 0.2
    # The lens too, where the boards were shown (the middle 60 % of the image; the corners are extrapolated): points
    # land within half a pixel of where the true camera sees them.
    u, v = np.meshgrid(np.linspace(0.2, 0.8, 9) * truth.width, np.linspace(0.2, 0.8, 7) * truth.height)
    rays = truth.rays_cam(u, v)
    np.testing.assert_allclose(camera.project_cam(rays)[0], truth.project_cam(rays)[0], atol=0.5)


def test_calibrate_camera_without_board_views_exits_2(tmp_path, capsys):
    source = tmp_path / "empty"
    source.mkdir()
    for index in range(3):
        cv2.imwrite(str(source / f"{index}.png"), np.full((120, 160), 128, np.uint8))
    assert main(["calibrate-camera", str(source), "-o", str(tmp_path / "camera.yml"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("semloc calibrate-camera: 0 view(s) of a 9x6 chessboard (inner corners, --board) in 3 "
                          "frame(s) searched: at least 3") and "\n" not in err
    assert not (tmp_path / "camera.yml").exists()


@pytest.mark.parametrize("camera", [PINHOLE, FISHEYE], ids=["pinhole", "fisheye"])
def test_resized_camera_sees_what_the_resized_image_shows(camera):
    """A point's pixel in the image resized by s is (u + 0.5) s - 0.5 (cv2.resize's mapping of pixel centres)."""
    smaller = resized(camera, camera.width * 4 // 5, camera.height * 4 // 5)
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, 7), np.linspace(0, camera.height - 1, 5))
    rays = camera.rays_cam(u, v)
    np.testing.assert_allclose(smaller.project_cam(rays)[0], (np.stack([u, v], -1) + 0.5) * 0.8 - 0.5, atol=1e-6)


def test_fit_to_frames_scales_at_the_same_aspect_ratio_and_refuses_another():
    same, warnings = fit_to_frames(PINHOLE, [(640, 480)], "camera.yml")
    assert same is PINHOLE and warnings == []
    scaled, [warning] = fit_to_frames(PINHOLE, [(512, 384)], "camera.yml")
    assert (scaled.width, scaled.height) == (512, 384) and np.isclose(scaled.K[0, 0], 416.0)
    assert "512x384" in warning and "640x480" in warning and "camera.yml" in warning
    with pytest.raises(CalibrationError, match=r"the calibration camera.yml is for 640x480 images, the source gives 640x360"):
        fit_to_frames(PINHOLE, [(640, 360)], "camera.yml")


def test_fisheye_calibration_file_and_frame_round_trip(tmp_path):
    from schemas import Header, decode, encode

    camera = load_camera(save_camera(FISHEYE, tmp_path / "fisheye.yml"))
    assert isinstance(camera, FisheyeCamera)
    np.testing.assert_array_equal(camera.dist, FISHEYE.dist)
    frame = decode(encode(camera_model_frame(camera, Header(robot="r1", stream="s", seq=0, stamp_ns=1))))
    back = camera_from_frame(frame)
    assert isinstance(back, FisheyeCamera) and np.array_equal(back.K, FISHEYE.K)


def test_calibrate_camera_keeps_views_that_moved(tmp_path, capsys):
    """A video starts with seconds of the board held still: the first 40 frames are one pose. Only views that moved
    are kept, so the fit sees the 12 poses shown (it once took the first 40 frames: one pose, no calibration)."""
    views = render_views(PINHOLE, 12, 12.0, (0.4, 0.6))
    source = tmp_path / "board"
    source.mkdir()
    frames = [views[0]] * 40 + views[1:]
    for index, image in enumerate(frames):
        cv2.imwrite(str(source / f"{index:03d}.png"), image)
    output = tmp_path / "camera.yml"
    code = main(["calibrate-camera", str(source), "-o", str(output), "--board", "9x6", "--square", "0.03", "--json",
                 "--quiet"])
    assert code == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["views"] == 12 and summary["boards_seen"] == 51 and summary["frames_read"] == 51
    np.testing.assert_allclose(intrinsics(load_camera(output)), intrinsics(PINHOLE), rtol=0.01)


def test_a_view_is_new_when_its_corners_moved_in_either_order():
    corners = BOARD.object_points()[:, :2] * 1000 + 100
    assert new_view(corners, [], 10.0)
    assert not new_view(corners + 5.0, [corners], 10.0) and new_view(corners + 12.0, [corners], 10.0)
    assert not new_view(corners[::-1] + 5.0, [corners], 10.0)  # the board found in its other orientation
    assert not new_view(corners + 12.0, [corners, corners + 15.0], 10.0)
