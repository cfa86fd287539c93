"""How sure the map is of an object: p(real | extraction score), fitted on calibration scenes.

A mapped object is a peak of back-projected heat above a threshold; some such peaks are look-alikes (a red box
scoring as a mug). The localizer's perception models expect a mapped object's detections only with the object's
existence probability π (``SemanticMap.existence``, docs/localization.md), so a doubtful object costs little where
it is not seen. π comes from the extraction score s by a logistic curve in ln(s / s₀) (s₀ the extraction threshold
it was fitted at):

    π(s) = 1 / (1 + exp(-(a + b ln(s / s₀))))

fitted by maximum a posteriori on candidates of calibration scenes with ground truth (real = matched to a
ground-truth object of its class), with a Gaussian prior N(0, ``prior_sd``²) on a and b that keeps the fit finite
when the calibration separates real from false completely.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from semloc_core.settings import settings

PRIOR_SD = 10.0
SAMPLE_FLOOR = 0.5  # candidates down to this fraction of the threshold are fitted: most false ones lie below it


@settings
class ExistenceCurve:
    """π(s) = σ(intercept + slope · ln(s / reference)); ``samples`` / ``real``: what it was fitted on."""

    # Strict numbers: a curve read from a file whose values are true/false or text is refused.
    reference: float = Field(gt=0, allow_inf_nan=False, strict=True,
                             description="the extraction threshold s₀ it was fitted at")
    intercept: float = Field(allow_inf_nan=False, strict=True, description="a: the log-odds of a candidate scoring s₀")
    slope: float = Field(ge=0, allow_inf_nan=False, strict=True, description="b: log-odds per unit of ln(s / s₀); "
                         ">= 0 (a higher score is not less likely real)")
    samples: int = Field(0, ge=0, description="candidates it was fitted on")
    real: int = Field(0, ge=0, description="... of which real")

    def __call__(self, scores) -> np.ndarray:
        """π of each score (scores <= 0 give the curve's floor, never 0: the format needs π in (0, 1])."""
        s = np.maximum(np.asarray(scores, dtype=float), 1e-12)
        z = self.intercept + self.slope * np.log(s / self.reference)
        return np.clip(0.5 * (1.0 + np.tanh(0.5 * z)), 1e-6, 1.0)  # the logistic, without overflow

    def to_document(self) -> dict:
        return {"reference": self.reference, "intercept": self.intercept, "slope": self.slope,
                "samples": self.samples, "real": self.real}

    @classmethod
    def from_document(cls, document) -> "ExistenceCurve":
        if not isinstance(document, dict):
            raise ValueError(f"an existence curve is a mapping of reference, intercept and slope, got {document!r}")
        return cls(**document)


def fit_existence(scores, real, reference: float, prior_sd: float = PRIOR_SD) -> ExistenceCurve:
    """MAP logistic regression of ``real`` (bool per candidate) on ln(score / reference)."""
    s = np.asarray(scores, dtype=float)
    y = np.asarray(real, dtype=bool)
    if s.ndim != 1 or s.shape != y.shape:
        raise ValueError(f"scores and real must be 1-D and alike, got {s.shape} and {y.shape}")
    if s.size == 0:
        raise ValueError("no candidates to fit an existence curve on")
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError("candidate scores must be positive and finite")
    if not (np.isfinite(reference) and reference > 0 and prior_sd > 0):
        raise ValueError(f"reference and prior_sd must be positive, got {reference!r}, {prior_sd!r}")
    x = np.log(s / reference)
    target = y.astype(float)

    def objective(p):
        z = p[0] + p[1] * x
        probability = 0.5 * (1.0 + np.tanh(0.5 * z))
        # -log-likelihood: log(1 + e^-z) for real ones, log(1 + e^z) for false ones; plus the prior
        value = np.sum(target * np.logaddexp(0.0, -z) + (1.0 - target) * np.logaddexp(0.0, z)) \
            + 0.5 * float(p @ p) / prior_sd ** 2
        residual = probability - target
        gradient = np.array([residual.sum(), residual @ x]) + p / prior_sd ** 2
        return value, gradient

    from scipy.optimize import minimize  # fitting only: not imported by every mapper's and localizer's start

    result = minimize(objective, np.zeros(2), jac=True, method="L-BFGS-B",
                      bounds=[(None, None), (0.0, None)])
    return ExistenceCurve(float(reference), float(result.x[0]), float(result.x[1]), int(s.size), int(y.sum()))
