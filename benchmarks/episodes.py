"""Closed-loop episodes per second: batched (`boxjax.control.batch.run_episodes`) against one at a time
(`controller.run_episode`), and the whole loop on the device (`boxjax.control.device_loop`, MJX, at the
widths of `--mjx-slots`), on the same random safe boxes and keys, measured in one run.

Both paths are compiled first on other boxes (a short warm-up episode each), so the timed part is
episodes only; the compile times are reported apart. Also reported: each path's success count (the
paths agree in distribution, not bit for bit: see boxjax/batch.py), the batched planner's cost per box
and control step, and one planner call timed alone at several widths (boxes per call) beside the
unbatched call: what batching can gain at most on this machine; and how often the widest call's actions
are bit-identical to one-box calls on the same boxes and keys (`agreement`).

Prints ONE JSON object (the last line).
Run: python benchmarks/episodes.py [--boxes 32] [--slots 8] [--devices 1] [--seed 0] [--max-steps 600]
                                  [--skip-single]
                                  [--widths 1 8 32] [--mjx-slots 16 64] [--skip-native]
                                  [--samples N] [--gradient-steps N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit, machine  # noqa: E402

from boxjax import control as controller
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.control import batch, device_loop
from boxjax.experiments import evaluation as experiments
from boxjax.planners.sampling import SamplingOptions


def _episodes(cfg, boxes, idx):
    return [boxes.dist(j) for j in idx], [jax.random.wrap_key_data(boxes.keys[j]) for j in idx]


def planner_widths(cfg, ctrl, boxes, widths, calls: int = 10) -> dict:
    """Median ms of one planner call for `widths` boxes at once (vmapped) and for one box unbatched: the
    planner's cost per box and step, which bounds what batching can gain."""
    import jax.numpy as jnp

    from boxjax import planning

    mpc = controller.make_planner(cfg, ctrl)
    w_max = max(widths)
    if len(boxes) < w_max:
        boxes = experiments.make_boxes(cfg, w_max, 0, 0)
    models = [controller.planning_model(cfg, ctrl, boxes.dist(j)) for j in range(w_max)]
    s = jnp.array([-0.11, 0.12, 0.01, -0.005, 0.4], jnp.float32)
    obs = planning.observation(
        jnp.stack(
            [
                s - (planning.MIN_WINDOW - 1 - i) * jnp.array([0, 0, 1e-3, 5e-4, 0.02])
                for i in range(planning.MIN_WINDOW)
            ]
        ),
        jnp.array([0.12, -0.1]),
        np.pi / 2,
    )
    out = {}
    ps = mpc.init(obs)
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    jax.block_until_ready(mpc.optimize(key, models[0], obs, ps)[0])
    compile_1 = time.perf_counter() - t0
    ts = []
    for i in range(calls):
        t0 = time.perf_counter()
        jax.block_until_ready(mpc.optimize(jax.random.fold_in(key, i), models[0], obs, ps)[0])
        ts.append(time.perf_counter() - t0)
    out["unbatched"] = {
        "compile_s": compile_1,
        "call_ms": 1e3 * float(np.median(ts)),
        "ms_per_box": 1e3 * float(np.median(ts)),
    }
    vm = jax.jit(jax.vmap(mpc.optimize))
    for w in widths:
        stack = lambda trees: jax.tree.map(lambda *x: jnp.stack(x), *trees)  # noqa: E731
        mb, ob = stack(models[:w]), stack([obs] * w)
        pb, kb = stack([ps] * w), jax.random.split(key, w)
        t0 = time.perf_counter()
        jax.block_until_ready(vm(kb, mb, ob, pb)[0])
        comp = time.perf_counter() - t0
        ts = []
        for i in range(calls):
            t0 = time.perf_counter()
            jax.block_until_ready(vm(jax.random.split(jax.random.fold_in(key, i), w), mb, ob, pb)[0])
            ts.append(time.perf_counter() - t0)
        med = 1e3 * float(np.median(ts))
        out[f"width_{w}"] = {"compile_s": comp, "call_ms": med, "ms_per_box": med / w}
    # Agreement: the widest call's first actions against one-box calls with the same box and key.
    kb = jax.random.split(key, w)
    batched = np.asarray(vm(kb, mb, ob, pb)[0])
    single = np.stack([np.asarray(mpc.optimize(kb[j], models[j], obs, ps)[0]) for j in range(w)])
    diff = np.abs(batched - single).max(axis=1)
    out["agreement"] = {
        "width": w,
        "boxes_bit_identical": int(np.sum(diff == 0)),
        "max_abs_action_diff": float(diff.max()),
    }
    return out


def mjx_loop(cfg, ctrl, warm_dists, warm_keys, dists, keys, width: int, max_steps) -> dict:
    """The on-device loop at `width` slots: compiled on the warm-up boxes (a 48-step cap: the cap is an
    argument of its programs), then timed on the boxes."""
    n = -(-width // len(warm_dists))
    t0 = time.perf_counter()
    device_loop.run_episodes(cfg, warm_dists * n, warm_keys * n, ctrl=ctrl, slots=width, max_steps=48)
    warm = time.perf_counter() - t0
    print(f"mjx {width} slots: compiled and warmed up in {warm:.1f} s", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    ended, said = 0, t0

    def progress(_b, _r):  # a run cut short by a time limit still says its rate so far (stderr)
        nonlocal ended, said
        ended += 1
        now = time.perf_counter()
        if now - said >= 10 or ended == len(dists):
            said = now
            print(
                f"mjx {width} slots: {ended}/{len(dists)} episodes ended in {now - t0:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    res = device_loop.run_episodes(
        cfg, dists, keys, ctrl=ctrl, slots=width, max_steps=max_steps, progress=progress
    )
    wall = time.perf_counter() - t0
    steps = sum(r.summary["steps"] for r in res)
    return {
        "slots": width,
        "warmup_s": warm,
        "wall_s": wall,
        "episodes_per_s": len(dists) / wall,
        "success": sum(r.summary["success"] for r in res),
        "control_steps": steps,
        "box_steps_per_s": steps / wall,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", type=int, default=32)
    ap.add_argument("--slots", type=int, default=None, help="boxes per planner call (default 8 per device)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-steps", type=int, default=None, help="control-step cap (default: the task's)")
    ap.add_argument("--skip-single", action="store_true", help="time the batched path only")
    ap.add_argument(
        "--devices", type=int, default=1, help="host devices the batched planner shards its boxes over"
    )
    ap.add_argument(
        "--widths",
        type=int,
        nargs="*",
        default=[1, 8, 32],
        help="planner-call widths timed alone (boxes per vmapped call); none: skip",
    )
    ap.add_argument(
        "--mjx-slots",
        type=int,
        nargs="*",
        default=[],
        help="the on-device loop (MJX) at these widths (boxes per program call); none: skip",
    )
    ap.add_argument("--skip-native", action="store_true", help="time the on-device loop only")
    ap.add_argument("--samples", type=int, help="the sampling planner's rollouts per step (default 64)")
    ap.add_argument("--gradient-steps", type=int, help="its Adam steps through the prior (default 5)")
    args = ap.parse_args()
    if args.boxes < 1 or (args.slots is not None and args.slots < 1) or args.devices < 1:
        ap.error("--boxes, --slots and --devices must be >= 1")
    n_dev = batch.use_host_devices(args.devices)  # before any JAX computation
    args.slots = args.slots or batch.SLOTS_PER_DEVICE * n_dev
    cfg = DEFAULT
    planner = {
        k: v
        for k, v in (("n_samples", args.samples), ("gradient_steps", args.gradient_steps))
        if v is not None
    }
    ctrl = controller.ControllerConfig(sampling=SamplingOptions(**planner) if planner else None)
    n_warm = min(args.slots, 4)
    boxes = experiments.make_boxes(cfg, args.boxes + n_warm, 0, args.seed)
    warm_idx = range(args.boxes, args.boxes + n_warm)
    idx = range(args.boxes)
    out = {
        "benchmark": "closed-loop episodes, batched vs one at a time",
        "boxes": args.boxes,
        "slots": args.slots,
        "devices": n_dev,
        "seed": args.seed,
        "planner": ctrl.planner,
        "sampling": planner or "default",
        **machine(),
    }

    wt, wk = _episodes(cfg, boxes, warm_idx)
    dists, keys = _episodes(cfg, boxes, idx)
    if args.mjx_slots:
        out["mjx"] = [mjx_loop(cfg, ctrl, wt, wk, dists, keys, w, args.max_steps) for w in args.mjx_slots]
    if args.skip_native:
        out["load_avg_1m"] = os.getloadavg()[0]
        emit(out)
        return

    # compile: one short episode per path on boxes outside the timed set
    t0 = time.perf_counter()
    batch.run_episodes(
        cfg,
        wt * (args.slots // n_warm + 1),
        wk * (args.slots // n_warm + 1),
        ctrl=ctrl,
        slots=args.slots,
        max_steps=48,
    )
    out["batched_warmup_s"] = time.perf_counter() - t0
    if not args.skip_single:
        t0 = time.perf_counter()
        controller.run_episode(cfg, wt[0], wk[0], ctrl=ctrl, max_steps=48)
        out["single_warmup_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    res = batch.run_episodes(cfg, dists, keys, ctrl=ctrl, slots=args.slots, max_steps=args.max_steps)
    wall_b = time.perf_counter() - t0
    steps_b = sum(r.summary["steps"] for r in res)
    mpc_steps_b = sum(len(r.plan_ms) + (1 if len(r.plan_ms) else 0) for r in res)
    calls = [ms for r in res for ms in r.plan_ms]
    out["batched"] = {
        "wall_s": wall_b,
        "episodes_per_s": args.boxes / wall_b,
        "success": sum(r.summary["success"] for r in res),
        "control_steps": steps_b,
        "plan_call_ms_median": float(np.median(calls)) if calls else None,
        "plan_ms_per_box_step": float(np.median(calls)) / min(args.slots, args.boxes) if calls else None,
        "mpc_box_steps": mpc_steps_b,
    }
    if not args.skip_single:
        t0 = time.perf_counter()
        single = [
            controller.run_episode(cfg, d, k, ctrl=ctrl, max_steps=args.max_steps)
            for d, k in zip(dists, keys, strict=True)
        ]
        wall_s = time.perf_counter() - t0
        plan = [ms for r in single for ms in r.plan_ms]
        out["single"] = {
            "wall_s": wall_s,
            "episodes_per_s": args.boxes / wall_s,
            "success": sum(r.summary["success"] for r in single),
            "control_steps": sum(r.summary["steps"] for r in single),
            "plan_ms_median": float(np.median(plan)) if plan else None,
        }
        out["speedup"] = wall_s / wall_b
        out["same_outcome"] = sum(
            experiments.outcome(a.summary) == experiments.outcome(b.summary)
            for a, b in zip(res, single, strict=True)
        )
    if args.widths:
        out["planner_call"] = planner_widths(cfg, ctrl, boxes, args.widths)
    out["load_avg_1m"] = os.getloadavg()[0]
    emit(out)


if __name__ == "__main__":
    main()
