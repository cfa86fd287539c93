"""The frequency-domain correlator of the §4.3 detector and the linear filters, against the sum it computes."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.detection.correlation import Correlator


def _direct(features: np.ndarray, kernels) -> np.ndarray:
    """out_k(x) = sum over the kernel's channels and blocks of K[c, b] F[c, x + b - centre] (zero outside F)."""
    _, rows, cols = features.shape
    out = np.zeros((len(kernels), rows, cols))
    for k, (channels, blocks) in enumerate(kernels):
        _, krows, kcols = blocks.shape
        padded = np.zeros((features.shape[0], rows + krows - 1, cols + kcols - 1))
        padded[:, krows // 2:krows // 2 + rows, kcols // 2:kcols // 2 + cols] = features
        for c, block in zip(channels, blocks):
            for a in range(krows):
                for b in range(kcols):
                    out[k] += block[a, b] * padded[c, a:a + rows, b:b + cols]
    return out


@pytest.mark.parametrize("n_channels, n_kernels, shape", [(5, 3, (17, 23)), (4, 4, (9, 30)), (1, 1, (3, 4))])
def test_correlations_equal_the_direct_sum(n_channels, n_kernels, shape):
    """Odd and even channel and kernel counts (two real maps share each complex DFT), kernels of different sizes
    and channel subsets, maps smaller than a kernel: the direct sum to float32 precision."""
    rng = np.random.default_rng(n_channels * 10 + n_kernels)
    kernels = []
    for k in range(n_kernels):
        channels = np.sort(rng.choice(n_channels, size=max(1, n_channels - k % 2), replace=False))
        krows, kcols = (5, 3) if k % 2 else (3, 7)
        kernels.append((channels, rng.uniform(-1, 1, (channels.size, krows, kcols)).astype(np.float32)))
    correlator = Correlator(n_channels, kernels)
    for _ in range(2):   # a second map of the same size reuses the plan and its buffers
        features = rng.uniform(0, 1, (n_channels,) + shape).astype(np.float32)
        fast = correlator.correlate(features)
        assert fast.shape == (n_kernels,) + shape
        np.testing.assert_allclose(fast, _direct(features, kernels), atol=2e-5)


@pytest.mark.parametrize("n_channels, shape", [(5, (17, 23)), (6, (9, 30)), (3, (4, 3))])
def test_mirrored_kernels_share_their_spectra_and_equal_the_direct_sum(n_channels, shape):
    """A kernel mirrored left-right with its channels permuted (a template's mirror: HOGE orientation theta read as
    pi - theta) is found, not stored, and still gives its own correlation; one that is no mirror stays stored."""
    rng = np.random.default_rng(n_channels)
    kernels, mirrors = [], []
    for k in range(3):
        channels = np.sort(rng.choice(n_channels, size=n_channels - k % 2, replace=False))
        blocks = rng.uniform(-1, 1, (channels.size, 3 + 2 * (k % 2), 5)).astype(np.float32)
        order = rng.permutation(channels.size)
        kernels.append((channels, blocks))
        mirrors.append((channels[order], np.ascontiguousarray(blocks[order][:, :, ::-1])))
    other = (np.arange(n_channels), rng.uniform(-1, 1, (n_channels, 3, 5)).astype(np.float32))
    kernels = [kernels[0], mirrors[0], other, kernels[1], kernels[2], mirrors[2], mirrors[1]]
    correlator = Correlator(n_channels, kernels)
    assert correlator._stored == [0, 2, 3, 4]
    for _ in range(2):
        features = rng.uniform(0, 1, (n_channels,) + shape).astype(np.float32)
        np.testing.assert_allclose(correlator.correlate(features), _direct(features, kernels), atol=2e-5)


def test_bad_kernels_and_maps_are_refused():
    with pytest.raises(ValueError, match="odd"):
        Correlator(2, [(np.arange(2), np.zeros((2, 2, 3)))])
    with pytest.raises(ValueError, match="channels must be in"):
        Correlator(2, [(np.array([0, 2]), np.zeros((2, 3, 3)))])
    with pytest.raises(ValueError, match="at least one"):
        Correlator(2, [])
    with pytest.raises(ValueError, match=r"\(2, rows, cols\)"):
        Correlator(2, [(np.arange(2), np.zeros((2, 3, 3)))]).correlate(np.zeros((3, 5, 5), np.float32))
