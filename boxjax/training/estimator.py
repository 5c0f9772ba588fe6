"""Training, evaluating and shipping the estimator H end to end (issue 4; the CLI calls these).

  train_estimator(key, n_boxes, out_dir, cfg)  ->  dataset.npz + estimator.npz + report.json in out_dir
  evaluate_estimator(key, n_boxes, weights_path, cfg)  ->  metrics on fresh, seeded random boxes
  default_estimator(cfg)  ->  the shipped weights (boxjax/data/estimator.npz), checked against cfg

The default estimator configuration (`DEFAULT_ESTIMATOR`) was chosen by measurement
(docs/results/estimator-and-hazards.md / the
report of the session that built it): see `DEFAULT_ESTIMATOR`'s comment.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import estimator as E
from boxjax import massdist
from boxjax.config import DEFAULT, Config
from boxjax.estimator import explore, moments, shipped
from boxjax.fileio import atomic_path
from boxjax.training import dataset as ds
from boxjax.training.randomise import SensorRandomisation, sensor_view

# Chosen by measurement (2000 boxes, 600 fresh test boxes, the exploration of the time): an ensemble of 5
# nets of 900 -> 256 -> 256 -> 256 -> (256 | 1 | 1), 2.1e6 parameters in all (the paper's H has ~2e6),
# checkpoint ~8 MB. Averaging members gave +0.03 median IoU and -0.2 cm centre-of-mass error over one
# net; a single 1.1e6-parameter net (512 x 3) was no better than one 256 x 3 member. The soft
# centre-of-mass loss term (com_weight = 1) cut the median COM error by ~0.4 cm at equal IoU.
# More boxes help (1000 fresh test boxes, the previous exploration, no hazard head): 8000 boxes 0.611
# median IoU / 1.59 cm / hazard precision 0.84 at recall 0.98; 32000 boxes 0.641 / 1.32 cm / 0.88. The
# hazard head (hazard_weight = 1), same 32000 boxes: 0.634 / 1.36 cm / 0.93: a sharper hazard decision
# than thresholding the occupancy, at the same IoU within noise. The shipped weights use 288000 boxes
# (the current exploration: 48000 boxes 0.655 median IoU / 1.33 cm, 288000 boxes 0.694 / 1.17 cm on the
# same 500 fresh boxes; docs/results/estimator-and-hazards.md). Wider members at the same parameter budget (2
# x
# 512^3) were no better with 96000 boxes (0.667 vs 0.671 median IoU, 8000 test boxes).
DEFAULT_ESTIMATOR = E.EstimatorConfig(hidden=(256, 256, 256), members=5, com_weight=1.0, patience=25)
# The hazard threshold is calibrated on the validation split for this recall: the operating point asked
# for is recall >= 0.98; 0.985 leaves a margin for the recall's sampling noise on fresh boxes (a few
# thousandths with the ~12000 hazardous validation boxes of a 288000-box run, ~1 % with a 2000-box run).
HAZARD_RECALL_TARGET = 0.985
METRIC_KEYS = (
    "iou_median",
    "iou_mean",
    "mass_rel_error_median",
    "com_error_cm_median",
    "hazard_precision",
    "hazard_recall",
    "boxes",
)


def _key_and_seed(key) -> tuple[jax.Array, int | None]:
    """Accept an int seed or a PRNG key; return (key, seed or None)."""
    if isinstance(key, (int, np.integer)):
        return jax.random.key(int(key)), int(key)
    return key, None


def _key_record(key) -> list[int]:
    if jax.numpy.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return [int(v) for v in np.asarray(key).reshape(-1)]


def _json_safe(x):
    """NaN -> None so that the report is strict JSON."""
    if isinstance(x, float) and x != x:
        return None
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def train_estimator(
    key,
    n_boxes: int = ds.DEFAULT_BOXES,
    out_dir: str | os.PathLike = "estimator_run",
    cfg: Config = DEFAULT,
    *,
    est_cfg: E.EstimatorConfig = DEFAULT_ESTIMATOR,
    p_hazardous: float = ds.P_HAZARDOUS,
    backend: str = "native",
    chunk: int = 500,
    progress: bool = True,
    weights_name: str = "estimator.npz",
    sensor: SensorRandomisation | None = None,
) -> dict:
    """Generate an exploration dataset, train H on it, calibrate its thresholds, write everything.

    Args:
      key: an int seed (recorded as such) or a PRNG key; split into the dataset's and training's keys.
      n_boxes: random boxes to simulate (default 2000 = 90k transitions).
      out_dir: created if needed; receives dataset.npz, `weights_name` and report.json.
      cfg: the Config (box grid and gripper); recorded in the dataset and the checkpoint.
      est_cfg: size and training of H.
      p_hazardous: share of boxes drawn hazardous (`boxjax.training.dataset`).
      backend: "native" or "mjx" simulation.
      chunk: boxes per batched rollout call (`boxjax.training.dataset.generate`; bounds memory, and larger
        batches fill an accelerator under MJX).
      sensor: train on the explorations as sensors drawn from this distribution show them
        (`boxjax.training.randomise`, domain randomisation: an H that keeps its hazard decision under
        pose noise and dropped frames); None: on the simulator's exact states. dataset.npz stays exact.
    Returns:
      the report (also written to out_dir/report.json): seed, paths, timings (data_s, train_s, total_s),
      dataset summary, training summary, calibration, and the validation-split metrics (METRIC_KEYS...).
    """
    t_start = time.perf_counter()
    key, seed = _key_and_seed(key)
    key_data, key_train = jax.random.split(key)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    data = ds.generate(
        key_data, n_boxes, cfg, p_hazardous=p_hazardous, backend=backend, progress=progress, chunk=chunk
    )
    data_s = time.perf_counter() - t0
    meta = ds.make_meta(cfg, seed, p_hazardous, backend, key=_key_record(key), seconds=data_s)
    ds.save(out / "dataset.npz", data, meta)
    if sensor is not None:
        data = sensor_view(data, cfg, sensor, seed if seed is not None else 0)

    t0 = time.perf_counter()
    provenance = {
        "trained_by": "boxjax.training.estimator.train_estimator",
        "seed": seed,
        "pipeline_key": _key_record(key),
        "n_boxes": int(n_boxes),
        "p_hazardous": float(p_hazardous),
        "backend": backend,
        "config": cfg.to_dict(),
        "exploration_actions": np.asarray(explore.exploration_actions(cfg)).tolist(),
        "sensor_randomisation": None if sensor is None else dataclasses.asdict(sensor),
    }
    model, history = E.train(key_train, data, est_cfg, box=cfg.box, progress=progress, provenance=provenance)
    val = {k: v[history["val_index"]] for k, v in data.items()}
    model, calibration = E.calibrate(model, val, HAZARD_RECALL_TARGET)
    train_s = time.perf_counter() - t0
    E.save(out / weights_name, model)
    val_metrics = E.evaluate(model, val)
    report = {
        "command": "train-estimator",
        "seed": seed,
        "key": _key_record(key),
        "boxes": int(n_boxes),
        "transitions": int(n_boxes * data["traj"].shape[1]),
        "out_dir": str(out),
        "dataset": str(out / "dataset.npz"),
        "weights": str(out / weights_name),
        "data_s": data_s,
        "train_s": train_s,
        "total_s": time.perf_counter() - t_start,
        "dataset_summary": ds.summary(data),
        "training": {
            "epochs_run": int(history["epochs_run"]),
            "best_epoch": int(history["best_epoch"]),
            "best_val_loss": float(history["best_val_loss"]),
            "stopped_early": bool(history["stopped_early"]),
            "n_train": int(len(history["train_index"])),
            "n_val": int(len(history["val_index"])),
            "parameters": E.mlp.n_params(model.net),
            "estimator_config": est_cfg.to_dict(),
        },
        "calibration": {
            k: calibration[k]
            for k in (
                "occupancy_threshold",
                "hazard_threshold",
                "hazard_recall_target",
                "boxes",
                "hazardous_boxes",
            )
        },
        "validation": val_metrics,
    }
    report = _json_safe(report)
    write_json(out / "report.json", report)
    return report


def write_json(path, obj) -> str:
    """Write `obj` as indented JSON, atomically, world-readable. Returns the path."""
    with atomic_path(path, suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(_json_safe(obj), f, indent=2, sort_keys=True)
            f.write("\n")
        os.chmod(tmp, 0o644)
    return os.fspath(path)


def evaluate_estimator(
    key,
    n_boxes: int = 500,
    weights_path: str | os.PathLike | None = None,
    cfg: Config = DEFAULT,
    *,
    p_hazardous: float = ds.P_HAZARDOUS,
    backend: str = "native",
    chunk: int = 500,
    progress: bool = True,
    moments_path: str | os.PathLike | None = None,
) -> dict:
    """Accuracy of H on `n_boxes` fresh random boxes (the same box prior as training: hazardous with
    probability p_hazardous, see `boxjax.training.dataset`), simulated with the fixed exploration.

    Args:
      key: int seed or PRNG key. The boxes come from `fold_in(key, 1)`, a stream that
        `train_estimator` never uses, so the same seed never re-draws training boxes.
      weights_path: a checkpoint (default: the shipped weights).
      backend, chunk: how the boxes are simulated (as for `train_estimator`).
    Returns:
      dict with iou_median, iou_mean, mass_rel_error_median, com_error_cm_median, hazard_precision,
      hazard_recall (None where undefined), boxes, plus mass_rel_error_mean, com_error_cm_mean,
      hazard_true, hazard_pred, seed, weights, thresholds and seconds (simulate / predict); "moments":
      the moments estimator (shipped, or `moments_path`) on the same explorations (`moments_report`).
    Raises:
      boxjax.estimator.CheckpointError for a missing, corrupt or incompatible checkpoint.
    """
    t_start = time.perf_counter()
    key, seed = _key_and_seed(key)
    path = shipped.SHIPPED_WEIGHTS if weights_path is None else Path(weights_path)
    model = E.load(path, expected_box_config=cfg.box)
    shipped.check_exploration(model, cfg, path)
    # Loaded before the simulation: a bad file fails before any work.
    if moments_path is None:
        moments_model, moments_skipped = shipped.moments_for(cfg)
    else:
        moments_model, moments_skipped = moments.load(moments_path, cfg.box)[0], None
    t0 = time.perf_counter()
    data = ds.generate(
        jax.random.fold_in(key, 1),
        n_boxes,
        cfg,
        p_hazardous=p_hazardous,
        backend=backend,
        progress=progress,
        chunk=chunk,
    )
    sim_s = time.perf_counter() - t0
    metrics = E.evaluate(model, data)
    result = {
        "command": "estimator-eval",
        **metrics,
        "moments": (
            moments_report(moments_model, data, cfg)
            if moments_model is not None
            else {"skipped": moments_skipped}
        ),
        "hazard_precision_at_recall": hazard_operating_points(model, data),
        "seed": seed,
        "weights": str(path),
        "occupancy_threshold": model.occupancy_threshold,
        "hazard_threshold": model.hazard_threshold,
        "p_hazardous": float(p_hazardous),
        "simulate_s": sim_s,
        "total_s": time.perf_counter() - t_start,
    }
    return _json_safe(result)


def moments_report(model: moments.MomentsModel, data: dict, cfg: Config = DEFAULT) -> dict:
    """The moments estimator on explorations `data`: per quantity, the coverage of its stated std at
    50 / 68.3 / 90 / 95 %, the median absolute error and the median stated std (QUANTITIES' units)."""
    est = moments.predict_batch(model, jnp.asarray(data["traj"]), jnp.asarray(data["final"]))
    est = moments.Moments(np.asarray(est.mean), np.asarray(est.std))
    dists = massdist.MassDistribution(jnp.asarray(data["occupancy"]), jnp.asarray(data["total_mass"]))
    truth = moments.true_moments_batch(dists, cfg.box)
    err = np.abs(est.mean - truth)
    return {
        "coverage": moments.coverage(est, truth),
        "median_abs_error": {q: float(np.median(err[:, i])) for i, q in enumerate(moments.QUANTITIES)},
        "median_std": {q: float(np.median(est.std[:, i])) for i, q in enumerate(moments.QUANTITIES)},
        "units": dict(zip(moments.QUANTITIES, moments.UNITS, strict=True)),
    }


def hazard_operating_points(model: E.EstimatorParams, data, recalls=(0.9, 0.95, 0.98)) -> dict:
    """For information: the best hazard precision reachable on `data` at each recall level, sweeping the
    threshold on the hazard head's probability over 0.01..0.99 (an oracle choice of threshold; the model's
    own calibrated threshold gives the hazard_precision / hazard_recall reported beside it).
    {recall: precision or None}."""
    (_, _, hazard_prob), occ, _ = E.chunked_predictions(model, data, 1024)
    curve = E.hazard_curve(hazard_prob, E.hazard_labels(model.box, occ))
    out = {}
    for target in recalls:
        ok = [p for _, p, r in curve if r >= target and p == p]
        out[str(target)] = max(ok) if ok else None
    return out


def ship_estimator(
    run_dir: str | os.PathLike, key=1, n_eval_boxes: int = 500, cfg: Config = DEFAULT, progress: bool = True
) -> dict:
    """Make the checkpoint of a `train_estimator` run the shipped one: copy run_dir/estimator.npz to
    boxjax/data/estimator.npz and write boxjax/data/estimator_report.json = {"training": the run's
    report.json, "heldout": evaluate_estimator(key, n_eval_boxes) of the copied weights}. That report is
    the accuracy tests/test_shipped_estimator.py holds the shipped weights to. Returns the report."""
    import shutil

    run = Path(run_dir)
    with open(run / "report.json") as f:
        training = json.load(f)
    E.load(run / "estimator.npz", expected_box_config=cfg.box)  # refuse to ship a broken file
    with atomic_path(shipped.SHIPPED_WEIGHTS, suffix=".npz") as tmp:
        shutil.copyfile(run / "estimator.npz", tmp)
        os.chmod(tmp, 0o644)
    shipped.default_estimator_cache_clear()
    heldout = evaluate_estimator(key, n_eval_boxes, shipped.SHIPPED_WEIGHTS, cfg, progress=progress)
    heldout["weights"] = "boxjax/data/estimator.npz"
    report = {"training": training, "heldout": heldout}
    write_json(shipped.SHIPPED_REPORT, report)
    return report


__all__ = [
    "DEFAULT_ESTIMATOR",
    "METRIC_KEYS",
    "ship_estimator",
    "evaluate_estimator",
    "train_estimator",
]
