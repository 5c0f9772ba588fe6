"""One `boxjax evaluate` run with sampling-planner or controller options the CLI does not expose (the
planner study in the README: horizon, knots, MPPI / CEM, gradient refinement, pose cost, observer).

    python scripts/planner_study.py --boxes 100 --seed 0 --sampling update=mppi --sampling horizon=20 \
        [--controller observer_gain=0.3] [--prior carriage_omega=30] [--estimator oracle|learned] [--out DIR]
    python scripts/planner_study.py --boxes 100 --seed 2 --sampling n_samples=32 \
        --mixture default --mixture carriage_omega=30,slip_eps=0.02      # a mixture of priors

`--simulator KEY=VALUE` sets `planners.simulator.SimulatorOptions` fields (with `--controller
planner=simulator`: e.g. `--simulator start=planar` plans with MuJoCo from what the planar observation
shows); `--safe-family F` draws the safe boxes from family F (as `boxjax evaluate --safe-family`).

`--monitor KEY=VALUE` sets `control.monitor.MonitorConfig` fields (e.g. `--monitor
recover_until_worse=false`, `--monitor 'prior_params={"carriage_omega": 30}'`), `--fault KEY=VALUE`
`sim.faults.Faults` fields (e.g. `--fault obs_latency=2 --fault friction=0.4`).

`--mixture` (two or more) plans over a mixture of physics priors, one per setting
(`ControllerConfig.prior_params` as a tuple, `planning.Mixture`), each candidate scored by its mean cost
over them (`--sampling particle_risk=worst` for the worst). The episodes run batched with one host
device per core, as `boxjax evaluate` runs them.

Values are parsed as JSON (numbers, true / false, "strings" or bare words). Prints one JSON line: the
evaluation summary (as `boxjax evaluate --json`) and the failed box indices.
"""

from __future__ import annotations

import argparse
import json
import sys

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.control.monitor import MonitorConfig
from boxjax.control.state_estimate import FilterConfig
from boxjax.experiments import evaluation as experiments
from boxjax.planners.sampling import SamplingOptions
from boxjax.planners.simulator import SimulatorOptions
from boxjax.prior.predictor import PriorParams
from boxjax.sim.faults import Faults


def _pairs(items: list[str], what: str) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--{what} {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--boxes", type=int, default=100)
    ap.add_argument("--hazardous", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--estimator", choices=("oracle", "learned"), default="oracle")
    ap.add_argument("--sampling", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--controller", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument(
        "--prior", action="append", default=[], metavar="KEY=VALUE", help="a prior.PriorParams field"
    )
    ap.add_argument(
        "--mixture",
        action="append",
        default=[],
        metavar="KEY=VALUE[,KEY=VALUE...]|default",
        help="one prior setting of a mixture of priors (give two or more)",
    )
    ap.add_argument("--simulator", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument(
        "--monitor", action="append", default=[], metavar="KEY=VALUE", help="a MonitorConfig field"
    )
    ap.add_argument("--filter", action="append", default=[], metavar="KEY=VALUE", help="a FilterConfig field")
    ap.add_argument(
        "--fault", action="append", default=[], metavar="KEY=VALUE", help="a sim.faults.Faults field"
    )
    ap.add_argument("--safe-family", default="gaussian", choices=massdist.FAMILIES)
    ap.add_argument("--out", help="write evaluation.json and boxes.npz here (for `boxjax rotate --replay`)")
    args = ap.parse_args(argv)
    if args.prior and args.mixture:
        ap.error("--prior sets the one prior; with --mixture give every setting as a --mixture")
    try:
        fields = _pairs(args.controller, "controller")
        variant = fields.get("variant", "slip")
        prior_params = None
        if args.prior:
            prior_params = PriorParams(variant=variant, **_pairs(args.prior, "prior"))
        if args.mixture:
            prior_params = tuple(
                PriorParams(variant=variant, **({} if m == "default" else _pairs(m.split(","), "mixture")))
                for m in args.mixture
            )
        if args.simulator:
            if fields.get("planner") != "simulator":
                raise ValueError("--simulator sets the simulator planner: add --controller planner=simulator")
            fields["simulator"] = SimulatorOptions(**_pairs(args.simulator, "simulator"))
        if args.monitor:
            if "monitor" in fields:
                raise ValueError(
                    "give the monitor's fields with --monitor KEY=VALUE, not --controller monitor="
                )
            mon = _pairs(args.monitor, "monitor")
            if isinstance(mon.get("prior_params"), dict):  # the monitor's own prior: PriorParams fields
                mon["prior_params"] = PriorParams(**mon["prior_params"])
            fields["monitor"] = MonitorConfig(**mon)
        if args.filter:
            if "pose_filter" in fields:
                raise ValueError("give the pose filter's fields with --filter KEY=VALUE, not --controller")
            fields["pose_filter"] = FilterConfig(**_pairs(args.filter, "filter"))
        ctrl = ControllerConfig(
            sampling=SamplingOptions(**_pairs(args.sampling, "sampling")), prior_params=prior_params, **fields
        )
        faults = Faults.from_dict(_pairs(args.fault, "fault"))
    except (TypeError, ValueError) as e:
        sys.stderr.write(f"planner_study: error: {e}\n")
        raise SystemExit(2) from e
    batch.use_host_devices()  # one host device per core, as `boxjax evaluate`
    ev = experiments.evaluate(
        DEFAULT,
        args.boxes,
        args.hazardous,
        args.seed,
        estimator=args.estimator,
        ctrl=ctrl,
        safe_family=args.safe_family,
        faults=faults,
    )
    if args.out:
        experiments.write_evaluation(ev, args.out, " ".join(["python", *sys.argv]))
    out = {**ev.summary, "failed": [r["index"] for r in ev.rows if r["outcome"] != "success"]}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
