"""Camera effects: the fused numba loops give the bytes of the plain cv2 / numpy formulation of the same steps."""

import cv2
import numpy as np
import pytest

from semloc_core.sim.effects import FrameLight, NoiseBank, Realism, _expose, finish_image, motion_blur, vignette_map


def _cv2_chain(colour, light, realism, rng, vignette, flows, noise, wrap):
    """The image formation written step by step with cv2 (the reference the kernels must match byte for byte)."""
    scale = (light.gain * np.asarray(light.balance, np.float64)).tolist() + [0.0]
    image = cv2.multiply(colour, tuple(scale))
    if vignette is not None:
        image = cv2.multiply(image, vignette)
    if flows is not None and realism.motion_blur:
        image = motion_blur(image, flows, wrap=wrap)
    if realism.noise_sigma > 0 or realism.shot_noise > 0:
        field = noise.window(rng) if noise is not None else rng.standard_normal(image.shape, dtype=np.float32)
        variance = cv2.add(cv2.multiply(cv2.max(image, 0.0), realism.shot_noise ** 2), realism.noise_sigma ** 2)
        image = cv2.add(image, cv2.multiply(cv2.sqrt(variance), field))
    return np.clip(image + 0.5, 0, 255, out=image).astype(np.uint8)


@pytest.mark.parametrize("realism", [Realism(), Realism(noise_sigma=0.7, shot_noise=0.13), Realism.off()],
                         ids=["default", "other-noise", "off"])
@pytest.mark.parametrize("with_bank", [True, False], ids=["bank", "fresh-noise"])
def test_effects_equal_the_cv2_formulation(realism, with_bank):
    rng = np.random.default_rng(7)
    height, width = 120, 160
    # Levels beyond 0..255 and below 0 exercise the clipping; a smooth ramp makes the blur visible.
    colour = (rng.uniform(-20, 290, (height, width, 3)) + np.linspace(0, 60, width)[None, :, None]).astype(np.float32)
    light = FrameLight(gain=1.137, balance=(0.96, 1.03, 1.011), light_azimuth=0.0)
    bank = NoiseBank(3, height, width) if with_bank else None
    flows = np.array([[2.6, 0.4], [0.2, 0.1], [-1.8, 1.3], [3.1, -0.7]])
    for vignette, wrap in ((vignette_map(height, width, 0.2), False), (None, True)):
        for seed in range(3):
            got = finish_image(colour, light, realism, np.random.default_rng(seed), vignette, flows, bank, wrap)
            want = _cv2_chain(colour, light, realism, np.random.default_rng(seed), vignette, flows, bank, wrap)
            assert got.dtype == np.uint8 and got.shape == colour.shape
            np.testing.assert_array_equal(got, want)
    if realism.noise_sigma > 0:
        noisy = finish_image(colour, light, realism, np.random.default_rng(0), None, None, bank)
        clean = finish_image(colour, light, Realism.off(), np.random.default_rng(0), None, None, bank)
        assert np.mean(noisy != clean) > 0.3  # the noise is really there


def test_effects_reject_mismatched_inputs():
    colour = np.zeros((8, 10, 3), np.float32)
    light = FrameLight(1.0, (1.0, 1.0, 1.0), 0.0)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="vignette"):
        finish_image(colour, light, Realism(), rng, vignette=np.ones((8, 9, 3), np.float32))
    with pytest.raises(ValueError, match="noise bank"):
        finish_image(colour, light, Realism(), rng, noise=NoiseBank(0, 8, 12))
    with pytest.raises(ValueError, match="colour"):
        finish_image(np.zeros((8, 10), np.float32), light, Realism(), rng)


def test_exposure_rounds_like_cv2():
    """Float-level check of the first loop (quantisation to uint8 would hide most rounding slips): cv2.multiply by
    a scalar rounds the double product once; a float32 product differs in thousands of values here."""
    rng = np.random.default_rng(1)
    colour = rng.uniform(0, 255, (60, 80, 3)).astype(np.float32)
    vignette = vignette_map(60, 80, 0.3)
    scale = np.array([1.137 * 0.96, 1.137 * 1.03, 1.137 * 1.011])
    want = cv2.multiply(cv2.multiply(colour, tuple(scale.tolist() + [0.0])), vignette)
    np.testing.assert_array_equal(_expose(colour, scale, vignette, True, np.empty_like(colour)), want)
    np.testing.assert_array_equal(_expose(colour, scale, colour, False, np.empty_like(colour)),
                                  cv2.multiply(colour, tuple(scale.tolist() + [0.0])))
    assert np.sum(colour * scale.astype(np.float32) != cv2.multiply(colour, tuple(scale.tolist() + [0.0]))) > 100
