"""What the exploration guard does after it trips, in the realistic world: re-centre the carriages under
the box (the default) or hold them (belts stopped, carriages still). Hazardous boxes only (the guard trips
on few safe ones: 0 of 300 in the realistic world at ccd45e9), the oracle refusing every box it sees
through the exploration, so what is counted is the boxes lost WHILE exploring (docs/results/faults.md,
"The exploration guard in a late, noisy world").

    python scripts/guard_stop_study.py --families gaussian items --seeds 5 6 --boxes 300 --out FILE

(benchmarks/results_guard_stop.json: (gaussian, 5), (items, 6), (gaussian, 7), (items, 8), (slabs, 9),
(scatter, 10), one family per process, merged.)

Both stops are the controller's (`ControllerConfig.explore_guard_stop`, `--guard-stop`), whose default
("auto") holds when the pose is an estimate (noise, latency or drops) and re-centres when it is exact. The
worlds with one fault each (noise, late, drops, friction) are what set that rule. Native batched episodes.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig
from boxjax.estimator import explore
from boxjax.experiments import evaluation as experiments
from boxjax.experiments import fault_table
from boxjax.fileio import check_writable_dir
from boxjax.sim.faults import Faults
from boxjax.training.estimator import write_json

REALISTIC = fault_table.row("realistic").faults
WORLDS = {  # the fault table's realistic row and each of its faults alone
    "none": Faults(),
    "realistic": REALISTIC,
    "noise": fault_table.row("noise 3 mm / 1.5 deg").faults,
    "late": fault_table.row("latency 2 steps").faults,
    "drops": fault_table.row("drops 5 %").faults,
    "friction": Faults(friction=REALISTIC.friction),
}


def run(family: str, seed: int, boxes: int, world: str, stop: str, first_turn_scale: float = 1.0) -> dict:
    ctrl = ControllerConfig(explore_guard_stop=stop)
    shipped = explore.VECTORS
    if first_turn_scale != 1.0:  # a what-if: the oracle refuses after any exploration; H reads only VECTORS
        explore.VECTORS = shipped.copy()
        explore.VECTORS[:3, :2] *= first_turn_scale
    try:
        ev = experiments.evaluate(
            cfg, 1, boxes, seed, family=family, ctrl=ctrl, faults=WORLDS[world], progress=False
        )
    finally:
        explore.VECTORS = shipped
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
    ap.add_argument("--stops", nargs="+", default=["recentre", "hold"], choices=("recentre", "hold"))
    ap.add_argument(
        "--first-turn-scale",
        type=float,
        default=1.0,
        help="what-if: scale the belt speeds of the exploration's first turn (its first three vectors)",
    )
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
            for stop in args.stops:
                row = {"family": family, "seed": seed, "world": world, "stop": stop}
                if args.first_turn_scale != 1.0:
                    row["first_turn_scale"] = args.first_turn_scale
                row.update(run(family, seed, args.boxes, world, stop, args.first_turn_scale))
                res["runs"].append(row)
                print(f"{time.time() - t0:6.0f} s  {json.dumps(row)}", flush=True)
    if args.out:
        write_json(args.out, res)
    return res


if __name__ == "__main__":
    main()
