"""Score likelihoods p(z|d), p(z|not d) by kernel density estimation (thesis §4.7.3, §4.8.2).

"The distribution is sampled at 1000 points using a normal kernel. The kernel bandwidth is taken as the robust
estimate of the sample standard deviation assuming a normal distribution for the scores": sigma = MAD / 0.6745
and, as in MATLAB's ``ksdensity`` which the thesis used, the normal-reference bandwidth h = sigma (4 / 3n)^(1/5).

Samples are heatline scores: ``d`` at bearings that hold an object of the class, ``not d`` at observed bearings far
from every object of the class (``heatline_samples``). Millions of negatives are usual, so the density is computed
by linear binning on the grid and a convolution with the sampled kernel (exact up to the binning, which is far finer
than any bandwidth that matters).

``bandwidth="robust_std"`` takes the thesis text literally (§4.7.3, §4.8.2: "Score likelihoods are assumed to be
normally distributed ... the kernel bandwidth was set from the robust standard-deviation of each sample set"): h =
sigma itself. The normal-reference h shrinks as n^(-1/5), so with thousands of samples from one training world the
densities become narrow spikes whose ratio p(z|d)/p(z|not d) swings by e^±14 between neighbouring scores; a localizer
multiplying that ratio over dozens of bins per frame (eq. 4.27) then follows the spikes of the training world
instead of where the scores peak (docs/localization.md, "Score likelihoods").
"""

from __future__ import annotations

import numpy as np

from semloc_core.bearing import Heatlines
from semloc_core.io.calibration import ScoreLikelihoods

MAD_TO_SIGMA = 1.0 / 0.6745   # a normal's standard deviation from its median absolute deviation


BANDWIDTH_RULES = ("normal_reference", "robust_std")


def robust_bandwidth(samples: np.ndarray, grid_step: float, rule: str = "normal_reference") -> float:
    """KDE bandwidth from the robust (MAD) standard deviation: the normal-reference rule (default) or, with
    ``rule="robust_std"``, that standard deviation itself (the thesis's wording); never below two grid steps."""
    if rule not in BANDWIDTH_RULES:
        raise ValueError(f"unknown bandwidth rule {rule!r}; choose from {BANDWIDTH_RULES}")
    samples = np.asarray(samples, dtype=np.float64).reshape(-1)
    if samples.size == 0:
        raise ValueError("no samples to estimate a bandwidth from")
    sigma = np.median(np.abs(samples - np.median(samples))) * MAD_TO_SIGMA
    if not sigma > 0:
        # More than half the samples share one value (e.g. a hard detector's zeros): fall back to the plain
        # standard deviation, then to the grid resolution.
        sigma = float(np.std(samples))
    bandwidth = sigma if rule == "robust_std" else sigma * (4.0 / (3.0 * samples.size)) ** 0.2
    return float(max(bandwidth, 2.0 * grid_step))


def kde_on_grid(samples: np.ndarray, z: np.ndarray, bandwidth: float) -> np.ndarray:
    """Gaussian KDE of ``samples`` evaluated on the uniform grid ``z``, normalised to integrate to 1 over it."""
    samples = np.asarray(samples, dtype=np.float64).reshape(-1)
    samples = samples[np.isfinite(samples)]
    if samples.size == 0:
        raise ValueError("no finite samples for the density")
    step = z[1] - z[0]
    # Linear binning: each sample splits its unit mass between its two neighbouring grid points. Samples beyond
    # the grid are kept on the end points, where the localizer will look them up anyway.
    position = np.clip((samples - z[0]) / step, 0.0, len(z) - 1.0)
    lower = np.minimum(position.astype(np.int64), len(z) - 2)
    fraction = position - lower
    weights = np.bincount(lower, weights=1.0 - fraction, minlength=len(z))
    weights += np.bincount(lower + 1, weights=fraction, minlength=len(z))
    radius = int(np.ceil(5.0 * bandwidth / step))
    offsets = np.arange(-radius, radius + 1) * step
    kernel = np.exp(-0.5 * (offsets / bandwidth) ** 2)
    # Reflect the mass at the grid ends (scores are bounded) so a density piled at z = 0, a common score, is not
    # halved by the edge.
    padded = np.pad(weights, radius, mode="reflect")
    density = np.convolve(padded, kernel, mode="valid")
    total = np.trapezoid(density, z)
    return density / total


def fit_score_likelihoods(samples_d: dict, samples_not_d: dict, z_range: tuple[float, float] = (0.0, 1.0),
                          count: int = 1000, detector: dict | None = None, source: str = "",
                          bandwidth: str = "normal_reference") -> ScoreLikelihoods:
    """KDE of each class's positive and negative scores on one uniform grid of ``count`` points (§4.8.2);
    ``bandwidth``: the rule of ``robust_bandwidth``."""
    classes = tuple(samples_d)
    if not classes or set(classes) != set(samples_not_d):
        raise ValueError(f"positive and negative samples must cover the same classes: {sorted(samples_d)} vs "
                         f"{sorted(samples_not_d)}")
    if count < 2 or not z_range[0] < z_range[1]:
        raise ValueError("need count >= 2 and z_range min < max")
    z = np.linspace(z_range[0], z_range[1], count)
    step = z[1] - z[0]
    pdf_d, pdf_not_d, widths_d, widths_not_d, n_d, n_not_d = [], [], [], [], [], []
    for name in classes:
        positives = np.asarray(samples_d[name], dtype=np.float64).reshape(-1)
        negatives = np.asarray(samples_not_d[name], dtype=np.float64).reshape(-1)
        if positives.size < 2 or negatives.size < 2:
            raise ValueError(f"class {name!r}: need at least 2 positive and 2 negative samples, got "
                             f"{positives.size} and {negatives.size}")
        h_d, h_not_d = robust_bandwidth(positives, step, bandwidth), robust_bandwidth(negatives, step, bandwidth)
        pdf_d.append(kde_on_grid(positives, z, h_d))
        pdf_not_d.append(kde_on_grid(negatives, z, h_not_d))
        widths_d.append(h_d)
        widths_not_d.append(h_not_d)
        n_d.append(positives.size)
        n_not_d.append(negatives.size)
    return ScoreLikelihoods(classes, float(z[0]), float(z[-1]), np.array(pdf_d), np.array(pdf_not_d), n_d, n_not_d,
                            widths_d, widths_not_d, detector or {}, source)


def heatline_samples(heatlines: Heatlines, objects, positive_deg: float = 2.0, negative_deg: float = 10.0):
    """Split one frame's heatline scores into per-class positives and negatives.

    ``objects`` lists the frame's visible objects as ``(class_name, bearing_rad, usable)``: bins within
    ``positive_deg`` of a usable object's bearing are positives of its class; observed bins farther than
    ``negative_deg`` from every object of the class (usable or not — a tiny or occluded one is ambiguous, not absent)
    are negatives; bins in between are left out. Returns two dicts class -> 1-D score arrays.
    """
    grid = heatlines.grid
    centres = grid.centers
    positives, negatives = {}, {}
    for k, name in enumerate(heatlines.classes):
        scores = heatlines.scores[k]
        near_any = np.zeros(grid.n_bins, bool)
        positive = np.zeros(grid.n_bins, bool)
        for object_class, bearing, usable in objects:
            if object_class != name:
                continue
            distance = np.abs(np.angle(np.exp(1j * (centres - bearing))))
            near_any |= distance <= np.radians(negative_deg)
            if usable:
                positive |= distance <= np.radians(positive_deg)
        positives[name] = scores[positive & heatlines.observed]
        negatives[name] = scores[heatlines.observed & ~near_any]
    return positives, negatives


def decision_threshold(likelihoods: ScoreLikelihoods, class_name: str, prior_d: float = 0.5) -> float:
    """The single score threshold of least expected error for the prior ``prior_d``: a principled threshold for
    the hard detector (§4.5.2) instead of a hand-picked one.

    Minimises ``(1 - prior_d) P(z >= t | not d) + prior_d P(z < t | d)`` over the grid (densities integrated with
    the trapezoid rule).
    """
    if not 0 < prior_d < 1:
        raise ValueError("prior_d must be in (0, 1)")
    k = likelihoods.class_index(class_name)
    z = likelihoods.z
    step = z[1] - z[0]

    def cdf(pdf: np.ndarray) -> np.ndarray:   # P(z < z_i)
        cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * step)])
        return cumulative / cumulative[-1]

    error = (1.0 - prior_d) * (1.0 - cdf(likelihoods.pdf_not_d[k])) + prior_d * cdf(likelihoods.pdf_d[k])
    return float(z[int(np.argmin(error))])
