"""Camera frames: ``Image`` (one image per member camera of a rig) and ``CameraModel`` (calibration).

Conventions (docs/conventions.md): pixel data is uint8 ``bgr8`` (OpenCV order), ``rgb8`` or ``mono8``; camera
frames are OpenCV's (x right, y down, z forward); ``T_body_cam`` is the 4x4 pose of the camera in the body frame.
An image may carry a per-frame ``T_body_cam`` override (e.g. a hand-held camera's pitch and roll from its IMU).

Converters to and from ``semloc_core.camera`` objects live in ``services.calibration`` (schemas depend on nothing
of ours).
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

import numpy as np
from pydantic import AfterValidator, Field, field_validator, model_validator

from schemas.base import Array, Frame, FrameError, Sub
from schemas.limits import MAX_DISTORTION, MAX_FOCAL, MAX_MOUNT_OFFSET
from semloc_core.geometry import check_rigid_transform

MAX_SIDE = 16384
MAX_CAMERAS = 32
PixelEncoding = Literal["bgr8", "rgb8", "mono8"]
Compression = Literal["none", "jpeg", "png"]
Side = Annotated[int, Field(ge=1, le=MAX_SIDE)]
Transform = Array("float64", shape=(4, 4), finite=True,
                  description=f"a proper rotation, last row (0, 0, 0, 1), |translation| <= {MAX_MOUNT_OFFSET} m")
_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


def check_mount(T: np.ndarray) -> np.ndarray:
    """A rigid transform (semloc_core.geometry.check_rigid_transform) with a translation within MAX_MOUNT_OFFSET (a
    camera on its body), or ValueError (FrameError ``range`` for the translation)."""
    T = check_rigid_transform(T, "T_body_cam")
    offset = float(np.linalg.norm(T[:3, 3]))
    if not offset <= MAX_MOUNT_OFFSET:
        raise FrameError(f"T_body_cam puts the camera {offset:.3g} m from the body (at most {MAX_MOUNT_OFFSET})",
                         reason="range")
    return T


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, extended, progressive, lossless; not DHT C4, JPG C8, DAC CC)
_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})


def compressed_size(data, compression: str | None = None) -> tuple[int, int]:
    """(width, height) written in the header of PNG (IHDR) or JPEG (start of frame) bytes, read without decoding;
    FrameError ``image_header`` when the bytes do not start like ``compression`` (None: either format) or have no
    such header. The decoder allocates what the header says: checking it against the declared size first is what
    stops a decompression bomb (a few hundred KB of PNG holding a 12000x12000 image)."""
    raw = memoryview(np.ascontiguousarray(np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray))
                                          else data, dtype=np.uint8)).cast("B")
    if compression is None:
        compression = "png" if bytes(raw[:8]) == _PNG_SIGNATURE else "jpeg"
    if compression == "png":
        if bytes(raw[:8]) != _PNG_SIGNATURE or bytes(raw[12:16]) != b"IHDR" or len(raw) < 24:
            raise FrameError("png data does not start with a PNG signature and IHDR header", reason="image_header")
        return int.from_bytes(raw[16:20], "big"), int.from_bytes(raw[20:24], "big")
    if bytes(raw[:2]) != b"\xff\xd8":
        raise FrameError("jpeg data does not start with a JPEG start-of-image marker", reason="image_header")
    at, size = 2, len(raw)
    while at + 4 <= size:
        if raw[at] != 0xFF:
            break
        marker = raw[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # markers without a length
            at += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before the data
            break
        if marker in _JPEG_SOF:
            if at + 9 > size:
                break
            return int.from_bytes(raw[at + 7 : at + 9], "big"), int.from_bytes(raw[at + 5 : at + 7], "big")
        at += 2 + int.from_bytes(raw[at + 2 : at + 4], "big")
    raise FrameError("jpeg data has no readable start-of-frame header", reason="image_header")


# A camera's pose on the body: finite, a proper rotation, last row (0, 0, 0, 1).
RigidTransform = Annotated[Transform, AfterValidator(check_mount)]


class CameraImage(Sub):
    """The image of one member camera. ``data`` is ``(height, width, 3)`` / ``(height, width)`` uint8 pixels when
    ``compression == "none"``, else the 1-D encoded file bytes (JPEG or PNG)."""

    camera: Annotated[int, Field(ge=0, lt=MAX_CAMERAS)] = 0
    width: Side
    height: Side
    encoding: PixelEncoding = "bgr8"
    compression: Compression = "none"
    data: Array("uint8", ndim=(1, 2, 3))
    T_body_cam: RigidTransform | None = None

    @model_validator(mode="after")
    def _consistent(self):
        if self.compression == "none":
            want = (self.height, self.width) if self.encoding == "mono8" else (self.height, self.width, 3)
            if self.data.shape != want:
                raise ValueError(f"{self.encoding} pixels must have shape {want}, got {self.data.shape}")
            return self
        if self.data.ndim != 1 or self.data.size == 0:
            raise ValueError(f"{self.compression} data must be non-empty 1-D bytes, got shape {self.data.shape}")
        size = compressed_size(self.data, self.compression)
        if size != (self.width, self.height):
            raise FrameError(f"{self.compression} header says {size[0]}x{size[1]}, the frame {self.width}x"
                             f"{self.height}", reason="image_header")
        return self

    def pixels(self) -> np.ndarray:
        """Pixels in this image's ``encoding`` (decompressed if needed; a read-only view when uncompressed)."""
        if self.compression == "none":
            return self.data
        import cv2  # only consumers of compressed images pay for the import

        flag = cv2.IMREAD_GRAYSCALE if self.encoding == "mono8" else cv2.IMREAD_COLOR
        pixels = cv2.imdecode(self.data, flag)
        if pixels is None or pixels.shape[:2] != (self.height, self.width):
            raise ValueError(f"{self.compression} data does not decode to a {self.width}x{self.height} image")
        if self.encoding == "rgb8":
            pixels = pixels[..., ::-1]
        return pixels

    def bgr(self) -> np.ndarray:
        """Pixels as semloc_core expects them: BGR ``(H, W, 3)`` or grey ``(H, W)``."""
        pixels = self.pixels()
        return np.ascontiguousarray(pixels[..., ::-1]) if self.encoding == "rgb8" else pixels


class Image(Frame, schema="semloc.Image", version=1, max_bytes=256 << 20):
    """Images captured together: one per member camera (a single camera has one)."""

    images: Annotated[list[CameraImage], Field(min_length=1, max_length=MAX_CAMERAS)]

    @model_validator(mode="after")
    def _distinct_cameras(self):
        indices = [image.camera for image in self.images]
        if len(set(indices)) != len(indices):
            raise ValueError(f"camera indices must be distinct, got {indices}")
        return self

    @classmethod
    def from_pixels(
        cls,
        header,
        pixels: np.ndarray,
        *,
        encoding: PixelEncoding | None = None,
        jpeg_quality: int | None = None,
        T_body_cam: np.ndarray | None = None,
        camera: int = 0,
    ) -> "Image":
        """A single-camera image frame; ``jpeg_quality`` (1-100) compresses it."""
        return cls(header=header, images=[camera_image(pixels, encoding=encoding, jpeg_quality=jpeg_quality,
                                                        T_body_cam=T_body_cam, camera=camera)])

    def bgr(self, index: int = 0) -> np.ndarray:
        return self.images[index].bgr()


def camera_image(
    pixels: np.ndarray,
    *,
    encoding: PixelEncoding | None = None,
    jpeg_quality: int | None = None,
    T_body_cam: np.ndarray | None = None,
    camera: int = 0,
) -> CameraImage:
    """One member camera's image from uint8 pixels (``(H, W, 3)`` BGR by default, or ``(H, W)`` grey)."""
    pixels = np.asarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] != 3):
        raise ValueError(f"pixels must be uint8 (H, W) or (H, W, 3), got {pixels.dtype} {pixels.shape}")
    if encoding is None:
        encoding = "mono8" if pixels.ndim == 2 else "bgr8"
    height, width = pixels.shape[:2]
    data, compression = pixels, "none"
    if jpeg_quality is not None:
        import cv2

        if not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        source = pixels[..., ::-1] if encoding == "rgb8" else pixels
        ok, buffer = cv2.imencode(".jpg", np.ascontiguousarray(source), [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise ValueError("JPEG encoding failed")
        data, compression = buffer.reshape(-1), "jpeg"
    return CameraImage(camera=camera, width=width, height=height, encoding=encoding, compression=compression,
                       data=data, T_body_cam=T_body_cam)


def _positive_focal(K):
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise FrameError("focal lengths must be positive", reason="range")
    return K


class PinholeSpec(Sub):
    """Pinhole intrinsics ``K`` with OpenCV distortion (0, 4, 5, 8, 12 or 14 coefficients)."""

    kind: Literal["pinhole"] = "pinhole"
    width: Side
    height: Side
    K: Array("float64", shape=(3, 3), finite=True, bounds=(-MAX_FOCAL, MAX_FOCAL))
    dist: Array("float64", ndim=1, finite=True, max_elements=14, bounds=(-MAX_DISTORTION, MAX_DISTORTION)) = Field(
        default_factory=lambda: np.zeros(0))
    T_body_cam: RigidTransform

    _focal = field_validator("K")(_positive_focal)

    @field_validator("dist")
    @classmethod
    def _dist(cls, dist):
        if dist.size not in _DISTORTION_LENGTHS:
            raise ValueError(f"distortion must have one of {_DISTORTION_LENGTHS} coefficients, got {dist.size}")
        return dist


class FisheyeSpec(Sub):
    """OpenCV's fisheye (equidistant) model: intrinsics ``K`` and 4 coefficients k1..k4 (``cv2.fisheye``)."""

    kind: Literal["fisheye"] = "fisheye"
    width: Side
    height: Side
    K: Array("float64", shape=(3, 3), finite=True, bounds=(-MAX_FOCAL, MAX_FOCAL))
    dist: Array("float64", shape=(4,), finite=True, bounds=(-MAX_DISTORTION, MAX_DISTORTION))
    T_body_cam: RigidTransform

    _focal = field_validator("K")(_positive_focal)


class EquirectangularSpec(Sub):
    """A 360-degree panorama: column -> longitude, row -> latitude between ``lat_top`` and ``lat_bottom``."""

    kind: Literal["equirectangular"] = "equirectangular"
    width: Side
    height: Side
    T_body_cam: RigidTransform
    lat_top: Annotated[float, Field(ge=-np.pi / 2, le=np.pi / 2)]
    lat_bottom: Annotated[float, Field(ge=-np.pi / 2, le=np.pi / 2)]

    @model_validator(mode="after")
    def _order(self):
        if not self.lat_bottom < self.lat_top:
            raise ValueError("lat_bottom must be below lat_top")
        return self


CameraSpec = Annotated[Union[PinholeSpec, FisheyeSpec, EquirectangularSpec], Field(discriminator="kind")]


class CameraModel(Frame, schema="semloc.CameraModel", version=1, max_bytes=1 << 20):
    """Calibration of a camera or rig; ``cameras[i]`` is member camera ``i`` of the ``Image`` frames."""

    name: Annotated[str, Field(max_length=128)] = ""
    cameras: Annotated[list[CameraSpec], Field(min_length=1, max_length=MAX_CAMERAS)]
