"""The black box W's Table-1 episodes (online adaptation every 20 steps, 1 epoch, as the paper): batched
(`comparison.blackbox_episodes`, each episode adapting its own copy of W) against one at a time
(`comparison.blackbox_episode`), on the same named boxes and seeds, measured in one run.

Both paths are compiled first on a short episode of another seed (the planner over W and W's adaptation
step), so the timed part is episodes only; the compile times are reported apart. Also reported: the
planner's median call time in each path, the adaptation time, and each path's outcomes (the paths agree
in distribution, not bit for bit: boxjax/batch.py).

Prints ONE JSON object (the last line).
Run: python benchmarks/blackbox_episodes.py [--boxes A B C D] [--seeds 2] [--max-steps 150]
                                            [--devices 2] [--method blackbox|pets] [--skip-single]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit, machine  # noqa: E402

from boxjax import blackbox
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.experiments import comparison


def _summary(rows, wall: float) -> dict:
    return {
        "wall_s": wall,
        "episodes_per_s": len(rows) / wall,
        "control_steps": sum(r["steps"] for r in rows),
        "outcomes": [r["outcome"] for r in rows],
        "steps": [r["steps"] for r in rows],
        "success": sum(r["success"] for r in rows),
        "adapt_s": sum(r["adapt_s"] for r in rows),
        "adaptations": sum(r["adaptations"] for r in rows),
        "plan_ms_median": float(np.median([r["plan_ms_median"] for r in rows if r["plan_ms_median"]])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", nargs="+", default=["A", "B", "C", "D"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--max-steps", type=int, default=150, help="control-step cap (the task's is 600)")
    ap.add_argument("--devices", type=int, default=os.cpu_count() or 1, help="host devices (default: cores)")
    ap.add_argument(
        "--slots", type=int, default=None, help="episodes per planner call (default 8 per device)"
    )
    ap.add_argument("--method", choices=comparison.BLACK_BOXES, default="blackbox")
    ap.add_argument("--skip-single", action="store_true", help="time the batched path only")
    args = ap.parse_args()
    if (
        args.seeds < 1
        or args.max_steps < 2
        or args.devices < 1
        or (args.slots is not None and args.slots < 1)
    ):
        ap.error("--seeds, --devices and --slots must be >= 1 and --max-steps >= 2")
    n_dev = batch.use_host_devices(args.devices)  # before any JAX computation
    cfg = DEFAULT
    model = blackbox.load_black_box(args.method, None, cfg.gripper)
    ctrl = ControllerConfig()
    jobs = [(b, s) for b in args.boxes for s in range(args.seeds)]
    warm = [("A", 100 + j) for j in range(min(len(jobs), args.slots or batch.SLOTS_PER_DEVICE * n_dev))]
    out = {
        "benchmark": f"{args.method} episodes with online adaptation, batched vs one at a time",
        "jobs": jobs,
        "max_steps": args.max_steps,
        "devices": n_dev,
        **machine(),
    }

    t0 = time.perf_counter()
    run_b = dict(adapt_every=20, ctrl=ctrl, method=args.method, slots=args.slots)
    comparison.blackbox_episodes(cfg, warm, model, **run_b, max_steps=25)  # past the first adaptation
    out["batched_warmup_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows_b = comparison.blackbox_episodes(cfg, jobs, model, **run_b, max_steps=args.max_steps)
    out["batched"] = _summary(rows_b, time.perf_counter() - t0)
    if not args.skip_single:
        t0 = time.perf_counter()
        comparison.blackbox_episode(cfg, "A", 100, model, 20, ctrl=ctrl, method=args.method, max_steps=25)
        out["single_warmup_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        rows_s = [
            comparison.blackbox_episode(
                cfg, b, s, model, 20, ctrl=ctrl, method=args.method, max_steps=args.max_steps
            )
            for b, s in jobs
        ]
        out["single"] = _summary(rows_s, time.perf_counter() - t0)
        out["speedup"] = out["single"]["wall_s"] / out["batched"]["wall_s"]
        out["same_outcome"] = sum(a["outcome"] == b["outcome"] for a, b in zip(rows_b, rows_s, strict=True))
    out["load_avg_1m"] = os.getloadavg()[0]
    emit(out)


if __name__ == "__main__":
    main()
