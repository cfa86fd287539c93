"""Camera effects applied after rendering: illumination change, exposure, vignetting, motion blur, sensor noise.

Deterministic: the noise of frame i comes from a generator seeded with (scenario seed, i).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit


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

    def offset(self, rng: np.random.Generator) -> tuple[int, int]:
        """(row, column) of this frame's window in ``field``."""
        y = int(rng.integers(0, self.height + 1))
        x = int(rng.integers(0, self.width + 1))
        return y, x

    def window(self, rng: np.random.Generator) -> np.ndarray:
        y, x = self.offset(rng)
        return self.field[y:y + self.height, x:x + self.width]


@njit(cache=True, nogil=True)
def _expose(colour, scale, vignette, use_vignette, out):
    """out = colour · scale[channel] (· vignette), all C-contiguous (H, W, 3). Rounded like the cv2 calls this
    replaced: cv2.multiply by a scalar computes in double and rounds once to float32; by an array, in float32."""
    source = colour.reshape(-1)
    result = out.reshape(-1)
    gain = vignette.reshape(-1)
    s0, s1, s2 = scale[0], scale[1], scale[2]
    for i in range(0, source.shape[0], 3):
        b = np.float32(np.float64(source[i]) * s0)
        g = np.float32(np.float64(source[i + 1]) * s1)
        r = np.float32(np.float64(source[i + 2]) * s2)
        if use_vignette:
            b, g, r = b * gain[i], g * gain[i + 1], r * gain[i + 2]
        result[i], result[i + 1], result[i + 2] = b, g, r
    return out


@njit(cache=True, nogil=True)
def _add_noise_and_quantise(image, field, y0, x0, noisy, shot2, read2, out):
    """out = uint8(clip(image + sqrt(read² + shot²·max(image, 0))·noise + 0.5, 0, 255)), the noise read from the
    window of ``field`` at row y0, column x0. Rounded like the cv2 / numpy calls this replaced (scalar products
    and sums in double, the rest in float32)."""
    height, width, channels = image.shape
    row = width * channels
    field_row = field.shape[1] * channels
    source = image.reshape(-1)
    noise = field.reshape(-1)
    result = out.reshape(-1)
    zero = np.float32(0.0)
    for y in range(height):
        base = y * row
        noise_base = (y0 + y) * field_row + x0 * channels
        for k in range(row):
            value = source[base + k]
            if noisy:
                level = np.float32(np.float64(max(value, zero)) * shot2)
                variance = np.float32(np.float64(level) + read2)
                value = value + np.sqrt(variance) * noise[noise_base + k]
            value = value + np.float32(0.5)
            result[base + k] = np.uint8(min(max(value, zero), np.float32(255.0)))
    return out


def finish_image(colour: np.ndarray, light: FrameLight, realism: Realism, rng: np.random.Generator,
                 vignette: np.ndarray | None = None, flows: np.ndarray | None = None,
                 noise: NoiseBank | None = None, wrap: bool = False) -> np.ndarray:
    """Exposure, white balance, vignetting, motion blur and noise; returns BGR uint8.

    The per-pixel steps are two numba loops, before and after the blur, one pass over the image each; the chain of
    cv2 calls they replaced (same bytes, tested) made a float image per step: 3-4x the time."""
    colour = np.ascontiguousarray(colour, dtype=np.float32)
    if colour.ndim != 3 or colour.shape[2] != 3:
        raise ValueError(f"colour must be a (H, W, 3) image, got shape {colour.shape}")
    use_vignette = vignette is not None
    if use_vignette:
        vignette = np.ascontiguousarray(vignette, dtype=np.float32)
        if vignette.shape != colour.shape:
            raise ValueError(f"vignette {vignette.shape} does not match the image {colour.shape}")
    scale = light.gain * np.asarray(light.balance, np.float64)
    image = _expose(colour, scale, vignette if use_vignette else colour, use_vignette, np.empty_like(colour))
    if flows is not None and realism.motion_blur:
        image = np.ascontiguousarray(motion_blur(image, flows, wrap=wrap))
    noisy = realism.noise_sigma > 0 or realism.shot_noise > 0
    field, (y0, x0) = image, (0, 0)  # the field is not read without noise
    if noisy and noise is not None:
        if (noise.height, noise.width) != image.shape[:2] or noise.field.shape[2] != image.shape[2]:
            raise ValueError(f"noise bank of {noise.height}x{noise.width} does not match the image {image.shape}")
        field, (y0, x0) = noise.field, noise.offset(rng)
    elif noisy:
        field = rng.standard_normal(image.shape, dtype=np.float32)
    return _add_noise_and_quantise(image, field, y0, x0, noisy, float(realism.shot_noise) ** 2,
                                   float(realism.noise_sigma) ** 2, np.empty(image.shape, np.uint8))
