"""One-step prediction error of the physics prior against the simulator, beside a constant-velocity baseline.

Transitions come from the native MuJoCo env (`boxjax.sim.make_env(cfg, "native")`) on boxes uniform, A, B,
C and a few random safe boxes (`massdist.sample`, hazardous ones rejected). Every action is a row of the
planner's restricted action set (`planner.action_set`, increment mode: velocity rows send setpoint = belt
speed + dv, position rows step one carriage), chosen by a mix of policies that visit the states the MPC
meets:
  * "random": a uniformly random row every step;
  * "drive": chases a target pair of belt speeds (turn: (v, -v); translate: (v, v), reversed before the
    box nears a belt end; stop: (0, 0); any pair), re-drawn every 10-30 steps, with the velocity row
    nearest the needed increment; holds the speeds once there (the box rides along or spins steadily, the
    states where constant velocity is a strong baseline); a balance-correcting position row when the
    balance error exceeds 1.5 cm, and a random row 25 % of the time.
The task's success rule is switched off (target yaw far away) so boxes can keep spinning; an episode ends
at the balance limit, off the belts, or after its length. Transitions whose step ended off the belts or
tipped are dropped (the planar state means nothing there).

For every transition t -> t+1 the predictors see the window s_{t-2..t} (the initial state repeated at
the start of an episode, where the box is at rest), the measured belt speeds at t, and the action:
  * prior: `prior.predict` with the box's true voxel masses (default PriorParams: variant "slip");
  * constant_velocity: x, y, yaw at t + (s_t - s_{t-1}); belt positions P from the action, as the prior;
  * constant_velocity_2nd_order: the same with the prior's own velocity estimate (3 s_t - 4 s_{t-1} +
    s_{t-2}) / 2 per step, so that what the prior gains over it is its physics, not its differencing.
Errors: position = |(x, y)_pred - (x, y)_sim| of the box's geometric centre, mm; yaw = |yaw_pred -
yaw_sim|, degrees. Reported as median / p90 / mean, over all transitions and split by action type
(velocity rows vs position rows), by box, by policy, by motion regime at t (rest, riding = moving with
the belts, spinning, sliding), and for steady spins (the states where constant velocity is at its best).

    python benchmarks/prediction_error.py [--transitions 20000] [--seed 0] [--out FILE.json]
        [--param cone=elliptic ...]

`--param NAME=VALUE` overrides a `prior.PriorParams` field (e.g. cone=elliptic for the isotropic friction
law, n_substeps=4) on the same transitions (same seed).

Prints one JSON object as its last stdout line (progress bar on stderr).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from boxjax import geometry, massdist, prior, task
from boxjax.config import DEFAULT, Config
from boxjax.fileio import atomic_path
from boxjax.planners import paper as planner
from boxjax.sim import make_env

NAMED_BOXES = ("uniform", "A", "B", "C")
POLICIES = ("random", "drive")
ACTION_TYPES = ("velocity", "position")
N_V = 9  # velocity grid of the action set: N_V x N_V velocity rows first, then the position rows
N_VELOCITY_ROWS = N_V * N_V
REGIMES = ("rest", "riding", "spinning", "sliding")
_FIELDS = (  # per-transition arrays returned by `collect`
    "window",
    "belt_speed",
    "action",
    "row",
    "s_next",
    "box",
    "policy",
    "qvel_box",
    "belt_speed_next",
    "p_target",
    "physics",
)
DROP = (task.REASONS.index("off_belts"), task.REASONS.index("tipped"), task.REASONS.index("invalid_action"))


def bench_config(cfg: Config = DEFAULT) -> Config:
    """`cfg` with the success rule out of reach (boxes may turn several times) and no step cap."""
    return cfg.replace(task=dataclasses.replace(cfg.task, target_yaw_delta=1e4, max_steps=10**6))


def boxes(n_random: int, seed: int, cfg: Config = DEFAULT) -> dict[str, massdist.MassDistribution]:
    """The named boxes uniform, A, B, C and `n_random` random safe ones (hazardous draws rejected)."""
    out = {name: massdist.named(name, cfg.box) for name in NAMED_BOXES}
    key = jax.random.key(seed + 1000)
    while len(out) < len(NAMED_BOXES) + n_random:
        key, sub = jax.random.split(key)
        d = massdist.sample(sub, cfg.box)
        if not bool(massdist.is_hazardous(d, cfg.box)):
            out[f"random{len(out) - len(NAMED_BOXES)}"] = d
    return out


class _Drive:
    """The "drive" policy (module docstring); rows index `planner.action_set(gripper)`."""

    def __init__(self, rng: np.random.Generator, cfg: Config, rows: np.ndarray):
        self.rng, self.g, self.rows = rng, cfg.gripper, rows
        self.dv = np.unique(rows[:N_VELOCITY_ROWS, 0])  # the increment grid (N_V values)
        self.steps_left = 0
        self.target = np.zeros(2)

    def _new_target(self, s):
        r, vmax = self.rng, 0.8 * self.g.belt_speed_limit
        mode = r.choice(["turn", "translate", "stop", "any"], p=[0.45, 0.2, 0.1, 0.25])
        v = r.uniform(0.03, vmax)
        if mode == "turn":
            self.target = np.array([v, -v]) * r.choice([-1, 1]) + r.normal(0, 0.01, 2)
        elif mode == "translate":
            sign = -np.sign(s[geometry.X]) if abs(s[geometry.X]) > 0.05 else r.choice([-1, 1])
            self.target = np.full(2, sign * min(v, 0.12))
        elif mode == "stop":
            self.target = np.zeros(2)
        else:
            self.target = r.uniform(-vmax, vmax, 2)
        self.steps_left = int(r.integers(10, 31))

    def __call__(self, s, belt_speed) -> int:
        r = self.rng
        if self.steps_left <= 0 or (abs(s[geometry.X]) > 0.12 and self.target[0] * s[geometry.X] > 0):
            self._new_target(s)
        self.steps_left -= 1
        if r.random() < 0.25:
            return int(r.integers(len(self.rows)))
        bal = s[geometry.Y] - 0.5 * (s[geometry.P1] + s[geometry.P2])
        if abs(bal) > 0.015:  # move one belt towards the box's centre
            col = 2 + int(r.integers(2))  # which belt
            pos = np.arange(N_VELOCITY_ROWS, len(self.rows))
            cand = pos[(self.rows[pos, 5 - col] == 0) & (self.rows[pos, col] * np.sign(bal) > 0)]
            if len(cand):
                return int(r.choice(cand))
        need = np.clip(self.target - belt_speed, self.dv[0], self.dv[-1])
        i1, i2 = (int(np.argmin(np.abs(self.dv - n))) for n in need)
        return i1 * len(self.dv) + i2


def collect(
    n_transitions: int,
    seed: int = 0,
    n_random_boxes: int = 4,
    episode_steps: int = 80,
    cfg: Config = DEFAULT,
    progress: bool = True,
) -> dict:
    """Simulated transitions (see module docstring) as numpy arrays with a leading transition axis.

    Returns dict: window (N, 3, 5), belt_speed (N, 2) m/s at t, action (N, 4) as sent to the env,
    row (N,) index into `planner.action_set`, s_next (N, 5), box (N,) index into `box_names`, policy (N,)
    index into POLICIES, qvel_box (N, 6) the box's free-joint velocity at t (linear: world frame at the
    geometric centre; angular: body frame), belt_speed_next (N, 2), p_target (N, 2) carriage targets at t,
    physics (N, K) the native physics state at t (mjSTATE_INTEGRATION, for diagnostics); plus box_names
    and the masses (B, nx, ny, nz).
    """
    cfg_env = bench_config(cfg)
    env = make_env(cfg_env, "native")
    dists = boxes(n_random_boxes, seed, cfg)
    names = list(dists)
    rows = planner.action_set(cfg.gripper, n_v=N_V)
    # Environment actions of every row at the current belt speeds (setpoint = speed + dv): one dispatch.
    to_env = jax.jit(lambda speed: planner.to_env_actions(rows, speed, cfg.gripper))
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed)
    recs: dict[str, list] = {k: [] for k in _FIELDS}
    bdof = env.ids.box_dof
    episode = 0
    bar = tqdm(total=n_transitions, desc="simulating", unit="tr", file=sys.stderr, disable=not progress)
    while len(recs["row"]) < n_transitions:
        pol = episode % len(POLICIES)
        b = (episode // len(POLICIES)) % len(names)
        episode += 1
        key, sub = jax.random.split(key)
        state = env.reset(sub, dists[names[b]])
        drive = _Drive(rng, cfg, rows)
        hist = [np.asarray(state.s, np.float64)] * 3
        for _ in range(episode_steps):
            s, speed = hist[-1], np.asarray(state.belt_speed, np.float64)
            row = int(rng.integers(len(rows))) if POLICIES[pol] == "random" else drive(s, speed)
            act = np.asarray(to_env(jnp.asarray(speed, jnp.float32)), np.float64)[row]
            qvel = _qvel(state)[bdof : bdof + 6]
            p_target = np.asarray(state.p_target, np.float64)
            nxt = env.step(state, act)
            if int(nxt.reason) in DROP:
                break
            rec = dict(
                window=np.stack(hist[-3:]),
                belt_speed=speed,
                action=act,
                row=row,
                s_next=np.asarray(nxt.s, np.float64),
                box=b,
                policy=pol,
                qvel_box=qvel,
                belt_speed_next=np.asarray(nxt.belt_speed, np.float64),
                p_target=p_target,
                physics=np.asarray(state.physics),
            )
            for k, v in rec.items():
                recs[k].append(v)
            bar.update(1)
            hist.append(np.asarray(nxt.s, np.float64))
            state = nxt
            if bool(nxt.done) or len(recs["row"]) >= n_transitions:
                break
    bar.close()
    out = {k: np.asarray(v) for k, v in recs.items()}
    out["box_names"] = np.asarray(names)
    out["masses"] = np.stack([np.asarray(massdist.voxel_masses(dists[n], cfg.box)) for n in names])
    out["episodes"] = episode
    return out


def _qvel(state) -> np.ndarray:
    """qvel from a native state's physics vector (mjSTATE_INTEGRATION: time, qpos, qvel, ...)."""
    nq, nv = state.model.nq, state.model.nv
    return np.asarray(state.physics)[1 + nq : 1 + nq + nv]


def _predict_one(masses, window, belt_speed, action, params: prior.PriorParams, cfg: Config):
    model = prior.make_prior(masses, None, cfg.box, cfg.gripper, params)
    return prior.predict(model, window, belt_speed, action)


def predict_prior(data: dict, cfg: Config = DEFAULT, chunk: int = 4096, **params) -> np.ndarray:
    """(N, 5) prior predictions with each transition's true voxel masses, vmapped in fixed-size chunks
    (one compile; the last chunk is padded)."""
    prm = dataclasses.replace(prior.PriorParams(), **params)
    fn = jax.jit(jax.vmap(functools.partial(_predict_one, params=prm, cfg=cfg)))
    n = len(data["row"])
    chunk = min(chunk, n)
    masses = data["masses"][data["box"]]
    args = [masses, data["window"], data["belt_speed"], data["action"]]
    out = []
    for i in range(0, n, chunk):
        part = [a[i : i + chunk] for a in args]
        k = len(part[0])
        part = [np.concatenate([p, np.repeat(p[-1:], chunk - k, 0)]) for p in part]
        out.append(np.asarray(fn(*(jnp.asarray(p, jnp.float32) for p in part)))[:k])
    return np.concatenate(out).astype(np.float64)


def predict_constant_velocity(data: dict, cfg: Config = DEFAULT) -> np.ndarray:
    """(N, 5): x, y, yaw extrapolated at the last observed velocity; P_i + dp_i clipped to its range."""
    w = data["window"]
    out = w[:, -1] + (w[:, -1] - w[:, -2])
    g = cfg.gripper
    lo, hi = np.array([g.p1_range[0], g.p2_range[0]]), np.array([g.p1_range[1], g.p2_range[1]])
    out[:, :2] = np.clip(w[:, -1, :2] + data["action"][:, 2:], lo, hi)
    return out


def predict_constant_velocity_2nd_order(data: dict, cfg: Config = DEFAULT) -> np.ndarray:
    """(N, 5): as `predict_constant_velocity` but with the prior's own velocity estimate, the second-order
    backward difference (3 s_t - 4 s_{t-1} + s_{t-2}) / (2 dt) (`calibrate.window_kinematics`)."""
    w = data["window"]
    out = predict_constant_velocity(data, cfg)
    out[:, 2:] = w[:, -1, 2:] + 0.5 * (3 * w[:, -1, 2:] - 4 * w[:, -2, 2:] + w[:, -3, 2:])
    return out


def errors(pred: np.ndarray, s_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position error mm, yaw error deg) per transition (geometric centre x, y; continuous yaw)."""
    pos = 1e3 * np.linalg.norm(pred[:, 2:4] - s_next[:, 2:4], axis=1)
    yaw = np.degrees(np.abs(pred[:, 4] - s_next[:, 4]))
    return pos, yaw


def regimes(data: dict, cfg: Config = DEFAULT) -> np.ndarray:
    """(N,) index into REGIMES of the motion at t, from the window (as a predictor sees it).

    rest: centre speed < 5 mm/s and yaw rate < 0.05 rad/s; riding: the bottom of the box moves with the
    belts (the centre within 1 cm/s of the mean belt speed, turning < 0.05 rad/s); spinning: yaw rate >=
    0.05 rad/s; sliding: the rest (translating against the belts).
    """
    w = data["window"]
    dt = cfg.gripper.control_dt
    v = (3 * w[:, 2, 2:4] - 4 * w[:, 1, 2:4] + w[:, 0, 2:4]) / (2 * dt)
    om = np.abs(3 * w[:, 2, 4] - 4 * w[:, 1, 4] + w[:, 0, 4]) / (2 * dt)
    speed = np.linalg.norm(v, axis=1)
    belt = np.stack([data["belt_speed"].mean(1), np.zeros(len(w))], axis=1)
    rest = (speed < 5e-3) & (om < 0.05)
    riding = ~rest & (om < 0.05) & (np.linalg.norm(v - belt, axis=1) < 0.01)
    spinning = om >= 0.05
    return np.select([rest, riding, spinning], [0, 1, 2], 3)


def stats(x: np.ndarray) -> dict:
    if len(x) == 0:
        return {"n": 0}
    return {
        "median": round(float(np.median(x)), 4),
        "p90": round(float(np.percentile(x, 90)), 4),
        "mean": round(float(np.mean(x)), 4),
    }


def summarise(data: dict, preds: dict[str, np.ndarray], cfg: Config = DEFAULT) -> dict:
    """Error statistics of every predictor, overall and per slice."""
    errs = {name: errors(p, data["s_next"]) for name, p in preds.items()}
    is_pos = data["row"] >= N_VELOCITY_ROWS
    reg = regimes(data, cfg)
    slices = {"all": np.ones(len(is_pos), bool)}
    slices.update({f"action={t}": m for t, m in zip(ACTION_TYPES, (~is_pos, is_pos), strict=True)})
    slices.update({f"box={n}": data["box"] == i for i, n in enumerate(data["box_names"].tolist())})
    slices.update({f"policy={p}": data["policy"] == i for i, p in enumerate(POLICIES)})
    slices.update({f"regime={r}": reg == i for i, r in enumerate(REGIMES)})
    slices.update(
        {
            f"regime={r},action={t}": (reg == i) & (is_pos == (t == "position"))
            for i, r in enumerate(REGIMES)
            for t in ACTION_TYPES
        }
    )
    # Where constant velocity is at its best: a steady spin (yaw rate changed < 0.02 rad/s over the last
    # step) under a velocity action, and among those the "hold" row (dv = 0: belts keep their speeds).
    w = data["window"]
    dom = np.abs(w[:, 2, 4] - 2 * w[:, 1, 4] + w[:, 0, 4]) / cfg.gripper.control_dt
    steady = (reg == REGIMES.index("spinning")) & (dom < 0.02) & ~is_pos
    slices["steady_spin,action=velocity"] = steady
    slices["steady_spin,action=hold"] = steady & (data["row"] == N_VELOCITY_ROWS // 2)
    out = {}
    for sname, m in slices.items():
        if not np.any(m):
            continue
        entry = {"n": int(np.sum(m))}
        for pname, (pe, ye) in errs.items():
            entry[pname] = {"position_mm": stats(pe[m]), "yaw_deg": stats(ye[m])}
        out[sname] = entry
    return out


def _parse_params(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        fields = {f.name: f for f in dataclasses.fields(prior.PriorParams)}
        if k not in fields or not v:
            raise SystemExit(f"--param {it!r}: expected NAME=VALUE with NAME one of {sorted(fields)}")
        default = getattr(prior.PriorParams(), k)
        out[k] = v if isinstance(default, str) else type(default)(float(v) if v != "inf" else math.inf)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--transitions", type=int, default=20000, help="simulated transitions (default 20000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--random-boxes", type=int, default=4, help="random safe boxes besides uniform, A, B, C")
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a prior.PriorParams field for the prior (repeatable)",
    )
    ap.add_argument("--out", help="also write the JSON summary here (atomically)")
    args = ap.parse_args(argv)
    if args.transitions < 1:
        raise SystemExit("--transitions must be >= 1")
    params = _parse_params(args.param)
    cfg = DEFAULT
    t0 = time.perf_counter()
    data = collect(args.transitions, args.seed, args.random_boxes, cfg=cfg)
    t_sim = time.perf_counter() - t0
    t1 = time.perf_counter()
    preds = {
        "prior": predict_prior(data, cfg, **params),
        "constant_velocity": predict_constant_velocity(data, cfg),
        "constant_velocity_2nd_order": predict_constant_velocity_2nd_order(data, cfg),
    }
    t_pred = time.perf_counter() - t1
    result = {
        "benchmark": "one-step prediction error: physics prior vs constant velocity (native MuJoCo)",
        "prior_params": dataclasses.asdict(dataclasses.replace(prior.PriorParams(), **params)),
        "transitions": int(len(data["row"])),
        "episodes": int(data["episodes"]),
        "boxes": data["box_names"].tolist(),
        "seed": args.seed,
        "units": {"position": "mm (geometric centre x, y)", "yaw": "deg"},
        "slices": summarise(data, preds, cfg),
        "wall_s": round(time.perf_counter() - t0, 2),
        "simulate_s": round(t_sim, 2),
        "predict_s": round(t_pred, 2),
    }
    if args.out:
        with atomic_path(args.out, suffix=".json") as tmp, open(tmp, "w") as f:
            json.dump(result, f, indent=1)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
