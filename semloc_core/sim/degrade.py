"""Degrade any image sequence the way robot cameras do (issue 33): downscaling, a circular fisheye warp with a dark
rim, a fixed body overlay, blur, noise, an exposure change between traversals, JPEG.

``Degradation`` says what to apply; ``degrade(image, frame, frames, degradation)`` applies it to one BGR frame of a
sequence of ``frames`` (the exposure change hits the second half, as a second traversal under other light).
Deterministic: frame k's noise comes from a generator seeded with (seed, k). The order is the camera's: optics
(fisheye warp, blur), the scene's light (exposure), the robot's body in front of the lens, the sensor (downscale,
noise), the encoder (JPEG).

``fisheye_camera(degradation, width, height)`` is the OpenCV fisheye model (equidistant, k1..k4 = 0) of the warped
image, so the bearings of a degraded sequence can be computed with the lens that made it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

RIM_LEVEL = 6  # grey level of the dark rim outside the image circle (a lens rim is not perfectly black)


@dataclass(frozen=True)
class Degradation:
    """What to do to each frame; the default does nothing.

    ``size``: (width, height) after downscaling (INTER_AREA), None keeps the size. ``fisheye``: warp the (pinhole,
    ``source_fov_deg`` horizontal) image into an equidistant fisheye whose image circle (diameter ``fisheye_circle``
    of the shorter side) sees ``fisheye_fov_deg`` across (None: the source's horizontal field, so the circle shows
    what the source saw), the rest a dark rim.
    ``body``: a fixed dark shape (the robot's bumper and a mast) over the lower ``body`` fraction of the image, 0 =
    none. ``blur_sigma`` pixels (of the output size). ``noise_sigma`` grey levels. ``exposure``: gain of the second
    half of the sequence (1 = none), with gamma ``exposure_gamma``. ``jpeg_quality`` 1-100, 0 = no re-encoding.
    """

    size: tuple[int, int] | None = None
    source_fov_deg: float = 60.0
    fisheye: bool = False
    fisheye_fov_deg: float | None = None
    fisheye_circle: float = 0.95
    body: float = 0.0
    blur_sigma: float = 0.0
    noise_sigma: float = 0.0
    exposure: float = 1.0
    exposure_gamma: float = 1.0
    jpeg_quality: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.size is not None:
            w, h = (int(v) for v in self.size)
            if w < 16 or h < 16:
                raise ValueError(f"degradation size must be at least 16x16, got {self.size}")
            object.__setattr__(self, "size", (w, h))
        if not 0 < self.source_fov_deg < 180 or not (self.fisheye_fov_deg is None or 0 < self.fisheye_fov_deg < 360):
            raise ValueError("source_fov_deg must be in (0, 180) and fisheye_fov_deg in (0, 360)")
        if not 0.1 <= self.fisheye_circle <= 1.5 or not 0 <= self.body < 0.6:
            raise ValueError("fisheye_circle must be in [0.1, 1.5] and body in [0, 0.6)")
        if self.blur_sigma < 0 or self.noise_sigma < 0 or not self.exposure > 0 or not self.exposure_gamma > 0:
            raise ValueError("blur_sigma and noise_sigma must be >= 0, exposure and exposure_gamma > 0")
        if not 0 <= self.jpeg_quality <= 100:
            raise ValueError("jpeg_quality must be in [0, 100] (0: no re-encoding)")

    @property
    def is_identity(self) -> bool:
        return self == Degradation(seed=self.seed, source_fov_deg=self.source_fov_deg)

    def output_size(self, width: int, height: int) -> tuple[int, int]:
        return self.size if self.size is not None else (int(width), int(height))


def fisheye_focal(degradation: Degradation, width: int, height: int) -> float:
    """f of the equidistant model r = f * theta: the image circle's radius sees half the fisheye's field."""
    radius = 0.5 * degradation.fisheye_circle * min(width, height)
    fov = degradation.source_fov_deg if degradation.fisheye_fov_deg is None else degradation.fisheye_fov_deg
    return radius / np.radians(0.5 * fov)


def fisheye_camera(degradation: Degradation, width: int, height: int):
    """The OpenCV fisheye model (k1..k4 = 0: equidistant) of a warped image of ``width`` x ``height``."""
    from semloc_core.camera import FisheyeCamera

    f = fisheye_focal(degradation, width, height)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    return FisheyeCamera(width, height, K, np.zeros(4))


def _fisheye_maps(degradation: Degradation, src_w: int, src_h: int, out_w: int, out_h: int):
    f_src = 0.5 * src_w / np.tan(np.radians(0.5 * degradation.source_fov_deg))
    f = fisheye_focal(degradation, out_w, out_h)
    v, u = np.mgrid[0:out_h, 0:out_w].astype(np.float64)
    dx, dy = u - (out_w - 1) / 2, v - (out_h - 1) / 2
    r = np.hypot(dx, dy)
    theta = r / f
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 0, f_src * np.tan(np.minimum(theta, np.radians(89.0))) / np.maximum(r, 1e-12), 0.0)
    map_x = (dx * scale + (src_w - 1) / 2).astype(np.float32)
    map_y = (dy * scale + (src_h - 1) / 2).astype(np.float32)
    radius = 0.5 * degradation.fisheye_circle * min(out_w, out_h)
    # An anti-aliased circle: 1 inside, 0 beyond a pixel outside it.
    inside = np.clip(radius - r + 0.5, 0.0, 1.0).astype(np.float32)
    return map_x, map_y, inside


def _body_mask(width: int, height: int, fraction: float) -> np.ndarray:
    """A fixed silhouette: a rounded bumper along the bottom and a mast rising at the left."""
    mask = np.zeros((height, width), np.uint8)
    top = int(round(height * (1 - fraction)))
    cv2.ellipse(mask, (width // 2, height + int(0.15 * height)), (int(0.6 * width), height - top + int(0.15 * height)),
                0, 180, 360, 255, -1)
    mast_w = max(2, width // 14)
    cv2.rectangle(mask, (width // 6, top - int(0.25 * height)), (width // 6 + mast_w, height), 255, -1)
    return mask


def degrade(image: np.ndarray, frame: int, frames: int, degradation: Degradation) -> np.ndarray:
    """Frame ``frame`` of a sequence of ``frames`` (BGR or grey uint8), degraded."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"degrade needs a uint8 grey or BGR image, got {image.dtype} {image.shape}")
    d = degradation
    if d.is_identity:
        return image
    src_h, src_w = image.shape[:2]
    out_w, out_h = d.output_size(src_w, src_h)
    out = image.astype(np.float32)
    if d.fisheye:
        # Warp at the source resolution (then downscale), so the fisheye is sampled as finely as the lens would.
        map_x, map_y, inside = _fisheye_maps(d, src_w, src_h, src_w, src_h)
        out = cv2.remap(out, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=RIM_LEVEL)
        weight = inside if out.ndim == 2 else inside[..., None]
        out = out * weight + RIM_LEVEL * (1 - weight)
    if d.exposure != 1.0 and frame >= frames // 2:
        out = 255.0 * np.clip(d.exposure * (out / 255.0) ** d.exposure_gamma, 0.0, 1.0)
    if d.body > 0:
        mask = _body_mask(src_w, src_h, d.body).astype(np.float32) / 255.0
        mask = cv2.GaussianBlur(mask, (0, 0), max(0.5, 0.004 * src_w))
        shade = 28.0 + 10.0 * np.linspace(0, 1, src_w, dtype=np.float32)[None, :]
        weight = mask if out.ndim == 2 else mask[..., None]
        out = out * (1 - weight) + (shade if out.ndim == 2 else shade[..., None]) * weight
    if (out_w, out_h) != (src_w, src_h):
        out = cv2.resize(out, (out_w, out_h), interpolation=cv2.INTER_AREA)
    if d.blur_sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), d.blur_sigma)
    if d.noise_sigma > 0:
        rng = np.random.default_rng([d.seed, frame])
        out = out + rng.normal(0.0, d.noise_sigma, out.shape).astype(np.float32)
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    if d.jpeg_quality:
        ok, buffer = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(d.jpeg_quality)])
        if not ok:
            raise ValueError("JPEG encoding failed")
        out = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    return out


PRESETS = {
    "none": Degradation(),
    "small": Degradation(size=(160, 120)),
    "fisheye": Degradation(fisheye=True),
    "body": Degradation(body=0.22),
    "exposure": Degradation(exposure=0.45, exposure_gamma=1.3),
    "robot": Degradation(size=(160, 120), fisheye=True, body=0.22, exposure=0.45, exposure_gamma=1.3,
                         blur_sigma=0.6, noise_sigma=2.0, jpeg_quality=75),
    "sensor": Degradation(exposure=0.45, exposure_gamma=1.3, blur_sigma=0.6, noise_sigma=2.0, jpeg_quality=75),
}
"""Named degradations for ``semloc eval loopclosure``'s ``degrade`` (and the sim): ``robot`` is all of them at
160x120, as the corridor that issue 33 describes; ``sensor`` its light, blur, noise and JPEG on the camera as it is
(the second traversal of ``semloc eval localization``'s ``prior_lap``)."""
