"""The on-device loop's check on the same physics: the host loop (`batch.run_episodes`) stepping MJX worlds
(`backend="mjx"`, `MjxBatch`) on the boxes `boxjax evaluate --backend mjx` runs, so that the two loops'
statistics can be compared with no difference of simulator between them (the native backend's differ by
the simulator as well: docs/results/batched-episodes.md, "The whole loop on the device").

Writes one JSON summary (as `boxjax evaluate --json`'s) to --out, atomically, and prints it.
Run: python scripts/mjx_loop_check.py --boxes 100 [--hazardous 30] [--seed 0] [--estimator learned]
                                      [--slots 100] --out FILE.json
"""

from __future__ import annotations

import argparse
import json
import time

import jax

from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig, batch
from boxjax.experiments import evaluation as ev
from boxjax.fileio import atomic_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", type=int, default=100)
    ap.add_argument("--hazardous", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--estimator", choices=("oracle", "learned"), default="oracle")
    ap.add_argument("--slots", type=int, default=None, help="planner width (default: every box at once)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    if args.boxes < 1 or args.hazardous < 0:
        ap.error("--boxes must be >= 1 and --hazardous >= 0")
    with atomic_path(args.out, suffix=".json") as tmp, open(tmp, "w") as f:  # writable: found before the work
        f.write("{}\n")
    batch.use_host_devices()
    boxes = ev.make_boxes(cfg, args.boxes, args.hazardous, args.seed, "gaussian")
    n = len(boxes)
    est = "oracle" if args.estimator == "oracle" else ev.learned_estimator(cfg)
    t0 = time.perf_counter()
    res = batch.run_episodes(
        cfg, [boxes.dist(j) for j in range(n)], [jax.random.wrap_key_data(boxes.keys[j]) for j in range(n)],
        estimator=est, ctrl=ControllerConfig(), slots=args.slots or n, backend="mjx",
    )  # fmt: skip
    rows = [ev._row(j, boxes, res[j], cfg) for j in range(n)]
    out = {
        "loop": "host (batch.run_episodes), MJX worlds",
        **ev.summarize(rows),
        **ev.settings(args.estimator, ControllerConfig(), args.seed, "gaussian"),
        "wall_s": time.perf_counter() - t0,
    }
    with atomic_path(args.out, suffix=".json") as tmp, open(tmp, "w") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
