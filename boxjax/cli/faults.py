"""`boxjax fault-table`: the controller under faults and mismatch, with the runtime safety monitor on and off
(`boxjax.experiments.fault_table`; docs/results/faults.md)."""

from __future__ import annotations

import os
import sys

from boxjax.cli.args import at_least, option, when


def cmd_fault_table(args) -> dict:
    from boxjax.control import batch
    from boxjax.experiments import fault_table
    from boxjax.fileio import check_writable_dir

    rows = tuple(args.rows) if args.rows else fault_table.ROW_NAMES
    for name in rows:
        fault_table.row(name)  # an unknown row is refused before any episode runs
    if args.weights:  # a checkpoint that does not fit is refused before any episode runs
        from boxjax.cli import models as cli_models
        from boxjax.config import DEFAULT as cfg

        cli_models.require_models(cfg, estimator=True, weights=args.weights)
    for path, what in ((args.out, "--out"), (args.plot, "--plot")):
        if path:
            check_writable_dir(os.path.dirname(os.path.abspath(path)), f"{what}'s directory")
    batch.use_host_devices()
    from boxjax.config import DEFAULT

    def progress(name, m, e, wall):
        if not args.quiet:
            sys.stderr.write(
                f"{name:>28} monitor {m:>3}: turned {e['safe_success']}/{e['safe_boxes']}, safe stops "
                f"{e['safe_stops']}, crossings {e['crossings']} (unnoticed {e['unnoticed_crossings']}), "
                f"near tips {(e.get('min_stability_margin_m') or {}).get('near_tips', '-')}, {wall:.0f} s\n"
            )

    monitors = ("on", "off") if args.monitor == "both" else (args.monitor,)
    table = fault_table.run(
        DEFAULT,
        args.boxes,
        args.seed,
        rows=rows,
        monitors=monitors,
        estimator=args.estimator,
        weights=args.weights,
        hazardous=args.hazardous,
        out=args.out,
        progress=progress,
    )
    summary = {"command": "fault-table", "out": args.out, "table": fault_table.markdown(table)}
    if args.plot:
        from boxjax.viz.plots import plot_fault_table

        summary["plot"] = plot_fault_table(table, args.plot)
    if not args.json:
        sys.stdout.write(summary.pop("table") + "\n")
    return summary


def add_parsers(sub) -> None:
    from boxjax.experiments.fault_table import ROW_NAMES

    p = sub.add_parser("fault-table", help="the controller under faults, monitor on and off (one table)")
    option(p, "--boxes", type=int, default=100, check=at_least(1), help="random safe boxes per row")
    option(p, "--hazardous", type=int, default=0, check=at_least(0), help="random hazardous boxes per row")
    option(p, "--seed", type=int, default=0, help="draws the boxes and every episode's key")
    option(p, "--estimator", default="oracle", choices=("oracle", "learned"), help="oracle or the learned H")
    option(
        p,
        "--weights",
        used_by=(when("estimator", "learned"),),
        help="the learned H's checkpoint, used for every sensor (default: the two shipped with boxjax, "
        "chosen by the sensor), e.g. one trained with train-estimator --randomise-sensor",
    )
    option(
        p,
        "--rows",
        nargs="+",
        choices=ROW_NAMES,
        metavar="ROW",
        help="rows to run (default all: " + ", ".join(repr(r) for r in ROW_NAMES).replace("%", "%%") + ")",
    )
    option(p, "--monitor", default="both", choices=("both", "on", "off"), help="the runtime safety monitor")
    option(p, "--out", metavar="FILE.json", help="write the table here after every row; run again to resume")
    option(
        p, "--plot", metavar="FILE.png", help="success, safe stops and crossings against each fault's level"
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    p.set_defaults(func=cmd_fault_table)
