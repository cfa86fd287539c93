"""Calibration YAML and CameraModel frames round-trip semloc_core cameras without changing their geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from schemas import Header, decode, encode
from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera, forward_extrinsic, pixel_bearings
from semloc_core.geometry import make_transform, rotation_about_x
from semloc_core.io.camera_model import CalibrationError, load_camera, save_camera
from services.frames import camera_from_frame, camera_model_frame

HEADER = Header(robot="r1", stream="camera/front/model")
K = np.array([[420.0, 0.0, 321.5], [0.0, 418.0, 239.0], [0.0, 0.0, 1.0]])


def _cameras():
    tilted = make_transform(rotation_about_x(0.1) @ forward_extrinsic()[:3, :3], (0.1, 0.0, 1.2))
    return {
        "pinhole": PinholeCamera(640, 480, K, np.array([-0.28, 0.07, 0.001, -0.0005, 0.0]), tilted),
        "pinhole_8": PinholeCamera(64, 48, K / 10 + np.diag([0, 0, 0.9]), np.linspace(-0.1, 0.1, 8)),
        "equirectangular": EquirectangularCamera(256, 128, forward_extrinsic(0.5), 1.0, -0.8),
        "rig": CameraRig.ring(3, 80, 60, 100.0, height_m=1.0),
    }


def _same_geometry(a, b):
    members_a = a.cameras if isinstance(a, CameraRig) else (a,)
    members_b = b.cameras if isinstance(b, CameraRig) else (b,)
    assert len(members_a) == len(members_b)
    for x, y in zip(members_a, members_b):
        assert type(x) is type(y) and (x.width, x.height) == (y.width, y.height)
        np.testing.assert_allclose(x.T_body_cam, y.T_body_cam, atol=1e-12)
        np.testing.assert_allclose(pixel_bearings(x)[::7, ::7], pixel_bearings(y)[::7, ::7], atol=1e-9)


@pytest.mark.parametrize("name", list(_cameras()))
def test_yaml_round_trip(name, tmp_path):
    camera = _cameras()[name]
    path = save_camera(camera, tmp_path / f"{name}.yaml", name=name)
    _same_geometry(camera, load_camera(path))


@pytest.mark.parametrize("name", list(_cameras()))
def test_camera_model_frame_round_trip(name):
    camera = _cameras()[name]
    frame = decode(encode(camera_model_frame(camera, HEADER, name=name)))
    _same_geometry(camera, camera_from_frame(frame))


def test_reads_opencv_filestorage_files(tmp_path):
    path = str(tmp_path / "opencv.yaml")
    storage = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("camera_matrix", K)
    storage.write("distortion_coefficients", np.array([[0.1, -0.2, 0.0, 0.0, 0.05]]))
    storage.release()
    camera = load_camera(path)
    assert isinstance(camera, PinholeCamera)
    np.testing.assert_allclose(camera.K, K)
    np.testing.assert_allclose(camera.dist, [0.1, -0.2, 0.0, 0.0, 0.05])
    np.testing.assert_allclose(camera.T_body_cam, forward_extrinsic())


@pytest.mark.parametrize("text, message", [
    ("image_width: 10\n", "image_height"),
    ("image_width: 10\nimage_height: 10\n", "camera_matrix"),
    ("model: orthographic\nimage_width: 10\nimage_height: 10\n", "unknown camera model"),
    ("image_width: 10\nimage_height: 10\ncamera_matrix: {rows: 3, cols: 3, data: [1, 2]}\n", "needs 9 values"),
    ("model: rig\ncameras: []\n", "non-empty"),
    ("image_width: 10\nimage_height: 10\ncamera_matrix: {rows: 3, cols: 3, data: [0,0,5,0,1,5,0,0,1]}\n", "focal"),
])
def test_bad_calibration_files_are_reported(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=message):
        load_camera(path)


def test_the_core_and_the_wire_agree_on_the_largest_image():
    """The wire contract stands alone (schemas imports nothing of semloc's): its image limit is written twice."""
    from schemas.camera import MAX_SIDE
    from semloc_core.camera import MAX_IMAGE_SIDE

    assert MAX_SIDE == MAX_IMAGE_SIDE
    with pytest.raises(ValueError, match="image sides"):
        PinholeCamera.from_fov(MAX_IMAGE_SIDE + 1, 10, 60.0)


FISHEYE_K = np.array([[230.0, 0.0, 321.3], [0.0, 229.0, 238.4], [0.0, 0.0, 1.0]])
FISHEYE_D = np.array([0.03, -0.012, 0.004, -0.001])


def _true_fisheye_pixels(rays):
    """Where OpenCV's fisheye model of FISHEYE_K, FISHEYE_D sees camera-frame rays: the lens's ground truth."""
    pixels, _ = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), FISHEYE_K, FISHEYE_D)
    return pixels.reshape(-1, 2)


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_reads_opencv_calibration_sample_fisheye_files(tmp_path, suffix):
    # What OpenCV's calibration sample writes for a fisheye lens (any FileStorage format): fisheye_model 1, K, and 4
    # coefficients. Read as a pinhole (4 coefficients are a valid plumb_bob), bearings were up to 24 degrees off.
    path = str(tmp_path / f"fisheye{suffix}")
    storage = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("fisheye_model", 1)
    storage.write("camera_matrix", FISHEYE_K)
    storage.write("distortion_coefficients", FISHEYE_D.reshape(-1, 1))
    storage.release()
    camera = load_camera(path)
    theta, phi = np.meshgrid(np.radians(np.linspace(0, 80, 9)), np.radians(np.linspace(-180, 180, 13)))
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    np.testing.assert_allclose(camera.rays_cam(*_true_fisheye_pixels(rays).T), rays, atol=1e-7)


def test_files_with_opencvs_fisheye_distortion_model_name_are_fisheye(tmp_path):
    path = tmp_path / "camera_info.yaml"
    path.write_text(f"image_width: 640\nimage_height: 480\ndistortion_model: fisheye\n"
                    f"camera_matrix: {{rows: 3, cols: 3, data: {FISHEYE_K.ravel().tolist()}}}\n"
                    f"distortion_coefficients: {{rows: 1, cols: 4, data: {FISHEYE_D.tolist()}}}\n")
    rays = np.array([[0.0, 0.0, 1.0], [np.sin(1.3), 0.0, np.cos(1.3)], [0.3, -0.4, 0.6]])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    np.testing.assert_allclose(load_camera(path).rays_cam(*_true_fisheye_pixels(rays).T), rays, atol=1e-7)


@pytest.mark.parametrize("header, distortion_model, message", [
    ("", "kannala_brandt", "'kannala_brandt' is not a model semloc reads"),
    ("model: fisheye\n", "plumb_bob", "'plumb_bob' is a pinhole lens's, the model is fisheye"),
])
def test_unknown_or_contradicting_distortion_models_are_refused(tmp_path, header, distortion_model, message):
    path = tmp_path / "camera.yaml"
    path.write_text(f"{header}image_width: 640\nimage_height: 480\ndistortion_model: {distortion_model}\n"
                    f"camera_matrix: {{rows: 3, cols: 3, data: {FISHEYE_K.ravel().tolist()}}}\n"
                    f"distortion_coefficients: {{rows: 1, cols: 4, data: {FISHEYE_D.tolist()}}}\n")
    with pytest.raises(CalibrationError, match=f"camera.yaml: distortion_model: {message}"):
        load_camera(path)
