"""What the exploration guard does after it trips, in the realistic world: re-centre the carriages under
the box (the default) or hold them (belts stopped, carriages still). Hazardous boxes only (the guard trips
on few safe ones: 0 of 300 in the realistic world at ccd45e9), the oracle refusing every box it sees
through the exploration, so what is counted is the boxes lost WHILE exploring (docs/results/faults.md,
"The exploration guard in a late, noisy world").

    python scripts/guard_stop_study.py --families gaussian items --seeds 5 6 --boxes 300 --out FILE

(benchmarks/results_guard_stop.json: (gaussian, 5), (items, 6), (gaussian, 7), (items, 8), (slabs, 9),
(scatter, 10), one family per process, merged.)

The hold variant is this study's (`HoldGuard`, injected where every path builds its guard,
`episode.guarded_exploration`); the controller has no such option today. Native batched episodes.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig
from boxjax.control import episode as episode_mod
from boxjax.estimator import explore
from boxjax.experiments import evaluation as experiments
from boxjax.fileio import check_writable_dir
from boxjax.sim.faults import Faults
from boxjax.training.estimator import write_json

WORLDS = {
    "none": Faults(),
    "realistic": Faults(obs_noise_mm=3, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.05, friction=0.4),
}


class HoldGuard(explore.Guarded):
    """The guard with its re-centring replaced by a hold: once tripped, belts stopped, carriages still."""

    def next(self, s, balance_error):
        a = super().next(s, balance_error)
        return a if a is None or not self.tripped else np.zeros(4)


ORIGINAL = episode_mod.guarded_exploration


def _hold_guard(cfg, ctrl, world, fraction):
    g = ORIGINAL(cfg, ctrl, world, fraction)
    return None if g is None else HoldGuard(cfg, fraction, settle=g.settle, lead=g.lead, noise=g.noise)


def run(family: str, seed: int, boxes: int, world: str, stop: str) -> dict:
    episode_mod.guarded_exploration = _hold_guard if stop == "hold" else ORIGINAL
    try:
        ev = experiments.evaluate(
            cfg, 1, boxes, seed, family=family, ctrl=ControllerConfig(), faults=WORLDS[world], progress=False
        )
    finally:
        episode_mod.guarded_exploration = ORIGINAL
    rows = [r for r in ev.rows if r["hazardous"]]
    lost = [r for r in rows if r.get("lost_exploring")]
    return {
        "hazardous_boxes": len(rows),
        "lost_exploring": len(lost),
        "lost_unnoticed": sum(bool(r["unnoticed_crossing"]) for r in lost),
        "lost_indices": [r["index"] for r in lost],
        "refused": sum(r["outcome"] == "aborted" for r in rows),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--families", nargs="+", default=["gaussian", "items"], choices=experiments.HAZARD_FAMILIES
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[5, 6], help="one box draw per family, in order")
    ap.add_argument("--boxes", type=int, default=300, help="hazardous boxes per family")
    ap.add_argument("--worlds", nargs="+", default=["realistic", "none"], choices=tuple(WORLDS))
    ap.add_argument("--out", help="write the JSON here")
    args = ap.parse_args(argv)
    if len(args.seeds) != len(args.families) or args.boxes < 1:
        ap.error("give one --seeds value per family and --boxes >= 1")
    if args.out:
        try:
            check_writable_dir(os.path.dirname(os.path.abspath(args.out)), "--out's folder")
        except ValueError as e:
            ap.error(str(e))
    res = {"boxes": args.boxes, "runs": []}
    t0 = time.time()
    for family, seed in zip(args.families, args.seeds, strict=True):
        for world in args.worlds:
            for stop in ("recentre", "hold"):
                row = {"family": family, "seed": seed, "world": world, "stop": stop}
                row.update(run(family, seed, args.boxes, world, stop))
                res["runs"].append(row)
                print(f"{time.time() - t0:6.0f} s  {json.dumps(row)}", flush=True)
    if args.out:
        write_json(args.out, res)
    return res


if __name__ == "__main__":
    main()
