"""The paper's comparison (Table 1) and W's generalisation gap, as functions that return plain data.

`compare`: for each named box (A, B, C, D) and seed, one closed-loop episode per method with the SAME
planner (`controller.make_planner`, default predictive sampling):
  * "prior": the physics-prior MPC with the learned H (45-step exploration, estimate, refuse if hazardous,
    turn), zero-shot;
  * "blackbox": the black box W (`baseline`) in the model slot, no exploration or estimate (it has none to
    make), adapted online for `adapt_epochs` epochs on the episode's data every `adapt_every` steps;
  * "pets" (beyond the paper): the probabilistic ensemble with trajectory sampling (`pets`), trained on
    W's data, in the same slot of the same planner (its particles' costs averaged), adapted as W.
Each row: method, box, seed, outcome, steps, wall time (adaptation included), adaptation time and count,
worst balance error. `table` aggregates rows per (box, method) beside the paper's numbers. The prior's
episodes run batched (`prior_episodes`: `boxjax.control.batch`, all boxes and seeds in one closed loop, the
same
per-episode keys `PRNGKey(seed)` and summaries as `prior_episode`; a batched row's `wall_s` is the batch's
wall time divided by its episodes) where the controller allows it. The black boxes' episodes can run
batched too (`blackbox_episodes`, `batch_black_boxes=True`: every episode its own copy of the model,
adapted online on its own data, the same schedule and keys as `blackbox_episode`), but by default run
one at a time: on a CPU their planning is bound by W's matrix products, so a batch is no faster
(`benchmarks/blackbox_episodes.py`, docs/results/batched-episodes.md).

`generalisation_gap`: one-step errors of W (trained on A), of PETS (when given) and of the physics prior
(true masses) on fresh episodes of A and of C (`training.baseline.collect`, another seed than W's data).

`load_black_box(method, weights)` and `adapter_for(model, epochs)` give a method's model and its online
adaptation (W's or PETS's), for this module and the CLI.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time

import jax

from boxjax import massdist
from boxjax.blackbox import baseline, pets
from boxjax.blackbox.loading import BLACK_BOXES, adapter_for, load_black_box
from boxjax.config import DEFAULT, Config
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import run_episode
from boxjax.estimator.belief import learned_estimator
from boxjax.estimator.shipped import SHIPPED_REPORT
from boxjax.experiments import evaluation as experiments
from boxjax.training import baseline as baseline_train

METHODS = ("prior", "blackbox", "pets")
PAPER_TABLE1 = {  # paper Table 1: success ratio, average steps (D: the prior aborts, W 0 %)
    ("A", "prior"): (1.0, 238.8),
    ("A", "blackbox"): (1.0, 367.4),
    ("B", "prior"): (1.0, 389.2),
    ("B", "blackbox"): (1.0, 269.6),
    ("C", "prior"): (1.0, 527.8),
    ("C", "blackbox"): (0.6, 401.0),
    ("D", "prior"): ("aborts", None),
    ("D", "blackbox"): (0.0, None),
}


def outcome(summary: dict) -> str:
    if summary["aborted"]:
        return "refused"
    if summary["success"]:
        return "success"
    return summary["failed_reason"] or "failed"


def blackbox_episode(
    cfg: Config,
    name: str,
    seed: int,
    model=None,
    adapt_every: int = 20,
    adapt_epochs: int = 1,
    ctrl: ControllerConfig | None = None,
    method: str = "blackbox",
    max_steps: int | None = None,
) -> dict:
    """One episode of a black box (W, or PETS with method="pets"; online adaptation) on the named box; a
    plain row named `method`. `max_steps`: the step cap (default the task's)."""
    model = load_black_box(method, None, cfg.gripper) if model is None else model
    adapter = adapter_for(model, adapt_epochs) if adapt_every > 0 else None
    ctrl = _blackbox_ctrl(ctrl, adapt_every, adapter)
    res = run_episode(
        cfg,
        massdist.named(name, cfg.box),
        jax.random.PRNGKey(seed),
        ctrl=ctrl,
        model=model,
        adapter=adapter,
        max_steps=max_steps,
    )
    return _row(method, name, seed, res.summary)


def _blackbox_ctrl(ctrl: ControllerConfig | None, adapt_every: int, adapter) -> ControllerConfig:
    """A black box's controller: no exploration (it has no estimate to make), its adaptation schedule."""
    ctrl = ctrl or ControllerConfig()
    return dataclasses.replace(ctrl, explore=False, adapt_every=adapt_every if adapter else 0)


def blackbox_episodes(
    cfg: Config,
    jobs,
    model=None,
    adapt_every: int = 20,
    adapt_epochs: int = 1,
    ctrl: ControllerConfig | None = None,
    method: str = "blackbox",
    slots: int | None = None,
    progress=None,
    max_steps: int | None = None,
) -> list[dict]:
    """`blackbox_episode(cfg, name, seed, model, ...)` for every (name, seed) of `jobs`, batched
    (`batch.run_episodes` with the model in the slot: one planner call per control step for all
    episodes, each episode adapting its own copy of the model on its own data every `adapt_every`
    steps). Rows as `prior_episodes`'s, each marked `batched`."""

    model = load_black_box(method, None, cfg.gripper) if model is None else model
    adapter = adapter_for(model, adapt_epochs) if adapt_every > 0 else None
    jobs = list(jobs)
    t0 = time.perf_counter()
    results = batch.run_episodes(
        cfg,
        [massdist.named(name, cfg.box) for name, _ in jobs],
        [jax.random.PRNGKey(seed) for _, seed in jobs],
        ctrl=_blackbox_ctrl(ctrl, adapt_every, adapter),
        slots=slots,
        progress=None if progress is None else (lambda b, res: progress()),
        model=model,
        adapter=adapter,
        max_steps=max_steps,
    )
    return _batched_rows(method, jobs, results, time.perf_counter() - t0)


def _batched_rows(method: str, jobs, results, wall: float) -> list[dict]:
    """Rows of a batch of episodes, in the order of `jobs`, each marked `batched`, its `wall_s` the
    batch's wall time over its episodes."""
    per_episode = wall / max(len(jobs), 1)
    return [
        {**_row(method, name, seed, res.summary), "wall_s": per_episode, "batched": True}
        for (name, seed), res in zip(jobs, results, strict=True)
    ]


def prior_episode(
    cfg: Config, name: str, seed: int, estimator="learned", ctrl: ControllerConfig | None = None
) -> dict:
    """One episode of the physics-prior MPC (learned H by default) on the named box; a plain row."""
    est = learned_estimator(cfg) if estimator == "learned" else estimator
    res = run_episode(
        cfg,
        massdist.named(name, cfg.box),
        jax.random.PRNGKey(seed),
        estimator=est,
        ctrl=ctrl or ControllerConfig(),
    )
    return _row("prior", name, seed, res.summary)


def prior_episodes(
    cfg: Config,
    jobs,
    estimator="learned",
    ctrl: ControllerConfig | None = None,
    slots: int | None = None,
    progress=None,
) -> list[dict]:
    """`prior_episode(cfg, name, seed)` for every (name, seed) of `jobs`, batched (`batch.run_episodes`:
    the same box, episode key `PRNGKey(seed)`, estimator and controller; agreement in distribution, not
    bit for bit, see boxjax/batch.py). Rows in the order of `jobs`, each marked `batched`, its `wall_s`
    the batch's wall time over the number of episodes. `progress`: callable() once per finished episode.

    Raises:
      ValueError: a controller the batched path cannot run (`batch.supports`).
    """

    ctrl = ctrl or ControllerConfig()
    jobs = list(jobs)
    est = learned_estimator(cfg) if estimator == "learned" else estimator
    t0 = time.perf_counter()
    results = batch.run_episodes(
        cfg,
        [massdist.named(name, cfg.box) for name, _ in jobs],
        [jax.random.PRNGKey(seed) for _, seed in jobs],
        estimator=est,
        ctrl=ctrl,
        slots=slots,
        progress=None if progress is None else (lambda b, res: progress()),
    )
    return _batched_rows("prior", jobs, results, time.perf_counter() - t0)


def _row(method: str, name: str, seed: int, s: dict) -> dict:
    return {
        "method": method,
        "box": name,
        "seed": seed,
        "outcome": outcome(s),
        "success": bool(s["success"]),
        "steps": int(s["steps"]),
        "wall_s": float(s["wall_s"]),
        "adapt_s": float(s["adapt_s"]),
        "adaptations": int(s["adaptations"]),
        "adapt_epoch_s": float(s["adapt_s"]) / s["adaptations"] if s["adaptations"] else None,
        "max_balance_error_m": float(s["max_balance_error_m"]),
        "plan_ms_median": s["plan_ms_median"],
    }


def compare(
    cfg: Config = DEFAULT,
    boxes=("A", "B", "C", "D"),
    seeds: int = 5,
    methods=METHODS,
    model=None,
    adapt_every: int = 20,
    adapt_epochs: int = 1,
    progress: bool = True,
    pets_model=None,
    *,
    estimator="learned",
    batched: bool | None = None,
    slots: int | None = None,
    ctrl: ControllerConfig | None = None,
    w_weights: str | None = None,
    h_report=None,
    batch_black_boxes: bool = False,
) -> dict:
    """Table 1: rows (one per box, method, seed) and `table` (aggregated); plain data. `model`: W for
    "blackbox", `pets_model`: the ensemble for "pets" (default: the shipped ones). `estimator`: the
    prior's ("learned": the shipped H; or a callable such as `learned_estimator(cfg, weights)`).
    `batched`: run the prior's episodes together (`prior_episodes`; default: where `batch.supports` the
    controller), `slots` boxes per planner call; `batch_black_boxes`: the black boxes' episodes too
    (`blackbox_episodes`; off by default, see the module docstring). `w_weights` / `h_report`:
    what Table 2 reads (default: the shipped files)."""

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {METHODS}")
    ctrl = ctrl or ControllerConfig()
    why_not = batch.supports(ctrl)
    if batched and why_not is not None:
        raise ValueError(f"cannot batch the prior's episodes: {why_not}")
    if batch_black_boxes and why_not is not None:
        raise ValueError(f"cannot batch the black boxes' episodes: {why_not}")
    batched = why_not is None if batched is None else batched
    models = {"blackbox": model, "pets": pets_model}
    from tqdm.auto import tqdm

    t0 = time.perf_counter()
    jobs = [(m, b, s) for b in boxes for m in methods for s in range(seeds)]
    done: dict[tuple, dict] = {}
    bar = tqdm(total=len(jobs), desc="compare (episodes)", disable=not progress, leave=False)
    est = learned_estimator(cfg) if "prior" in methods and estimator == "learned" else estimator
    if batched and "prior" in methods:
        prior_jobs = [(b, s) for m, b, s in jobs if m == "prior"]
        for r in prior_episodes(cfg, prior_jobs, est, ctrl, slots, progress=lambda: bar.update(1)):
            done[("prior", r["box"], r["seed"])] = r
    for m in [m for m in methods if m in BLACK_BOXES] if batch_black_boxes else ():
        if models[m] is None:
            models[m] = load_black_box(m, None, cfg.gripper)
        m_jobs = [(b, s) for mm, b, s in jobs if mm == m]
        rows_m = blackbox_episodes(
            cfg, m_jobs, models[m], adapt_every, adapt_epochs, ctrl, m, slots, progress=lambda: bar.update(1)
        )
        for r in rows_m:
            done[(m, r["box"], r["seed"])] = r
    for m, b, s in jobs:
        if (m, b, s) in done:
            continue
        if m == "prior":
            done[(m, b, s)] = prior_episode(cfg, b, s, est, ctrl)
        else:
            if models[m] is None:
                models[m] = load_black_box(m, None, cfg.gripper)
            done[(m, b, s)] = blackbox_episode(
                cfg, b, s, models[m], adapt_every, adapt_epochs, ctrl=ctrl, method=m
            )
        bar.update(1)
    bar.close()
    rows = [done[j] for j in jobs]
    pets_weights = pets.shipped_path() if "pets" in methods else None
    return {
        "rows": rows,
        "table": table(rows),
        "table2": table2(w_weights, pets_weights, h_report),
        "wall_s": time.perf_counter() - t0,
        "adapt_every": adapt_every,
        "adapt_epochs": adapt_epochs,
        "prior_batched": bool(batched and "prior" in methods),
        "blackbox_batched": bool(batch_black_boxes and any(m in BLACK_BOXES for m in methods)),
    }


def random_safe(
    cfg: Config = DEFAULT,
    n: int = 30,
    seed: int = 0,
    methods=METHODS,
    model=None,
    adapt_every: int = 20,
    adapt_epochs: int = 1,
    jsonl: str | None = None,
    progress: bool = True,
    pets_model=None,
) -> list[dict]:
    """Beyond the paper: both methods on the first `n` random label-safe boxes of `boxjax evaluate
    --seed SEED` (`experiments.make_boxes`, the same boxes and episode keys), one episode each. Rows as
    `compare`'s, box = "safe<j>"; appended to `jsonl` (one JSON object per line) as they finish."""
    import json

    from tqdm.auto import tqdm

    boxes = experiments.make_boxes(cfg, n, 0, seed)
    models = {"blackbox": model, "pets": pets_model}
    for m in BLACK_BOXES:
        if m in methods and models[m] is None:
            models[m] = load_black_box(m, None, cfg.gripper)
    est = learned_estimator(cfg) if "prior" in methods else None
    adapters = {m: adapter_for(x, adapt_epochs) if adapt_every > 0 else None for m, x in models.items()}
    rows = []
    for j in tqdm(range(len(boxes)), desc="random safe boxes", disable=not progress, leave=False):
        key = jax.numpy.asarray(boxes.keys[j])
        for m in methods:
            if m == "prior":
                res = run_episode(cfg, boxes.dist(j), key, estimator=est)
            else:
                ad = adapters[m]
                ctrl = ControllerConfig(explore=False, adapt_every=adapt_every if ad else 0)
                res = run_episode(cfg, boxes.dist(j), key, ctrl=ctrl, model=models[m], adapter=ad)
            rows.append(_row(m, f"safe{j}", seed, res.summary))
            if jsonl:
                with open(jsonl, "a") as f:
                    f.write(json.dumps(rows[-1]) + "\n")
    return rows


def table2(w_weights: str | None = None, pets_weights: str | None = None, h_report=None) -> list[dict]:
    """Paper Table 2 from what the shipped (or given) models were really trained on: transitions, where
    the data came from, zero-shot or not (read from the estimator's report and W's checkpoint; a PETS
    row from `pets_weights` when given). `h_report`: H's training report (a `train_estimator` report
    dict or its report.json path; default: the shipped estimator's)."""
    import json

    if h_report is None or isinstance(h_report, (str, os.PathLike)):
        with open(SHIPPED_REPORT if h_report is None else h_report) as f:
            h = json.load(f)
        h = h["training"] if h_report is None else h
    else:
        h = h_report
    _, meta = baseline.load(w_weights or baseline.shipped_path(), with_meta=True)
    info = meta.get("info", {})
    kinds = ", ".join(f"{v} {k}" for k, v in info.get("episodes_by_kind", {}).items())
    return [
        {
            "model": "H (physical priors estimation)",
            "transitions": h["dataset_summary"]["transitions"],
            "data_from": f"{h['boxes']} random boxes, 45 fixed exploration steps each",
            "zero_shot": True,
            "paper": "~90k transitions, 2000 random boxes x 45 steps, zero-shot",
        },
        {
            "model": "W (black-box MPC baseline)",
            "transitions": info.get("transitions"),
            "data_from": f"{info.get('episodes')} full episodes of box {info.get('distribution')}: {kinds}",
            "zero_shot": False,
            "online_adaptation": True,
            "paper": "~122k transitions, ~200 episodes of one box (random + successful policies), adapted",
        },
    ] + ([] if pets_weights is None else [_pets_table2_row(pets_weights)])


def _pets_table2_row(path) -> dict:
    _, meta = pets.load(path, with_meta=True)
    info = meta.get("info", {})
    kinds = ", ".join(f"{v} {k}" for k, v in info.get("episodes_by_kind", {}).items())
    return {
        "model": "PETS (probabilistic ensemble, beyond the paper)",
        "transitions": info.get("transitions"),
        "data_from": f"W's data, {info.get('episodes')} full episodes of box {info.get('distribution')}: "
        + kinds,
        "zero_shot": False,
        "online_adaptation": True,
        "paper": None,
    }


def table(rows: list[dict]) -> list[dict]:
    """Per (box, method): success ratio, refusals, mean steps over successes, mean wall time per episode,
    mean adaptation time per episode and per epoch, worst balance error; beside the paper's numbers."""
    out = []
    keys = list(dict.fromkeys((r["box"], r["method"]) for r in rows))
    for box, method in keys:
        rs = [r for r in rows if r["box"] == box and r["method"] == method]
        ok = [r for r in rs if r["success"]]
        epochs = [r["adapt_epoch_s"] for r in rs if r["adapt_epoch_s"] is not None]
        ran = [r for r in rs if r["outcome"] != "refused"]
        paper = PAPER_TABLE1.get((box, method))
        out.append(
            {
                "box": box,
                "method": method,
                "episodes": len(rs),
                "success_ratio": len(ok) / len(rs),
                "refused": sum(r["outcome"] == "refused" for r in rs),
                "outcomes": {
                    o: sum(r["outcome"] == o for r in rs) for o in dict.fromkeys(x["outcome"] for x in rs)
                },
                "mean_steps_successes": statistics.mean(r["steps"] for r in ok) if ok else None,
                "mean_wall_s": statistics.mean(r["wall_s"] for r in rs),
                "mean_adapt_s": statistics.mean(r["adapt_s"] for r in rs),
                "adapt_epoch_s_median": statistics.median(epochs) if epochs else None,
                "worst_balance_m": max(r["max_balance_error_m"] for r in ran) if ran else None,
                "paper_success": paper[0] if paper else None,
                "paper_steps": paper[1] if paper else None,
            }
        )
    return out


def generalisation_gap(
    cfg: Config = DEFAULT,
    model=None,
    boxes=("A", "C"),
    n_episodes: int = 20,
    seed: int = 1000,
    progress: bool = True,
    pets_model=None,
) -> dict:
    """One-step errors (median / p90 / mean, mm and degrees) of W, the prior (true masses), constant
    velocity and, when `pets_model` is given, PETS (members' mean; with its calibration) on `n_episodes`
    fresh episodes of each box (training.baseline's episode mix, seed `seed`)."""
    model = baseline.default_model(cfg.gripper) if model is None else model
    out = {}
    for name in boxes:
        truth = massdist.named(name, cfg.box)
        t0 = time.perf_counter()
        eps = baseline_train.collect(cfg, truth, n_episodes, seed, progress)
        tr = baseline_train.transitions_of(eps)
        out[name] = baseline_train.compare_errors(model, tr, truth, cfg)
        if pets_model is not None:
            out[name]["pets"] = baseline.summarise_errors(baseline.one_step_errors(pets_model, tr))
            out[name]["pets_calibration"] = pets.calibration(pets_model, tr)
        out[name]["wall_s"] = time.perf_counter() - t0
    return out


def format_table(rows: list[dict]) -> str:
    """Markdown of `table` rows."""
    cols = (
        "box",
        "method",
        "success",
        "steps (successes)",
        "wall s / episode",
        "adaptation s / episode",
        "worst balance",
        "paper success",
        "paper steps",
    )
    lines = ["| " + " | ".join(cols) + " |", "| --- " * len(cols) + "|"]

    def f(x, p="{:.1f}"):
        return "-" if x is None else p.format(x)

    for r in rows:
        n_ok = round(r["success_ratio"] * r["episodes"])
        refused = f" (refused {r['refused']})" if r["refused"] else ""
        bal = None if r["worst_balance_m"] is None else 100 * r["worst_balance_m"]
        cells = (
            r["box"],
            r["method"],
            f"{n_ok}/{r['episodes']}{refused}",
            f(r["mean_steps_successes"]),
            f(r["mean_wall_s"]),
            f(r["mean_adapt_s"], "{:.2f}"),
            f(bal, "{:.1f} cm"),
            str(r["paper_success"]),
            f(r["paper_steps"]),
        )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
