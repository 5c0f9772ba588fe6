"""The planner's action limits under a late sensor: development boxes, one fault row, several settings.

How docs/results/faults.md ("Latency: a late loop slows the planner") chose the slow-down rule: each
setting runs the same 100 development boxes (`sample_safe(PRNGKey(1000), n)`, keys
`fold_in(PRNGKey(1001), j)`; never the fault table's) with `--latency` steps of sensor latency and the
runtime safety monitor on, `batch.run_episodes` on the host's cores. The rule itself is off in every run
(`delay_reference=None`) so that each setting is exactly the planner named.

    python scripts/latency_levers.py --latency 4 --settings base cap60 pos50 rate1 \\
        --out benchmarks/results_latency_levers.json     # ~5 min per setting on the 2-core CPU
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter

import jax
import numpy as np

from boxjax.config import DEFAULT
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.experiments.evaluation import outcome, sample_safe
from boxjax.fileio import atomic_path
from boxjax.planners.sampling import SamplingOptions
from boxjax.sim.faults import Faults

SETTINGS = {  # SamplingOptions overrides
    "base": {},  # as at 2 steps: speed cap 0.12 m/s, carriage steps up to the hardware's 10 mm
    "cap60": {"speed_cap": 0.072, "position_cap": 0.006},  # 0.6 x both: the rule at 4 steps
    "pos50": {"position_cap": 0.005},
    "speed60": {"speed_cap": 0.072},
    "rate1": {"w_position_rate": 1.0},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latency", type=int, default=4, help="sensor latency, control steps")
    ap.add_argument("--boxes", type=int, default=100)
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--out", help="JSON file")
    args = ap.parse_args()
    if args.latency < 0 or args.boxes < 1:
        ap.error("--latency must be >= 0 and --boxes >= 1")
    batch.use_host_devices()  # before JAX starts its backend: the boxes are sharded over the cores
    truths = sample_safe(jax.random.PRNGKey(1000), args.boxes, DEFAULT)
    keys = [jax.random.fold_in(jax.random.PRNGKey(1001), j) for j in range(args.boxes)]
    results = {}
    for name in args.settings:
        ctrl = ControllerConfig(sampling=SamplingOptions(**SETTINGS[name]), delay_reference=None)
        t0 = time.time()
        runs = batch.run_episodes(DEFAULT, truths, keys, ctrl=ctrl, faults=Faults(obs_latency=args.latency))
        summaries = [r.summary for r in runs]
        turned = [s["steps"] for s in summaries if s["success"]]
        results[name] = {
            "sampling": SETTINGS[name],
            "outcomes": dict(Counter(outcome(s) for s in summaries)),
            "crossings": sum(bool(s["crossing"]) for s in summaries),
            "unnoticed": [j for j, s in enumerate(summaries) if s["unnoticed_crossing"]],
            "monitor_stops": sum(s.get("monitor_stops", 0) for s in summaries),
            "steps_success_median": float(np.median(turned)) if turned else None,
            "wall_s": time.time() - t0,
        }
        print(json.dumps({name: results[name]}), flush=True)
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as f:
            json.dump({"latency": args.latency, "boxes": args.boxes, "settings": results}, f, indent=1)


if __name__ == "__main__":
    main()
