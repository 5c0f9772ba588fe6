"""How good H is, and where its thresholds go (`boxjax.estimator`): IoU, mass and centre-of-mass errors,
hazard precision and recall, `estimate` (one box's belief with its members), `evaluate` over a dataset
and `calibrate` (occupancy and hazard thresholds on held-out boxes). `estimator` re-exports all.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist
from boxjax.config import BoxConfig
from boxjax.estimator.net import (
    EstimatorParams,
    Prediction,
    _dataset_arrays,
    predict_batch,
    predict_checked,
    predict_members,
    to_distribution,
)
from boxjax.massdist import MassDistribution, iou

# ----------------------------------------------------------------------------------------------------------
# Metrics (pure; `iou` is `massdist.iou`).


def mass_rel_error(pred_mass: jax.Array, true_mass: jax.Array) -> jax.Array:
    """|pred - true| / true (dimensionless), elementwise."""
    return jnp.abs(pred_mass - true_mass) / true_mass


def com_error_cm(pred: MassDistribution, true: MassDistribution, box: BoxConfig) -> jax.Array:
    """() cm: distance between the centres of mass of ONE predicted and true distribution (box frame)."""
    com_p = massdist.mass_properties(pred, box).com
    com_t = massdist.mass_properties(true, box).com
    return 100.0 * jnp.linalg.norm(com_p - com_t)


def hazard_precision_recall(pred_hazard: jax.Array, true_hazard: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Precision and recall of the hazard flag over boxes, "hazardous" being the positive class.

    Args:
      pred_hazard, true_hazard: (B,) bool.
    Returns:
      (precision, recall) float32 scalars; NaN where undefined (no predicted / no true hazardous box).
    """
    p, t = jnp.asarray(pred_hazard, bool), jnp.asarray(true_hazard, bool)
    tp = jnp.sum(p & t)
    n_pred, n_true = jnp.sum(p), jnp.sum(t)
    precision = jnp.where(n_pred > 0, tp / jnp.maximum(n_pred, 1), jnp.nan)
    recall = jnp.where(n_true > 0, tp / jnp.maximum(n_true, 1), jnp.nan)
    return precision.astype(jnp.float32), recall.astype(jnp.float32)


def predict_hazard(model: EstimatorParams, hazard_prob: jax.Array) -> jax.Array:
    """The calibrated hazard decision (pure; any shape): the hazard head's probability exceeds
    `model.hazard_threshold`."""
    return jnp.asarray(hazard_prob) > model.hazard_threshold


def occupancy_hazard(prob: jax.Array, threshold, box: BoxConfig) -> jax.Array:
    """() bool, the hazard rule applied to an occupancy prediction (ONE box; vmap for batches):
    `massdist.is_hazardous` of the distribution thresholded at `threshold` (with `to_distribution`'s
    fallback to the most probable voxel), i.e. every voxel outside one of the regions U1..U4 has an
    occupancy probability <= threshold. For estimators without a hazard head (scripts/estimator_ceiling.py);
    H's own decision is its hazard head (`predict_hazard`), which is more precise at the same recall."""
    return massdist.is_hazardous(to_distribution(prob, jnp.ones(()), threshold), box)


def estimate(model: EstimatorParams, traj, final) -> dict:
    """Everything the controller needs from ONE exploration trajectory (host side, validated input).

    Args:
      traj: (T, 11), final: (5,) as built by `boxjax.estimator.explore.trajectory` / `explore.run`.
    Returns:
      dict: "prob" (nx, ny, nz) numpy occupancy probabilities; "distribution" the MassDistribution
      thresholded at model.occupancy_threshold with the predicted total mass; "members" the same for
      each ensemble member (`predict_members`); "total_mass" float kg;
      "hazard_prob" float, the hazard head's probability; "hazardous" bool (`predict_hazard`).
    Raises:
      ValueError for a trajectory of the wrong shape / length or with NaN / inf (`predict_checked`).
    """
    prob, mass, hazard = predict_checked(model, traj, final)
    dist = to_distribution(jnp.asarray(prob), jnp.asarray(mass), model.occupancy_threshold)
    mem = _predict_members_jit(model, jnp.asarray(traj, jnp.float32), jnp.asarray(final, jnp.float32))
    members = [
        to_distribution(mem.prob[e], mem.mass[e], model.occupancy_threshold) for e in range(mem.mass.shape[0])
    ]
    return {
        "prob": prob,
        "distribution": dist,
        "members": [jax.tree.map(np.asarray, m) for m in members],
        "total_mass": float(mass),
        "hazard_prob": float(hazard),
        "hazardous": bool(predict_hazard(model, hazard)),
    }


_predict_members_jit = jax.jit(predict_members)


@functools.partial(jax.jit, static_argnums=0)
def thresholded_metrics(
    box: BoxConfig, prob, pred_mass, occ, mass, occ_threshold, hazard_threshold, hazard_prob=None
):
    """Per-box metrics of batched predictions: prob (B, nx, ny, nz) occupancy probabilities, pred_mass (B,)
    kg against the truth occ, mass. The hazard flag is hazard_prob (B,) > hazard_threshold when the
    hazard head's probabilities are given, else `occupancy_hazard(prob, hazard_threshold)`. Returns
    {"iou", "mass_rel_error", "com_error_cm", "pred_hazard", "true_hazard"}, each (B,). Both thresholds
    are traced (no recompile per value)."""
    pred = jax.vmap(to_distribution, in_axes=(0, 0, None))(prob, pred_mass, occ_threshold)
    true = MassDistribution(occ, mass)
    if hazard_prob is None:
        pred_hazard = jax.vmap(occupancy_hazard, in_axes=(0, None, None))(prob, hazard_threshold, box)
    else:
        pred_hazard = hazard_prob > hazard_threshold
    return {
        "iou": jax.vmap(iou)(pred.occupancy, occ),
        "mass_rel_error": mass_rel_error(pred_mass, mass),
        "com_error_cm": jax.vmap(com_error_cm, in_axes=(0, 0, None))(pred, true, box),
        "pred_hazard": pred_hazard,
        "true_hazard": jax.vmap(massdist.is_hazardous, in_axes=(0, None))(true, box),
    }


def chunked_predictions(model: EstimatorParams, dataset, chunk: int):
    """(Prediction of numpy arrays with a leading axis B, occ, mass), predicting in chunks of boxes."""
    traj, final, occ, mass = _dataset_arrays(dataset, model.box, model.n_steps)
    parts = [
        jax.device_get(predict_batch(model, traj[i : i + chunk], final[i : i + chunk]))
        for i in range(0, traj.shape[0], chunk)
    ]
    return Prediction(*(np.concatenate(arrays) for arrays in zip(*parts, strict=True))), occ, mass


def _per_box_metrics(model: EstimatorParams, predictions, occ_threshold: float, hazard_threshold: float):
    (prob, pred_mass, hazard), occ, mass = predictions
    out = thresholded_metrics(
        model.box,
        prob,
        pred_mass,
        occ,
        mass,
        jnp.float32(occ_threshold),
        jnp.float32(hazard_threshold),
        hazard,
    )
    return {k: np.asarray(v) for k, v in out.items()}


def evaluate(model: EstimatorParams, dataset, threshold: float | None = None, chunk: int = 1024) -> dict:
    """Prediction quality of H on a dataset (same fields as for `train`), in chunks of `chunk` boxes.

    IoU and the centre-of-mass error use the distribution thresholded at `threshold` (default: the
    model's calibrated `occupancy_threshold`); the hazard flag is `predict_hazard` (the hazard head at the
    model's `hazard_threshold`).

    Returns a dict of Python numbers: iou_median, iou_mean, mass_rel_error_median, mass_rel_error_mean,
    com_error_cm_median, com_error_cm_mean, hazard_precision, hazard_recall (NaN when undefined),
    hazard_true, hazard_pred (counts), boxes.
    """
    threshold = model.occupancy_threshold if threshold is None else float(threshold)
    m = _per_box_metrics(model, chunked_predictions(model, dataset, chunk), threshold, model.hazard_threshold)
    precision, recall = hazard_precision_recall(m["pred_hazard"], m["true_hazard"])
    return {
        "iou_median": float(np.median(m["iou"])),
        "iou_mean": float(np.mean(m["iou"])),
        "mass_rel_error_median": float(np.median(m["mass_rel_error"])),
        "mass_rel_error_mean": float(np.mean(m["mass_rel_error"])),
        "com_error_cm_median": float(np.median(m["com_error_cm"])),
        "com_error_cm_mean": float(np.mean(m["com_error_cm"])),
        "hazard_precision": float(precision),
        "hazard_recall": float(recall),
        "hazard_true": int(np.sum(m["true_hazard"])),
        "hazard_pred": int(np.sum(m["pred_hazard"])),
        "boxes": int(len(m["iou"])),
    }


OCCUPANCY_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(2, 19))  # 0.10 .. 0.90
HAZARD_THRESHOLDS = tuple(round(0.01 * i, 2) for i in range(1, 100))  # 0.01 .. 0.99


def hazard_curve(hazard_prob, true_hazard, thresholds=HAZARD_THRESHOLDS) -> list[tuple[float, ...]]:
    """[(threshold, precision, recall), ...] of the decision hazard_prob > threshold against true_hazard
    (both (B,)), for every threshold at once; precision / recall NaN where undefined, as in
    `hazard_precision_recall`."""
    t = np.asarray(thresholds, np.float64)[:, None]
    pred = np.asarray(hazard_prob)[None, :] > t
    true = np.asarray(true_hazard, bool)[None, :]
    tp, n_pred, n_true = np.sum(pred & true, 1), np.sum(pred, 1), np.sum(true)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(n_pred > 0, tp / n_pred, np.nan)
        recall = np.where(n_true > 0, tp / n_true, np.nan)
    return [(float(a), float(b), float(c)) for a, b, c in zip(t[:, 0], precision, recall, strict=True)]


def choose_hazard_threshold(curve, recall_target: float) -> float:
    """The hazard threshold to use, from `curve` = [(threshold, precision, recall), ...] measured on
    held-out boxes: among the thresholds whose recall reaches the target, the one with the highest
    precision (ties: the lower threshold); if none reaches it, the one with the highest recall."""
    ok = [c for c in curve if c[2] >= recall_target and not math.isnan(c[1])]
    if ok:
        return max(ok, key=lambda c: (c[1], -c[0]))[0]
    return max(curve, key=lambda c: (c[2], c[1]))[0]


def calibrate(
    model: EstimatorParams, dataset, hazard_recall_target: float = 0.99
) -> tuple[EstimatorParams, dict]:
    """Choose the model's two decision thresholds on held-out boxes (never the training boxes).

    occupancy_threshold: the value in 0.10..0.90 (step 0.05) with the highest median IoU.
    hazard_threshold: on the hazard head's probability, among 0.01..0.99 (step 0.01, `hazard_curve`), the
    values whose hazard recall on `dataset` is >= the target, the one with the highest precision (ties:
    the lower threshold); if none reaches the target, the one with the highest recall. Undefined when
    `dataset` holds no hazardous box: then 0.5 is kept.

    Returns (model with both thresholds set, a dict of what was chosen and the per-threshold curves).
    """
    ious = []
    predictions = chunked_predictions(model, dataset, 1024)
    for t in OCCUPANCY_THRESHOLDS:
        m = _per_box_metrics(model, predictions, t, 0.5)
        ious.append(float(np.median(m["iou"])))
    true_h = m["true_hazard"]
    haz_curve = hazard_curve(predictions[0].hazard, true_h)
    occ_t = OCCUPANCY_THRESHOLDS[int(np.argmax(ious))]
    haz_t = choose_hazard_threshold(haz_curve, hazard_recall_target) if np.any(true_h) else 0.5
    info = {
        "occupancy_threshold": occ_t,
        "hazard_threshold": haz_t,
        "hazard_recall_target": hazard_recall_target,
        "boxes": int(len(true_h)),
        "hazardous_boxes": int(np.sum(true_h)),
        "iou_median_by_threshold": dict(zip(OCCUPANCY_THRESHOLDS, ious, strict=True)),
        "hazard_precision_recall_by_threshold": {t: (p, r) for t, p, r in haz_curve},
    }
    return dataclasses.replace(model, occupancy_threshold=occ_t, hazard_threshold=haz_t), info
