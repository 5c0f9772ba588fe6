"""Planner latency: one MPC step with the physics prior, for the paper planner and the sampling planners.

Prints ONE JSON object:
  * the paper's planner (sample restricted actions, predict each with the prior, Pareto front, select):
    compile time, per-step latency for 50 actions (median and p99 over >= 200 calls after compile, each
    call waited on with block_until_ready), and the latency for 4096 actions;
  * the sampling planner (the controller's default, `sampling_planner`): compile time and per-step
    latency at its default (64 sequences x 10 steps = 640 prior predictions + 5 gradient steps) and
    for each setting of `SAMPLING_CONFIGS` (the planner study of the README), all in one run;
  * the runtime safety monitor (`boxjax.control.monitor`): what it adds to a control step, its jitted
    check (two 10-step prior rollouts) plus the host-side decision, and the latency compensation
    (`planning.compensate`, 2 steps), beside the default sampling planner's step in the same run;
  * the backend / device and the machine's load.
  * the tipping barrier's static margin (`--margin-only`): the default planner's step with each
    `PriorParams.margin`, one box and 16 vmapped, the calls interleaved;
  * robust planning over three belt frictions (`--friction-set-only`): the default planner's step with
    the prior and with the Mixture, same run.
  * the program's structure (`--structure-only`, on every kind of device present: the accelerator where
    there is one, then the CPU; each device's part also on stderr as it ends): the default planner, the
    one without gradient steps and the wide ones (STRUCTURE_PLANNERS; `--structure-planners` picks), with
    the prior's step looped (`PriorParams(unroll=False)`) and unrolled (the default; `--unrolled-only`),
    for one call and 16 calls vmapped (one box, 16 keys: the width of a batched evaluation's call):
    compile time, latency (the variants' calls interleaved, median), and the operations and loop
    iterations one call runs, counted from the compiled HLO (`_hlo.dynamic_ops`; on a GPU each operation
    is a kernel launch and each loop iteration a read-back of its condition), and for one call the
    functions the operations come from (`_hlo.by_source`). `--structure-devices accelerator|cpu`: one.
Run: python benchmarks/planner.py [--calls 300] [--variant slip|paper] [--rule random] [--monitor-only]
     [--friction-set-only] [--structure-only [--structure-devices all|accelerator|cpu]
     [--structure-planners NAME ...] [--unrolled-only]]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _hlo import by_source, dynamic_ops  # noqa: E402

from boxjax import massdist, planning, prior  # noqa: E402
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.control import monitor  # noqa: E402
from boxjax.planners import paper as planner  # noqa: E402
from boxjax.planners import sampling as sp  # noqa: E402
from boxjax.prior import force_map as calibrate  # noqa: E402

# Sampling-planner settings timed (SamplingOptions overrides; "default" is the class default).
SAMPLING_CONFIGS = {
    "default": {},  # 64 x 10, L1 pose cost, 5 gradient steps, turn-end term
    "no_turn_end": {"w_reach": 0.0},
    "no_gradient": {"gradient_steps": 0},
    "quadratic_pose_no_gradient": {"pose_cost": "quadratic", "gradient_steps": 0},
    "n256_no_gradient": {"n_samples": 256, "gradient_steps": 0},
    "mppi_no_gradient": {"update": "mppi", "gradient_steps": 0},
    "cem_2x32_no_gradient": {"n_samples": 32, "update": "cem", "iterations": 2, "gradient_steps": 0},
    "n32": {"n_samples": 32},
    "knots4_no_gradient": {"n_knots": 4, "gradient_steps": 0},
    "n128_h20_knots4_no_gradient": {"n_samples": 128, "horizon": 20, "n_knots": 4, "gradient_steps": 0},
}


def _latency(fn, args_for_call, calls: int) -> dict:
    times = []
    for i in range(calls):
        args = args_for_call(i)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    ms = 1e3 * np.asarray(times)
    return {
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "calls": calls,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--calls", type=int, default=300, help="timed calls per setting (>= 200)")
    ap.add_argument("--variant", default="slip", choices=prior.VARIANTS)
    ap.add_argument("--rule", default="random", choices=planner.RULES)
    ap.add_argument("--horizon", type=int, default=1)
    ap.add_argument("--monitor-only", action="store_true", help="time the monitor (and the default planner)")
    ap.add_argument(
        "--friction-set-only",
        action="store_true",
        help="time robust planning over a friction set (ControllerConfig.friction_set) beside the default",
    )
    ap.add_argument(
        "--margin-only",
        action="store_true",
        help="the default planner's step with each stability margin (PriorParams.margin), one box and 16",
    )
    ap.add_argument(
        "--structure-only",
        action="store_true",
        help="the planners' operations, loops, compile time and latency (STRUCTURE_PLANNERS), every device",
    )
    ap.add_argument(
        "--structure-devices",
        choices=("all", "accelerator", "cpu"),
        default="all",
        help="with --structure-only: every kind of device (the accelerator first), or one (default all)",
    )
    ap.add_argument(
        "--structure-planners",
        nargs="+",
        choices=tuple(STRUCTURE_PLANNERS),
        help="with --structure-only: only these planners (default all)",
    )
    ap.add_argument(
        "--unrolled-only",
        action="store_true",
        help="with --structure-only: only the prior's unrolled step (the default), not the looped one",
    )
    args = ap.parse_args()
    structure_opts = (args.structure_devices != "all", args.structure_planners, args.unrolled_only)
    if any(structure_opts) and not args.structure_only:
        ap.error("--structure-devices, --structure-planners and --unrolled-only need --structure-only")
    devices = _device_kinds()
    if args.structure_devices != "all":
        devices = [d for d in devices if (d.platform == "cpu") == (args.structure_devices == "cpu")]
        if not devices:
            ap.error(f"--structure-devices {args.structure_devices}: none here (JAX sees {jax.devices()})")
    calls = max(args.calls, 200)
    cfg = DEFAULT
    box, gripper = cfg.box, cfg.gripper
    masses = massdist.voxel_masses(massdist.named("A", box), box)
    fm = calibrate.ForceMap(
        grid=jnp.asarray(calibrate.default_grid(gripper, 9)),
        mean=jnp.zeros((4, 9)),
        std=jnp.zeros((4, 9)),
        count=jnp.ones((4, 9), jnp.int32),
    )
    model = prior.make_prior(masses, fm, box, gripper, variant=args.variant)
    # A box part-way through a turn: moving, rotating, belts running.
    s = jnp.array([-0.11, 0.12, 0.01, -0.005, 0.4])
    window = jnp.stack(
        [s - 2 * jnp.array([0, 0, 1e-3, 5e-4, 0.02]), s - jnp.array([0, 0, 1e-3, 5e-4, 0.02]), s]
    )
    speed = jnp.array([0.12, -0.1])
    target = jnp.float32(np.pi / 2)
    keys = jax.random.split(jax.random.key(0), calls)

    out = {
        "benchmark": "planner step: paper (random shooting + Pareto) and predictive sampling, physics prior",
        "variant": args.variant,
        "prior_params": {k: v for k, v in vars(model.params).items()},
        "rule": args.rule,
        "horizon": args.horizon,
    }
    if args.structure_only:
        planners = {
            name: (kw, tuple(u for u in unrolls if u or not args.unrolled_only), vmapped)
            for name, (kw, unrolls, vmapped) in STRUCTURE_PLANNERS.items()
            if args.structure_planners is None or name in args.structure_planners
        }
        out["structure"] = {}
        for d in devices:  # the accelerator first: a run cut short still has its numbers on stderr
            res = _structure(cfg, masses, window, speed, target, keys, min(calls, 100), d, planners)
            print(json.dumps({d.platform: res}), file=sys.stderr, flush=True)
            out["structure"][d.platform] = res
        _finish(out)
        return
    if args.margin_only:
        out["margin"] = _margins(cfg, masses, window, speed, target, keys, min(calls, 200))
        _finish(out)
        return
    if args.friction_set_only:
        out["friction_set"] = _friction_set(cfg, model, window, speed, target, keys, min(calls, 200))
        _finish(out)
        return
    if args.variant == "slip":
        out["monitor"] = _monitor(cfg, model, window, speed, target, keys, min(calls, 300))
    if args.monitor_only:
        _finish(out)
        return
    plan50 = planner.make_planner(cfg, n_samples=50, rule=args.rule, horizon=args.horizon)
    t0 = time.perf_counter()
    jax.block_until_ready(plan50(keys[0], model, window, speed, target))
    out["compile_s_50"] = time.perf_counter() - t0
    out["latency_50_actions"] = _latency(plan50, lambda i: (keys[i], model, window, speed, target), calls)

    # 4096 actions: a finer restricted set (63 x 63 speed increments + 2 x 64 position steps = 4097).
    big = planner.action_set(gripper, n_v=63, n_p=64)
    plan4096 = planner.make_planner(cfg, actions=big, n_samples=4096, rule=args.rule, horizon=args.horizon)
    t0 = time.perf_counter()
    jax.block_until_ready(plan4096(keys[0], model, window, speed, target))
    out["compile_s_4096"] = time.perf_counter() - t0
    out["latency_4096_actions"] = _latency(
        plan4096, lambda i: (keys[i], model, window, speed, target), min(calls, 50)
    )

    # The sampling planners ("slip" prior only: they plan full 4-d actions), each option set by name.
    if args.variant == "slip":
        for name, kw in SAMPLING_CONFIGS.items():
            opts = sp.SamplingOptions(**kw)
            splan = sp.make_sampling_planner(cfg, opts)
            nominal = sp.initial_nominal(cfg, opts, speed)
            t0 = time.perf_counter()
            jax.block_until_ready(splan(keys[0], model, window, speed, target, nominal))
            out[f"sampling_{name}"] = {
                "options": kw,
                "compile_s": time.perf_counter() - t0,
                "predictions_per_step": opts.n_samples * opts.horizon * opts.iterations,
                **_latency(
                    splan,
                    lambda i, nom=nominal: (keys[i], model, window, speed, target, nom),
                    min(calls, 100),
                ),
            }
    _finish(out)


def _monitor(cfg, model, window, speed, target, keys, calls: int) -> dict:
    """The monitor's cost per control step, and the default planner's step it is added to (same run)."""
    opts = sp.SamplingOptions()
    splan = sp.make_sampling_planner(cfg, opts)
    nominal = sp.initial_nominal(cfg, opts, speed)
    action = jnp.array([0.15, -0.15, 0.002, 0.002], jnp.float32)
    horizon = monitor.MonitorConfig().horizon
    in_flight = jnp.zeros((2, 4), jnp.float32)
    compensate = jax.jit(planning.compensate)
    res = {"horizon": horizon}
    checked = lambda i: (cfg, model, window, speed, action, horizon)  # noqa: E731
    sigma_spread = np.array([0.004, 0.004, 0.01, monitor.tip_drag(monitor.MonitorConfig())], np.float32)
    for name, fn, args_for in (
        ("planner_default", splan, lambda i: (keys[i], model, window, speed, target, nominal)),
        ("check", monitor.check, checked),
        # with the tipping watch (`MonitorConfig.tip_stop`): the stability margin along the action's rollout
        ("check_tip", partial(monitor.check, tip=True), checked),
        # the "sigma" watch (`MonitorConfig.tip_uncertainty`): the margin at 27 poses around every state
        ("check_tip_sigma", partial(monitor.check, tip="sigma", tip_spread=sigma_spread), checked),
        ("compensate_2_steps", compensate, lambda i: (model, window, speed, in_flight)),
    ):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args_for(0)))
        res[name] = {"compile_s": time.perf_counter() - t0, **_latency(fn, args_for, calls)}

    def step(i):  # the whole per-step cost as the episode loop pays it: check, to host, decide
        c = monitor.check(cfg, model, window, speed, action, horizon)
        return mon.decide(i, np.asarray(action), monitor.to_host(c), 0.002, 0, np.asarray(speed))

    mon = monitor.Monitor(cfg, monitor.MonitorConfig(stop_at=1.0, resume_below=0.99))
    res["check_and_decide"] = _latency(step, lambda i: (i,), calls)
    res["added_fraction_of_planner_step"] = (
        res["check_and_decide"]["median_ms"] / res["planner_default"]["median_ms"]
    )
    return res


def _friction_set(cfg, model, window, speed, target, keys, calls: int) -> dict:
    """The default sampling planner's step with the prior, and with a `planning.Mixture` of the prior at
    three belt frictions (`ControllerConfig.friction_set`, each candidate scored over the three), same run."""
    import dataclasses

    opts = sp.SamplingOptions()
    splan = sp.make_sampling_planner(cfg, opts)
    nominal = sp.initial_nominal(cfg, opts, speed)
    frictions = (0.35, 0.5, 0.65)
    mixture = planning.Mixture(
        tuple(
            dataclasses.replace(model, gripper=dataclasses.replace(model.gripper, friction=m))
            for m in frictions
        )
    )
    res = {"frictions": frictions}
    for name, m in (("prior", model), ("friction_set", mixture)):
        t0 = time.perf_counter()
        jax.block_until_ready(splan(keys[0], m, window, speed, target, nominal))
        res[name] = {
            "compile_s": time.perf_counter() - t0,
            **_latency(splan, lambda i, m=m: (keys[i], m, window, speed, target, nominal), calls),
        }
    res["ratio_median"] = res["friction_set"]["median_ms"] / res["prior"]["median_ms"]
    return res


def _margins(cfg, masses, window, speed, target, keys, calls: int, boxes: int = 16) -> dict:
    """The default sampling planner's step with each `PriorParams.margin` (the tipping barrier's static
    margin on every predicted state), for one box and vmapped over `boxes` (a batched evaluation's call),
    compile apart, the variants' calls interleaved (median)."""
    opts = sp.SamplingOptions()
    splan = sp.make_sampling_planner(cfg, opts)
    nominal = sp.initial_nominal(cfg, opts, speed)
    wide = jax.jit(jax.vmap(splan, in_axes=(0, 0, None, None, None, None)))
    res = {}
    fns = {}
    for m in prior.MARGINS:
        model = prior.make_prior(masses, None, cfg.box, cfg.gripper, prior.PriorParams(margin=m))
        stacked = planning.stack([model] * boxes)
        fns[m] = (
            lambda i, model=model: splan(keys[i], model, window, speed, target, nominal),
            lambda i, stacked=stacked: wide(
                jax.random.split(keys[i], boxes), stacked, window, speed, target, nominal
            ),
        )
        res[m] = {}
        for kind, fn in zip(("one_box", f"{boxes}_boxes"), fns[m], strict=True):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(0))
            res[m][kind] = {"compile_s": time.perf_counter() - t0, "times": []}
    for i in range(calls):
        for m in prior.MARGINS:
            for kind, fn in zip(("one_box", f"{boxes}_boxes"), fns[m], strict=True):
                if kind != "one_box" and i >= calls // 4:
                    continue
                t0 = time.perf_counter()
                jax.block_until_ready(fn(i))
                res[m][kind]["times"].append(time.perf_counter() - t0)
    for m in prior.MARGINS:
        for kind in res[m]:
            t = 1e3 * np.asarray(res[m][kind].pop("times"))
            res[m][kind].update(median_ms=float(np.median(t)), calls=len(t))
    for kind in res["sampled"]:
        for m in prior.MARGINS:
            res[m][kind]["ratio_to_sampled"] = res[m][kind]["median_ms"] / res["sampled"][kind]["median_ms"]
    return res


def _device_kinds() -> list:
    """The first device of each platform present: the accelerator where there is one, then the CPU."""
    kinds = [jax.devices()[0]] if jax.default_backend() != "cpu" else []
    return [*kinds, jax.devices("cpu")[0]]


# The planners of `--structure-only`: name -> (SamplingOptions, prior unrolled / looped, also vmapped over
# boxes). The wide ones without gradient steps are the candidates for an accelerator, where the width of
# a call is nearly free and its operations are launches (docs/results/planner.md).
STRUCTURE_PLANNERS = {
    "default": ({}, (False, True), True),
    "no_gradient": ({"gradient_steps": 0}, (False, True), True),
    "wide1024_no_gradient": ({"n_samples": 1024, "gradient_steps": 0}, (True,), False),
    "cem3x256_no_gradient": (
        {"n_samples": 256, "update": "cem", "iterations": 3, "n_elite": 32, "gradient_steps": 0},
        (True,),
        False,
    ),
}


def _structure(
    cfg, masses, window, speed, target, keys, calls: int, device, planners=None, boxes: int = 16
) -> dict:
    """The planners of `planners` (default STRUCTURE_PLANNERS) on `device`, one call and (where asked)
    `boxes` calls vmapped (one box, as many keys): compile time, operations and loop iterations per call
    (`_hlo.dynamic_ops`), and the latency with every variant's calls interleaved (median)."""
    variants = {}
    for planner_name, (kw, unrolls, vmapped) in (planners or STRUCTURE_PLANNERS).items():
        opts = sp.SamplingOptions(**kw)
        for unroll in unrolls:
            model = jax.device_put(prior.make_prior(masses, unroll=unroll), device)
            nominal = sp.initial_nominal(cfg, opts, speed)
            one = jax.jit(lambda k, m, n, o=opts: sp.plan(k, m, window, speed, target, n, cfg, o))
            many = jax.jit(
                jax.vmap(
                    lambda k, m, n, o=opts: sp.plan(k, m, window, speed, target, n, cfg, o),
                    in_axes=(0, None, None),
                )
            )
            calls_of = ((1, one, lambda i: keys[i]), (boxes, many, lambda i: keys[i : i + boxes]))
            for width, fn, key_of in calls_of if vmapped else calls_of[:1]:
                name = f"{planner_name}_{'unrolled' if unroll else 'looped'}_x{width}"
                with jax.default_device(device):
                    args = (key_of(0), model, nominal)
                    t0 = time.perf_counter()
                    compiled = fn.lower(*args).compile()
                    compile_s = time.perf_counter() - t0
                    jax.block_until_ready(compiled(*args))
                variants[name] = {"options": kw, "unroll": unroll, "boxes": width, "compile_s": compile_s}
                text = compiled.as_text()
                variants[name].update(dynamic_ops(text))
                if width == 1:  # where the operations come from: the 12 largest functions of boxjax
                    variants[name]["sources"] = dict(list(by_source(text).items())[:12])
                variants[name]["_call"] = (compiled, key_of, model, nominal)
                early = []  # 10 calls now, on stderr: a run cut short before the interleaved timing has these
                for i in range(10):
                    t0 = time.perf_counter()
                    jax.block_until_ready(compiled(key_of(i), model, nominal))
                    early.append(time.perf_counter() - t0)
                said = {k: variants[name][k] for k in ("compile_s", "ops", "while_iterations")}
                said["early_median_ms"] = float(1e3 * np.median(early))
                print(json.dumps({"device": device.platform, name: said}), file=sys.stderr, flush=True)
    times = {name: [] for name in variants}
    for i in range(calls):
        for name, v in variants.items():
            compiled, key_of, model, nominal = v["_call"]
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(key_of(i % (len(keys) - boxes)), model, nominal))
            times[name].append(time.perf_counter() - t0)
    for name, v in variants.items():
        del v["_call"]
        v["median_ms"] = float(1e3 * np.median(times[name]))
        v["calls"] = calls
    return {"device": f"{device.platform}:{getattr(device, 'device_kind', '')}", "variants": variants}


def _finish(out: dict) -> None:
    dev = jax.devices()[0]
    out["backend"] = jax.default_backend()
    out["device"] = f"{dev.platform}:{getattr(dev, 'device_kind', '')}"
    out["cpu_count"] = os.cpu_count()
    out["load_avg_1m"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    out["jax"] = jax.__version__
    out["python"] = platform.python_version()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
