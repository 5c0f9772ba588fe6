"""Two settings compared on the same boxes and episode keys, box by box (`boxjax.experiments.paired`).

    boxjax evaluate --boxes 100 --seed 0 --out base/                     # or scripts/planner_study.py
    boxjax evaluate --boxes 100 --seed 0 --tip-stop-cm 0.8 --out other/
    python scripts/compare_evaluations.py base/ other/ [base_s1/ other_s1/ ...] [--plot margins.png]

The directories come in pairs (A then B, each pair of the same boxes: same seed, box count and families);
prints one JSON line per pair and, with several pairs, one for all of them pooled (the rows concatenated).
`--plot`: each pooled box's smallest true stability margin under A against under B, and the paired
differences' histogram; `--turn`: the margins over the turns alone (the exploration is the same under both).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from boxjax.control.episode import NEAR_TIP_M
from boxjax.experiments import paired


def _rows(d: str) -> list[dict]:
    with open(os.path.join(d, "evaluation.json")) as f:
        return json.load(f)["rows"]


def _plotted(rows_a: list[dict], rows_b: list[dict], turn: bool):
    pairs = [(a, b) for a, b in zip(rows_a, rows_b, strict=True) if not a["hazardous"]]
    return paired.margin_pairs(pairs, "turn_min_stability_margin_m" if turn else "min_stability_margin_m")


def plot(rows_a: list[dict], rows_b: list[dict], path: str, turn: bool = False) -> str:
    from boxjax.viz.plots import plot_paired_margins

    m = _plotted(rows_a, rows_b, turn)
    return plot_paired_margins(m[:, 0], m[:, 1], path, NEAR_TIP_M)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", help="evaluation directories (written with --out), in pairs A B")
    ap.add_argument("--plot", default=None, help="a PNG of the pooled margins")
    ap.add_argument("--turn", action="store_true", help="plot the margins over the turns alone")
    args = ap.parse_args(argv)
    if len(args.dirs) % 2:
        ap.error(f"the directories come in pairs (A B ...): {len(args.dirs)} given")
    for d in args.dirs:
        if not os.path.isfile(os.path.join(d, "evaluation.json")):
            ap.error(f"{d} has no evaluation.json (write one with boxjax evaluate --out {d})")
    if args.turn and not args.plot:
        ap.error("--turn chooses the margins --plot draws: give --plot FILE.png")
    if args.plot and not os.access(os.path.dirname(os.path.abspath(args.plot)), os.W_OK):
        ap.error(f"--plot {args.plot}: its directory cannot be written")
    pairs = [(_rows(a), _rows(b)) for a, b in zip(args.dirs[::2], args.dirs[1::2], strict=True)]
    out = []
    try:
        for (ra, rb), a, b in zip(pairs, args.dirs[::2], args.dirs[1::2], strict=True):
            out.append({"a": a, "b": b, **paired.compare(ra, rb)})
    except ValueError as e:
        ap.error(str(e))
    rows_a = [r for ra, _ in pairs for r in ra]
    rows_b = [r for _, rb in pairs for r in rb]
    if args.turn and not len(_plotted(rows_a, rows_b, True)):
        ap.error(
            "--turn: no box has a turn's margin under both settings (evaluations written before 2026-12-07)"
        )
    if len(pairs) > 1:
        out.append({"pooled": len(pairs), **paired.compare(rows_a, rows_b)})
    for o in out:
        print(json.dumps(o))
    if args.plot:
        print(f"figure: {plot(rows_a, rows_b, args.plot, args.turn)}", file=sys.stderr)
    return out


if __name__ == "__main__":
    main()
