"""One episode of a written evaluation replayed from its recorded actions, with what the runtime safety
monitor's recoveries predicted and what the box then did (docs/results/faults.md, "Recoveries that leave
the box further out").

    boxjax evaluate --boxes 100 --seed 2 --out ev/          # or scripts/planner_study.py ... --out ev/
    python scripts/recovery_replay.py ev/ 48 [--from 360] [--plot box48.png]

A recovery is found in the actions: the planner's action (belt setpoints not zero) sent from rest (the
action before it all zeros) and followed by a stop's (belt setpoints zero). For an evaluation without
faults the monitor's check is recomputed on the true states (its window then is the true state); with
faults only the true balance errors are shown. Prints one JSON line per recovery.
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import planning
from boxjax.config import DEFAULT
from boxjax.control import batch, monitor
from boxjax.control.models import planning_model
from boxjax.experiments import evaluation as experiments
from boxjax.sim.faults import NONE


def recoveries(actions: np.ndarray) -> list[int]:
    """Control steps of the recoveries in an episode's actions (T, 4)."""
    a = np.asarray(actions)
    return [
        t
        for t in range(1, len(a) - 1)
        if np.any(a[t, :2] != 0) and np.all(a[t - 1] == 0) and np.all(a[t + 1, :2] == 0)
    ]


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="an evaluation written with --out (with recorded actions)")
    ap.add_argument("index", type=int, help="the box's row")
    ap.add_argument("--from", dest="start", type=int, default=0, help="first control step to plot")
    ap.add_argument("--plot", help="write the balance error and the recoveries here (.png)")
    args = ap.parse_args(argv)
    cfg = DEFAULT
    boxes, summary = experiments.load_boxes(args.dir)
    recorded = experiments.load_actions(args.dir)
    if recorded is None:
        ap.error(f"{args.dir} has no recorded actions")
    if not 0 <= args.index < len(boxes):
        ap.error(f"index {args.index} is outside the evaluation's {len(boxes)} boxes")
    actions = np.asarray(recorded[args.index], np.float64).reshape(-1, 4)
    ctrl = experiments.controller_from_settings(summary)
    faults = experiments.faults_from_settings(summary)
    truth, key = boxes.dist(args.index), jax.random.wrap_key_data(boxes.keys[args.index])
    res = batch.replay_episode(cfg, truth, key, actions, ctrl=ctrl, faults=faults)
    tr = res.trace
    model = planning_model(cfg, ctrl, truth) if faults == NONE and summary["estimator"] == "oracle" else None
    rows = []
    for t in recoveries(actions):
        row = {"step": t, "balance_mm": 1e3 * float(tr.balance_error[t])}
        row["then_mm"] = [round(1e3 * float(x), 1) for x in tr.balance_error[t + 1 : t + 4]]
        if model is not None:
            window = jnp.asarray(tr.s[t - planning.MIN_WINDOW + 1 : t + 1], jnp.float32)
            c = monitor.to_host(
                monitor.check(
                    cfg, model, window, jnp.asarray(tr.belt_speed[t], jnp.float32),
                    jnp.asarray(actions[t], jnp.float32), ctrl.monitor.horizon, ctrl.monitor.backup,
                )
            )  # fmt: skip
            row["predicted_ahead_mm"], row["predicted_end_mm"] = (
                1e3 * float(c.go_ahead),
                1e3 * float(c.go_end),
            )
        rows.append(row)
        print(json.dumps({k: round(v, 1) if isinstance(v, float) else v for k, v in row.items()}))
    print(json.dumps({"outcome": experiments.outcome(res.summary), "steps": res.summary["steps"]}))
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from boxjax.fileio import atomic_path

        be = 1e3 * np.asarray(tr.balance_error)
        steps = np.arange(len(be))
        fig, ax = plt.subplots(figsize=(7, 3.4))
        ax.plot(steps[args.start :], be[args.start :], "k.-", label="true balance error")
        limit = 1e3 * cfg.task.balance_limit
        ax.axhline(limit, color="r", lw=1, label=f"limit {limit:.0f} mm")
        ax.axhline(ctrl.monitor.stop_at * limit, color="orange", lw=1, ls="--", label="stop_at")
        ax.axhline(ctrl.monitor.resume_below * limit, color="g", lw=1, ls=":", label="resume_below")
        for r in rows:
            if r["step"] < args.start:
                continue
            ax.axvline(r["step"], color="b", lw=0.6, ls="--")
            if "predicted_end_mm" in r:  # the recovery's prediction: where the box ends once its stop is over
                ax.annotate(
                    "", xy=(r["step"] + ctrl.monitor.horizon, r["predicted_end_mm"]),
                    xytext=(r["step"], r["balance_mm"]), arrowprops=dict(arrowstyle="->", color="b"),
                )  # fmt: skip
        last = max([len(be) - 1] + [r["step"] + ctrl.monitor.horizon for r in rows])
        ax.set_xlim(args.start - 1, last + 1)
        ax.set_xlabel("control step (50 ms); dashed blue: recoveries, arrows: their predicted ends")
        ax.set_ylabel("balance error (mm)")
        name = os.path.basename(os.path.normpath(args.dir))
        ax.set_title(f"{name}, box {args.index}: {experiments.outcome(res.summary)}", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
        fig.tight_layout()
        with atomic_path(args.plot) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    return rows


if __name__ == "__main__":
    main()
