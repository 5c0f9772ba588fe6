"""H-step prediction error of the physics prior along CLOSED-LOOP episodes (the states and actions the
MPC itself visits), for the prior with some of its parameters changed: does fitting the prior to the
regime the controller drives the box into make a better model?

Episodes: the default controller (oracle, batched) on `--boxes` random safe boxes of `--seed` (choose a
seed that no evaluation uses: the README's evaluations use 0-2). Every MPC step t (after the exploration)
whose next H steps stayed in the episode is a case: the prior sees the window s[t-2..t], the belt speeds
and the H actions the simulator received, with the box's true voxel masses, and predicts s[t+1..t+H].
Errors at steps 1, 5 and H (median / p90): position of the geometric centre (mm), yaw (degrees), balance
error (mm, what the safety barrier sees), beside constant velocity; and `carriage_follow`: how far the box
follows a net carriage move over the horizon, true against predicted (the planner's balance lever).

    python benchmarks/closed_loop_error.py [--boxes 64] [--seed 7] [--horizon 10] [--stride 3] \
        [--param carriage_omega=30,100 --param slip_eps=0.002,0.02] [--traces FILE.npz] [--out FILE.json] \
        [--residual FILE.npz] [--policy-residual FILE.npz] [--safe-family F] [--simulator planar,...]

`--param NAME=V1,V2,...` (repeatable) spans a grid over `prior.PriorParams` fields (all combinations);
`--traces` keeps the episodes (written when absent, read when present). Prints one JSON line.

`--simulator planar[,flat,velocity,exact]`: the simulator itself as the predictor of the same cases, with
the TRUE box, started from what the planar observation shows (`planners.simulator.planar_start`: the box
flat at the observed pose with finite-difference velocities; the belts and carriages exact), or from one
half of that (`flat`, `velocity`), or from the exact state (`exact`: error 0, a check); and the default
prior once more with its first step started from the exact velocity (`prior_exact_velocity`). Nothing that
predicts from the planar observation has a better model than this one; what it still gets wrong is
what the planar observation does not determine (slip and contact switching amplify the box's small
tilt and the velocity within a step). Each episode is re-simulated from its key and actions (checked
bit for bit against the traces), so `--traces` must come from the same `--boxes` and `--seed`.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import sys
import time

from boxjax.control import batch

if __name__ == "__main__":
    batch.use_host_devices()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))

from _util import emit_to, machine  # noqa: E402

from boxjax import geometry, massdist, planning, prior
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.experiments import evaluation as experiments
from boxjax.fileio import atomic_path  # noqa: E402
from boxjax.prior import residual


def collect(n_boxes: int, seed: int, policy_residual: str | None = None, family: str = "gaussian") -> dict:
    """Closed-loop oracle episodes of the default controller (planning with the learned residual
    `policy_residual` when given): per box s (T+1, 5), belt_speed, actions, masses and the exploration
    length, flattened into one npz-able dict."""
    from boxjax.control.config import ControllerConfig

    cfg = DEFAULT
    boxes = experiments.make_boxes(cfg, n_boxes, 0, seed, safe_family=family)
    truths = [boxes.dist(j) for j in range(n_boxes)]
    ctrl = ControllerConfig(residual=policy_residual)
    res = batch.run_episodes(cfg, truths, list(boxes.keys), estimator="oracle", ctrl=ctrl)
    out = {"success": np.asarray([r.summary["success"] for r in res])}
    for j, r in enumerate(res):
        out[f"s_{j}"], out[f"bs_{j}"], out[f"a_{j}"] = r.trace.s, r.trace.belt_speed, r.trace.actions
        out[f"m_{j}"] = np.asarray(massdist.voxel_masses(truths[j], cfg.box))
        out[f"nx_{j}"] = np.asarray(r.summary["exploration_steps"])
    return out


def cases(tr: dict, horizon: int, stride: int) -> dict:
    """Every `stride`-th MPC step with `horizon` steps left (`residual.segments`), each with its box's voxel
    masses: window (C, 3, 5), belt_speed (C, 2), actions (C, H, 4), masses (C, nx, ny, nz),
    truth (C, H, 5)."""
    seg = residual.segments(tr, horizon, stride, "exploration")
    seg["masses"] = seg["masses"][seg.pop("box")]
    return seg


def predict(c: dict, params: dict, chunk: int = 2048, corrected=None, velocity=None) -> np.ndarray:
    """The prior's predictions of every case; `corrected` = (net, ResidualConfig): with a learned residual;
    `velocity` (C, 3): each case's first step starts from this centre-of-mass velocity, not the window's."""
    cfg = DEFAULT

    def one(masses, window, belt_speed, actions, *u0):
        model = prior.make_prior(masses, None, cfg.box, cfg.gripper, **params)
        if u0:
            return prior.rollout_sequence(model, window, belt_speed, actions, velocity=u0[0])
        if corrected is not None:
            model = residual.Residual(model, *corrected)
        return model.rollout_sequence(window, belt_speed, actions)

    fn = jax.jit(jax.vmap(one))
    names = ("masses", "window", "belt_speed", "actions")
    if velocity is not None:
        c, names = {**c, "velocity": velocity}, (*names, "velocity")
    return np.concatenate(
        [
            np.asarray(fn(*(jnp.asarray(c[k][i : i + chunk]) for k in names)))
            for i in range(0, len(c["window"]), chunk)
        ]
    )


def constant_velocity(c: dict) -> np.ndarray:
    w = c["window"]
    h = np.arange(1, c["actions"].shape[1] + 1)[None, :, None]
    pred = np.repeat(w[:, -1:], h.shape[1], axis=1)
    pred[..., 2:] += h * (w[:, -1:, 2:] - w[:, -2:-1, 2:])
    pred[..., :2] = c["truth"][..., :2]  # the carriages follow the actions in both
    return pred


def carriage_follow(c: dict, pred: np.ndarray) -> dict:
    """How far the box's centre moves along the net carriage move over the horizon (cases whose mean
    carriage displacement exceeds 5 mm), true against predicted (medians, mm): the effect the planner
    corrects the balance with."""
    w = c["window"]
    net = c["actions"][..., 2:].sum(1).mean(-1)
    sel = np.abs(net) > 0.005
    along = np.sign(net[sel])
    return {
        "cases": int(sel.sum()),
        "true_mm": float(1e3 * np.median((c["truth"][sel, -1, 3] - w[sel, -1, 3]) * along)),
        "predicted_mm": float(1e3 * np.median((pred[sel, -1, 3] - w[sel, -1, 3]) * along)),
    }


def errors(pred: np.ndarray, truth: np.ndarray) -> dict:
    bal = jax.vmap(jax.vmap(geometry.balance_error))
    b_err = 1e3 * np.abs(np.asarray(bal(jnp.asarray(pred))) - np.asarray(bal(jnp.asarray(truth))))
    out = {}
    for h in sorted({1, 5, truth.shape[1]}):
        p, t = pred[:, h - 1], truth[:, h - 1]
        parts = {
            "position_mm": 1e3 * np.linalg.norm(p[:, 2:4] - t[:, 2:4], axis=1),
            "yaw_deg": np.degrees(np.abs(p[:, 4] - t[:, 4])),
            "balance_mm": b_err[:, h - 1],
        }
        out[str(h)] = {k: [float(np.median(v)), float(np.percentile(v, 90))] for k, v in parts.items()}
    return out


def simulator_predictions(
    tr: dict, n_boxes: int, seed: int, horizon: int, stride: int, starts, family: str = "gaussian"
) -> dict:
    """{start: (C, H, 5)} the simulator's own predictions of the cases of `cases(tr, horizon, stride)`,
    from each start (`planners.simulator.planar_start`, or "exact"), in the same order; and under
    "velocity_now" (C, 3) each case's exact centre-of-mass velocity (vx, vy, omega) at t."""
    from boxjax.planners import simulator as simp
    from boxjax.sim import core
    from boxjax.sim.native import NativeEnv

    cfg = DEFAULT
    boxes = experiments.make_boxes(cfg, n_boxes, 0, seed, safe_family=family)
    env = NativeEnv(cfg)
    roll = simp.Rollouts(cfg, 1, horizon, nthread=1)
    idx = simp.model.ids(simp.model.template(cfg))  # every box model has these indices

    @jax.jit
    def planar(qpos, yaw0):  # (H, nq) -> (H, 5) planar states, the yaw continuous from yaw0
        def step(yaw, q):
            p = core.planar_state(idx, q, yaw)
            return p[geometry.YAW], p

        return jax.lax.scan(step, yaw0, qpos)[1]

    w = planning.MIN_WINDOW
    out: dict[str, list] = {k: [] for k in (*starts, "velocity_now")}
    for j in range(n_boxes):
        s_tr, a = tr[f"s_{j}"], np.asarray(tr[f"a_{j}"], np.float64)
        st = env.reset(jax.random.wrap_key_data(boxes.keys[j]), boxes.dist(j))
        states = [st]
        for a_t in a:
            st = env.step(st, a_t)
            states.append(st)
        if not np.array_equal(np.stack([np.asarray(x.s) for x in states]), s_tr):
            raise SystemExit(
                f"box {j}: the re-simulated episode differs from the traces (other boxes or seed?)"
            )
        m = states[0].model
        ipos = np.array(m.body("box").ipos)
        for t in range(max(int(tr[f"nx_{j}"]), w - 1), len(a) - horizon + 1, stride):
            vel, rot = simp.box_velocity(m, states[t].physics[1 : 1 + m.nq], states[t].physics[1 + m.nq :])
            v_com = vel[:3] + np.cross(vel[3:], rot @ ipos)
            out["velocity_now"].append([v_com[0], v_com[1], vel[5]])
            for k in starts:
                x = states[t]
                if k != "exact":
                    x = x._replace(physics=simp.planar_start(cfg, x, s_tr[t - w + 1 : t + 1], start=k))
                qpos, _ = roll(x, a[None, t : t + horizon])
                out[k].append(np.asarray(planar(qpos[0], x.s[geometry.YAW])))
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


def _grid(items: list[str]) -> list[dict]:
    fields = {f.name: f for f in dataclasses.fields(prior.PriorParams)}
    axes = []
    for item in items:
        name, _, values = item.partition("=")
        if name not in fields or not values:
            raise SystemExit(f"--param {item!r}: expected NAME=V1,V2 with NAME a prior.PriorParams field")
        kind = type(getattr(prior.PriorParams(), name))
        axes.append([(name, kind(v)) for v in values.split(",")])
    return [dict(combo) for combo in itertools.product(*axes)] if axes else [{}]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--boxes", type=int, default=64)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--stride", type=int, default=3)
    ap.add_argument("--param", action="append", default=[])
    ap.add_argument("--traces", help="episodes npz: read if it exists, else written")
    ap.add_argument("--out", help="also write the JSON here (atomically)")
    ap.add_argument(
        "--residual", help="also the default prior with this learned residual (boxjax.prior.residual)"
    )
    ap.add_argument("--policy-residual", help="the episodes' controller plans with this residual")
    ap.add_argument(
        "--safe-family", default="gaussian", choices=massdist.FAMILIES, help="the boxes' family (evaluate's)"
    )
    ap.add_argument(
        "--simulator",
        help="comma-separated starts (planar, flat, velocity, exact): the simulator itself as the predictor",
    )
    args = ap.parse_args(argv)
    starts = [k for k in (args.simulator or "").split(",") if k]
    from boxjax.planners.simulator import STARTS

    bad = [k for k in starts if k not in STARTS]
    if bad:
        ap.error(f"--simulator {','.join(bad)}: expected some of {','.join(STARTS)}")
    default = prior.PriorParams()
    grid = [{}] + [g for g in _grid(args.param) if dataclasses.replace(default, **g) != default]
    t0 = time.perf_counter()
    if args.traces and os.path.exists(args.traces):
        tr = dict(np.load(args.traces))
    else:
        tr = collect(args.boxes, args.seed, args.policy_residual, args.safe_family)
        if args.traces:
            with atomic_path(args.traces, suffix=".npz") as tmp:
                np.savez(tmp, **tr)
    t_sim = time.perf_counter() - t0
    c = cases(tr, args.horizon, args.stride)
    out = {
        "benchmark": f"{args.horizon}-step prediction error along closed-loop episodes (oracle, default MPC)",
        "boxes": int(len(tr["success"])),
        "turned": int(np.sum(tr["success"])),
        "seed": args.seed,
        "safe_family": args.safe_family,
        "cases": int(len(c["window"])),
        "episodes_s": t_sim,
        "constant_velocity": errors(constant_velocity(c), c["truth"]),
        "prior": [],
        "machine": machine(),
    }
    for params in grid:
        t1 = time.perf_counter()
        pred = predict(c, params)
        out["prior"].append(
            {
                "params": params,
                **errors(pred, c["truth"]),
                "carriage_follow": carriage_follow(c, pred),
                "s": time.perf_counter() - t1,
            }
        )
        print(json.dumps(out["prior"][-1]), file=sys.stderr, flush=True)
    if args.residual:
        net, rcfg, _ = residual.load(args.residual)
        t1 = time.perf_counter()
        pred = predict(c, {}, corrected=(net, rcfg))
        out["residual"] = {
            "file": args.residual,
            **errors(pred, c["truth"]),
            "carriage_follow": carriage_follow(c, pred),
            "s": time.perf_counter() - t1,
        }
        print(json.dumps(out["residual"]), file=sys.stderr, flush=True)
    if starts:
        t1 = time.perf_counter()
        preds = simulator_predictions(
            tr, out["boxes"], args.seed, args.horizon, args.stride, starts, args.safe_family
        )
        velocity = preds.pop("velocity_now")
        out["simulator"] = {k: errors(p, c["truth"]) for k, p in preds.items()}
        out["simulator"]["s"] = time.perf_counter() - t1
        # The default prior again, its first step from the exact velocity instead of the window's.
        out["prior_exact_velocity"] = errors(predict(c, {}, velocity=velocity), c["truth"])
        print(json.dumps(out["simulator"]), file=sys.stderr, flush=True)
    out["wall_s"] = time.perf_counter() - t0
    emit_to(out, args.out)
    return out


if __name__ == "__main__":
    main()
