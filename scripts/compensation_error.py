"""How far the latency compensation's present is from the truth, per pose axis, over d steps of delay.

Along the turns of a written evaluation (its recorded actions replayed on the TRUE boxes,
`batch.replay_episode`), at every step t of the turn with the belts moving: the window of true states d
steps old moved forward over the d actions sent since (`planning.compensate`, with the evaluation's
planning model) against the true state at t. What the monitor's `delay_std` (y) and
`MonitorConfig.tip_yaw_std` (yaw) stand for: the prediction's own error over the delay, without the
sensor's.

    python scripts/planner_study.py --boxes 100 --seed 0 --fault obs_latency=4 --out ev/
    python scripts/compensation_error.py ev/ [--boxes 40] [--delays 1 2 4] [--out F.json]

Prints one JSON object: per delay, the samples and each axis's std (x, y in mm, yaw in degrees), its 99th
percentile of |error|, and the std per square-root step.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, planning
from boxjax.config import DEFAULT
from boxjax.control import batch
from boxjax.control.models import planning_model
from boxjax.estimator import explore
from boxjax.experiments import evaluation as experiments
from boxjax.fileio import atomic_path, check_writable_dir

MOVING = 0.01  # m/s: a step counts when a belt runs faster than this
PAD = 256  # the turn's steps padded to a multiple of this: the jitted compensation compiles once or twice


def _present(model, windows, belts, actions):
    return planning.compensate(model, windows, belts, actions)[0][-1]


PRESENT = jax.jit(jax.vmap(_present, in_axes=(None, 0, 0, 0)))


def errors(out_dir: str, boxes: int, delays) -> dict:
    """{d: (n, 3) errors (x m, y m, yaw rad)} over the first `boxes` episodes of `out_dir` that turned."""
    cfg = DEFAULT
    ev_boxes, settings = experiments.load_boxes(out_dir)
    recorded = experiments.load_actions(out_dir)
    ctrl = experiments.controller_from_settings(settings)
    faults = experiments.faults_from_settings(settings)
    rows = json.load(open(f"{out_dir}/evaluation.json"))["rows"]
    out = {d: [] for d in delays}
    used = 0
    for r in rows:
        i = r["index"]
        actions = np.asarray(recorded[i], np.float64).reshape(-1, 4)
        if r["outcome"] == "aborted" or len(actions) <= explore.N_STEPS + max(delays) + 3:
            continue
        truth, key = ev_boxes.dist(i), jax.random.wrap_key_data(ev_boxes.keys[i])
        res = batch.replay_episode(cfg, truth, key, actions, ctrl=ctrl, faults=faults)
        s = np.asarray(res.trace.s, np.float32)
        belts = np.asarray(res.trace.belt_speed, np.float32)
        model = planning_model(cfg, ctrl, truth)
        for d in delays:
            ts = np.arange(explore.N_STEPS + d + 2, len(actions))  # the turn's steps
            padded = np.concatenate([ts, np.repeat(ts[-1:], -len(ts) % PAD)])  # one compile for most turns
            windows = np.stack([s[t - d - 2 : t - d + 1] for t in padded])
            sent = np.stack([actions[t - d : t] for t in padded]).astype(np.float32)
            present = PRESENT(model, jnp.asarray(windows), jnp.asarray(belts[padded - d]), jnp.asarray(sent))
            e = (np.asarray(present)[: len(ts)] - s[ts])[:, [geometry.X, geometry.Y, geometry.YAW]]
            out[d].append(e[np.abs(belts[ts]).max(axis=1) > MOVING])
        used += 1
        print(f"box {i}: {len(actions)} steps", file=sys.stderr)
        if used >= boxes:
            break
    return {d: np.concatenate(es) if es else np.zeros((0, 3)) for d, es in out.items()}


def summary(errs: dict) -> dict:
    out = {}
    for d, e in errs.items():
        std = e.std(axis=0)
        p99 = np.percentile(np.abs(e), 99, axis=0) if len(e) else np.zeros(3)
        scale = np.array([1e3, 1e3, math.degrees(1.0)])
        out[str(d)] = {
            "samples": len(e),
            "std": dict(zip(("x_mm", "y_mm", "yaw_deg"), (std * scale).round(3).tolist(), strict=True)),
            "p99_abs": dict(zip(("x_mm", "y_mm", "yaw_deg"), (p99 * scale).round(3).tolist(), strict=True)),
            "std_per_sqrt_step": dict(
                zip(("x_mm", "y_mm", "yaw_deg"), (std * scale / math.sqrt(d)).round(3).tolist(), strict=True)
            ),
        }
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="an evaluation written with --out (with recorded actions)")
    ap.add_argument("--boxes", type=int, default=40, help="episodes to replay (those refused are skipped)")
    ap.add_argument("--delays", type=int, nargs="+", default=[1, 2, 4], help="control steps of delay")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    if args.boxes < 1 or any(d < 1 for d in args.delays):
        ap.error("--boxes and --delays must be >= 1")
    try:
        recorded = experiments.load_actions(args.dir)
    except ValueError as e:  # no boxes.npz, or not an evaluation's
        ap.error(f"{args.dir}: {e}")
    if recorded is None:
        ap.error(f"{args.dir} has no recorded actions (write it with --out)")
    if args.out:
        try:
            check_writable_dir(os.path.dirname(os.path.abspath(args.out)), "--out's directory")
        except ValueError as e:
            ap.error(str(e))
    result = {
        "command": "python scripts/compensation_error.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "delays": summary(errors(args.dir, args.boxes, args.delays)),
    }
    text = json.dumps(result)
    if args.out:
        with atomic_path(args.out, suffix=".json") as tmp, open(tmp, "w") as f:
            f.write(text + "\n")
    print(text)
    return result


if __name__ == "__main__":
    main()
