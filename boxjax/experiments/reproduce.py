"""`boxjax reproduce`: the paper's experiments in one call, each part a function that returns plain data.

`run(out, quick, retrain)` checks the output folder and the weights it needs, optionally regenerates the
weights into `out/weights/` (`retrain_weights`: calibration, H, W), runs the parts in order, times each,
and writes `out/results.json` and `out/report.md` (`boxjax.experiments.report.render`) atomically at the very
end
(figures go to `out/figures/` as they are made). An interrupted run leaves no report: with `force` the
old report.md / results.json are removed before anything runs.

Parts (sizes in `FULL` / `QUICK`; every reduction against the paper is listed in the results' `reductions`):
  * `table1`: paper Table 1, `comparison.compare`: the physics prior with the learned H (its episodes
    batched, `boxjax.control.batch`) and the black box W adapted online (one episode at a time: batched they
    are
    no faster on a CPU, `comparison.blackbox_episodes`) on boxes A, B, C, D, seeds 0-4;
  * `table2`: paper Table 2, `comparison.table2` (what H, W and PETS were trained on, read from their
    files);
  * `validation`: paper §4.3, `experiments.evaluate` with the learned H on 100 random safe and 30 random
    hazardous boxes (seed 0, batched), and the paper's "30 random safe boxes" as the FIRST 30 safe boxes
    of that run (`experiments.make_boxes` draws the safe boxes in sequence from their own key and gives
    box j the episode key fold_in(key, j), safe boxes first, so the first 30 are the boxes and keys of
    `boxjax evaluate --boxes 30 --seed 0`); Fig. 3 (c) from it, and Fig. 2 (c, d): the first validation
    box's true voxels and H's prediction from its exploration (`batch.replay_episode`, the same states);
  * `force_map`: paper Fig. 3 (a, b) for all four forces: the calibration's map with samples collected
    again by its own command's seed (`training.calibration.calibrate_by_simulation`) and how far the refit map
    is from the file;
  * `data_efficiency`: the data-efficiency curve of `boxjax.experiments.data_efficiency` when its results
    (benchmarks/results_data_efficiency.json) exist; otherwise the part says it was not measured.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import time
from pathlib import Path
from typing import Any

from boxjax import blackbox
from boxjax.blackbox import baseline as w_model
from boxjax.blackbox import pets as pets_model
from boxjax.config import DEFAULT, Config
from boxjax.control import batch
from boxjax.estimator import explore, shipped
from boxjax.estimator.belief import learned_estimator
from boxjax.experiments import comparison, report
from boxjax.experiments import evaluation as experiments
from boxjax.fileio import atomic_path
from boxjax.prior import force_map as calibrate
from boxjax.run_info import CACHE_ENV, machine, use_compilation_cache, versions  # noqa: F401 (re-exported)
from boxjax.training import baseline as baseline_train
from boxjax.training import estimator as estimator_pipeline
from boxjax.training.calibration import GRID_POINTS, calibrate_by_simulation
from boxjax.viz import plots

REPO = Path(__file__).resolve().parents[2]
DATA_EFFICIENCY_JSON = REPO / "benchmarks" / "results_data_efficiency.json"
DATA_EFFICIENCY_COMMAND = "python -m boxjax.experiments.data_efficiency"
PAPER_VALIDATION = {"safe_boxes": 30, "safe_success": 25, "safe_success_rate": 25 / 30}
FIGURES = "figures"
REPORT, RESULTS = "report.md", "results.json"


@dataclasses.dataclass(frozen=True)
class Sizes:
    """How much of each experiment a run does."""

    t1_boxes: tuple[str, ...]  # the prior's boxes in Table 1
    t1_blackbox_boxes: tuple[str, ...]  # W's boxes in Table 1
    t1_seeds: int
    val_safe: int
    val_hazardous: int
    val_first: int  # the paper's "30 random safe boxes": the first ones of the validation
    val_seed: int = 0
    cal_transitions: int | None = None  # None: as many as the calibration file was made with
    slots: int | None = None  # boxes per batched planner call (None: batch's default)
    # --retrain
    h_boxes: int = 2000
    w_episodes: int = 200
    retrain_cal_transitions: int = 2000
    retrain_seed: int = 0


FULL = Sizes(
    t1_boxes=("A", "B", "C", "D"),
    t1_blackbox_boxes=("A", "B", "C", "D"),
    t1_seeds=5,
    val_safe=100,
    val_hazardous=30,
    val_first=30,
)
# --quick: a few boxes and one seed, small enough for the default test suite. W runs on A only (its D
# episodes run to the 555-step cap at ~0.2 s a step); 2 slots per planner call, shared by Table 1's prior
# episodes and the validation so that the batched planner compiles once.
QUICK = Sizes(
    t1_boxes=("A", "D"),
    t1_blackbox_boxes=("A",),
    t1_seeds=1,
    val_safe=2,
    val_hazardous=1,
    val_first=1,
    cal_transitions=64,
    slots=2,
    h_boxes=40,
    w_episodes=2,
    retrain_cal_transitions=64,
)


class ReproduceError(ValueError):
    """Bad input to `run` (an existing output folder without force, a missing weight file)."""


@dataclasses.dataclass
class Weights:
    """The files the experiments use: None means the shipped one."""

    estimator: str | None = None
    estimator_report: str | None = None  # H's training report (Table 2)
    baseline: str | None = None
    calibration: str | None = None
    pets: str | None = None
    calibration_samples: Any = None  # a training.calibration.Calibration made by --retrain (its samples)

    def paths(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "calibration_samples"}


def shipped_files() -> dict[str, tuple[str, str]]:
    """{name: (path, the command that makes it)} of the weights a run from the shipped files reads (paths
    read now, so a test can point them elsewhere)."""

    make_h = (
        'boxjax train-estimator --boxes 288000 --seed 0 --out h_run, then `python -c "from '
        "boxjax.training.estimator import ship_estimator; ship_estimator('h_run')\"`"
    )
    return {
        "estimator": (str(shipped.SHIPPED_WEIGHTS), make_h),
        "estimator_report": (str(shipped.SHIPPED_REPORT), make_h),
        "baseline": (
            w_model.shipped_path(),
            "boxjax train-baseline --episodes 200 --seed 0 --out w_run, then copy w_run/baseline.npz there",
        ),
        "calibration": (
            str(calibrate.SHIPPED_CALIBRATION),
            "boxjax calibrate --transitions 2000 --seed 0 --out boxjax/data/calibration.npz",
        ),
        "pets": (
            pets_model.shipped_path(),
            "python -m boxjax.training.pets --data w_run/dataset.npz --out p_run, "
            "then copy its pets.npz there",
        ),
    }


SHIPPED_NEEDED = ("estimator", "estimator_report", "baseline", "calibration", "pets")


def require_shipped(names) -> None:
    """Refuse (ReproduceError) when a shipped file a run needs is missing, naming it and its command."""
    files = shipped_files()
    missing = [n for n in names if not os.path.isfile(files[n][0])]
    if missing:
        says = "; ".join(f"{files[n][0]} (made by `{files[n][1]}`)" for n in missing)
        raise ReproduceError(
            f"missing shipped weight file(s): {says}; or run `boxjax reproduce --retrain` to make them"
        )


def check_out(out, force: bool) -> None:
    """Refuse an existing non-empty `out` unless `force`; refuse a path that is a file."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise ReproduceError(f"--out {out} is a file, not a folder")
    if os.path.isdir(out) and os.listdir(out) and not force:
        raise ReproduceError(f"--out {out} exists and is not empty; pass --force to write into it")


# ------------------------------------------------------------------------------------------------------
# --retrain


def retrain_weights(out, sizes: Sizes, cfg: Config = DEFAULT, progress: bool = True) -> tuple[Weights, dict]:
    """Make the calibration, H and W again into `out/weights/` (calibration: `boxjax calibrate`'s
    function; H: `boxjax train-estimator --boxes sizes.h_boxes`'s; W: `training.baseline.train_baseline`
    with `sizes.w_episodes` episodes). Returns (the weights, plain data: what was made and each step's
    wall time)."""
    import jax

    seed = sizes.retrain_seed
    wdir = os.path.join(out, "weights")
    os.makedirs(wdir, exist_ok=True)
    info: dict = {"seed": seed}
    t0 = time.perf_counter()
    cal = calibrate_by_simulation(
        cfg, jax.random.PRNGKey(seed), sizes.retrain_cal_transitions, grid_points=GRID_POINTS,
        progress=progress,
    )  # fmt: skip
    cal_path = os.path.join(wdir, "calibration.npz")
    meta = {k: v for k, v in cal.info.items() if k != "wall_s"}
    calibrate.save(
        cal_path, cal.force_map, cfg, {**meta, "seed": seed, "made_by": "boxjax reproduce --retrain"}
    )
    info["calibration"] = {
        "transitions": cal.info["transitions"],
        "file": cal_path,
        "wall_s": time.perf_counter() - t0,
    }

    t0 = time.perf_counter()
    h_dir = os.path.join(wdir, "h")
    rep = estimator_pipeline.train_estimator(seed, sizes.h_boxes, h_dir, cfg, progress=progress)
    val = rep["validation"]
    info["estimator"] = {
        "boxes": sizes.h_boxes,
        "transitions": rep["transitions"],
        "file": rep["weights"],
        "data_s": rep["data_s"],
        "train_s": rep["train_s"],
        "validation": {
            k: val.get(k) for k in ("iou_median", "com_error_cm_median", "hazard_precision", "hazard_recall")
        },
        "wall_s": time.perf_counter() - t0,
    }

    t0 = time.perf_counter()
    w_dir = os.path.join(wdir, "w")
    wrep = baseline_train.train_baseline(cfg, "A", sizes.w_episodes, seed, w_dir, progress=progress)
    info["baseline"] = {
        "episodes": sizes.w_episodes,
        "transitions": wrep["transitions"],
        "file": wrep["weights"],
        "data_s": wrep["data_s"],
        "train_s": wrep["train_s"],
        "wall_s": time.perf_counter() - t0,
    }
    weights = Weights(
        estimator=rep["weights"],
        estimator_report=os.path.join(h_dir, "report.json"),
        baseline=wrep["weights"],
        calibration=cal_path,
        pets=None,
        calibration_samples=cal,
    )
    return weights, info


# ------------------------------------------------------------------------------------------------------
# The parts


def _estimator(cfg: Config, weights: Weights):

    return learned_estimator(cfg, weights.estimator)


def table1(cfg: Config, sizes: Sizes, weights: Weights, progress: bool = True) -> dict:
    """Paper Table 1: the prior with the learned H (batched) on `sizes.t1_boxes` and W with online
    adaptation (every 20 steps, 1 epoch, as the paper) on `sizes.t1_blackbox_boxes`, seeds
    0..t1_seeds-1. Rows, the table beside the paper's numbers, and each method's wall time."""

    w = blackbox.load_black_box("blackbox", weights.baseline, cfg.gripper)
    t0 = time.perf_counter()
    prior = comparison.compare(
        cfg, sizes.t1_boxes, sizes.t1_seeds, ("prior",), progress=progress,
        estimator=_estimator(cfg, weights), slots=sizes.slots, w_weights=weights.baseline,
        h_report=weights.estimator_report,
    )  # fmt: skip
    t_prior = time.perf_counter() - t0
    t0 = time.perf_counter()
    black = comparison.compare(
        cfg, sizes.t1_blackbox_boxes, sizes.t1_seeds, ("blackbox",), model=w, progress=progress,
        w_weights=weights.baseline, h_report=weights.estimator_report,
    )  # fmt: skip
    t_black = time.perf_counter() - t0
    order = {b: i for i, b in enumerate(dict.fromkeys(sizes.t1_boxes + sizes.t1_blackbox_boxes))}
    rows = sorted(
        prior["rows"] + black["rows"],
        key=lambda r: (order[r["box"]], comparison.METHODS.index(r["method"]), r["seed"]),
    )
    return {
        "boxes": {"prior": list(sizes.t1_boxes), "blackbox": list(sizes.t1_blackbox_boxes)},
        "seeds": list(range(sizes.t1_seeds)),
        "episode_key": "jax.random.PRNGKey(seed)",
        "adapt_every": black["adapt_every"],
        "adapt_epochs": black["adapt_epochs"],
        "prior_batched": prior["prior_batched"],
        "blackbox_batched": black["blackbox_batched"],
        "rows": rows,
        "table": comparison.table(rows),
        "wall_s": {"prior": t_prior, "blackbox": t_black},
    }


def table2(weights: Weights) -> dict:
    """Paper Table 2 from the files the run used (PETS: the shipped one, beyond the paper; left out when
    the run retrained the other weights, PETS not being retrained)."""

    pets_path = None if weights.estimator is not None else (weights.pets or pets_model.shipped_path())
    return {"rows": comparison.table2(weights.baseline, pets_path, weights.estimator_report)}


def validation(cfg: Config, sizes: Sizes, weights: Weights, fig_dir, progress: bool = True) -> dict:
    """Paper §4.3 with the learned H: `sizes.val_safe` safe + `sizes.val_hazardous` hazardous random boxes
    (seed `sizes.val_seed`, batched), the first `sizes.val_first` safe boxes as the paper's row, Fig. 3 (c)
    and Fig. 2 (c, d) (the first validation box with an estimate: true voxels and H's prediction)."""
    import jax

    est = _estimator(cfg, weights)
    ev = experiments.evaluate(
        cfg, sizes.val_safe, sizes.val_hazardous, sizes.val_seed, estimator="learned", estimator_fn=est,
        progress=progress, slots=sizes.slots,
    )  # fmt: skip
    k = min(sizes.val_first, sizes.val_safe)
    first = experiments.summarize(ev.rows[:k])  # the safe boxes come first (make_boxes)
    fig3c = os.path.join(fig_dir, "fig3c_balance.png")
    plots.plot_evaluation(
        ev,
        fig3c,
        cfg,
        f"learned H: {sizes.val_safe} safe + {sizes.val_hazardous} hazardous boxes, seed {sizes.val_seed}",
    )
    fig2 = None
    n_explore = len(explore.exploration_actions(cfg))
    for j, row in enumerate(ev.rows):
        if row["hazardous"] or row["lost_exploring"]:
            continue
        truth, key = ev.boxes.dist(j), jax.random.wrap_key_data(ev.boxes.keys[j])
        res = batch.replay_episode(cfg, truth, key, ev.actions[j][:n_explore], estimator=est)
        if res.belief is None:
            continue
        s = res.summary
        path = os.path.join(fig_dir, "fig2cd_voxels.png")
        plots.plot_mass_distributions(
            {
                f"(c) ground truth, validation box {j}": truth,
                f"(d) H's prediction (IoU {s['iou']:.2f})": res.belief,
            },
            cfg.box,
            path,
        )
        fig2 = {
            "box": j,
            "iou": s["iou"],
            "mass_error_kg": s["mass_error_kg"],
            "com_error_cm": s["com_error_cm"],
            "true_mass_kg": float(truth.total_mass),
            "figure": path,
        }
        break
    return {
        "seed": sizes.val_seed,
        "summary": ev.summary,
        "first": {"safe_boxes": k, **first},
        "paper": PAPER_VALIDATION,
        "rows": ev.rows,
        "fig3c": fig3c,
        "fig2": fig2,
    }


def force_map(cfg: Config, sizes: Sizes, weights: Weights, fig_dir, progress: bool = True) -> dict:
    """Paper Fig. 3 (a, b), all four forces: the calibration file's map (mean +- std) with the samples of
    its calibration (made again with the file's seed and `sizes.cal_transitions`, default the file's own
    number; --retrain's own samples), and the largest difference between the refit and the file's means."""
    import jax
    import numpy as np

    path = weights.calibration or str(calibrate.SHIPPED_CALIBRATION)
    fm, meta = calibrate.load(path, cfg)
    cal = weights.calibration_samples
    seed = int(meta.get("seed", 0))
    if cal is None:
        n = sizes.cal_transitions or int(meta["transitions"])
        cal = calibrate_by_simulation(
            cfg, jax.random.PRNGKey(seed), n, grid_points=int(fm.grid.shape[1]), progress=progress
        )
    diff = float(np.max(np.abs(np.asarray(cal.force_map.mean) - np.asarray(fm.mean))))
    fig = os.path.join(fig_dir, "fig3ab_force_map.png")
    n = int(cal.info["transitions"])
    plots.plot_force_map(
        fm, cal.component, cal.value, cal.force, fig,
        f"action -> force map (paper Fig. 3 a, b): {os.path.basename(path)}, samples of {n} transitions, "
        f"seed {seed}",
    )  # fmt: skip
    mean, std = np.asarray(fm.mean, np.float64), np.asarray(fm.std, np.float64)
    return {
        "file": path,
        "file_command": meta.get("command"),
        "file_transitions": meta.get("transitions"),
        "samples_transitions": n,
        "samples_seed": seed,
        "refit_max_abs_mean_diff_N": diff,
        "forces": {
            name: {
                "mean_range_N": [float(mean[c].min()), float(mean[c].max())],
                "std_range_N": [float(std[c].min()), float(std[c].max())],
            }
            for c, name in enumerate(calibrate.FORCE_NAMES)
        },
        "figure": fig,
    }


def data_efficiency(fig_dir) -> dict:
    """The data-efficiency curve (`boxjax.experiments.data_efficiency.plot_curve`) from its results file, or
    why not."""
    not_measured = {
        "measured": False,
        "command": DATA_EFFICIENCY_COMMAND,
        "source": str(DATA_EFFICIENCY_JSON),
    }
    if not DATA_EFFICIENCY_JSON.is_file():
        return {**not_measured, "reason": f"{DATA_EFFICIENCY_JSON.name} does not exist"}
    try:  # imported here: the report is still written when the curve's module cannot be imported
        from boxjax.experiments import data_efficiency as de
    except ImportError as e:
        return {**not_measured, "reason": f"boxjax.experiments.data_efficiency cannot be imported ({e})"}
    try:
        with open(DATA_EFFICIENCY_JSON) as f:
            curve = json.load(f)
    except (OSError, ValueError) as e:  # e.g. being rewritten by a run of the curve
        return {**not_measured, "reason": f"{DATA_EFFICIENCY_JSON.name} cannot be read ({e})"}
    try:
        fig = de.plot_curve(curve, os.path.join(fig_dir, "data_efficiency.png"))
    except Exception as e:  # another module's plot: say it failed, keep the rest of the report
        return {**not_measured, "reason": f"plot_curve failed: {type(e).__name__}: {e}"}
    return {"measured": True, "source": str(DATA_EFFICIENCY_JSON), "figure": fig, "curve": curve}


PARTS = ("table1", "table2", "validation", "force_map", "data_efficiency")


def reductions(sizes: Sizes, retrain: bool) -> list[str]:
    """What this run does less than the paper's experiment (empty for the full run from shipped weights)."""
    out = []
    if sizes.t1_boxes != FULL.t1_boxes or sizes.t1_seeds != FULL.t1_seeds:
        out.append(
            f"Table 1: the prior on boxes {', '.join(sizes.t1_boxes)}, W on "
            f"{', '.join(sizes.t1_blackbox_boxes)}, {sizes.t1_seeds} seed(s) (paper: A, B, C, D, 5 "
            "executions each)"
        )
    if (sizes.val_safe, sizes.val_hazardous) != (FULL.val_safe, FULL.val_hazardous):
        out.append(
            f"validation: {sizes.val_safe} safe + {sizes.val_hazardous} hazardous boxes (full run: 100 + "
            f"30); the paper's row from the first {min(sizes.val_first, sizes.val_safe)} safe boxes (paper: "
            "30)"
        )
    if sizes.cal_transitions is not None:
        out.append(
            f"Fig. 3 (a, b): samples of {sizes.cal_transitions} calibration transitions, not the file's own "
            "number, so the refit map is not expected to equal the file's"
        )
    if retrain and sizes.h_boxes != FULL.h_boxes:
        out.append(
            f"--retrain: H on {sizes.h_boxes} boxes (paper 2000), W on {sizes.w_episodes} episodes (paper "
            f"~200), calibration of {sizes.retrain_cal_transitions} transitions: weights for testing the "
            "pipeline, not for judging the methods"
        )
    return out


def run(
    out,
    quick: bool = False,
    retrain: bool = False,
    force: bool = False,
    *,
    cfg: Config = DEFAULT,
    command: str | None = None,
    progress: bool = True,
    sizes: Sizes | None = None,
) -> dict:
    """Run every part, write `out/results.json` and `out/report.md`; returns the results (plain data,
    figure paths relative to `out`).

    Raises:
      ReproduceError: `out` exists and is not empty (without `force`), or a shipped weight file is missing
        (named with the command that makes it).
    """

    out = os.fspath(out)
    check_out(out, force)
    if not retrain:
        require_shipped(SHIPPED_NEEDED)
    sizes = sizes or (QUICK if quick else FULL)
    for name in (REPORT, RESULTS):  # an interrupted run must not leave the previous report behind
        if os.path.exists(os.path.join(out, name)):
            os.unlink(os.path.join(out, name))
    fig_dir = os.path.join(out, FIGURES)
    os.makedirs(fig_dir, exist_ok=True)
    t_start = time.perf_counter()
    results: dict = {
        "command": command,
        "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "mode": {"quick": quick, "retrain": retrain},
        "machine": machine(),
        "versions": versions(),
        "sizes": dataclasses.asdict(sizes),
        "reductions": reductions(sizes, retrain),
        "seeds": {
            "table1": f"episode keys jax.random.PRNGKey(s), s = 0..{sizes.t1_seeds - 1}",
            "validation": f"experiments.make_boxes(seed={sizes.val_seed})",
            "force_map": "the calibration file's seed",
            **({"retrain": sizes.retrain_seed} if retrain else {}),
        },
        "wall_s": {},
    }
    weights = Weights()
    if retrain:
        t0 = time.perf_counter()
        weights, results["retrain"] = retrain_weights(out, sizes, cfg, progress)
        results["wall_s"]["retrain"] = time.perf_counter() - t0
    results["weights"] = {k: v for k, v in weights.paths().items()}
    parts = {
        "table1": lambda: table1(cfg, sizes, weights, progress),
        "table2": lambda: table2(weights),
        "validation": lambda: validation(cfg, sizes, weights, fig_dir, progress),
        "force_map": lambda: force_map(cfg, sizes, weights, fig_dir, progress),
        "data_efficiency": lambda: data_efficiency(fig_dir),
    }
    for name in PARTS:
        t0 = time.perf_counter()
        results[name] = parts[name]()
        results["wall_s"][name] = time.perf_counter() - t0
    results["wall_s"]["total"] = time.perf_counter() - t_start
    results["machine"]["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    results = _relative(results, out)
    text = report.render(results)

    with atomic_path(os.path.join(out, RESULTS), suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(results, f, indent=1)
    with atomic_path(os.path.join(out, REPORT), suffix=".md") as tmp:
        with open(tmp, "w") as f:
            f.write(text)
    return results


def _relative(results: dict, out: str) -> dict:
    """Figure paths relative to `out` (the report links them so)."""
    out_abs = os.path.abspath(out)

    def rel(p):
        return None if p is None else os.path.relpath(os.path.abspath(p), out_abs)

    val = results["validation"]
    val["fig3c"] = rel(val["fig3c"])
    if val["fig2"] is not None:
        val["fig2"]["figure"] = rel(val["fig2"]["figure"])
    results["force_map"]["figure"] = rel(results["force_map"]["figure"])
    if results["data_efficiency"].get("figure"):
        results["data_efficiency"]["figure"] = rel(results["data_efficiency"]["figure"])
    return results
