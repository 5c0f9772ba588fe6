"""Does training H on explorations seen through randomised sensors keep its hazard decision under sensor
faults? (issue: the real world, item 3: domain randomisation of H's training data.)

Two estimators are trained on the SAME simulated explorations with the same key and settings
(`training.estimator.DEFAULT_ESTIMATOR`): "clean" on the simulator's exact states, "randomised" on the
same explorations seen through a sensor drawn per box (`training.randomise.SensorRandomisation`: a quarter
perfect, the rest 0-5 mm / 0-2.5 degrees of pose noise and 0-20 % dropped frames, through the run-time
filter and `World.for_estimator`). Both, and the shipped H (trained on 288k clean explorations), then
decide on fresh boxes (safe and hazardous, seed 2000, never trained on) explored in several sensor rows:
hazardous boxes refused, safe boxes refused (false aborts), with 95 % intervals. The randomised H of
`--boxes 90000` is the one shipped for imperfect sensors (boxjax/data/estimator_sensor.npz).

    python scripts/estimator_randomisation.py --boxes 30000 --work /tmp/dr \
        --out benchmarks/results_estimator_randomisation.json

The explorations are simulated in parts of --part boxes, part i from seed + i (more boxes extend the same
data), and every stage is cached in --work (the parts, their randomised views, the checkpoints), so a
second run only evaluates. `--exploration gentle|designed` trains on that sequence instead (the same boxes
and sensor draws; the shipped H, trained on the fixed sequence, is then not evaluated).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

from boxjax import estimator as E
from boxjax.config import DEFAULT, EXPLORATIONS
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.estimator import explore
from boxjax.estimator.belief import learned_estimator
from boxjax.estimator.shipped import SHIPPED_WEIGHTS
from boxjax.experiments.evaluation import make_boxes, wilson_interval
from boxjax.fileio import atomic_path, check_writable_dir
from boxjax.sim.faults import Faults
from boxjax.training import dataset as ds
from boxjax.training.estimator import DEFAULT_ESTIMATOR, HAZARD_RECALL_TARGET
from boxjax.training.randomise import SensorRandomisation, sensor_view

CFG = DEFAULT  # with --exploration, the default config with that exploration (set in main)
ROWS = {
    "no fault": Faults(),
    "noise 1 mm / 0.5 deg": Faults(obs_noise_mm=1, obs_noise_deg=0.5),
    "noise 3 mm / 1.5 deg": Faults(obs_noise_mm=3, obs_noise_deg=1.5),
    "drops 5 %": Faults(drop_rate=0.05),
    "drops 20 %": Faults(drop_rate=0.2),
    "latency 2 steps": Faults(obs_latency=2),
    "friction 0.4": Faults(friction=0.4),
    "realistic": Faults(obs_noise_mm=3, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.05, friction=0.4),
}


def _train(data: dict, path: str, seed: int, provenance: dict) -> dict:
    t0 = time.perf_counter()
    model, history = E.train(
        jax.random.PRNGKey(seed), data, DEFAULT_ESTIMATOR, box=CFG.box, progress=False, provenance=provenance
    )
    val = {k: v[history["val_index"]] for k, v in data.items()}
    model, calibration = E.calibrate(model, val, HAZARD_RECALL_TARGET)
    E.save(path, model)
    metrics = E.evaluate(model, val)
    return {
        "train_s": time.perf_counter() - t0,
        "epochs_run": int(history["epochs_run"]),
        "hazard_threshold": float(calibration["hazard_threshold"]),
        "validation": {k: float(v) for k, v in metrics.items() if np.ndim(v) == 0},
    }


def _decisions(weights: str, boxes, faults: Faults) -> dict:
    """Explore every box through `faults` and decide (no turn: the step cap ends the episode there)."""
    est = learned_estimator(CFG, weights)
    keys = [jax.random.wrap_key_data(k) for k in boxes.keys]
    dists = [boxes.dist(j) for j in range(len(boxes))]
    res = batch.run_episodes(
        CFG, dists, keys, estimator=est, ctrl=ControllerConfig(), faults=faults, max_steps=55
    )
    refused = np.asarray([bool(r.summary["aborted"]) for r in res])
    haz = boxes.hazardous
    n_h, n_s = int(haz.sum()), int((~haz).sum())
    r_h, r_s = int(refused[haz].sum()), int(refused[~haz].sum())
    return {
        "hazardous_refused": r_h,
        "hazardous": n_h,
        "hazardous_refused_ci95": wilson_interval(r_h, n_h),
        "false_aborts": r_s,
        "safe": n_s,
        "false_aborts_ci95": wilson_interval(r_s, n_s),
    }


def _parts(args) -> tuple[dict, dict, dict]:
    """(exact explorations, their randomised view, timings) of args.boxes boxes, in cached parts."""
    if args.boxes % args.part:
        raise SystemExit(f"--boxes ({args.boxes}) must be a multiple of --part ({args.part})")
    datas, views, times = [], [], {"data_s": 0.0, "view_s": 0.0}
    for i in range(args.boxes // args.part):
        seed = args.seed + i
        tag = "" if args.exploration == "fixed" else f"{args.exploration}_"
        clean_path = os.path.join(args.work, f"part_{tag}s{seed}_{args.part}.npz")
        view_path = os.path.join(args.work, f"view_{tag}s{seed}_{args.part}.npz")
        if os.path.exists(clean_path):
            data, _ = ds.load(clean_path)
        else:
            t0 = time.perf_counter()
            data = ds.generate(jax.random.PRNGKey(seed), args.part, CFG, progress=True)
            ds.save(clean_path, data, ds.make_meta(CFG, seed, ds.P_HAZARDOUS, "native"))
            times["data_s"] += time.perf_counter() - t0
        if os.path.exists(view_path):
            view = dict(np.load(view_path))
        else:
            t0 = time.perf_counter()
            view = sensor_view(data, CFG, SensorRandomisation(), seed)
            np.savez(view_path, **view)
            times["view_s"] += time.perf_counter() - t0
            print(f"randomised view of part {i}: {time.perf_counter() - t0:.0f} s", flush=True)
        datas.append(data)
        views.append(view)

    def cat(parts):
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    return cat(datas), cat(views), times


ESTIMATORS = ("clean", "randomised")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=30000, help="simulated explorations to train on")
    ap.add_argument("--part", type=int, default=30000, help="boxes per simulated (and cached) part")
    ap.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    ap.add_argument("--work", default="/tmp/estimator_randomisation", help="cache of data and checkpoints")
    ap.add_argument("--eval-safe", type=int, default=100)
    ap.add_argument("--eval-hazardous", type=int, default=100)
    ap.add_argument("--seed", type=int, default=7, help="seed of the training data, its view and training")
    ap.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(ROWS))
    ap.add_argument("--exploration", choices=EXPLORATIONS, default="fixed", help="the sequence to train on")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    global CFG
    CFG = DEFAULT.replace(task=dataclasses.replace(DEFAULT.task, exploration=args.exploration))
    os.makedirs(args.work, exist_ok=True)
    if args.out:  # writable before the work starts
        check_writable_dir(os.path.dirname(os.path.abspath(args.out)), "--out's directory")
    report: dict = {"boxes": args.boxes, "seed": args.seed, "randomisation": vars(SensorRandomisation())}
    data, view, times = _parts(args)
    report.update(times)

    weights = {"shipped (288k clean)": str(SHIPPED_WEIGHTS)} if args.exploration == "fixed" else {}
    report["exploration"] = args.exploration
    report["training"] = {}
    for name in args.estimators:
        tag = "" if args.exploration == "fixed" else f"{args.exploration}_"
        path = os.path.join(args.work, f"H_{tag}{name}_{args.boxes}.npz")
        if not os.path.exists(path):
            provenance = {
                "trained_by": "scripts/estimator_randomisation.py",
                "command": f"python scripts/estimator_randomisation.py --boxes {args.boxes} "
                f"--part {args.part} --seed {args.seed} --estimators {name} --exploration {args.exploration}",
                "part_seeds": [args.seed + i for i in range(args.boxes // args.part)],
                "n_boxes": args.boxes,
                "config": CFG.to_dict(),
                "exploration_actions": np.asarray(explore.exploration_actions(CFG)).tolist(),
                "sensor_randomisation": None if name == "clean" else vars(SensorRandomisation()),
            }
            data_used = data if name == "clean" else view
            report["training"][name] = _train(data_used, path, args.seed, provenance)
            print(name, json.dumps(report["training"][name]), flush=True)
        weights[f"{name} ({args.boxes // 1000}k)"] = path

    boxes = make_boxes(CFG, args.eval_safe, args.eval_hazardous, seed=2000)
    report["rows"] = {}
    for row in args.rows:
        report["rows"][row] = {}
        for name, w in weights.items():
            r = _decisions(w, boxes, ROWS[row])
            report["rows"][row][name] = r
            print(f"{row:22s} {name:22s} refused {r['hazardous_refused']}/{r['hazardous']}, "
                  f"false aborts {r['false_aborts']}/{r['safe']}", flush=True)  # fmt: skip
    if args.out:
        with atomic_path(args.out, suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
