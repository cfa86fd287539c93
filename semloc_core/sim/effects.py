"""Camera effects applied after rendering: illumination change, exposure, vignetting, motion blur, sensor noise.

Deterministic: the noise of frame i comes from a generator seeded with (scenario seed, i).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Realism:
    """Knobs of the image formation; ``Realism.off()`` gives the bare render (for geometry checks)."""

    noise_sigma: float = 1.5  # additive read noise, grey levels
    shot_noise: float = 0.25  # signal-dependent noise: sigma = shot_noise * sqrt(level)
    exposure_time: float = 1.0 / 60.0  # seconds; motion blur spans the motion during it
    motion_blur: bool = True
    vignetting: float = 0.2  # relative darkening at the image corners (pinhole only)
    illumination_change: float = 0.2  # amplitude of the slow exposure/lighting drift (log gain)
    illumination_period: float = 90.0  # seconds: revisits later in a sequence see another light
    colour_cast: float = 0.05  # amplitude of the white-balance drift per channel
    light_swing_deg: float = 35.0  # how far the light direction turns over a period

    @classmethod
    def off(cls) -> "Realism":
        return cls(noise_sigma=0.0, shot_noise=0.0, exposure_time=0.0, motion_blur=False, vignetting=0.0,
                   illumination_change=0.0, colour_cast=0.0, light_swing_deg=0.0)

    def validate(self) -> "Realism":
        for name in ("noise_sigma", "shot_noise", "exposure_time", "vignetting", "illumination_change",
                     "colour_cast", "light_swing_deg"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"realism.{name} must be finite and >= 0, got {value}")
        if self.illumination_period <= 0:
            raise ValueError("realism.illumination_period must be positive")
        return self


@dataclass(frozen=True)
class FrameLight:
    """Illumination of one frame: global gain, per-channel white balance, light azimuth offset (radians)."""

    gain: float
    balance: tuple[float, float, float]
    light_azimuth: float


def illumination_schedule(realism: Realism, stamps_s: np.ndarray, seed: int) -> list[FrameLight]:
    """Slowly varying illumination over the sequence (so a place revisited later looks different)."""
    rng = np.random.default_rng([seed, 424242])
    phases = rng.uniform(0, 2 * np.pi, 6)
    t = np.asarray(stamps_s, float)
    period = realism.illumination_period
    w = 2 * np.pi / period
    log_gain = realism.illumination_change * (np.sin(w * t + phases[0]) + 0.5 * np.sin(2.7 * w * t + phases[1]))
    out = []
    for i, ti in enumerate(t):
        balance = tuple(1.0 + realism.colour_cast * np.sin(w * 0.8 * ti + phases[2 + c]) for c in range(3))
        azimuth = np.radians(realism.light_swing_deg) * np.sin(w * 0.6 * ti + phases[5])
        out.append(FrameLight(float(np.exp(log_gain[i])), balance, float(azimuth)))
    return out


def vignette_map(height: int, width: int, strength: float) -> np.ndarray:
    """(H, W, 3) float32 gain: 1 at the centre, 1 - strength at the corners."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = ((x - (width - 1) / 2) / (width / 2)) ** 2 + ((y - (height - 1) / 2) / (height / 2)) ** 2
    gain = (1.0 - strength * r2 / 2.0).astype(np.float32)
    return np.ascontiguousarray(np.repeat(gain[..., None], 3, axis=2))


def line_kernel(dx: float, dy: float) -> np.ndarray | None:
    """Normalised motion-blur kernel along the displacement (dx, dy) pixels; None if shorter than a pixel."""
    length = float(np.hypot(dx, dy))
    if length < 1.0:
        return None
    size = int(np.ceil(length)) | 1
    size += 2
    kernel = np.zeros((size, size), np.float32)
    c = (size - 1) / 2
    samples = max(3, int(np.ceil(length * 4)))
    for s in np.linspace(-0.5, 0.5, samples):
        x, y = c + s * dx, c + s * dy
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        for xx, yy, wgt in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)), (x0, y0 + 1, (1 - fx) * fy),
                            (x0 + 1, y0 + 1, fx * fy)):
            if 0 <= xx < size and 0 <= yy < size:
                kernel[yy, xx] += wgt
    return kernel / kernel.sum()


def motion_blur(image: np.ndarray, flows: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Blur along per-column-band displacements ``flows`` (B, 2) in pixels over the exposure (B = 1: global);
    ``wrap`` for panoramas, whose first and last columns are neighbours."""
    flows = np.asarray(flows, float).reshape(-1, 2)
    if len(flows) == 1:
        kernel = line_kernel(*flows[0])
        return image if kernel is None else cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT)
    width = image.shape[1]
    bands = len(flows)
    edges = np.linspace(0, width, bands + 1).astype(int)
    out = image.copy()
    pad = int(np.ceil(np.abs(flows).max())) + 2
    for b in range(bands):
        kernel = line_kernel(*flows[b])
        if kernel is None:
            continue
        a0, a1 = edges[b], edges[b + 1]
        if wrap and (a0 - pad < 0 or a1 + pad > width):
            # The panorama's columns are periodic.
            strip = image[:, np.arange(a0 - pad, a1 + pad) % width]
            lo = pad
        else:
            c0 = max(a0 - pad, 0)
            strip = image[:, c0:min(a1 + pad, width)]
            lo = a0 - c0
        blurred = cv2.filter2D(strip, -1, kernel, borderType=cv2.BORDER_REFLECT)
        out[:, a0:a1] = blurred[:, lo:lo + (a1 - a0)]
    return out


class NoiseBank:
    """A fixed field of standard normal noise twice the image size; each frame reads a window at a seeded offset.

    Drawing fresh Gaussian noise for every pixel of every frame costs more than rendering; windows of one larger
    field are as random to any detector and cost a slice.
    """

    def __init__(self, seed: int, height: int, width: int, channels: int = 3) -> None:
        rng = np.random.default_rng([seed, height, width, 5150])
        self.height, self.width = height, width
        self.field = rng.standard_normal((2 * height, 2 * width, channels), dtype=np.float32)

    def window(self, rng: np.random.Generator) -> np.ndarray:
        y = int(rng.integers(0, self.height + 1))
        x = int(rng.integers(0, self.width + 1))
        return self.field[y:y + self.height, x:x + self.width]


def finish_image(colour: np.ndarray, light: FrameLight, realism: Realism, rng: np.random.Generator,
                 vignette: np.ndarray | None = None, flows: np.ndarray | None = None,
                 noise: NoiseBank | None = None, wrap: bool = False) -> np.ndarray:
    """Exposure, white balance, vignetting, motion blur and noise; returns BGR uint8."""
    scale = (light.gain * np.asarray(light.balance, np.float64)).tolist() + [0.0]
    image = cv2.multiply(colour, tuple(scale))
    if vignette is not None:
        image = cv2.multiply(image, vignette)
    if flows is not None and realism.motion_blur:
        image = motion_blur(image, flows, wrap=wrap)
    if realism.noise_sigma > 0 or realism.shot_noise > 0:
        field = noise.window(rng) if noise is not None else rng.standard_normal(image.shape, dtype=np.float32)
        # sigma^2 = read^2 + shot^2 * level
        variance = cv2.add(cv2.multiply(cv2.max(image, 0.0), realism.shot_noise ** 2), realism.noise_sigma ** 2)
        image = cv2.add(image, cv2.multiply(cv2.sqrt(variance), field))
    return np.clip(image + 0.5, 0, 255, out=image).astype(np.uint8)
