"""Particle-filter localization against a map of labelled objects (thesis chapter 4; docs/localization.md).

Parts (each replaceable on its own):

* motion models - ``DifferentialDriveModel`` (eq. 4.5), ``OmniDriveModel``, ``RandomWalkModel``; ``Odometry``,
  ``OdometryBuffer`` (odometry integrated exactly up to an observation's stamp);
* perception models - ``InnerProductModel`` (model A, eq. 4.6-4.8), ``GenerativeScoreModel`` (model B,
  eq. 4.17-4.28) with ``ScoreLikelihood`` (p(z|d), p(z|d̄));
* ``FreeSpace`` - where particles may be;
* ``ParticleFilter`` with ``FilterConfig`` -> ``PoseEstimate``;
* observation sources from ground truth (§4.8.3) - ``synthetic_scores_heatlines``, ``simulated_dpm_heatlines``.
"""

from semloc_core.localization.filter import (FilterConfig, NonFiniteStepError, ParticleFilter, PoseEstimate, Status,
                                            weighted_pose_mean)
from semloc_core.localization.free_space import FreeSpace
from semloc_core.localization.motion import (DifferentialDriveModel, Odometry, OdometryBuffer, OmniDriveModel,
                                             RandomWalkModel)
from semloc_core.localization.observations import (ObjectViews, field_of_view_mask, simulated_dpm_heatlines, synthetic_scores_heatlines,
                                                   visible_objects)
from semloc_core.localization.perception import (DEFAULT_SIGMA, DEFAULT_VISIBILITY_RADIUS, GenerativeScoreModel,
                                                 InnerProductModel, ViewGeometry, Weighing, expected_heatlines,
                                                 inner_product_reference, log_likelihood_reference,
                                                 object_visibility)
from semloc_core.localization.score_likelihood import (ScoreLikelihood, load_score_likelihood,
                                                       synthetic_scores_likelihood)

__all__ = [
    "DEFAULT_SIGMA", "DEFAULT_VISIBILITY_RADIUS", "DifferentialDriveModel", "FilterConfig", "FreeSpace",
    "GenerativeScoreModel", "InnerProductModel", "NonFiniteStepError", "ObjectViews", "Odometry", "OdometryBuffer", "OmniDriveModel", "ParticleFilter",
    "PoseEstimate", "RandomWalkModel", "ScoreLikelihood", "Status", "ViewGeometry", "Weighing", "expected_heatlines",
    "field_of_view_mask", "inner_product_reference", "load_score_likelihood", "log_likelihood_reference", "object_visibility",
    "simulated_dpm_heatlines", "synthetic_scores_heatlines", "synthetic_scores_likelihood", "visible_objects",
    "weighted_pose_mean",
]
