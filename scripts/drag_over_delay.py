"""How much of the drag the model predicts over the loop's delay the world gives: the monitor's two
predictions of the present (`planning.compensate`: the carriage moves in flight drag the box as the model
says; `planning.compensate_held`: they do not drag it) against the box's true present, every control
step of closed-loop episodes (docs/results/faults.md, "The carriages' drag over the delay, bounded").

    python scripts/drag_over_delay.py --boxes 30 --seed 1000 --fault obs_latency=2 [--fault friction=0.4]
        [--prior carriage_omega=30] [--out FILE.json]

The monitor runs in shadow mode (it checks every action with `drag_bound` 1 and records both predictions;
the planner's actions are sent unchanged), the episodes one at a time (`run_episode`, as `boxjax evaluate`
without batching). Per step, with m the model's balance offset, h the held one and t the true one:
lambda = (t - h) / (m - h) where |m - h| > 3 mm (1: the model's drag came, 0: none did); the rms miss of
m + a (h - m) for a in 0 .. 1 (the present with the fraction a of the drag withheld); and, with the
monitor's margin (`--margin-mm`), how often max(|m|, |m + a (h - m)|) + margin stays under the stop
threshold while the box is truly past 3 cm (an alarm missed) or reaches it while the box is truly within
2 cm (a needless one). The true present is the simulator's state when the checked action applies.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from boxjax import fileio, geometry
from boxjax.config import DEFAULT as CFG
from boxjax.control import episode, monitor
from boxjax.control.config import ControllerConfig
from boxjax.control.monitor import MonitorConfig
from boxjax.experiments import evaluation
from boxjax.prior.predictor import PriorParams
from boxjax.sim.faults import Faults

FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)


def _pairs(items: list[str]) -> dict:
    out = {}
    for item in items:
        k, _, v = item.partition("=")
        if not v:
            raise SystemExit(f"{item!r}: expected KEY=VALUE")
        out[k] = json.loads(v)
    return out


def collect(n: int, seed: int, faults: Faults, prior: PriorParams | None = None) -> dict:
    """(model, held, true) balance offsets (m) of every checked step of n safe boxes' episodes."""
    rows: list[tuple[float, float, float]] = []
    current: list[tuple[float, float]] = []
    check, run = monitor.check, episode.run_episode

    def recording_check(cfg, model, window, belt, action, horizon, backup="best", held=None, tip=False):
        current.append(
            (
                float(geometry.balance_offset(np.asarray(window[-1], np.float64))),
                float(geometry.balance_offset(np.asarray(held[-1], np.float64)))
                if held is not None
                else np.nan,
            )
        )
        return check(cfg, model, window, belt, action, horizon, backup, held, tip)

    def recording_run(*args, **kwargs):
        current.clear()
        res = run(*args, **kwargs)
        first = len(res.trace.actions) - len(current)  # the exploration's actions come first
        for i, (m, h) in enumerate(current):  # the true present: the state the checked action met
            rows.append((m, h, float(geometry.balance_offset(res.trace.s[first + i]))))
        return res

    monitor.check, evaluation.run_episode = recording_check, recording_run
    try:
        ctrl = ControllerConfig(monitor=MonitorConfig(shadow=True, drag_bound=1.0), prior_params=prior)
        ev = evaluation.evaluate(CFG, n, 0, seed, ctrl=ctrl, faults=faults, progress=True, batched=False)
    finally:
        monitor.check, evaluation.run_episode = check, run
    a = np.asarray(rows, np.float64).reshape(-1, 3)
    return {"offsets": a[np.isfinite(a[:, 1])], "summary": ev.summary}


def analyse(offsets: np.ndarray, margin: float, stop_at: float) -> dict:
    m, h, t = offsets.T
    gap = np.abs(h - m) > 0.003
    lam = (t[gap] - h[gap]) / (m[gap] - h[gap])
    far, near = np.abs(t) > 0.03, np.abs(t) < 0.02
    per = {}
    for a in FRACTIONS:
        present = m + a * (h - m)
        alarm = np.maximum(np.abs(m), np.abs(present)) + margin >= stop_at
        per[str(a)] = {
            "rms_miss_mm": 1e3 * float(np.sqrt(np.mean((t - present) ** 2))),
            "no_alarm_past_3cm": int(np.sum(~alarm & far)),
            "alarm_within_2cm": int(np.sum(alarm & near)),
        }
    return {
        "steps": len(t),
        "steps_past_3cm": int(far.sum()),
        "steps_within_2cm": int(near.sum()),
        "steps_drag_gap_over_3mm": int(gap.sum()),
        "lambda_quantiles_5_25_50_75_95": np.round(
            np.quantile(lam, [0.05, 0.25, 0.5, 0.75, 0.95]), 3
        ).tolist()
        if len(lam)
        else None,
        "by_fraction_withheld": per,
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--boxes", type=int, default=30)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--fault", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument(
        "--prior", action="append", default=[], metavar="KEY=VALUE", help="a prior.PriorParams field"
    )
    p.add_argument(
        "--margin-mm", type=float, default=None, help="the monitor's margin (default: the delay's)"
    )
    p.add_argument("--out", default=None, metavar="FILE.json")
    args = p.parse_args(argv)
    faults = Faults(**_pairs(args.fault))
    if not faults.obs_latency and not faults.action_latency:
        raise SystemExit("no delay to predict over: give --fault obs_latency=N (or action_latency)")
    if args.out:
        fileio.check_writable_dir(os.path.dirname(os.path.abspath(args.out)))
    m = MonitorConfig()
    delay = faults.obs_latency + faults.action_latency
    margin = 1e-3 * args.margin_mm if args.margin_mm is not None else m.k_delay * m.delay_std * delay**0.5
    t0 = time.perf_counter()
    got = collect(args.boxes, args.seed, faults, PriorParams(**_pairs(args.prior)) if args.prior else None)
    out = {
        "command": "python " + " ".join(sys.argv),
        "boxes": args.boxes,
        "seed": args.seed,
        "faults": _pairs(args.fault),
        "prior": _pairs(args.prior),
        "margin_mm": 1e3 * margin,
        "stop_at_mm": 1e3 * m.stop_at * CFG.task.balance_limit,
        **analyse(got["offsets"], margin, m.stop_at * CFG.task.balance_limit),
        "wall_s": time.perf_counter() - t0,
    }
    print(json.dumps(out))
    if args.out:
        with fileio.atomic_path(args.out) as tmp, open(tmp, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
