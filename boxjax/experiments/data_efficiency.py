"""The data-efficiency curve (issue 12, beyond the paper): success on random safe boxes against training
transitions, for the estimator H (the physics-prior MPC) and for the black box W, as plain data and one
figure.

    python -m boxjax.experiments.data_efficiency --out benchmarks/results_data_efficiency.json \
        --plot benchmarks/data_efficiency.png [--h-boxes 100 250 500 1000 2000] \
        [--w-episodes 10 25 50 100 200] [--data /tmp/wrun0/dataset.npz] [--adapt-every 20] [--only H|W]

* H points (`h_point`): `training.estimator.train_estimator(seed, n_boxes)` (what `boxjax
  train-estimator --boxes N --seed 0` runs) into a temporary directory, then `experiments.evaluate` of the
  physics-prior MPC with that H (`controller.learned_estimator(cfg, weights)`, as `boxjax evaluate
  --estimator learned --weights FILE`) on the first `n_eval` random safe boxes of `boxjax evaluate --seed
  EVAL_SEED` (batched). Transitions: n_boxes x 45 exploration steps (validation boxes included: H uses
  them for early stopping and its thresholds). The shipped H (288,000 boxes) is one more point.
* W points (`w_point`): W trained (`training.baseline.train`, the shipped W's settings: `BaselineConfig()`,
  12 epochs, seed 0) on the first n episodes of W's dataset (`boxjax train-baseline` writes it:
  200 episodes of box A; `w_episodes`), split as `train_baseline` splits (one episode in 10 held out),
  then `comparison.random_safe` with W in the model slot on the same boxes (one episode at a time;
  online adaptation every `adapt_every` steps, 0: none). Transitions: all of those n episodes' (train and
  held out, as H's count includes its validation boxes). The dataset's episodes cycle through the kinds
  prior, prior, prior-noisy, prior-noisy, random (`training.baseline.KINDS`), so the first n keep the
  kinds mixed in the dataset's proportions (2:2:1) for any n that is a multiple of 5. The 200-episode
  point is the shipped W (`boxjax/data/baseline.npz`), not retrained.

`write_curve` writes the JSON (atomically) that `boxjax reproduce` reads; its schema is `check_curve`'s.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

from boxjax import blackbox
from boxjax.blackbox import baseline, pets
from boxjax.config import DEFAULT, Config
from boxjax.control import batch
from boxjax.estimator.belief import learned_estimator
from boxjax.estimator.shipped import SHIPPED_WEIGHTS
from boxjax.experiments import comparison
from boxjax.experiments import evaluation as experiments
from boxjax.experiments.evaluation import wilson_interval
from boxjax.fileio import atomic_path, save_figure
from boxjax.training import baseline as baseline_train
from boxjax.training import estimator as estimator_pipeline
from boxjax.training import pets as pets_train

H_BOXES = (100, 250, 500, 1000, 2000)
W_EPISODES = (10, 25, 50, 100, 200)
SHIPPED_H_BOXES = 288000
SHIPPED_W_EPISODES = 200
EXPLORATION_STEPS = 45  # transitions per H training box
EVAL_BOXES = 30
DEFAULT_DATA = "/tmp/wrun0/dataset.npz"
H_KEYS = ("boxes", "transitions", "safe_success", "safe_boxes", "ci95", "train_s", "eval_s")
W_KEYS = ("episodes", "transitions", "safe_success", "safe_boxes", "ci95", "adapt_every", "train_s", "eval_s")


def _ci(k: int, n: int) -> list[float]:

    return list(wilson_interval(k, n))


def h_point(
    n_boxes: int,
    eval_seed: int = 0,
    cfg: Config = DEFAULT,
    *,
    train_seed: int = 0,
    n_eval: int = EVAL_BOXES,
    weights: str | None = None,
    progress: bool = True,
) -> dict:
    """One H point: train H on `n_boxes` random boxes (unless `weights` names a checkpoint, e.g. the
    shipped one: `n_boxes` is then what it was trained on) and evaluate the prior MPC with it on the
    first `n_eval` safe boxes of `evaluate --seed eval_seed`."""

    point: dict = {"boxes": int(n_boxes), "transitions": int(n_boxes) * EXPLORATION_STEPS}
    with tempfile.TemporaryDirectory(prefix="boxjax-de-h-") as tmp:
        if weights is None:
            rep = estimator_pipeline.train_estimator(train_seed, n_boxes, tmp, cfg, progress=progress)
            weights_used = rep["weights"]
            point.update(transitions=int(rep["transitions"]), data_s=float(rep["data_s"]))
            point.update(train_s=float(rep["train_s"]), iou_median_val=rep["validation"].get("iou_median"))
        else:
            weights_used = weights
            point.update(shipped=True, **_shipped_h_times())
        est = learned_estimator(cfg, weights_used)
        t0 = time.perf_counter()
        ev = experiments.evaluate(
            cfg, n_eval, 0, eval_seed, estimator="learned", estimator_fn=est, progress=progress
        )
        point["eval_s"] = time.perf_counter() - t0
    s = ev.summary
    point.update(
        safe_success=int(s["safe_success"]),
        safe_boxes=int(s["safe_boxes"]),
        ci95=[float(x) for x in s["safe_success_ci95"]],
        failures=s["failures"],
        false_aborts=int(s["false_aborts"]),
    )
    return point


def _shipped_h_times() -> dict:
    path = os.path.join(
        os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", "estimator_report.json"
    )
    with open(path) as f:
        tr = json.load(f)["training"]
    return {"train_s": tr.get("train_s"), "data_s": tr.get("data_s"), "transitions": int(tr["transitions"])}


def h_curve(
    sizes=H_BOXES,
    eval_seed: int = 0,
    cfg: Config = DEFAULT,
    *,
    train_seed: int = 0,
    n_eval: int = EVAL_BOXES,
    shipped: bool = True,
    progress: bool = True,
    on_point=None,
) -> list[dict]:
    """`h_point` for every size (and the shipped H when `shipped`); `on_point("H", point)` after each."""

    jobs = [(n, None) for n in sizes] + ([(SHIPPED_H_BOXES, str(SHIPPED_WEIGHTS))] if shipped else [])
    out = []
    for n, w in _bar(jobs, "H curve (points)", progress):
        out.append(
            h_point(n, eval_seed, cfg, train_seed=train_seed, n_eval=n_eval, weights=w, progress=progress)
        )
        if on_point:
            on_point("H", out[-1])
    return out


def w_episodes(tr: dict, n: int) -> dict:
    """The transitions (and `episode_kind`, `episode_outcome`) of the first `n` episodes of a W dataset
    (`training.baseline.load_dataset`), in the dataset's order."""
    kinds = np.asarray(tr["episode_kind"])
    if not 2 <= n <= len(kinds):
        raise ValueError(f"need 2 <= episodes <= {len(kinds)} (the dataset's), got {n}")
    keep = np.asarray(tr["episode"]) < n
    per_tr = {k: np.asarray(v)[keep] for k, v in tr.items() if k not in ("episode_kind", "episode_outcome")}
    return {**per_tr, "episode_kind": kinds[:n], "episode_outcome": np.asarray(tr["episode_outcome"])[:n]}


def train_w(sub: dict, cfg: Config = DEFAULT, seed: int = 0, config=None, progress: bool = True):
    """W trained on a `w_episodes` subset as `training.baseline.train_baseline` trains it (its split, its
    config); returns (model, info: transitions, train/held-out counts, kinds, held-out W error, train_s)."""
    import jax

    config = config or baseline.BaselineConfig()
    tr = {k: v for k, v in sub.items() if k not in ("episode_kind", "episode_outcome")}
    train_tr, held = pets_train.split_episodes(tr, len(sub["episode_kind"]))
    t0 = time.perf_counter()
    model, _ = baseline_train.train(train_tr, config, seed, cfg, progress)
    jax.block_until_ready(model.params)
    kinds = [str(k) for k in sub["episode_kind"]]
    info = {
        "transitions": int(tr["action"].shape[0]),
        "train_transitions": int(train_tr["action"].shape[0]),
        "heldout_transitions": int(held["action"].shape[0]),
        "episodes_by_kind": {k: kinds.count(k) for k in dict.fromkeys(kinds)},
        "train_s": time.perf_counter() - t0,
        "heldout_error_median": {
            k: v["median"]
            for k, v in baseline.summarise_errors(baseline.one_step_errors(model, held)).items()
        },
    }
    return model, info


def w_point(
    n_episodes: int,
    dataset_path: str = DEFAULT_DATA,
    eval_seed: int = 0,
    cfg: Config = DEFAULT,
    *,
    seed: int = 0,
    adapt_every: int = 20,
    n_eval: int = EVAL_BOXES,
    weights: str | None = None,
    config=None,
    progress: bool = True,
    tr: dict | None = None,
    method: str = "blackbox",
) -> dict:
    """One W point: W on the first `n_episodes` of the dataset (or the checkpoint `weights`, trained on
    them, e.g. the shipped W for 200), evaluated by `comparison.random_safe` on the first `n_eval` safe
    boxes of `evaluate --seed eval_seed`. method="pets" with `weights`: a PETS checkpoint instead."""

    tr = baseline_train.load_dataset(dataset_path) if tr is None else tr
    sub = w_episodes(tr, n_episodes)
    point: dict = {"episodes": int(n_episodes)}
    if weights is None:
        if method != "blackbox":
            raise ValueError(f"only W is trained here; give the {method} checkpoint as weights")
        model, info = train_w(sub, cfg, seed, config, progress)
        point.update(info)
    else:
        model = blackbox.load_black_box(method, weights, cfg.gripper)
        info = _shipped_info(method, weights, dataset_path)
        point.update(shipped=True, transitions=int(sub["action"].shape[0]), **info)
    t0 = time.perf_counter()
    rows = comparison.random_safe(
        cfg, n_eval, eval_seed, methods=(method,), adapt_every=adapt_every, progress=progress,
        **{"pets_model" if method == "pets" else "model": model},
    )  # fmt: skip
    point["eval_s"] = time.perf_counter() - t0
    k = sum(r["success"] for r in rows)
    fails: dict = {}
    for r in rows:
        if not r["success"]:
            fails[r["outcome"]] = fails.get(r["outcome"], 0) + 1
    point.update(
        safe_success=int(k),
        safe_boxes=len(rows),
        ci95=_ci(k, len(rows)),
        adapt_every=int(adapt_every),
        failures=dict(sorted(fails.items())),
        episode_wall_s_mean=float(np.mean([r["wall_s"] for r in rows])),
        adapt_s_mean=float(np.mean([r["adapt_s"] for r in rows])),
    )
    return point


def _shipped_info(method: str, weights: str, dataset_path: str) -> dict:
    """A shipped black box's training counts (its checkpoint) and training time (the report beside its
    dataset when it is that run's: same transitions)."""

    _, meta = (pets if method == "pets" else baseline).load(weights, with_meta=True)
    info = meta.get("info", {})
    out = {"train_transitions": info.get("train_transitions"), "train_s": info.get("train_s")}
    rep = os.path.join(os.path.dirname(os.path.abspath(dataset_path)), "report.json")
    if out["train_s"] is None and os.path.isfile(rep):
        with open(rep) as f:
            r = json.load(f)
        if r.get("transitions") == info.get("transitions"):
            out["train_s"] = r.get("train_s")
    return out


def w_curve(
    episodes=W_EPISODES,
    dataset_path: str = DEFAULT_DATA,
    eval_seed: int = 0,
    cfg: Config = DEFAULT,
    *,
    shipped: bool = True,
    progress: bool = True,
    on_point=None,
    **kw,
) -> list[dict]:
    """`w_point` (keywords `kw`: seed, adapt_every, n_eval, config) for every episode count; with
    `shipped`, the count SHIPPED_W_EPISODES is the shipped W (`boxjax/data/baseline.npz`) rather than a
    retraining. `on_point("W", point)` after each."""

    tr = baseline_train.load_dataset(dataset_path)
    out = []
    for n in _bar(list(episodes), "W curve (points)", progress):
        w = baseline.shipped_path() if shipped and n == SHIPPED_W_EPISODES else None
        out.append(w_point(n, dataset_path, eval_seed, cfg, weights=w, progress=progress, tr=tr, **kw))
        if on_point:
            on_point("W", out[-1])
    return out


def _bar(items, desc, progress):
    from tqdm.auto import tqdm

    return tqdm(items, desc=desc, disable=not progress, leave=False)


def check_curve(doc: dict) -> dict:
    """`doc` if it has the curve file's schema (H and W lists of points with H_KEYS / W_KEYS, eval_seed,
    command), else ValueError naming what is missing."""
    for k in ("H", "W", "eval_seed", "command"):
        if k not in doc:
            raise ValueError(f"data-efficiency curve: missing {k!r}")
    for name, keys in (("H", H_KEYS), ("W", W_KEYS), ("PETS", W_KEYS)):
        for i, p in enumerate(doc.get(name, [])):
            missing = [k for k in keys if k not in p]
            if missing:
                raise ValueError(f"data-efficiency curve: {name}[{i}] lacks {missing}")
            if not (0 <= p["safe_success"] <= p["safe_boxes"]) or len(p["ci95"]) != 2:
                raise ValueError(f"data-efficiency curve: {name}[{i}] has an impossible count or interval")
    return doc


def write_curve(doc: dict, path) -> str:
    """Write the curve (checked by `check_curve`) to `path` as JSON, atomically."""

    check_curve(doc)
    with atomic_path(path, suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(doc, f, indent=1)
    return os.fspath(path)


def _is_shipped(name: str, p: dict) -> bool:
    if "shipped" in p:
        return bool(p["shipped"])
    return p["boxes"] == SHIPPED_H_BOXES if name == "H" else False


def plot_curve(curve: dict, path) -> str:
    """The curve as one PNG: safe boxes turned (of `safe_boxes`, with 95 % Wilson intervals) against
    training transitions (log scale), one line for H (the physics-prior MPC) and one for W; the shipped
    models' points starred. Returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.2, 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    styles = {
        "H": ("tab:blue", "o", "physics-prior MPC with H (H's data: random boxes x 45 steps)"),
        "W": ("tab:red", "s", "black box W (episodes of box A)"),
        "PETS": ("tab:green", "D", "PETS ensemble (W's data)"),
    }
    n_max = 0
    series = []
    for name in styles:
        pts = curve.get(name, [])
        for adapt in sorted({p.get("adapt_every", 0) for p in pts}, reverse=True) if name != "H" else [None]:
            group = [p for p in pts if adapt is None or p.get("adapt_every", 0) == adapt]
            series.append((name, adapt, sorted(group, key=lambda p: p["transitions"])))
    for name, adapt, pts in series:
        color, marker, label = styles[name]
        x = np.asarray([p["transitions"] for p in pts], float)
        k = np.asarray([p["safe_success"] for p in pts], float)
        n = np.asarray([p["safe_boxes"] for p in pts], float)
        lo = np.asarray([p["ci95"][0] for p in pts]) * n
        hi = np.asarray([p["ci95"][1] for p in pts]) * n
        n_max = max(n_max, int(n.max()))
        if adapt is not None:
            label += f", adapted online every {adapt} steps" if adapt else ", no online adaptation"
        ls = "--" if adapt == 0 else "-"
        ax.errorbar(
            x,
            k,
            yerr=[np.maximum(k - lo, 0), np.maximum(hi - k, 0)],
            color=color,
            marker=marker,
            ls=ls,
            capsize=3,
            label=label,
        )
        for p, xi, ki in zip(pts, x, k, strict=True):
            size = p["boxes"] if name == "H" else p["episodes"]
            unit = "boxes" if name == "H" else "ep."
            if _is_shipped(name, p):
                ax.plot([xi], [ki], marker="*", ms=16, color=color, mec="k", zorder=5, ls="none")
                # where the label goes: the shipped W and PETS share their x (W's data)
                text, (dx, dy) = f"shipped {name}\n{size:,} {unit}", (6, -22)
                if name == "PETS":
                    text, (dx, dy) = f"shipped PETS ({size} {unit})", (9, -3)
                elif adapt:
                    text, (dx, dy) = f"shipped W, adapted online ({size} {unit})", (9, -3)
                ax.annotate(
                    text, (xi, ki), textcoords="offset points", xytext=(dx, dy), fontsize=8, color=color
                )
            else:
                ax.annotate(f"{size:,}", (xi, ki), textcoords="offset points", xytext=(4, 5), fontsize=7,
                            color=color)  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlabel("training transitions")
    ax.set_ylabel(f"random safe boxes turned (of {n_max or EVAL_BOXES})")
    ax.set_ylim(-0.5, (n_max or EVAL_BOXES) + 0.5)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    seed = curve.get("eval_seed")
    ax.set_title(
        f"data efficiency: the same {n_max or EVAL_BOXES} random safe boxes (evaluate --seed {seed})"
    )
    return save_figure(fig, path)


def format_table(curve: dict) -> str:
    """Markdown table of the curve's points: model, data, transitions, turned (95 % interval), refused
    safe boxes (H), other failures, training and evaluation time."""
    cols = (
        "model",
        "data",
        "transitions",
        "turned",
        "95 % interval",
        "refused",
        "failures",
        "data s",
        "train s",
        "eval s",
    )
    lines = ["| " + " | ".join(cols) + " |", "| --- " * len(cols) + "|"]
    for name in ("H", "W", "PETS"):
        for p in sorted(curve.get(name, []), key=lambda q: q["transitions"]):
            what = f"{p['boxes']:,} boxes" if name == "H" else f"{p['episodes']} episodes"
            if name != "H":
                what += f", adapted every {p['adapt_every']}" if p["adapt_every"] else ", no adaptation"
            if _is_shipped(name, p):
                what += " (shipped)"
            fails = ", ".join(f"{k} {v}" for k, v in sorted(p.get("failures", {}).items())) or "-"
            t, d = ("-" if p.get(k) is None else f"{p[k]:.0f}" for k in ("train_s", "data_s"))
            cells = (
                "prior MPC + H" if name == "H" else name,
                what,
                f"{p['transitions']:,}",
                f"{p['safe_success']}/{p['safe_boxes']}",
                f"{100 * p['ci95'][0]:.0f}-{100 * p['ci95'][1]:.0f} %",
                str(p.get("false_aborts", "-")),
                fails,
                d,
                t,
                f"{p['eval_s']:.0f}",
            )
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m boxjax.experiments.data_efficiency", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", required=True, help="the curve's JSON (kept points are not re-run: resumable)")
    p.add_argument("--plot", help="write the figure to this PNG")
    p.add_argument("--h-boxes", type=int, nargs="*", default=list(H_BOXES))
    p.add_argument("--w-episodes", type=int, nargs="*", default=list(W_EPISODES))
    p.add_argument("--data", default=DEFAULT_DATA, help="W's dataset.npz (boxjax train-baseline --out DIR)")
    p.add_argument("--eval-seed", type=int, default=0)
    p.add_argument("--eval-boxes", type=int, default=EVAL_BOXES)
    p.add_argument("--adapt-every", type=int, default=20, help="W's online adaptation period (0: none)")
    p.add_argument("--only", choices=("H", "W"), help="run only this curve")
    p.add_argument("--no-shipped", action="store_true", help="leave out the shipped models' points")
    p.add_argument("--pets", action="store_true", help="add the shipped PETS on the same boxes (key PETS)")
    p.add_argument("--plot-only", action="store_true", help="redraw --plot from --out (and print the table)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    a = p.parse_args(argv)
    if a.plot_only:
        if not a.plot:
            p.error("--plot-only needs --plot")
        with open(a.out) as f:
            doc = check_curve(json.load(f))
        print(format_table(doc))
        print(plot_curve(doc, a.plot))
        return 0

    batch.use_host_devices()  # before JAX starts: the batched evaluations shard their boxes over the cores
    command = "python -m boxjax.experiments.data_efficiency " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    doc = {"H": [], "W": [], "eval_seed": a.eval_seed, "command": command}
    if os.path.isfile(a.out):
        with open(a.out) as f:
            old = check_curve(json.load(f))
        if old["eval_seed"] == a.eval_seed:
            doc.update({k: old[k] for k in ("H", "W", "PETS") if k in old})
    have_h = {pt["boxes"] for pt in doc["H"] if pt["safe_boxes"] == a.eval_boxes}
    have_w = {(pt["episodes"], pt["adapt_every"]) for pt in doc["W"] if pt["safe_boxes"] == a.eval_boxes}

    def keep(name, point):
        doc[name] = sorted(doc[name] + [point], key=lambda q: q["transitions"])
        write_curve(doc, a.out)
        print(json.dumps({name: point}), flush=True)

    progress = not a.quiet
    if a.only in (None, "H"):
        sizes = [n for n in a.h_boxes if n not in have_h]
        ship_h = not a.no_shipped and SHIPPED_H_BOXES not in have_h
        h_curve(sizes, a.eval_seed, n_eval=a.eval_boxes, shipped=ship_h, progress=progress, on_point=keep)
    if a.only in (None, "W"):
        eps = [n for n in a.w_episodes if (n, a.adapt_every) not in have_w]
        w_curve(eps, a.data, a.eval_seed, adapt_every=a.adapt_every, n_eval=a.eval_boxes,
                shipped=not a.no_shipped, progress=progress, on_point=keep)  # fmt: skip
    have_pets = {pt["adapt_every"] for pt in doc.get("PETS", []) if pt["safe_boxes"] == a.eval_boxes}
    if a.pets and a.adapt_every not in have_pets:
        pt = w_point(SHIPPED_W_EPISODES, a.data, a.eval_seed, adapt_every=a.adapt_every, n_eval=a.eval_boxes,
                     weights=pets.shipped_path(), progress=progress, method="pets")  # fmt: skip
        doc["PETS"] = doc.get("PETS", [])
        keep("PETS", pt)
    write_curve(doc, a.out)
    if a.plot:
        print(plot_curve(doc, a.plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
