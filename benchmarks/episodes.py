"""Closed-loop episodes per second: batched (`boxjax.batch.run_episodes`) against one at a time
(`controller.run_episode`), on the same random safe boxes and keys, measured in one run.

Both paths are compiled first on other boxes (a short warm-up episode each), so the timed part is
episodes only; the compile times are reported apart. Also reported: each path's success count (the
paths agree in distribution, not bit for bit: see boxjax/batch.py), the batched planner's cost per box
and control step, and what a batched control step is made of (planner call, physics, bookkeeping).

Prints ONE JSON object (the last line).
Run: python benchmarks/episodes.py [--boxes 32] [--slots 16] [--seed 0] [--max-steps 600] [--skip-single]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit, machine  # noqa: E402

from boxjax import batch, controller, experiments  # noqa: E402
from boxjax.config import DEFAULT  # noqa: E402


def _episodes(cfg, boxes, idx):
    return [boxes.dist(j) for j in idx], [jax.random.wrap_key_data(boxes.keys[j]) for j in idx]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", type=int, default=32)
    ap.add_argument("--slots", type=int, default=batch.DEFAULT_SLOTS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-steps", type=int, default=None, help="control-step cap (default: the task's)")
    ap.add_argument("--skip-single", action="store_true", help="time the batched path only")
    args = ap.parse_args()
    if args.boxes < 1 or args.slots < 1:
        ap.error("--boxes and --slots must be >= 1")
    cfg = DEFAULT
    ctrl = controller.ControllerConfig()
    n_warm = min(args.slots, 4)
    boxes = experiments.make_boxes(cfg, args.boxes + n_warm, 0, args.seed)
    warm_idx = range(args.boxes, args.boxes + n_warm)
    idx = range(args.boxes)
    out = {
        "benchmark": "closed-loop episodes, batched vs one at a time",
        "boxes": args.boxes,
        "slots": args.slots,
        "seed": args.seed,
        "planner": ctrl.planner,
        **machine(),
    }

    # compile: one short episode per path on boxes outside the timed set
    wt, wk = _episodes(cfg, boxes, warm_idx)
    t0 = time.perf_counter()
    batch.run_episodes(
        cfg,
        wt * (args.slots // n_warm + 1),
        wk * (args.slots // n_warm + 1),
        ctrl=ctrl,
        slots=args.slots,
        max_steps=48,
    )
    out["batched_warmup_s"] = time.perf_counter() - t0
    if not args.skip_single:
        t0 = time.perf_counter()
        controller.run_episode(cfg, wt[0], wk[0], ctrl=ctrl, max_steps=48)
        out["single_warmup_s"] = time.perf_counter() - t0

    dists, keys = _episodes(cfg, boxes, idx)
    t0 = time.perf_counter()
    res = batch.run_episodes(cfg, dists, keys, ctrl=ctrl, slots=args.slots, max_steps=args.max_steps)
    wall_b = time.perf_counter() - t0
    steps_b = sum(r.summary["steps"] for r in res)
    mpc_steps_b = sum(len(r.plan_ms) + (1 if len(r.plan_ms) else 0) for r in res)
    calls = [ms for r in res for ms in r.plan_ms]
    out["batched"] = {
        "wall_s": wall_b,
        "episodes_per_s": args.boxes / wall_b,
        "success": sum(r.summary["success"] for r in res),
        "control_steps": steps_b,
        "plan_call_ms_median": float(np.median(calls)) if calls else None,
        "plan_ms_per_box_step": float(np.median(calls)) / min(args.slots, args.boxes) if calls else None,
        "mpc_box_steps": mpc_steps_b,
    }
    if not args.skip_single:
        t0 = time.perf_counter()
        single = [
            controller.run_episode(cfg, d, k, ctrl=ctrl, max_steps=args.max_steps)
            for d, k in zip(dists, keys, strict=True)
        ]
        wall_s = time.perf_counter() - t0
        plan = [ms for r in single for ms in r.plan_ms]
        out["single"] = {
            "wall_s": wall_s,
            "episodes_per_s": args.boxes / wall_s,
            "success": sum(r.summary["success"] for r in single),
            "control_steps": sum(r.summary["steps"] for r in single),
            "plan_ms_median": float(np.median(plan)) if plan else None,
        }
        out["speedup"] = wall_s / wall_b
        out["same_outcome"] = sum(
            experiments.outcome(a.summary) == experiments.outcome(b.summary)
            for a, b in zip(res, single, strict=True)
        )
    out["load_avg_1m"] = os.getloadavg()[0]
    emit(out)


if __name__ == "__main__":
    main()
