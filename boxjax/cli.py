"""The `boxjax` command line.

    boxjax simulate --distribution D --policy naive --steps 300 [--backend native|mjx] [--plot f.png] [--json]
    boxjax rotate --distribution C --estimator oracle|learned [--planner sampling|paper] [--seed S]
        [--plot f.png] [--json]
    boxjax demo [--distribution A|B|C|D|uniform] [--plot boxjax_demo.png] [--json]
    boxjax train-estimator [--boxes 2000] [--seed S] --out DIR [--backend native|mjx] [--chunk 500] [--json]
    boxjax estimator-eval [--boxes 500] [--seed S] [--weights FILE] [--backend native|mjx] [--chunk 500]
        [--json]
    boxjax calibrate [--transitions 400] [--seed S] --out FILE [--plot FILE.png] [--json]

With --json the last line printed is one JSON object (the summary); everything else goes before it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def _emit(summary: dict, as_json: bool):
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        for k, v in summary.items():
            sys.stdout.write(f"  {k:>22}: {v}\n")
    sys.stdout.flush()


def cmd_simulate(args) -> dict:
    import jax

    from boxjax import massdist
    from boxjax.config import DEFAULT
    from boxjax.sim import make_env
    from boxjax.sim.episode import naive_policy, random_policy, run_episode

    cfg = DEFAULT
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    dist = massdist.named(args.distribution, cfg.box)
    key = jax.random.PRNGKey(args.seed)
    key_reset, key_run = jax.random.split(key)
    t0 = time.perf_counter()
    env = make_env(cfg, args.backend)
    state = env.reset(key_reset, dist)
    if args.policy == "naive":
        if not 0 < args.speed <= cfg.gripper.belt_speed_limit:
            raise ValueError(
                f"--speed {args.speed} m/s is beyond the belt speed limit {cfg.gripper.belt_speed_limit} m/s"
            )
        policy = naive_policy(args.speed)
    else:
        policy = random_policy(cfg)
    state, trace = run_episode(env, state, policy, key_run, args.steps)
    wall = time.perf_counter() - t0
    summary = {
        "command": "simulate",
        "distribution": args.distribution,
        "policy": args.policy,
        "backend": args.backend,
        "seed": args.seed,
        **state.summary(),
        "any_action_clipped": bool(trace.clipped.any()),
        "simulated_s": float(trace.time[-1]),
        "wall_s": wall,
        "episode_wall_s": trace.wall_s,
    }
    if not args.json:
        sys.stdout.write(f"{args.distribution}: {massdist.describe(dist, cfg.box)}\n")
    if args.plot:
        from boxjax.plots import plot_episode

        title = f"distribution {args.distribution}, policy {args.policy}, {args.backend}"
        summary["plot"] = plot_episode(
            trace, args.plot, cfg.task.balance_limit, float(state.target_yaw), title
        )
    return summary


def cmd_rotate(args) -> dict:
    import jax

    from boxjax import massdist
    from boxjax.config import DEFAULT
    from boxjax.controller import ControllerConfig, run_episode

    cfg = DEFAULT
    dist = massdist.named(args.distribution, cfg.box)
    estimator = "oracle"
    if args.estimator == "learned":
        from boxjax.controller import learned_estimator

        estimator = learned_estimator(cfg, args.weights)
    ctrl = ControllerConfig(
        rule=args.rule,
        n_samples=args.samples,
        horizon=args.horizon,
        variant=args.variant,
        planner=args.planner,
    )
    res = run_episode(
        cfg, dist, jax.random.PRNGKey(args.seed), estimator=estimator, ctrl=ctrl, backend=args.backend
    )
    summary = {
        "command": "rotate",
        "distribution": args.distribution,
        "estimator": args.estimator,
        "backend": args.backend,
        "seed": args.seed,
        "planner": args.planner,
        "variant": args.variant,
        **res.summary,
    }
    if not args.json:
        sys.stdout.write(f"{args.distribution}: {massdist.describe(dist, cfg.box)}\n")
        if res.summary["aborted"]:
            sys.stdout.write(res.summary["abort_reason"] + "\n")
    if args.plot:
        from boxjax.plots import plot_episode

        title = f"rotate {args.distribution} ({args.estimator}), seed {args.seed}"
        target = float(res.trace.s[0, 4]) + cfg.task.target_yaw_delta
        summary["plot"] = plot_episode(res.trace, args.plot, cfg.task.balance_limit, target, title)
    return summary


def _simulation(args) -> dict:
    """The --backend / --chunk keywords of the estimator pipeline, checked."""
    if args.chunk < 1:
        raise ValueError(f"--chunk must be >= 1 box per batched rollout, got {args.chunk}")
    return {"backend": args.backend, "chunk": args.chunk, "progress": not args.json}


def cmd_train_estimator(args) -> dict:
    from boxjax import estimator_pipeline as P
    from boxjax.config import DEFAULT

    if args.boxes < 10:
        raise ValueError(f"--boxes must be >= 10 (train and validation splits), got {args.boxes}")
    report = P.train_estimator(args.seed, args.boxes, args.out, DEFAULT, **_simulation(args))
    return {"command": "train-estimator", "boxes": args.boxes, "seed": args.seed, "out": args.out, **report}


def cmd_estimator_eval(args) -> dict:
    from boxjax import estimator_pipeline as P
    from boxjax.config import DEFAULT

    if args.boxes < 1:
        raise ValueError(f"--boxes must be >= 1, got {args.boxes}")
    res = P.evaluate_estimator(args.seed, args.boxes, args.weights, DEFAULT, **_simulation(args))
    return {"command": "estimator-eval", **res}


_FORCE_UNITS = (("dv1", "m/s"), ("dv2", "m/s"), ("dp1", "m"), ("dp2", "m"))


def cmd_calibrate(args) -> dict:
    """The action -> force map of paper §2.4 by simulation (calibration_run), saved with its command."""
    import os

    import jax
    import mujoco
    import numpy as np

    from boxjax import __version__, calibrate
    from boxjax.calibration_run import GRID_POINTS, calibrate_by_simulation
    from boxjax.config import DEFAULT

    cfg = DEFAULT
    if args.transitions < 8:
        raise ValueError(
            f"--transitions must be >= 8 (samples for all four components), got {args.transitions}"
        )
    for opt, path in (("--out", args.out), ("--plot", args.plot)):
        if path is not None and (path == "" or os.path.isdir(path)):
            raise ValueError(f"{opt} must be a file path, got {path!r}")
    t0 = time.perf_counter()
    cal = calibrate_by_simulation(
        cfg, jax.random.PRNGKey(args.seed), args.transitions, grid_points=GRID_POINTS, progress=not args.json
    )
    # Everything that decides the file's content, and nothing that does not (no wall time): the same
    # command gives the same bytes.
    command = f"boxjax calibrate --transitions {args.transitions} --seed {args.seed} --out {args.out}"
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
        from boxjax.plots import plot_force_map

        title = f"action -> force map (paper Fig. 3), {cal.info['transitions']} transitions, seed {args.seed}"
        summary["plot"] = plot_force_map(fm, cal.component, cal.value, cal.force, args.plot, title)
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def cmd_demo(args) -> dict:
    """The whole pipeline on one box: explore, estimate with the shipped H, refuse or rotate, plot."""
    import jax

    from boxjax import massdist
    from boxjax.config import DEFAULT
    from boxjax.controller import learned_estimator, run_episode

    cfg = DEFAULT
    t0 = time.perf_counter()
    truth = massdist.named(args.distribution, cfg.box)
    say = (lambda msg: None) if args.json else (lambda msg: sys.stdout.write(msg + "\n"))
    say(f"box {args.distribution} (hidden from the controller): {massdist.describe(truth, cfg.box)}")
    say("exploring (45 steps), estimating the mass distribution with the shipped H, then planning ...")
    res = run_episode(cfg, truth, jax.random.PRNGKey(args.seed), estimator=learned_estimator(cfg))
    s = res.summary
    say(f"estimate: {massdist.describe(res.belief, cfg.box)}")
    say(
        f"  mass {float(res.belief.total_mass):.2f} kg (true {float(truth.total_mass):.2f}), centre-of-mass "
        f"error {s['com_error_cm']:.1f} cm, IoU {s['iou']:.2f}"
    )
    if s["aborted"]:
        say(s["abort_reason"])
    else:
        outcome = "turned the box by pi/2" if s["success"] else f"failed: {s['failed_reason']}"
        say(
            f"MPC {outcome} in {s['steps']} steps ({s['steps'] - s['exploration_steps']} after exploring), "
            f"max balance error {100 * s['max_balance_error_m']:.1f} cm, "
            f"planning {s['plan_ms_median']:.2f} ms per step (median)"
        )
    summary = {
        "command": "demo",
        "distribution": args.distribution,
        "estimator": "learned",
        "backend": "native",
        "seed": args.seed,
        **s,
    }
    if args.plot:
        from boxjax.plots import plot_demo

        target = float(res.trace.s[0, 4]) + cfg.task.target_yaw_delta
        verdict = "refused (hazardous)" if s["aborted"] else ("success" if s["success"] else "failure")
        title = f"box {args.distribution}: {verdict}"
        summary["plot"] = plot_demo(
            truth, res.belief, res.trace, args.plot, cfg.box, cfg.task.balance_limit, target, title
        )
        say(f"figure: {summary['plot']}")
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def _simulation_args(p: argparse.ArgumentParser) -> None:
    from boxjax.sim import BACKENDS

    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="native",
        help="simulate the boxes with native MuJoCo (mujoco.rollout, fastest on CPU) or MJX (accelerators)",
    )
    p.add_argument(
        "--chunk",
        type=int,
        default=500,
        help="boxes per batched rollout call (bounds memory; larger batches fill an accelerator under MJX)",
    )


def build_parser() -> argparse.ArgumentParser:
    from boxjax.massdist import NAMES
    from boxjax.sim import BACKENDS

    p = argparse.ArgumentParser(prog="boxjax", description="Safe box rotation on a two-belt gripper.")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="run the simulator with a simple policy")
    s.add_argument("--distribution", choices=NAMES, default="uniform")
    s.add_argument("--policy", choices=("naive", "random"), default="naive")
    s.add_argument("--steps", type=int, default=300, help="control steps (0.05 s each)")
    s.add_argument("--backend", choices=BACKENDS, default="native")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--speed", type=float, default=0.15, help="naive policy belt speed (m/s)")
    s.add_argument("--plot", help="write yaw / balance / belt commands to this PNG")
    s.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("rotate", help="explore, estimate, then refuse or turn the box with the MPC")
    r.add_argument("--distribution", choices=NAMES, default="A")
    r.add_argument("--estimator", choices=("oracle", "learned"), default="oracle")
    r.add_argument("--weights", help="estimator checkpoint (default: the one shipped with boxjax)")
    r.add_argument("--backend", choices=BACKENDS, default="native")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--rule", default="random", help="Pareto-front selection rule (planner.RULES)")
    r.add_argument("--samples", type=int, default=50, help="actions scored per control step")
    r.add_argument("--horizon", type=int, default=1, help="prediction steps per candidate")
    r.add_argument(
        "--planner",
        choices=("sampling", "paper"),
        default="sampling",
        help="paper: one-step Pareto random shooting (§2.3); sampling: predictive sampling over sequences",
    )
    r.add_argument(
        "--variant",
        choices=("slip", "paper"),
        default="slip",
        help="physics prior: slip (friction on the belt-box slip) or paper (calibrated force map, eqs. 4-14)",
    )
    r.add_argument("--plot", help="write yaw / balance / belts over the episode to this PNG")
    r.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    r.set_defaults(func=cmd_rotate)

    t = sub.add_parser("train-estimator", help="generate exploration data and train the estimator H")
    t.add_argument("--boxes", type=int, default=2000)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--out", required=True, help="directory for dataset.npz, estimator.npz, report.json")
    _simulation_args(t)
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_train_estimator)

    e = sub.add_parser("estimator-eval", help="accuracy of H on fresh random boxes")
    e.add_argument("--boxes", type=int, default=500)
    e.add_argument("--seed", type=int, default=1)
    e.add_argument("--weights", help="checkpoint (default: the one shipped with boxjax)")
    _simulation_args(e)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_estimator_eval)

    c = sub.add_parser("calibrate", help="calibrate the action -> force map by simulation (paper §2.4)")
    c.add_argument("--transitions", type=int, default=400, help="calibration transitions to collect")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", required=True, help="calibration file to write (.npz)")
    c.add_argument("--plot", help="write the force map (paper Fig. 3, all four forces) to this PNG")
    c.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    c.set_defaults(func=cmd_calibrate)

    d = sub.add_parser("demo", help="the whole pipeline on one box (what `make demo` runs)")
    d.add_argument("--distribution", choices=NAMES, default="A")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--plot", default="boxjax_demo.png", help="figure path ('' for none)")
    d.add_argument("--json", action="store_true")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        summary = args.func(args)
    except (ValueError, FileNotFoundError) as e:  # bad input (incl. CheckpointError): say what, no traceback
        sys.stderr.write(f"boxjax {args.command}: error: {e}\n")
        return 2
    if args.command != "demo" or args.json:
        _emit(summary, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
