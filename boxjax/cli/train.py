"""`boxjax train-estimator`, `estimator-eval`, `calibrate`, `train-baseline` and `compare`: the models
and the paper's tables. Every one takes --config, so a model can be made for another gripper."""

from __future__ import annotations

import os
import sys
import time

from boxjax.cli import models as cli_models
from boxjax.cli.args import at_least, config_option, exploration_option, option, when
from boxjax.cli.episodes import load_config


def _simulation(args) -> dict:
    """The --backend / --chunk keywords of the estimator pipeline."""
    return {"backend": args.backend, "chunk": args.chunk, "progress": not args.json}


def _with_config(command: str, args) -> str:
    return f"{command} --config {args.config}" if args.config else command


def cmd_train_estimator(args) -> dict:
    from boxjax.training import estimator as P

    cfg = load_config(args)
    sensor = None
    if args.randomise_sensor:
        from boxjax.training.randomise import SensorRandomisation

        sensor = SensorRandomisation()
    report = P.train_estimator(args.seed, args.boxes, args.out, cfg, sensor=sensor, **_simulation(args))
    out = {"command": "train-estimator", "boxes": args.boxes, "seed": args.seed, "out": args.out, **report}
    return {**out, "config": args.config} if args.config else out


def cmd_train_moments(args) -> dict:
    from boxjax.fileio import check_writable_dir
    from boxjax.training import moments as TM

    cfg = load_config(args)
    if not args.out.endswith(".npz") or os.path.isdir(args.out):
        raise ValueError(f"--out must be a .npz file path, got {args.out!r}")
    check_writable_dir(os.path.dirname(os.path.abspath(args.out)), "--out's directory")
    log = (lambda s: None) if args.json else (lambda s: print(s, file=sys.stderr))
    report = TM.train_moments(args.seed, args.boxes, args.out, cfg, log=log, **_simulation(args))
    out = {"command": "train-moments", "boxes": args.boxes, "seed": args.seed, **report}
    return {**out, "config": args.config} if args.config else out


def cmd_estimator_eval(args) -> dict:
    from boxjax.training import estimator as P

    cfg = load_config(args)
    cli_models.require_models(cfg, estimator=True, weights=args.weights, config_path=args.config)
    res = P.evaluate_estimator(
        args.seed, args.boxes, args.weights, cfg, moments_path=args.moments, **_simulation(args)
    )
    return {"command": "estimator-eval", **res}


_FORCE_UNITS = (("dv1", "m/s"), ("dv2", "m/s"), ("dp1", "m"), ("dp2", "m"))


def cmd_calibrate(args) -> dict:
    """The action -> force map of paper §2.4 by simulation (boxjax.training.calibration), saved with its
    command."""
    import jax
    import mujoco
    import numpy as np

    from boxjax import __version__
    from boxjax.prior import force_map as calibrate
    from boxjax.training.calibration import GRID_POINTS, calibrate_by_simulation

    cfg = load_config(args)
    for opt, path in (("--out", args.out), ("--plot", args.plot)):
        if path is not None and (path == "" or os.path.isdir(path)):
            raise ValueError(f"{opt} must be a file path, got {path!r}")
    t0 = time.perf_counter()
    cal = calibrate_by_simulation(
        cfg, jax.random.PRNGKey(args.seed), args.transitions, grid_points=GRID_POINTS, progress=not args.json
    )
    # Everything that decides the file's content, and nothing that does not (no wall time): the same
    # command gives the same bytes.
    command = _with_config(
        f"boxjax calibrate --transitions {args.transitions} --seed {args.seed} --out {args.out}", args
    )
    info = {k: v for k, v in cal.info.items() if k != "wall_s"}
    meta = {
        "command": command,
        "seed": args.seed,
        "key": f"jax.random.PRNGKey({args.seed})",
        "box": "uniform",
        "backend": "native",
        "grid_points": GRID_POINTS,
        "boxjax": __version__,
        "mujoco": mujoco.__version__,
        **info,
    }
    calibrate.save(args.out, cal.force_map, cfg, meta)
    fm = cal.force_map
    forces = {}
    for c, name in enumerate(calibrate.FORCE_NAMES):
        grid, mean, std = (np.asarray(a[c], np.float64) for a in (fm.grid, fm.mean, fm.std))
        var, unit = _FORCE_UNITS[c]
        forces[name] = {
            "action": var,
            "action_unit": unit,
            "action_range": [float(grid[0]), float(grid[-1])],
            "mean_at_ends_N": [float(mean[0]), float(mean[-1])],
            "mean_range_N": [float(mean.min()), float(mean.max())],
            "std_range_N": [float(std.min()), float(std.max())],
            "samples": int(np.asarray(fm.count[c]).sum()),
        }
        if not args.json:
            sys.stdout.write(
                f"{name} ({var}, {unit}): mean {mean[0]:+.2f} N at {grid[0]:+.4g} ... {mean[-1]:+.2f} N at "
                f"{grid[-1]:+.4g}, range [{mean.min():+.2f}, {mean.max():+.2f}] N, "
                f"std {std.min():.2f}..{std.max():.2f} N\n"
            )
    summary = {
        "command": "calibrate",
        "transitions": cal.info["transitions"],
        "seed": args.seed,
        "out": args.out,
        "episodes": cal.info["episodes"],
        "per_component": cal.info["per_component"],
    }
    if args.json:  # the human-readable form is the table printed above
        summary["forces"] = forces
    if args.plot:
        from boxjax.viz.plots import plot_force_map

        title = f"action -> force map (paper Fig. 3), {cal.info['transitions']} transitions, seed {args.seed}"
        summary["plot"] = plot_force_map(fm, cal.component, cal.value, cal.force, args.plot, title)
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def cmd_train_baseline(args) -> dict:
    """W (`--model blackbox`, training.baseline) or the PETS ensemble (`--model pets`, training.pets) on the
    episodes of one box, collected or read from an earlier run's dataset.npz (--data)."""
    import dataclasses

    cfg = load_config(args)
    weights = "pets.npz" if args.model == "pets" else "baseline.npz"
    if os.path.exists(os.path.join(args.out, weights)) and not args.force:
        raise ValueError(f"--out {args.out} already holds {weights}; pass --force to overwrite it")
    sizes = {k: v for k, v in (("epochs", args.epochs), ("members", args.members)) if v is not None}
    common = {
        "distribution": args.distribution,
        "n_episodes": args.episodes,
        "seed": args.seed,
        "out": args.out,
        "progress": not args.json,
        "data": args.data,
        "backend": args.backend,
    }
    if args.model == "pets":
        from boxjax.blackbox import pets
        from boxjax.training import pets as pets_train

        config = dataclasses.replace(pets.PETSConfig(), **sizes)
        report = pets_train.train_pets(cfg, config=config, **common)
        return {**report, "command": "train-baseline", "model": "pets"}
    from boxjax.blackbox import baseline
    from boxjax.training import baseline as baseline_train

    config = dataclasses.replace(baseline.BaselineConfig(), **sizes)
    return {**baseline_train.train_baseline(cfg, config=config, **common), "model": "blackbox"}


def cmd_compare(args) -> dict:
    """Paper Table 1: the physics prior (learned H) and the black box W (online adaptation), same planner."""
    import json

    from boxjax.blackbox import load_black_box
    from boxjax.experiments import comparison

    cfg = load_config(args)
    with_w = "blackbox" in args.methods
    cli_models.require_models(
        cfg,
        estimator="prior" in args.methods,
        baseline=with_w,
        baseline_weights=args.model_weights,
        config_path=args.config,
    )
    model = load_black_box("blackbox", args.model_weights, cfg.gripper) if with_w else None
    res = comparison.compare(
        cfg,
        tuple(args.boxes),
        args.seeds,
        tuple(args.methods),
        model,
        args.adapt_every,
        args.adapt_epochs,
        progress=not args.json,
    )
    if args.out:
        from boxjax.fileio import atomic_path

        os.makedirs(args.out, exist_ok=True)
        with atomic_path(os.path.join(args.out, "comparison.json"), suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(res, f, indent=1)
        res["file"] = os.path.join(args.out, "comparison.json")
    if not args.json:
        sys.stdout.write(comparison.format_table(res["table"]) + "\n")
    return {"command": "compare", **res}


def _simulation_options(p) -> None:
    from boxjax.sim import BACKENDS

    option(
        p,
        "--backend",
        choices=BACKENDS,
        default="native",
        help="simulate the boxes with native MuJoCo (mujoco.rollout, fastest on CPU) or MJX (accelerators)",
    )
    option(
        p,
        "--chunk",
        type=int,
        default=500,
        check=at_least(1),
        help="boxes per batched rollout call (bounds memory; larger batches fill an accelerator under MJX)",
    )


def add_parsers(sub) -> None:
    from boxjax.massdist import NAMES

    t = sub.add_parser("train-estimator", help="generate exploration data and train the estimator H")
    option(t, "--boxes", type=int, default=2000, check=at_least(10), help="random boxes (train + validation)")
    option(t, "--seed", type=int, default=0, help="PRNG seed of the data and the training")
    t.add_argument("--out", required=True, help="directory for dataset.npz, estimator.npz, report.json")
    t.add_argument(
        "--randomise-sensor",
        action="store_true",
        help="train on the explorations seen through randomised sensors (0-5 mm pose noise, 0-20 %% dropped "
        "frames, a quarter perfect): keeps the hazard decision under sensor faults (docs/results/faults.md)",
    )
    _simulation_options(t)
    config_option(t)
    exploration_option(t)
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_train_estimator)

    m = sub.add_parser(
        "train-moments",
        help="train the moments estimator (mass, centre of mass, spreads, I_zz with calibrated std) on the "
        "wide training mixture (gaussian mixtures, items, slabs)",
    )
    option(m, "--boxes", type=int, default=2000, check=at_least(20), help="random boxes (train + validation)")
    option(m, "--seed", type=int, default=0, help="PRNG seed of the boxes and the training")
    m.add_argument("--out", required=True, help="the checkpoint to write (.npz)")
    _simulation_options(m)
    config_option(m)
    exploration_option(m)
    m.add_argument("--json", action="store_true")
    m.set_defaults(func=cmd_train_moments)

    e = sub.add_parser("estimator-eval", help="accuracy of H on fresh random boxes")
    option(e, "--boxes", type=int, default=500, check=at_least(1), help="fresh random boxes")
    option(e, "--seed", type=int, default=1, help="PRNG seed of the boxes")
    option(e, "--weights", help="checkpoint (default: the one shipped with boxjax)")
    option(e, "--moments", help="moments checkpoint (train-moments; default: the one shipped with boxjax)")
    _simulation_options(e)
    config_option(e)
    exploration_option(e)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_estimator_eval)

    c = sub.add_parser("calibrate", help="calibrate the action -> force map by simulation (paper §2.4)")
    option(
        c,
        "--transitions",
        type=int,
        default=400,
        check=at_least(8),
        help="calibration transitions to collect (>= 8: samples for all four components)",
    )
    option(c, "--seed", type=int, default=0, help="PRNG seed")
    c.add_argument("--out", required=True, help="calibration file to write (.npz)")
    option(c, "--plot", help="write the force map (paper Fig. 3, all four forces) to this PNG")
    config_option(c)
    c.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    c.set_defaults(func=cmd_calibrate)

    b = sub.add_parser(
        "train-baseline", help="collect episodes of one box and train the black box W (or PETS: --model pets)"
    )
    option(b, "--model", choices=("blackbox", "pets"), default="blackbox", help="W or the PETS ensemble")
    option(b, "--distribution", choices=NAMES, default="A", help="the single training environment")
    pets_data = (
        lambda a: (
            "does nothing with --model pets --data: PETS trains on all of the dataset's episodes"
            if a.model == "pets" and a.data
            else None
        ),
    )
    option(b, "--episodes", type=int, default=200, used_by=pets_data, help="episodes to collect")
    option(b, "--seed", type=int, default=0, help="PRNG seed")
    option(b, "--epochs", type=int, check=at_least(1), help="training epochs (default: W 12, PETS 30)")
    option(
        b,
        "--members",
        type=int,
        check=at_least(1),
        used_by=(when("model", "pets", owner="the PETS ensemble"),),
        help="ensemble members (default 5)",
    )
    b.add_argument(
        "--out",
        required=True,
        help="directory for baseline.npz, dataset.npz, report.json (PETS: pets.npz, pets_report.json)",
    )
    b.add_argument("--data", help="train on the dataset.npz of an earlier run instead of collecting")
    option(
        b,
        "--backend",
        choices=("native", "mjx"),
        default="native",
        used_by=(
            lambda a: "does nothing with --data: the episodes are read, not simulated" if a.data else None,
        ),
        help="collect the episodes one by one with native MuJoCo, or in batches on the device with MJX",
    )
    b.add_argument("--force", action="store_true", help="overwrite OUT/baseline.npz (PETS: OUT/pets.npz)")
    config_option(b)
    b.add_argument("--json", action="store_true", help="print the report as one JSON line (no progress bars)")
    b.set_defaults(func=cmd_train_baseline)

    m = sub.add_parser("compare", help="paper Table 1: physics prior vs black box W on boxes A-D")
    option(m, "--seeds", type=int, default=5, check=at_least(1), help="episodes per box and method")
    m.add_argument("--boxes", nargs="+", choices=NAMES, default=["A", "B", "C", "D"])
    m.add_argument(
        "--methods", nargs="+", choices=("prior", "blackbox", "pets"), default=["prior", "blackbox"]
    )
    uses_w = (lambda a: None if "blackbox" in a.methods else "is an option of --methods blackbox",)
    adapts = (lambda a: None if {"blackbox", "pets"} & set(a.methods) else "is an option of the black boxes",)
    option(m, "--model-weights", used_by=uses_w, help="W checkpoint (default: the shipped one)")
    option(
        m,
        "--adapt-every",
        type=int,
        default=20,
        used_by=adapts,
        check=at_least(0),
        help="steps between W's online adaptations (0: none)",
    )
    option(m, "--adapt-epochs", type=int, default=1, used_by=adapts, check=at_least(0), help="epochs each")
    m.add_argument("--out", help="directory for comparison.json")
    config_option(m)
    m.add_argument("--json", action="store_true", help="print the result as one JSON line")
    m.set_defaults(func=cmd_compare)
