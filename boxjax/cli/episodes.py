"""`boxjax simulate`, `rotate`, `demo` and `evaluate`: episodes on one box or many."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

from boxjax.cli import models as cli_models
from boxjax.cli.args import (
    at_least,
    box_options,
    config_option,
    exploration_option,
    fault_options,
    needs,
    option,
    output_options,
    planner_options,
    when,
    without,
)

CLI_SETTINGS = "cli.json"  # evaluate --out DIR: what the CLI adds to the evaluation (config, box, weights)


def load_config(args):
    """The Config of --config (the defaults without it) with --exploration applied; also checks an
    --animate path up front, so a bad one is refused before the episode runs."""
    import dataclasses

    from boxjax.config import DEFAULT

    if getattr(args, "animate", None):
        from boxjax.viz.animate import check_path

        check_path(args.animate)

    cfg = DEFAULT
    if getattr(args, "config", None) is not None:
        from boxjax import config_io

        cfg = config_io.load(args.config)
    if getattr(args, "exploration", None) is not None:
        cfg = cfg.replace(task=dataclasses.replace(cfg.task, exploration=args.exploration))
    contacts = cfg.gripper.mjx_box_contacts
    if contacts != DEFAULT.gripper.mjx_box_contacts and getattr(args, "backend", "native") != "mjx":
        raise ValueError(
            f"gripper.mjx_box_contacts = {contacts!r} (--config) chooses how MJX finds the box's contacts; "
            "it does nothing here (native MuJoCo uses its own collider): use it with --backend mjx"
        )
    return cfg


def the_box(args, cfg):
    """(name, MassDistribution) of --box FILE or --distribution NAME."""
    from boxjax import massdist

    if args.box is not None:
        from boxjax import boxfile

        return args.box, boxfile.load(args.box, cfg.box)
    return args.distribution, massdist.named(args.distribution, cfg.box)


def _say(args):
    return (lambda msg: None) if args.json else (lambda msg: sys.stdout.write(msg + "\n"))


def _figures(args, summary: dict, trace, cfg, truth, title: str) -> None:
    """--plot (time series) and --animate (top view) of one episode."""
    target = float(trace.s[0, 4]) + cfg.task.target_yaw_delta
    if args.plot:
        from boxjax.viz.plots import plot_episode

        summary["plot"] = plot_episode(trace, args.plot, cfg.task.balance_limit, target, title)
    if getattr(args, "animate", None):
        from boxjax.viz.animate import animate_episode

        if summary.get("success"):
            outcome = "success"
        elif summary.get("aborted"):
            outcome = "refused (hazardous)"
        else:
            outcome = summary.get("failed_reason") or "not finished"
        t0 = time.perf_counter()
        summary["animation"] = animate_episode(trace, args.animate, cfg, truth, title=title, outcome=outcome)
        summary["animation_s"] = time.perf_counter() - t0


# ----------------------------------------------------------------------------------------------------------
# simulate


def cmd_simulate(args) -> dict:
    import jax

    from boxjax import massdist
    from boxjax.sim import make_env
    from boxjax.sim.episode import naive_policy, random_policy, run_episode

    cfg = load_config(args)
    name, dist = the_box(args, cfg)
    key_reset, key_run = jax.random.split(jax.random.PRNGKey(args.seed))
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
        "distribution": name,
        "policy": args.policy,
        "backend": args.backend,
        "seed": args.seed,
        **state.summary(),
        "any_action_clipped": bool(trace.clipped.any()),
        "simulated_s": float(trace.time[-1]),
        "wall_s": wall,
        "episode_wall_s": trace.wall_s,
    }
    if args.config:
        summary["config"] = args.config
    _say(args)(f"{name}: {massdist.describe(dist, cfg.box)}")
    _figures(args, summary, trace, cfg, dist, f"{name}, policy {args.policy}, {args.backend}")
    return summary


# ----------------------------------------------------------------------------------------------------------
# rotate


def _controller_config(args):
    """The ControllerConfig of --planner / --variant / the planner's own options (`cli.args` has already
    refused the options the chosen planner does not use)."""
    from boxjax.control.config import ControllerConfig

    if args.planner == "simulator" and getattr(args, "estimator", None) == "learned":
        raise ValueError("--planner simulator needs the true simulator state: use --estimator oracle")
    sampling = None
    # --samples: the paper planner's actions per step, or the sampling planner's rollouts per step
    width = {} if args.samples is None else {"n_samples": args.samples}
    widths = width if args.planner == "sampling" else {}
    if widths and args.samples < 2:
        raise ValueError("--samples must be >= 2 with the sampling planner (the nominal and a rollout)")
    if args.gradient_steps is not None or widths:
        from boxjax.planners.sampling import SamplingOptions

        steps = {} if args.gradient_steps is None else {"gradient_steps": args.gradient_steps}
        sampling = SamplingOptions(**steps, **widths)
    from boxjax.control import monitor

    tip = {} if getattr(args, "tip_stop_cm", None) is None else {"tip_stop": args.tip_stop_cm / 100}
    if getattr(args, "tip_uncertainty", None):
        tip["tip_uncertainty"] = args.tip_uncertainty
    return ControllerConfig(
        rule=args.rule,
        **(width if args.planner == "paper" else {}),
        horizon=args.horizon,
        variant=args.variant,
        planner=args.planner,
        sampling=sampling,
        belief=getattr(args, "belief", None) or "mean",
        explore_guard=args.explore_guard or None,
        explore_guard_lead=args.guard_lead,
        explore_guard_stop=args.guard_stop,
        friction_set=tuple(args.friction_set) if getattr(args, "friction_set", None) else None,
        monitor=monitor.OFF if getattr(args, "monitor", "on") == "off" else monitor.MonitorConfig(**tip),
        delay_reference=getattr(args, "slow_when_late", 2),
    )


FAULT_FLAGS = {  # CLI option -> Faults field
    "obs_noise_mm": "obs_noise_mm",
    "obs_noise_deg": "obs_noise_deg",
    "obs_latency": "obs_latency",
    "drop_rate": "drop_rate",
    "action_latency": "action_latency",
    "friction": "friction",
    "friction_belt": "friction_belt",
    "mass_shift_kg": "mass_shift_kg",
}


def _faults(args):
    """The Faults of --config's [faults] table, overridden by the fault options given (validated by name:
    a bad level is refused before any episode runs)."""
    from boxjax import config_io
    from boxjax.sim.faults import Faults

    table = config_io.load_table(args.config, "faults") if getattr(args, "config", None) else {}
    given = {f: getattr(args, a) for a, f in FAULT_FLAGS.items() if getattr(args, a, None) is not None}
    return Faults.from_dict({**table, **given})


def _estimator(args, cfg):
    """ "oracle", or the learned H (the shipped one or --weights) after checking it fits the config."""
    if args.estimator != "learned":
        return "oracle"
    from boxjax.estimator.belief import learned_estimator

    cli_models.require_models(cfg, estimator=True, weights=args.weights, config_path=args.config)
    return learned_estimator(cfg, args.weights)


def _force_map(args, cfg, ctrl):
    """The paper prior's force map: --calibration FILE, or the shipped one if it fits the config."""
    if ctrl.variant != "paper":
        return None
    from boxjax.prior import force_map as calibrate

    if args.calibration is not None:
        return calibrate.load(args.calibration, cfg)[0]
    cli_models.require_models(cfg, calibration=True, config_path=args.config)
    return None


def _model_slot(args, ctrl, cfg):
    """(ctrl, model, adapter, summary fields) for --model prior|blackbox|pets: a learned black box (W, or
    the PETS ensemble) fills the planners' model slot (no exploration, no estimator), adapted online
    every --adapt-every steps."""
    from boxjax import blackbox

    if args.model == "prior":
        return ctrl, None, None, {"model": "prior"}

    if args.model == "blackbox":
        cli_models.require_models(
            cfg, baseline=True, baseline_weights=args.model_weights, config_path=args.config
        )
    model = blackbox.load_black_box(args.model, args.model_weights, cfg.gripper)
    every, epochs = args.adapt_every, args.adapt_epochs
    adapter = blackbox.adapter_for(model, epochs) if every > 0 else None
    ctrl = dataclasses.replace(ctrl, explore=False, adapt_every=every if adapter else 0)
    return ctrl, model, adapter, {"model": args.model, "adapt_every": every, "adapt_epochs": epochs}


def cmd_rotate(args) -> dict:
    import jax

    from boxjax import massdist
    from boxjax.control.episode import run_episode

    if args.replay is not None:
        return _replay(args)
    cfg = load_config(args)
    faults = _faults(args)
    if faults.any and args.backend != "native":
        raise ValueError(f"faults are simulated on the native backend only, not --backend {args.backend}")
    name, dist = the_box(args, cfg)
    ctrl = _controller_config(args)
    ctrl, model, adapter, slot = _model_slot(args, ctrl, cfg)
    estimator = _estimator(args, cfg) if model is None else "oracle"
    res = run_episode(
        cfg,
        dist,
        jax.random.PRNGKey(args.seed),
        estimator=estimator,
        ctrl=ctrl,
        backend=args.backend,
        force_map=_force_map(args, cfg, ctrl) if model is None else None,
        model=model,
        adapter=adapter,
        faults=faults,
    )
    summary = {
        "command": "rotate",
        **slot,
        "distribution": name,
        "estimator": args.estimator,
        "backend": args.backend,
        "seed": args.seed,
        "planner": args.planner,
        "variant": args.variant,
        "faults": faults.to_dict() if faults.any else None,
        **res.summary,
    }
    if args.config:
        summary["config"] = args.config
    return _finish_rotate(args, cfg, res, summary, name, massdist.describe(dist, cfg.box))


def _replay(args) -> dict:
    """`rotate --replay DIR --index K`: box K of an evaluation, with its key, estimator, controller and
    (from DIR/cli.json) the config, box file and estimator weights it ran with."""
    from boxjax import massdist
    from boxjax.experiments import evaluation as experiments

    if args.index is None:
        raise ValueError("--replay DIR needs --index K (the box's row in DIR/evaluation.json)")
    extra = {}
    if os.path.isfile(os.path.join(args.replay, CLI_SETTINGS)):
        with open(os.path.join(args.replay, CLI_SETTINGS)) as f:
            extra = json.load(f)
    cfg = load_config(args)  # the defaults (--config is refused with --replay); checks --animate
    if os.path.isfile(os.path.join(args.replay, "config.toml")):
        from boxjax import config_io

        cfg = config_io.load(os.path.join(args.replay, "config.toml"))
    estimator_fn = None
    if extra.get("weights"):
        from boxjax.estimator.belief import learned_estimator

        estimator_fn = learned_estimator(cfg, extra["weights"])
    res, st = experiments.replay(cfg, args.replay, args.index, estimator_fn=estimator_fn)
    name = f"{args.replay}#{args.index}"
    args.estimator = st["estimator"]
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
    return _finish_rotate(args, cfg, res, summary, name, massdist.describe(res.truth, cfg.box))


def _finish_rotate(args, cfg, res, summary: dict, name: str, described: str) -> dict:
    say = _say(args)
    say(f"{name}: {described}")
    if res.summary["aborted"]:
        say(res.summary["abort_reason"])
    title = f"rotate {name} ({args.estimator}), seed {summary['seed']}"
    _figures(args, summary, res.trace, cfg, res.truth, title)
    return summary


# ----------------------------------------------------------------------------------------------------------
# demo


def cmd_demo(args) -> dict:
    """The whole pipeline on one box: explore, estimate with the shipped H, refuse or rotate, plot."""
    import jax

    from boxjax import massdist
    from boxjax.control.episode import run_episode
    from boxjax.estimator.belief import learned_estimator

    cfg = load_config(args)
    t0 = time.perf_counter()
    name, truth = the_box(args, cfg)
    cli_models.require_models(cfg, estimator=True, weights=args.weights, config_path=args.config)
    say = _say(args)
    say(f"box {name} (hidden from the controller): {massdist.describe(truth, cfg.box)}")
    say("exploring (45 steps), estimating the mass distribution with the shipped H, then planning ...")
    res = run_episode(
        cfg, truth, jax.random.PRNGKey(args.seed), estimator=learned_estimator(cfg, args.weights)
    )
    s = res.summary
    if res.belief is not None:
        say(f"estimate: {massdist.describe(res.belief, cfg.box)}")
        say(
            f"  mass {float(res.belief.total_mass):.2f} kg (true {float(truth.total_mass):.2f}), "
            f"centre-of-mass error {s['com_error_cm']:.1f} cm, IoU {s['iou']:.2f}"
        )
    if s["aborted"]:
        say(s["abort_reason"])
    else:
        outcome = "turned the box by pi/2" if s["success"] else f"failed: {s['failed_reason']}"
        if s.get("safe_stop"):
            outcome = f"was stopped by the safety monitor ({s['safe_stop_reason']}), the box balanced,"
        say(
            f"MPC {outcome} in {s['steps']} steps ({s['steps'] - s['exploration_steps']} after exploring), "
            f"max balance error {100 * s['max_balance_error_m']:.1f} cm, "
            f"closest to tipping {1000 * s['min_stability_margin_m']:.0f} mm (true stability margin), "
            f"planning {s['plan_ms_median']:.2f} ms per step (median)"
        )
    summary = {
        "command": "demo",
        "distribution": name,
        "estimator": "learned",
        "backend": "native",
        "seed": args.seed,
        **s,
    }
    if s.get("monitor_stops"):
        say(f"the runtime safety monitor stopped the belts {s['monitor_stops']} time(s)")
    verdict = "refused (hazardous)" if s["aborted"] else ("success" if s["success"] else "failure")
    if s.get("safe_stop"):
        verdict = "safe stop"
    if args.plot and res.belief is not None:
        from boxjax.viz.plots import plot_demo

        target = float(res.trace.s[0, 4]) + cfg.task.target_yaw_delta
        summary["plot"] = plot_demo(
            truth,
            res.belief,
            res.trace,
            args.plot,
            cfg.box,
            cfg.task.balance_limit,
            target,
            f"box {name}: {verdict}",
        )
        say(f"figure: {summary['plot']}")
    if args.animate:
        _figures(
            argparse.Namespace(plot=None, animate=args.animate),
            summary,
            res.trace,
            cfg,
            truth,
            f"demo, box {name}: {verdict}",
        )
        say(f"animation: {summary['animation']}")
    summary["wall_s"] = time.perf_counter() - t0
    return summary


# ----------------------------------------------------------------------------------------------------------
# evaluate


def _evaluate_file_box(args, cfg, est, ctrl, faults):
    """--box FILE: --boxes episodes of that one box, episode j with key fold_in(split(seed)[2], j) as in
    `experiments.make_boxes`, as an `experiments.Evaluation` (so --out, --plot and --replay work)."""
    import jax
    import numpy as np

    from boxjax import massdist
    from boxjax.control.episode import run_episode
    from boxjax.experiments import evaluation as experiments

    _, dist = the_box(args, cfg)
    n = args.boxes
    key_ep = jax.random.split(jax.random.PRNGKey(args.seed), 3)[2]
    keys = np.stack([np.asarray(jax.random.key_data(jax.random.fold_in(key_ep, j))) for j in range(n)])
    hazardous = bool(massdist.is_hazardous(dist, cfg.box))
    boxes = experiments.EvalBoxes(
        occupancy=np.repeat(np.asarray(dist.occupancy, np.float32)[None], n, axis=0),
        total_mass=np.full(n, float(dist.total_mass), np.float32),
        hazardous=np.full(n, hazardous),
        family=np.asarray(["file"] * n),
        keys=keys.astype(np.uint32),
    )
    t0 = time.perf_counter()
    rows, balance, results = [], [], []
    for j in range(n):
        key = jax.random.wrap_key_data(boxes.keys[j])
        res = run_episode(cfg, boxes.dist(j), key, estimator=est, ctrl=ctrl, faults=faults)
        results.append(res)
        rows.append(experiments._row(j, boxes, res, cfg))
        balance.append(np.asarray(res.trace.balance_error, np.float32))
        if not args.quiet:
            sys.stderr.write(f"\r{args.box}: episode {j + 1}/{n}, {rows[-1]['outcome']}   ")
    if not args.quiet:
        sys.stderr.write("\n")
    summary = {
        **experiments.summarize(rows),
        **experiments.settings(args.estimator, ctrl, args.seed, "file", faults, safe_family="file"),
        "box": args.box,
        "wall_s": time.perf_counter() - t0,
    }
    actions = [np.asarray(r.trace.actions) for r in results]
    extra = {"actions": actions} if "actions" in experiments.Evaluation._fields else {}
    return experiments.Evaluation(summary, rows, boxes, balance, **extra)


def cmd_evaluate(args) -> dict:
    from boxjax import config_io
    from boxjax.control import batch
    from boxjax.experiments import distributed
    from boxjax.experiments import evaluation as experiments
    from boxjax.fileio import check_writable_dir

    distributed.check(args.coordinator, args.num_processes, args.process_id)
    main = not args.process_id  # the process that writes (the only one without --process-id)
    cfg = load_config(args)
    faults = _faults(args)
    if main and args.out and os.path.exists(args.out) and os.listdir(args.out) and not args.force:
        raise ValueError(f"--out {args.out} exists and is not empty; pass --force to overwrite its results")
    if main and args.out:  # found now, not after every episode has run
        check_writable_dir(args.out, "--out")
    if main and args.plot:
        check_writable_dir(os.path.dirname(os.path.abspath(args.plot)), "--plot's directory")
    ctrl = _controller_config(args)
    if args.backend == "mjx":
        from boxjax.control import device_loop

        why = device_loop.supports(ctrl, faults)
        if why is not None:
            raise ValueError(f"--backend mjx cannot run these episodes: {why}")
    if args.coordinator:  # the settings are checked: join the other processes (before JAX starts its backend)
        distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    if not args.one_at_a_time:
        batch.use_host_devices()  # one host device per core: the batched planner shards boxes over them
    if ctrl.variant == "paper":
        cli_models.require_models(cfg, calibration=True, config_path=args.config)
    est = _estimator(args, cfg)
    if args.box is not None:
        ev = _evaluate_file_box(args, cfg, est, ctrl, faults)
    else:
        ev = experiments.evaluate(
            cfg,
            args.boxes,
            args.hazardous,
            args.seed,
            estimator=args.estimator,
            ctrl=ctrl,
            family=args.hazard_family,
            safe_family=args.safe_family,
            progress=not args.quiet,
            estimator_fn=None if est == "oracle" else est,
            batched=False if args.one_at_a_time else None,
            slots=args.slots,
            faults=faults,
            backend=args.backend,
        )
    summary = {"command": "evaluate", **ev.summary}
    if args.config:
        summary["config"] = args.config
    if not main:  # process 0 writes the gathered results
        return {**summary, "process_id": args.process_id}
    if args.out:
        summary["files"] = experiments.write_evaluation(ev, args.out, " ".join(["boxjax", *sys.argv[1:]]))
        summary["files"]["config"] = config_io.save(os.path.join(args.out, "config.toml"), cfg)
        from boxjax.training.estimator import write_json

        settings = {"config": args.config, "box": args.box, "weights": args.weights}
        summary["files"]["cli"] = write_json(os.path.join(args.out, CLI_SETTINGS), settings)
    if args.plot:
        from boxjax.viz.plots import plot_evaluation

        summary["plot"] = plot_evaluation(ev, args.plot, cfg)
    if args.animate_failures:
        summary["failure_animations"] = experiments.animate_failures(ev, cfg, args.out)
    return summary


# ----------------------------------------------------------------------------------------------------------
# parsers


def belief_option(p, *used_by) -> None:
    """--belief: plan on H's estimate or over each of its ensemble members (ControllerConfig.belief)."""
    from boxjax.control.config import BELIEFS

    option(
        p,
        "--belief",
        default="mean",
        choices=BELIEFS,
        used_by=(*used_by, when("planner", "sampling", owner="the sampling planner")),
        help="mean: plan on H's estimate; ensemble: one prior per member of H's ensemble, costs averaged",
    )


def add_parsers(sub) -> None:
    from boxjax.sim import BACKENDS

    s = sub.add_parser("simulate", help="run the simulator with a simple policy")
    box_options(s, "uniform")
    option(
        s, "--policy", default="naive", choices=("naive", "random"), help="naive: belts opposite, constant"
    )
    option(s, "--steps", type=int, default=300, check=at_least(1), help="control steps (0.05 s each)")
    option(s, "--backend", default="native", choices=BACKENDS, help="simulator")
    option(s, "--seed", type=int, default=0, help="PRNG seed")
    option(
        s,
        "--speed",
        type=float,
        default=0.15,
        used_by=(when("policy", "naive"),),
        help="naive policy belt speed (m/s)",
    )
    config_option(s)
    output_options(s, "write yaw / balance / belt commands to this PNG")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("rotate", help="explore, estimate, then refuse or turn the box with the MPC")
    no_replay = without("replay", "it re-runs the evaluation's own episode")
    prior_only = when("model", "prior")
    box_options(r, "A", no_replay)
    option(
        r,
        "--estimator",
        default="oracle",
        choices=("oracle", "learned"),
        used_by=(no_replay, prior_only),
        help="the mass distribution the controller believes in",
    )
    option(
        r,
        "--weights",
        used_by=(no_replay, when("estimator", "learned")),
        help="estimator checkpoint for --estimator learned (default: the two shipped with boxjax, chosen by "
        "the sensor)",
    )
    option(r, "--replay", metavar="DIR", help="re-run one box of `boxjax evaluate --out DIR` (with --index)")
    option(
        r,
        "--index",
        type=int,
        used_by=(needs("replay", " DIR"),),
        help="the box's row in DIR/evaluation.json",
    )
    option(r, "--backend", default="native", choices=BACKENDS, used_by=(no_replay,), help="simulator")
    option(r, "--seed", type=int, default=0, used_by=(no_replay,), help="the episode's PRNG seed")
    planner_options(r, no_replay, prior=(prior_only,))
    fault_options(r, no_replay)
    belief_option(r, no_replay, prior_only, when("estimator", "learned", owner="the learned estimator"))
    option(
        r,
        "--model",
        default="prior",
        choices=("prior", "blackbox", "pets"),
        used_by=(no_replay,),
        help="the planners' model: the physics prior, or the black box W (baseline.py)",
    )
    blackbox = (no_replay, when("model", "blackbox", "pets"))
    option(r, "--model-weights", used_by=blackbox, help="W or PETS checkpoint (default: the shipped one)")
    option(
        r,
        "--adapt-every",
        type=int,
        default=20,
        used_by=blackbox,
        check=at_least(0),
        help="MPC steps between online adaptations of W (0: none)",
    )
    option(
        r,
        "--adapt-epochs",
        type=int,
        default=1,
        used_by=blackbox,
        check=at_least(0),
        help="epochs over the episode's data per adaptation of W",
    )
    config_option(r, without("replay", "it uses the evaluation's own config (DIR/config.toml)"))
    exploration_option(r, without("replay", "it uses the evaluation's own config (DIR/config.toml)"))
    output_options(r, "write yaw / balance / belts over the episode to this PNG")
    r.set_defaults(func=cmd_rotate)

    d = sub.add_parser("demo", help="the whole pipeline on one box (what `make demo` runs)")
    box_options(d, "A")
    option(d, "--weights", help="estimator checkpoint (default: the one shipped with boxjax)")
    option(d, "--seed", type=int, default=0, help="the episode's PRNG seed")
    config_option(d)
    exploration_option(d)
    option(d, "--plot", default="boxjax_demo.png", help="figure path ('' for none)")
    option(d, "--animate", metavar="FILE.gif", help="write a top-view animation of the episode")
    d.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    d.set_defaults(func=cmd_demo)

    v = sub.add_parser("evaluate", help="the controller on many random safe and hazardous boxes (paper §4.3)")
    no_file = without("box", "evaluate --box FILE runs that one box --boxes times")
    option(
        v,
        "--boxes",
        type=int,
        default=100,
        check=at_least(1),
        help="random label-safe boxes (with --box FILE: episodes of that box)",
    )
    option(v, "--box", metavar="FILE", help="your own box (.npz or .json): --boxes episodes of it")
    option(
        v,
        "--hazardous",
        type=int,
        default=0,
        used_by=(no_file,),
        check=at_least(0),
        help="random hazardous boxes (all mass in one quarter)",
    )
    option(
        v,
        "--hazard-family",
        default="gaussian",
        choices=("gaussian", "items", "slabs", "scatter"),
        used_by=(no_file, lambda a: None if a.hazardous > 0 else "does nothing with --hazardous 0"),
        help="gaussian: massdist.sample_hazardous (H's training family); items: 1-16 voxels; slabs: a wall "
        "1-2 voxels thick; scatter: loose contents, held out of all training and tuning",
    )
    option(
        v,
        "--safe-family",
        default="gaussian",
        choices=("gaussian", "items", "slabs", "scatter"),
        used_by=(no_file,),
        help="the safe boxes' family (the label-safe draws of its free sampler): gaussian: massdist.sample "
        "(paper §4.3, what H and the controller were shaped on); items, slabs; scatter: held out",
    )
    option(v, "--seed", type=int, default=0, help="draws the boxes and every episode's key")
    option(v, "--estimator", default="oracle", choices=("oracle", "learned"), help="oracle or the learned H")
    option(
        v,
        "--weights",
        used_by=(when("estimator", "learned"),),
        help="estimator checkpoint (default: shipped)",
    )
    planner_options(v, calibration=False)
    fault_options(v)
    belief_option(v, when("estimator", "learned", owner="the learned estimator"))
    batchable = when("planner", "sampling", "paper", owner="the batched jnp planners")
    option(
        v,
        "--one-at-a-time",
        action="store_true",
        used_by=(batchable, no_file),
        help="run the episodes one by one (controller.run_episode) instead of batched (boxjax.control.batch)",
    )
    option(
        v,
        "--backend",
        default="native",
        choices=BACKENDS,
        used_by=(no_file, without("one_at_a_time", "the episodes run one by one on native MuJoCo")),
        help="native: MuJoCo on the host, the planner batched (default); mjx: the whole closed loop on the "
        "device (boxjax.control.device_loop; no faults)",
    )
    option(
        v,
        "--slots",
        type=int,
        used_by=(batchable, no_file, without("one_at_a_time", "the episodes run one by one")),
        check=at_least(1),
        help="boxes per batched planner call (default 8 per device; --backend mjx: 64 per CPU device, at "
        "most 256, and 1024 per accelerator)",
    )
    option(
        v,
        "--coordinator",
        metavar="HOST:PORT",
        used_by=(no_file,),
        help="run across processes or hosts (jax.distributed): process 0's address, with --num-processes "
        "and --process-id; each process runs its share of the boxes, process 0 writes them all",
    )
    option(v, "--num-processes", type=int, used_by=(needs("coordinator"),), help="processes in the run")
    option(v, "--process-id", type=int, used_by=(needs("coordinator"),), help="this process, 0 .. N - 1")
    option(v, "--out", help="directory: evaluation.json, boxes.npz (for rotate --replay), config.toml")
    option(v, "--force", action="store_true", used_by=(needs("out"),), help="overwrite a non-empty --out")
    option(
        v,
        "--animate-failures",
        action="store_true",
        used_by=(needs("out"), when("backend", "native", owner="evaluations on the native backend")),
        help="a top-view GIF of every failed episode in OUT/failures/ (re-simulated from its actions)",
    )
    option(v, "--plot", help="balance error over time (paper Fig. 3c) and outcomes over the centre of mass")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    config_option(v)
    exploration_option(v)
    v.add_argument("--json", action="store_true", help="print the summary as one JSON line")
    v.set_defaults(func=cmd_evaluate)
