"""`boxjax box` (make and inspect box files) and `boxjax config` (the config as TOML)."""

from __future__ import annotations

import sys

from boxjax.cli.args import config_option, needs, option
from boxjax.cli.episodes import load_config


def cmd_box(args) -> dict:
    """Draw a random box (--random SEED, saved with --out) or inspect a box file; describe it, plot it."""
    from boxjax import boxfile, massdist

    cfg = load_config(args)
    if (args.file is None) == (args.random is None):
        raise ValueError("give either a box FILE to inspect or --random SEED to draw one")
    if args.random is not None:
        name, dist = f"random box, seed {args.random}", boxfile.random_box(args.random, cfg.box)
    else:
        name, dist = args.file, boxfile.load(args.file, cfg.box)
    summary = {"command": "box", "box": name, **boxfile.report(dist, cfg.box)}
    if args.out:
        command = " ".join(["boxjax box --random", str(args.random), "--out", args.out])
        meta = {"command": command + (f" --config {args.config}" if args.config else ""), "seed": args.random}
        summary["file"] = boxfile.save(args.out, dist, cfg.box, meta)
    if not args.json:
        sys.stdout.write(f"{name}: {massdist.describe(dist, cfg.box)}\n")
    if args.plot:
        from boxjax.viz.plots import plot_mass_distributions

        summary["plot"] = plot_mass_distributions({name: dist}, cfg.box, args.plot)
    return summary


def cmd_config(args) -> None:
    """Print the config (the defaults, or --config FILE with every field filled in) as TOML."""
    from boxjax import config_io

    cfg = load_config(args)
    if args.out:
        config_io.save(args.out, cfg)
        sys.stderr.write(f"wrote {args.out}\n")
    else:
        sys.stdout.write(config_io.dumps(cfg))
    return None


def add_parsers(sub) -> None:
    b = sub.add_parser(
        "box",
        help="make (--random SEED --out FILE) or inspect (FILE) a box file for --box",
        description="Box files: .npz with occupancy (nx, ny, nz) of 0/1 and total_mass (kg), or a .json "
        'gaussian mixture {"means": [[x, y, z], ...] (m, box frame), "stds": [[sx, sy, sz], ...] (m), '
        '"weights": [...], "threshold": 0.4, "total_mass": 5.0, "region": null or "U1".."U4"}.',
    )
    b.add_argument("file", nargs="?", help="a box file to inspect (.npz or .json)")
    option(b, "--random", type=int, metavar="SEED", help="draw a random mixture box (massdist.sample)")
    option(
        b, "--out", metavar="FILE.npz", used_by=(needs("random", " SEED"),), help="save the drawn box here"
    )
    option(b, "--plot", metavar="FILE.png", help="3-D voxel plot with the centre of mass")
    config_option(b)
    b.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    b.set_defaults(func=cmd_box)

    c = sub.add_parser("config", help="print the configuration as TOML (the defaults; a start for --config)")
    config_option(c)
    option(c, "--out", metavar="FILE.toml", help="write it to this file instead of printing it")
    c.set_defaults(func=cmd_config, json=False)
