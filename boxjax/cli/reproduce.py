"""`boxjax reproduce --out DIR [--quick] [--retrain] [--force] [--json]`: the paper's experiments, one report.

From the shipped weights (or, with --retrain, weights made again into DIR/weights),
`boxjax.experiments.reproduce.run`
runs Table 1, Table 2, the §4.3 validation and the figures and writes DIR/report.md
(`boxjax.experiments.report`),
DIR/results.json and DIR/figures/*.png. It takes no --config: the shipped weights were made for the
default gripper (`boxjax compare` and `boxjax evaluate` take one).
"""

from __future__ import annotations

import os
import shlex
import sys


def cmd_reproduce(args) -> dict:
    from boxjax.control import batch
    from boxjax.experiments import reproduce

    reproduce.check_out(args.out, args.force)  # before JAX starts: a refusal costs nothing
    if not args.retrain:
        reproduce.require_shipped(reproduce.SHIPPED_NEEDED)
    batch.use_host_devices()  # one host device per core: the batched planner shards boxes over them
    cache = reproduce.use_compilation_cache()
    flags = [f for f, on in (("--quick", args.quick), ("--retrain", args.retrain), ("--force", args.force),
                             ("--json", args.json)) if on]  # fmt: skip
    command = shlex.join(["boxjax", "reproduce", "--out", args.out, *flags])
    res = reproduce.run(
        args.out,
        quick=args.quick,
        retrain=args.retrain,
        force=args.force,
        command=command,
        progress=not args.json,
    )
    out = {
        "command": "reproduce",
        "report": os.path.join(args.out, reproduce.REPORT),
        "results": os.path.join(args.out, reproduce.RESULTS),
        "wall_s": res["wall_s"],
        "load_average": res["machine"]["load_average"],
        "reductions": res["reductions"],
        "compilation_cache": cache,
        "table1": res["table1"]["table"],
        "validation": {"first": res["validation"]["first"], "all": res["validation"]["summary"]},
    }
    if not args.json:
        sys.stdout.write(f"wrote {out['report']} and {out['results']}\n")
        for part, s in res["wall_s"].items():
            sys.stdout.write(f"  {part:>16}: {s:.1f} s\n")
        return None
    return out


def add_parsers(sub) -> None:
    r = sub.add_parser(
        "reproduce",
        help="run the paper's experiments (Tables 1-2, §4.3, Figs. 2-3) and write DIR/report.md",
        description="Run the paper's experiments from the shipped weights and write DIR/report.md (every "
        "table beside the paper's numbers, figures linked), DIR/figures/*.png and DIR/results.json.",
    )
    r.add_argument("--out", required=True, help="output folder (refused if it exists and is not empty)")
    r.add_argument(
        "--quick",
        action="store_true",
        help="every part on a few boxes and one seed (Table 1: prior on A and D, W on A; validation: 2 safe "
        "+ 1 hazardous boxes); with --retrain: H on 40 boxes, W on 2 episodes, calibration of 64 transitions",
    )
    r.add_argument(
        "--retrain",
        action="store_true",
        help="make the weights first into DIR/weights (calibration of 2000 transitions, H on 2000 boxes, W "
        "on 200 episodes of A) and run the experiments with them",
    )
    r.add_argument("--force", action="store_true", help="write into an existing non-empty --out")
    r.add_argument(
        "--json", action="store_true", help="print the summary as one JSON line (no progress bars)"
    )
    r.set_defaults(func=cmd_reproduce)
