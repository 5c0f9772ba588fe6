"""Does the turn show that the belief is wrong? The evidence a Bayesian update during the turn would use
(issue 30, item 3), measured on recorded episodes before building one.

An update of the belief from what the box does while it turns (particles weighted by how well the physics
prior predicts the observed motion with each) can only move towards the truth if the prior on the TRUE
mass distribution predicts the turn measurably better than the prior on the belief. For every episode of
the given evaluations that turned its box (or reached the step cap), this replays it bit for bit
(`evaluation.replay`: the recorded actions re-simulated with the episode's key) and, at every control step
of the turn, predicts the state `k` steps ahead from the observed window and the actions that were sent,
once with the prior on the estimator's belief and once with the prior on the truth. It reports the rms
errors (x, y in mm, yaw in degrees) of both and their ratio, for the hazardous boxes the pipeline turned
(the ones an update would have to catch) and a quarter of the safe ones.

    boxjax evaluate --boxes 100 --hazardous 30 --hazard-family F --estimator learned --seed 0 --out runs/F
    python scripts/turn_evidence.py --evals runs/gaussian runs/items ... --k 1 5 10 \\
        --out benchmarks/results_turn_evidence.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import planning
from boxjax.config import DEFAULT
from boxjax.control.config import ControllerConfig
from boxjax.control.models import planning_model
from boxjax.experiments import evaluation
from boxjax.fileio import atomic_path

W = planning.MIN_WINDOW


def prediction_errors(model, s, belt, actions, k: int) -> np.ndarray:
    """(T - k - W + 1, 5) errors of the k-step predictions from every window of the turn (T + 1 states).
    The arrays are padded to the task's step cap so that every episode shares one compiled function."""
    n = DEFAULT.task.max_steps + 1
    T = s.shape[0]

    def pad(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], n - x.shape[0], axis=0)])

    e = _errors(model, pad(s), pad(belt), pad(actions), k)
    return np.asarray(e)[: T - k - W + 1]


@partial(jax.jit, static_argnames="k")
def _errors(model, s, belt, actions, k: int):
    steps = jnp.arange(W - 1, s.shape[0] - k)

    def one(t):
        window = jax.lax.dynamic_slice(s, (t - W + 1, 0), (W, 5))
        a = jax.lax.dynamic_slice(actions, (t, 0), (k, 4))
        return model.rollout_sequence(window, belt[t], a)[-1] - s[t + k]

    return jax.vmap(one)(steps)


def rms(e) -> dict:
    e = np.asarray(e, np.float64)
    return {
        "x_mm": float(1e3 * np.sqrt(np.mean(e[:, 2] ** 2))),
        "y_mm": float(1e3 * np.sqrt(np.mean(e[:, 3] ** 2))),
        "yaw_deg": float(np.degrees(np.sqrt(np.mean(e[:, 4] ** 2)))),
    }


def episodes(out_dir: str, ks: tuple[int, ...], safe_every: int) -> list[dict]:
    ev = json.load(open(os.path.join(out_dir, "evaluation.json")))
    ctrl = ControllerConfig()
    rows = []
    for r in ev["rows"]:
        j = r["index"]
        if r["outcome"] not in ("success", "step_cap") or (not r["hazardous"] and j % safe_every):
            continue
        res, _ = evaluation.replay(DEFAULT, out_dir, j)
        n0 = res.summary["exploration_steps"]
        s, belt, a = (
            jnp.asarray(x[n0:], jnp.float32) for x in (res.trace.s, res.trace.belt_speed, res.trace.actions)
        )
        if s.shape[0] < max(ks) + 10:
            continue
        row = {"eval": out_dir, "index": j, "family": r["family"], "hazardous": r["hazardous"],
               "outcome": r["outcome"], "turn_steps": int(s.shape[0] - 1)}  # fmt: skip
        models = {
            "belief": planning_model(DEFAULT, ctrl, res.belief),
            "truth": planning_model(DEFAULT, ctrl, res.truth),
        }
        for k in ks:
            row[f"k{k}"] = {name: rms(prediction_errors(m, s, belt, a, k)) for name, m in models.items()}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def summarise(rows: list[dict], ks) -> dict:
    out = {}
    for group, pick in (("hazardous_turned", True), ("safe_turned", False)):
        g = [r for r in rows if r["hazardous"] == pick]
        out[group] = {"episodes": len(g)}
        for k in ks:
            for q in ("x_mm", "y_mm", "yaw_deg"):
                b = np.array([r[f"k{k}"]["belief"][q] for r in g])
                t = np.array([r[f"k{k}"]["truth"][q] for r in g])
                if len(g):
                    out[group][f"k{k}_{q}"] = {
                        "belief_median": float(np.median(b)),
                        "truth_median": float(np.median(t)),
                        "ratio_median": float(np.median(b / t)),
                        "ratio_p90": float(np.percentile(b / t, 90)),
                        "ratio_max": float(np.max(b / t)),
                    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--evals", nargs="+", required=True, help="evaluation output directories (evaluate --out)"
    )
    ap.add_argument(
        "--k", nargs="+", type=int, default=[1, 5, 10], help="prediction horizons (control steps)"
    )
    ap.add_argument("--safe-every", type=int, default=4, help="every n-th safe box (by index)")
    ap.add_argument("--out", help="JSON file")
    args = ap.parse_args()
    if min(args.k) < 1 or args.safe_every < 1:
        ap.error("--k and --safe-every must be >= 1")
    for d in args.evals:
        if not os.path.exists(os.path.join(d, "evaluation.json")):
            ap.error(f"{d} is not an evaluation output (no evaluation.json)")
    t0 = time.time()
    rows = [r for d in args.evals for r in episodes(d, tuple(args.k), args.safe_every)]
    result = {"evals": args.evals, "k": args.k, "summary": summarise(rows, args.k), "episodes": rows,
              "wall_s": time.time() - t0}  # fmt: skip
    print(json.dumps(result["summary"], indent=1))
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
