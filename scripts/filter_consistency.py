"""Whether the pose filter's stated uncertainty is honest: its balance-offset error against the std it
states (`PoseFilter.y_std`, what the safety monitor's margin counts), along the recorded episodes of an
evaluation, for several settings of the filter (docs/results/faults.md, "The estimate after a carriage
move").

    python scripts/planner_study.py --boxes 100 --seed 2 \
        --fault obs_noise_mm=10 --fault obs_noise_deg=5 --out ev/
    python scripts/filter_consistency.py ev/ --drag-std 0 0.3 0.6 [--boxes 30] [--out FILE.json]

Each episode is replayed from its recorded actions (`batch.replay_episode`: the same physics and sensor
draws, bit for bit); the frames and rest flags its filter was given are then fed to a fresh filter per
setting (the actions stay the recorded ones, so only the estimate differs), and its estimate is compared
with the true state at the newest frame's measurement time (what it estimates; the monitor adds the
prediction over the delay's own std). Per setting, over the steps
after the exploration: the rms error of the balance offset, the rms of the normalised error z = error /
stated std (1 for an honest filter), and the share of steps with |z| > 2 and > 3 (4.6 % and 0.27 % for an
honest Gaussian one), all steps, the steps within `--after` control steps of a carriage move made from
rest (a stop's re-centring, a recovery, a resume: where the filter has averaged its estimate at rest), and
those of them at which the box had truly moved over `--moved-mm` since (it was dragged).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np

from boxjax import fileio, geometry
from boxjax.config import DEFAULT as CFG
from boxjax.control import batch
from boxjax.control import state_estimate as se
from boxjax.experiments import evaluation as experiments


def _frames(boxes, summary, recorded, i: int, ctrl, faults):
    """One episode replayed: the (frame, fresh, still) its filter was given per step, the true states."""
    calls, step = [], se.PoseFilter.step

    def recording(self, s_obs, fresh=True, still=False, predicted=None):
        calls.append((np.array(s_obs, np.float64), bool(fresh), bool(still), predicted))
        return step(self, s_obs, fresh, still, predicted)

    se.PoseFilter.step = recording
    try:
        actions = np.asarray(recorded[i], np.float64).reshape(-1, 4)
        key = jax.random.wrap_key_data(boxes.keys[i])
        res = batch.replay_episode(CFG, boxes.dist(i), key, actions, ctrl=ctrl, faults=faults)
    finally:
        se.PoseFilter.step = step
    return calls, np.asarray(res.trace.s, np.float64), actions, int(res.summary["exploration_steps"])


def _moves_from_rest(actions: np.ndarray) -> np.ndarray:
    """Control steps at which a carriage move was sent after a step of rest (all zeros)."""
    a = np.asarray(actions)
    return np.array(
        [t for t in range(1, len(a)) if np.any(a[t, 2:] != 0) and not np.any(a[t - 1])], dtype=int
    )


def _stats(err: np.ndarray, z: np.ndarray) -> dict:
    if len(err) == 0:
        return {"steps": 0}
    return {
        "steps": len(err),
        "rms_error_mm": round(1e3 * float(np.sqrt(np.mean(err**2))), 3),
        "rms_z": round(float(np.sqrt(np.mean(z**2))), 3),
        "share_z_over_2": round(float(np.mean(np.abs(z) > 2)), 4),
        "share_z_over_3": round(float(np.mean(np.abs(z) > 3)), 4),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("eval", help="an evaluation written with --out (recorded actions, a sensor with faults)")
    ap.add_argument("--drag-std", type=float, nargs="+", default=[0.0, 0.3, 0.6])
    ap.add_argument("--boxes", type=int, default=None, help="the first N safe boxes (default all)")
    ap.add_argument("--after", type=int, default=5, help="steps after a carriage move from rest")
    ap.add_argument(
        "--moved-mm", type=float, default=3.0, help="'dragged': the box moved this far since the move"
    )
    ap.add_argument("--out", help="write the JSON here too")
    args = ap.parse_args(argv)
    if args.out:
        fileio.check_writable_dir(os.path.dirname(os.path.abspath(args.out)), "--out's directory")
    boxes, summary = experiments.load_boxes(args.eval)
    recorded = experiments.load_actions(args.eval)
    if recorded is None:
        ap.error(f"{args.eval} has no recorded actions")
    if any(d < 0 or not np.isfinite(d) for d in args.drag_std):
        ap.error("--drag-std: each must be a number >= 0")
    ctrl = experiments.controller_from_settings(summary)
    faults = experiments.faults_from_settings(summary)
    if se.make_filter(ctrl.pose_filter, faults, CFG.gripper.control_dt) is None:
        ap.error(f"{args.eval}: its sensor is perfect, so no filter ran (nothing to measure)")
    safe = [i for i in range(len(boxes)) if not boxes.hazardous[i]][: args.boxes]
    model_comp = ctrl.pose_filter.compensation == "model"
    lag = se.sensor_latency(ctrl.pose_filter, faults) if model_comp else 0
    parts = ("all", "after_move", "dragged")
    per = {d: {part: ([], []) for part in parts} for d in args.drag_std}
    t0 = time.perf_counter()
    for n, i in enumerate(safe):
        calls, s_true, actions, n_explore = _frames(boxes, summary, recorded, i, ctrl, faults)
        near, dragged = np.zeros(len(s_true), bool), np.zeros(len(s_true), bool)
        for t in _moves_from_rest(actions):
            near[t + 1 : t + 1 + args.after] = True
            moved = np.abs(s_true[t + 1 : t + 1 + args.after, geometry.Y] - s_true[t, geometry.Y])
            dragged[t + 1 : t + 1 + args.after] |= moved > 1e-3 * args.moved_mm
        # the filter's estimate is of the newest frame's measurement time (model compensation then predicts
        # it over the delay), `lag` steps before the present; the constant-velocity one extrapolates
        true_off = np.array([geometry.balance_offset(s) for s in s_true])
        true_off = np.concatenate([np.full(lag, true_off[0]), true_off[: len(true_off) - lag]])
        for d in args.drag_std:
            settings = dataclasses.replace(ctrl.pose_filter, carriage_drag_std=d)
            flt = se.make_filter(settings, faults, CFG.gripper.control_dt)
            est, std = [], []
            for c in calls:
                est.append(geometry.balance_offset(flt.step(*c)))
                std.append(flt.y_std())
            est, std = np.array(est), np.maximum(np.array(std), 1e-9)
            k = min(len(est), len(true_off))
            err, z = est[:k] - true_off[:k], (est[:k] - true_off[:k]) / std[:k]
            after = np.arange(k) > n_explore
            masks = (after, after & near[:k], after & dragged[:k])
            for part, mask in zip(parts, masks, strict=True):
                per[d][part][0].append(err[mask])
                per[d][part][1].append(z[mask])
        sys.stderr.write(f"\r{n + 1}/{len(safe)} boxes, {time.perf_counter() - t0:.0f} s")
    sys.stderr.write("\n")
    out = {
        "command": " ".join(["python", *sys.argv]),
        "eval": args.eval,
        "faults": faults.to_dict(),
        "boxes": len(safe),
        "after_steps": args.after,
        "moved_mm": args.moved_mm,
        "settings": {
            str(d): {part: _stats(np.concatenate(e), np.concatenate(z)) for part, (e, z) in parts.items()}
            for d, parts in per.items()
        },
    }
    text = json.dumps(out, indent=1)
    print(text)
    if args.out:
        with fileio.atomic_path(args.out) as tmp, open(tmp, "w") as f:
            f.write(text + "\n")
    return out


if __name__ == "__main__":
    main()
