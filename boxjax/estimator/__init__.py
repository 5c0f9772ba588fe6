"""The estimator H and the belief it gives the controller (paper §2.2).

Modules, one way down: `net` (features, the MLP ensemble, prediction), `metrics` (estimate, evaluate,
calibrate the decision thresholds), `io` (checkpoints and the shipped H), `training` (loss and the
training loop), `explore` (the fixed exploration and its guard), `hazard` (the physics hazard rule on H's
ensemble), `belief` (the estimator slot of the controller: oracle or learned H, and the refusal).

This face re-exports the estimator's public API: `from boxjax import estimator as E; E.load(path)`.
"""

from boxjax import mlp
from boxjax.estimator.belief import decide, hazard_explanation, learned_estimator, oracle_estimator
from boxjax.estimator.io import (
    FORMAT,
    FORMAT_VERSION,
    CheckpointError,
    load,
    save,
)
from boxjax.estimator.metrics import (
    HAZARD_THRESHOLDS,
    OCCUPANCY_THRESHOLDS,
    calibrate,
    choose_hazard_threshold,
    chunked_predictions,
    com_error_cm,
    estimate,
    evaluate,
    hazard_curve,
    hazard_precision_recall,
    mass_rel_error,
    occupancy_hazard,
    predict_hazard,
    thresholded_metrics,
)
from boxjax.estimator.net import (
    HEADS,
    MIN_MASS,
    N_ACTION,
    N_STATE,
    N_STEP_FEATURES,
    N_TRAJ_COLUMNS,
    Batch,
    EstimatorConfig,
    EstimatorParams,
    Normaliser,
    Prediction,
    features,
    init_members,
    init_net,
    predict,
    predict_batch,
    predict_checked,
    predict_members,
    to_distribution,
)
from boxjax.estimator.shipped import SHIPPED_WEIGHTS, default_estimator
from boxjax.estimator.training import (
    hazard_labels,
    loss_and_metrics,
    losses,
    make_optimizer,
    make_train_step,
    train,
)
from boxjax.massdist import iou

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "HAZARD_THRESHOLDS",
    "HEADS",
    "MIN_MASS",
    "N_ACTION",
    "N_STATE",
    "N_STEP_FEATURES",
    "N_TRAJ_COLUMNS",
    "OCCUPANCY_THRESHOLDS",
    "SHIPPED_WEIGHTS",
    "Batch",
    "CheckpointError",
    "EstimatorConfig",
    "EstimatorParams",
    "Normaliser",
    "Prediction",
    "calibrate",
    "choose_hazard_threshold",
    "chunked_predictions",
    "com_error_cm",
    "decide",
    "default_estimator",
    "estimate",
    "evaluate",
    "features",
    "hazard_curve",
    "hazard_explanation",
    "hazard_labels",
    "hazard_precision_recall",
    "init_members",
    "init_net",
    "iou",
    "learned_estimator",
    "load",
    "loss_and_metrics",
    "losses",
    "make_optimizer",
    "make_train_step",
    "mlp",
    "mass_rel_error",
    "occupancy_hazard",
    "oracle_estimator",
    "predict",
    "predict_batch",
    "predict_checked",
    "predict_hazard",
    "predict_members",
    "save",
    "thresholded_metrics",
    "to_distribution",
    "train",
]
