"""Open-loop H-step prediction error of the physics prior against the simulator (what the planners use:
`PriorModel.rollout_sequence` over their horizon), for the prior with and without its two rollout
mechanisms, beside constant velocity.

Transitions are `benchmarks/prediction_error.py`'s (same boxes, policies and seed): native MuJoCo episodes
on uniform, A, B, C and random safe boxes under restricted actions. Every run of H consecutive transitions
of one episode is a test case: the prior sees the window and belt speeds at its start and the H actions
the simulator received, and predicts the state after the H-th. Variants (`prior.PriorParams`):
  * prior: the default (friction load transfer + the velocity carried between predicted steps);
  * no_load_transfer: loads from gravity alone (load_transfer=False);
  * no_carried_velocity: every step re-derives its velocity from the window (carry_velocity=False);
  * neither: both off (the prior before these two mechanisms);
  * constant_velocity: x, y, yaw extrapolated from s_t - s_{t-1} (belt positions from the actions).
Errors at step H: position |(x, y)_pred - (x, y)_sim| of the geometric centre (mm), yaw (degrees), and
the balance error's error |b_pred - b_sim| (mm, what the safety barrier sees); median / p90 / mean, over
all cases and over the cases whose H actions include a carriage (position) step.

    python benchmarks/rollout_error.py [--transitions 6000] [--horizon 10] [--seed 0] [--out FILE.json]

Prints one JSON object as its last stdout line (progress on stderr).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

import prediction_error as pe  # noqa: E402
from _util import emit_to  # noqa: E402

from boxjax import geometry, prior
from boxjax.config import DEFAULT  # noqa: E402

VARIANTS = {
    "prior": {},
    "no_load_transfer": {"load_transfer": False},
    "no_carried_velocity": {"carry_velocity": False},
    "neither": {"load_transfer": False, "carry_velocity": False},
}


def cases(data: dict, horizon: int) -> np.ndarray:
    """Start indices i whose transitions i .. i+H-1 follow each other within one episode."""
    n = len(data["row"])
    follows = np.zeros(n, bool)  # transition k continues transition k - 1
    follows[1:] = np.all(np.isclose(data["window"][1:, -1], data["s_next"][:-1], atol=1e-9), axis=1)
    starts = []
    for i in range(n - horizon + 1):
        if follows[i + 1 : i + horizon].all():
            starts.append(i)
    return np.asarray(starts, np.int64)


def predict(data: dict, starts: np.ndarray, horizon: int, params: dict, chunk: int = 1024) -> np.ndarray:
    """(C, 5) predicted state after H steps for each start, with the box's true voxel masses."""
    cfg = DEFAULT

    def one(masses, window, belt_speed, actions):
        model = prior.make_prior(masses, None, cfg.box, cfg.gripper, **params)
        return model.rollout_sequence(window, belt_speed, actions)[-1]

    fn = jax.jit(jax.vmap(one))
    idx = starts[:, None] + np.arange(horizon)[None]
    masses = data["masses"][data["box"][starts]]
    out = []
    for k in range(0, len(starts), chunk):
        sl = slice(k, k + chunk)
        out.append(
            np.asarray(
                fn(
                    jnp.asarray(masses[sl], jnp.float32),
                    jnp.asarray(data["window"][starts[sl]], jnp.float32),
                    jnp.asarray(data["belt_speed"][starts[sl]], jnp.float32),
                    jnp.asarray(data["action"][idx[sl]], jnp.float32),
                )
            )
        )
    return np.concatenate(out)


def constant_velocity(data: dict, starts: np.ndarray, horizon: int) -> np.ndarray:
    w = data["window"][starts]
    pred = w[:, -1].copy()
    pred[:, 2:] += horizon * (w[:, -1, 2:] - w[:, -2, 2:])
    last = data["s_next"][starts + horizon - 1]
    pred[:, :2] = last[:, :2]  # belt positions follow the actions exactly in both
    return pred


def _stats(x: np.ndarray) -> dict:
    return {"median": float(np.median(x)), "p90": float(np.percentile(x, 90)), "mean": float(np.mean(x))}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--transitions", type=int, default=6000)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="also write the JSON here (atomically)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data = pe.collect(args.transitions, args.seed, progress=True)
    t_sim = time.perf_counter() - t0
    starts = cases(data, args.horizon)
    truth = data["s_next"][starts + args.horizon - 1]
    idx = starts[:, None] + np.arange(args.horizon)[None]
    moved = np.any(np.abs(data["action"][idx][..., 2:]) > 0, axis=(1, 2))
    preds = {name: predict(data, starts, args.horizon, p) for name, p in VARIANTS.items()}
    preds["constant_velocity"] = constant_velocity(data, starts, args.horizon)
    bal_true = np.asarray(jax.vmap(geometry.balance_error)(jnp.asarray(truth)))
    out = {
        "benchmark": f"open-loop {args.horizon}-step prediction error vs native MuJoCo",
        "transitions": int(len(data["row"])),
        "cases": int(len(starts)),
        "cases_with_position_steps": int(moved.sum()),
        "horizon": args.horizon,
        "seed": args.seed,
        "simulate_s": t_sim,
    }
    for name, p in preds.items():
        pos = 1e3 * np.linalg.norm(p[:, 2:4] - truth[:, 2:4], axis=1)
        yaw = np.degrees(np.abs(p[:, 4] - truth[:, 4]))
        bal = 1e3 * np.abs(np.asarray(jax.vmap(geometry.balance_error)(jnp.asarray(p))) - bal_true)
        out[name] = {
            "all": {"position_mm": _stats(pos), "yaw_deg": _stats(yaw), "balance_mm": _stats(bal)},
            "with_position_steps": {
                "position_mm": _stats(pos[moved]),
                "yaw_deg": _stats(yaw[moved]),
                "balance_mm": _stats(bal[moved]),
            },
        }
    out["wall_s"] = time.perf_counter() - t0
    emit_to(out, args.out)
    return out


if __name__ == "__main__":
    main()
