"""The `boxjax` command line.

    boxjax simulate --distribution D --policy naive --steps 300 [--backend native|mjx] [--plot f.png] [--json]
    boxjax rotate --distribution C --estimator oracle|learned [--planner sampling|paper] [--seed S]
        [--plot f.png] [--json]
    boxjax demo [--distribution A|B|C|D|uniform] [--plot boxjax_demo.png] [--json]
    boxjax train-estimator [--boxes 2000] [--seed S] --out DIR [--backend native|mjx] [--chunk 500] [--json]
    boxjax estimator-eval [--boxes 500] [--seed S] [--weights FILE] [--backend native|mjx] [--chunk 500]
        [--json]
    boxjax calibrate [--transitions 400] [--seed S] --out FILE [--plot FILE.png] [--json]
    boxjax train-baseline [--distribution A] [--episodes 200] [--seed 0] --out DIR [--data FILE] [--json]
    boxjax rotate ... --model blackbox [--model-weights FILE] [--adapt-every 20] [--adapt-epochs 1]
    boxjax compare [--seeds 5] [--boxes A B C D] [--methods prior blackbox] [--out DIR] [--json]

With --json the last line printed is one JSON object (the summary); everything else goes before it.
"""

from __future__ import annotations

import argparse
import json
import os
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
    from boxjax.controller import run_episode

    cfg = DEFAULT
    if args.replay is not None and (args.model != "prior" or args.model_weights is not None):
        raise ValueError(
            "--replay runs the evaluation's own episode; --model / --model-weights would do nothing"
        )
    if args.replay is not None:
        return _replay(args, cfg)
    if args.index is not None:
        raise ValueError("--index picks a box of --replay DIR; it does nothing without --replay")
    args.distribution = args.distribution or "A"
    args.estimator = args.estimator or "oracle"
    dist = massdist.named(args.distribution, cfg.box)
    estimator = "oracle"
    if args.estimator == "learned":
        from boxjax.controller import learned_estimator

        estimator = learned_estimator(cfg, args.weights)
    ctrl = _controller_config(args)
    ctrl, model, adapter, slot = _model_slot(args, ctrl)
    res = run_episode(
        cfg,
        dist,
        jax.random.PRNGKey(args.seed),
        estimator=estimator,
        ctrl=ctrl,
        backend=args.backend,
        model=model,
        adapter=adapter,
    )
    summary = {
        "command": "rotate",
        **slot,
        "distribution": args.distribution,
        "estimator": args.estimator,
        "backend": args.backend,
        "seed": args.seed,
        "planner": args.planner,
        "variant": args.variant,
        **res.summary,
    }
    summary = _finish_rotate(args, cfg, res, summary, massdist.describe(dist, cfg.box))
    return summary


def _replay(args, cfg) -> dict:
    """`rotate --replay DIR --index K`: box K of an evaluation, with its key, estimator and controller."""
    from boxjax import experiments, massdist

    given = [f"--{n}" for n in ("distribution", "estimator", "weights") if getattr(args, n) is not None]
    given += [
        f"--{n.replace('_', '-')}"
        for n, d in (
            ("seed", 0),
            ("planner", "sampling"),
            ("variant", "slip"),
            ("rule", "random"),
            ("samples", 50),
            ("horizon", 1),
            ("backend", "native"),
            ("gradient_steps", None),
        )
        if getattr(args, n) != d
    ]
    if given:
        raise ValueError(f"--replay runs the evaluation's own episode; {', '.join(given)} would do nothing")
    if args.index is None:
        raise ValueError("--replay DIR needs --index K (the box's row in DIR/evaluation.json)")
    res, st = experiments.replay(cfg, args.replay, args.index)
    args.distribution, args.estimator = f"{args.replay}#{args.index}", st["estimator"]
    summary = {
        "command": "rotate",
        "replay": args.replay,
        "index": args.index,
        "estimator": st["estimator"],
        "seed": st["seed"],
        "planner": st["controller"]["planner"],
        "variant": st["controller"]["variant"],
        "outcome": experiments.outcome(res.summary),
        **res.summary,
    }
    return _finish_rotate(args, cfg, res, summary, massdist.describe(res.truth, cfg.box))


def _finish_rotate(args, cfg, res, summary: dict, described: str) -> dict:
    seed = summary["seed"]
    if not args.json:
        sys.stdout.write(f"{args.distribution}: {described}\n")
        if res.summary["aborted"]:
            sys.stdout.write(res.summary["abort_reason"] + "\n")
    if args.plot:
        from boxjax.plots import plot_episode

        title = f"rotate {args.distribution} ({args.estimator}), seed {seed}"
        target = float(res.trace.s[0, 4]) + cfg.task.target_yaw_delta
        summary["plot"] = plot_episode(res.trace, args.plot, cfg.task.balance_limit, target, title)
    return summary


def _model_slot(args, ctrl):
    """(ctrl, model, adapter, summary fields) for `rotate --model prior|blackbox`: the black box W fills
    the planners' model slot (no exploration, no estimator), adapted online every --adapt-every steps
    (default 20, 0: never) for --adapt-epochs epochs (default 1)."""
    import dataclasses

    if args.model == "prior":
        given = [
            f"--{n}"
            for n in ("adapt-every", "adapt-epochs", "model-weights")
            if getattr(args, n.replace("-", "_")) is not None
        ]
        if given:
            raise ValueError(
                f"{', '.join(given)}: options of --model blackbox; --model prior has no W to adapt"
            )
        return ctrl, None, None, {"model": "prior"}
    from boxjax import baseline

    if args.estimator != "oracle" or args.variant != "slip":
        raise ValueError("--model blackbox plans with W alone: --estimator and --variant do nothing with it")
    every = 20 if args.adapt_every is None else args.adapt_every
    epochs = 1 if args.adapt_epochs is None else args.adapt_epochs
    if every < 0 or epochs < 0:
        raise ValueError(f"--adapt-every and --adapt-epochs must be >= 0, got {every}, {epochs}")
    model = baseline.default_model() if args.model_weights is None else baseline.load(args.model_weights)
    adapter = baseline.make_adapter(epochs) if every > 0 and epochs > 0 else None
    ctrl = dataclasses.replace(ctrl, explore=False, adapt_every=every if adapter else 0)
    return ctrl, model, adapter, {"model": "blackbox", "adapt_every": every, "adapt_epochs": epochs}


def cmd_train_baseline(args) -> dict:
    from boxjax import baseline_train

    if os.path.exists(os.path.join(args.out, "baseline.npz")) and not args.force:
        raise ValueError(f"--out {args.out} already holds baseline.npz; pass --force to overwrite it")
    return baseline_train.train_baseline(
        distribution=args.distribution,
        n_episodes=args.episodes,
        seed=args.seed,
        out=args.out,
        progress=not args.json,
        data=args.data,
    )


def cmd_compare(args) -> dict:
    """Paper Table 1: the physics prior (learned H) and the black box W (online adaptation), same planner."""
    import json as _json

    from boxjax import comparison
    from boxjax.config import DEFAULT

    if args.seeds < 1 or args.adapt_every < 0 or args.adapt_epochs < 0:
        raise ValueError("--seeds must be >= 1, --adapt-every and --adapt-epochs >= 0")
    model = None
    if "blackbox" in args.methods:
        from boxjax import baseline

        model = baseline.default_model() if args.model_weights is None else baseline.load(args.model_weights)
    res = comparison.compare(DEFAULT, tuple(args.boxes), args.seeds, tuple(args.methods), model,
                             args.adapt_every, args.adapt_epochs, progress=not args.json)  # fmt: skip
    if args.out:
        from boxjax.fileio import atomic_path

        os.makedirs(args.out, exist_ok=True)
        with atomic_path(os.path.join(args.out, "comparison.json"), suffix=".json") as tmp:
            with open(tmp, "w") as f:
                _json.dump(res, f, indent=1)
        res["file"] = os.path.join(args.out, "comparison.json")
    if not args.json:
        sys.stdout.write(comparison.format_table(res["table"]) + "\n")
    return {"command": "compare", **res}


def _controller_config(args):
    """The ControllerConfig of --planner / --variant / paper-planner options, refusing options the chosen
    planner does not use."""
    from boxjax.controller import ControllerConfig

    if args.planner == "simulator" and getattr(args, "estimator", None) == "learned":
        raise ValueError("--planner simulator needs the true simulator state: use --estimator oracle")
    if args.planner != "paper":
        for name, default in (("rule", "random"), ("samples", 50), ("horizon", 1)):
            if getattr(args, name) != default:
                raise ValueError(
                    f"--{name} is an option of the paper planner; it does nothing for "
                    f"--planner {args.planner}"
                )
    if args.samples < 1 or args.horizon < 1:
        raise ValueError(f"--samples and --horizon must be >= 1, got {args.samples}, {args.horizon}")
    sampling = None
    if args.gradient_steps is not None:
        if args.planner != "sampling":
            raise ValueError(
                "--gradient-steps is an option of the sampling planner; it does nothing for "
                f"--planner {args.planner}"
            )
        if args.gradient_steps < 0:
            raise ValueError(f"--gradient-steps must be >= 0, got {args.gradient_steps}")
        from boxjax.sampling_planner import SamplingOptions

        sampling = SamplingOptions(gradient_steps=args.gradient_steps)
    return ControllerConfig(
        rule=args.rule,
        n_samples=args.samples,
        horizon=args.horizon,
        variant=args.variant,
        planner=args.planner,
        sampling=sampling,
    )


def cmd_evaluate(args) -> dict:
    from boxjax import experiments
    from boxjax.config import DEFAULT

    cfg = DEFAULT
    if args.boxes < 1:
        raise ValueError(f"--boxes must be >= 1, got {args.boxes}")
    if args.hazardous < 0:
        raise ValueError(f"--hazardous must be >= 0, got {args.hazardous}")
    if args.out and os.path.exists(args.out) and os.listdir(args.out) and not args.force:
        raise ValueError(f"--out {args.out} exists and is not empty; pass --force to overwrite its results")
    ctrl = _controller_config(args)
    ev = experiments.evaluate(
        cfg,
        args.boxes,
        args.hazardous,
        args.seed,
        estimator=args.estimator,
        ctrl=ctrl,
        family=args.hazard_family,
        progress=not args.quiet,
    )
    summary = {"command": "evaluate", **ev.summary}
    if args.out:
        summary["files"] = experiments.write_evaluation(ev, args.out, " ".join(["boxjax", *sys.argv[1:]]))
    if args.plot:
        from boxjax.plots import plot_evaluation

        summary["plot"] = plot_evaluation(ev, args.plot, cfg)
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


def _planner_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--gradient-steps",
        type=int,
        default=None,
        help="sampling planner: Adam steps through the prior on the chosen sequence (default 5; 0: none)",
    )
    from boxjax.controller import PLANNERS

    p.add_argument("--rule", default="random", help="Pareto-front selection rule (planner.RULES)")
    p.add_argument("--samples", type=int, default=50, help="actions scored per control step")
    p.add_argument("--horizon", type=int, default=1, help="prediction steps per candidate")
    p.add_argument(
        "--planner",
        choices=PLANNERS,
        default="sampling",
        help="paper: one-step Pareto random shooting (§2.3); sampling: predictive sampling over sequences; "
        "simulator: privileged reference that plans with MuJoCo itself (oracle estimator only, slow)",
    )
    p.add_argument(
        "--variant",
        choices=("slip", "paper"),
        default="slip",
        help="physics prior: slip (friction on the belt-box slip) or paper (calibrated force map, eqs. 4-14)",
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
    r.add_argument("--distribution", choices=NAMES, default=None, help="named box (default A)")
    r.add_argument("--estimator", choices=("oracle", "learned"), default=None, help="default oracle")
    r.add_argument("--weights", help="estimator checkpoint (default: the one shipped with boxjax)")
    r.add_argument(
        "--replay", metavar="DIR", help="re-run one box of `boxjax evaluate --out DIR` (with --index)"
    )
    r.add_argument("--index", type=int, help="the box's index in DIR/evaluation.json")
    r.add_argument("--backend", choices=BACKENDS, default="native")
    r.add_argument("--seed", type=int, default=0)
    _planner_args(r)
    r.add_argument(
        "--model",
        choices=("prior", "blackbox"),
        default="prior",
        help="the planners' model: the physics prior, or the black box W (baseline.py)",
    )
    r.add_argument("--model-weights", help="W checkpoint for --model blackbox (default: the shipped one)")
    r.add_argument(
        "--adapt-every",
        type=int,
        default=None,
        help="--model blackbox: MPC steps between online adaptations of W (default 20; 0: none)",
    )
    r.add_argument(
        "--adapt-epochs",
        type=int,
        default=None,
        help="--model blackbox: epochs over the episode's data per adaptation (default 1)",
    )
    r.add_argument("--plot", help="write yaw / balance / belts over the episode to this PNG")
    r.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    r.set_defaults(func=cmd_rotate)

    b = sub.add_parser("train-baseline", help="collect episodes of one box and train the black box W")
    b.add_argument("--distribution", choices=NAMES, default="A", help="the single training environment")
    b.add_argument("--episodes", type=int, default=200)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", required=True, help="directory for baseline.npz, dataset.npz, report.json")
    b.add_argument("--data", help="train on the dataset.npz of an earlier run instead of collecting")
    b.add_argument("--force", action="store_true", help="overwrite OUT/baseline.npz")
    b.add_argument("--json", action="store_true", help="print the report as one JSON line (no progress bars)")
    b.set_defaults(func=cmd_train_baseline)

    m = sub.add_parser("compare", help="paper Table 1: physics prior vs black box W on boxes A-D")
    m.add_argument("--seeds", type=int, default=5)
    m.add_argument("--boxes", nargs="+", choices=NAMES, default=["A", "B", "C", "D"])
    m.add_argument("--methods", nargs="+", choices=("prior", "blackbox"), default=["prior", "blackbox"])
    m.add_argument("--model-weights", help="W checkpoint (default: the shipped one)")
    m.add_argument(
        "--adapt-every", type=int, default=20, help="steps between W's online adaptations (0: none)"
    )
    m.add_argument("--adapt-epochs", type=int, default=1)
    m.add_argument("--out", help="directory for comparison.json")
    m.add_argument("--json", action="store_true", help="print the result as one JSON line")
    m.set_defaults(func=cmd_compare)

    v = sub.add_parser("evaluate", help="the controller on many random safe and hazardous boxes (paper §4.3)")
    v.add_argument("--boxes", type=int, default=100, help="random label-safe boxes")
    v.add_argument(
        "--hazardous", type=int, default=0, help="random hazardous boxes (all mass in one quarter)"
    )
    v.add_argument(
        "--hazard-family",
        choices=("gaussian", "items"),
        default="gaussian",
        help="gaussian: massdist.sample_hazardous (H's training family); items: 1-16 voxels",
    )
    v.add_argument("--seed", type=int, default=0, help="draws the boxes and every episode's key")
    v.add_argument("--estimator", choices=("oracle", "learned"), default="oracle")
    _planner_args(v)
    v.add_argument("--out", help="directory: evaluation.json (one row per box) and boxes.npz (for --replay)")
    v.add_argument("--force", action="store_true", help="overwrite the results in a non-empty --out")
    v.add_argument(
        "--plot", help="balance error over time (paper Fig. 3c) and outcomes over the centre of mass"
    )
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    v.set_defaults(func=cmd_evaluate)

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
