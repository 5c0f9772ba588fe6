"""The paper's Table 3 for this implementation: each named box, several seeds, oracle and learned H.

    python scripts/rotation_table.py [--seeds 5] [--estimators oracle learned] [--planner sampling|paper]
        [--out table.json]

Prints one JSON object (last line): per estimator and box, success rate, aborts, steps, max balance
error, and the per-seed rows.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import jax
from tqdm import tqdm

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import run_episode
from boxjax.estimator.belief import learned_estimator
from boxjax.planners.registry import PLANNERS


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--boxes", nargs="+", default=["A", "B", "C", "D", "uniform"])
    ap.add_argument("--estimators", nargs="+", default=["oracle", "learned"])
    ap.add_argument("--planner", choices=PLANNERS, default=ControllerConfig().planner)
    ap.add_argument("--out")
    args = ap.parse_args()
    cfg = DEFAULT
    ctrl = ControllerConfig(planner=args.planner)
    table = {}
    jobs = [(e, b, s) for e in args.estimators for b in args.boxes for s in range(args.seeds)]
    est = {"oracle": "oracle"}
    for e, b, seed in tqdm(jobs, desc="episodes", file=sys.stderr):
        if e not in est:
            est[e] = learned_estimator(cfg)
        res = run_episode(
            cfg, massdist.named(b, cfg.box), jax.random.PRNGKey(seed), estimator=est[e], ctrl=ctrl
        )
        row = {
            k: res.summary.get(k)
            for k in (
                "success",
                "aborted",
                "failed_reason",
                "steps",
                "max_balance_error_m",
                "plan_ms_median",
                "iou",
            )
        }
        table.setdefault(e, {}).setdefault(b, {"rows": []})["rows"].append({"seed": seed, **row})
    for per_box in table.values():
        for cell in per_box.values():
            rows = cell["rows"]
            ok = [r for r in rows if r["success"]]
            cell["success_rate"] = len(ok) / len(rows)
            cell["aborted"] = sum(r["aborted"] for r in rows)
            cell["steps_mean_success"] = statistics.mean(r["steps"] for r in ok) if ok else None
            ran = [r["max_balance_error_m"] for r in rows if not r["aborted"]]
            cell["max_balance_error_m_max"] = max(ran) if ran else None
    out = {"seeds": args.seeds, "planner": args.planner, "table": table}
    if args.out:
        from boxjax.fileio import atomic_path

        with atomic_path(args.out, suffix=".json") as tmp, open(tmp, "w") as f:
            json.dump(out, f, indent=1)
    sys.stdout.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
