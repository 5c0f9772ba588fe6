"""Data and offline training for the black-box baseline W (paper §4.1, Table 2); `boxjax train-baseline`.

Data (paper Table 2: ~200 full episodes in the single environment of box A, "random exploration + known
successful policies"). Episodes cycle through four kinds (index i mod 5):
  * "prior" (i mod 5 in {0, 1}): the physics-prior pipeline as it is (`controller.run_episode`, oracle
    estimator, default sampling planner), with the 45-step exploration for even i and without it for odd
    i (W is run without exploration, so its episodes start from rest under MPC);
  * "prior-noisy" (i mod 5 in {2, 3}): the same planner with the true prior, but the action sent is the
    planned one plus gaussian noise (sigma ~ U(0.01, 0.04) m/s on the setpoints, U(1, 4) mm on the
    position steps, drawn per episode) and, with probability 0.1 per step, a uniformly random action
    (within the planner's speed cap): the states next to the successful trajectories, where a model
    that plans must be right too;
  * "random" (i mod 5 == 4): random exploration: belt-speed targets (turn, translate, stop or any pair,
    as benchmarks/prediction_error.py's "drive" policy) held 10-30 steps and approached at the belts'
    acceleration limit, a balance-correcting carriage step when the balance error exceeds 1.5 cm, and a
    uniformly random action 25 % of the time. These run with the success rule off (the box may keep
    turning) until the balance limit, the belts' ends or the step cap.
The last transition of an episode that ended off the belts or tipped is dropped (the planar state means
nothing there). The split is by episode (every `holdout_every`-th episode is held out).
"""

from __future__ import annotations

import json
import os
import time

import jax
import numpy as np
import optax

from boxjax import control as controller
from boxjax import geometry, massdist, planning, prior, task
from boxjax.blackbox import baseline
from boxjax.config import DEFAULT, Config
from boxjax.fileio import atomic_path, read_npz
from boxjax.planners.sampling import SamplingOptions, clip_actions
from boxjax.training import baseline_device
from boxjax.training import baseline_rules as rules

KINDS = rules.KINDS

_DROP = ("off_belts", "tipped", "invalid_action")


def _tqdm(total, desc, progress):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not progress, leave=False)


def perturb(cfg: Config, rng: np.random.Generator, planned, scales, cap: float) -> np.ndarray:
    """The prior-noisy kind's action (module docstring; `baseline_device.noisy_action` on the device): the
    planned action plus gaussian noise of std `scales` (4,), or with probability `rules.P_RANDOM_NOISY` a
    uniformly random action within (cap, cap, max step, max step); clipped to the planner's limits."""
    hi = np.array([cap, cap, cfg.gripper.max_position_step, cfg.gripper.max_position_step])
    if rng.random() < rules.P_RANDOM_NOISY:
        a = rng.uniform(-hi, hi)
    else:
        a = planned + rng.normal(0, 1, 4) * scales
    return np.asarray(clip_actions(a, cfg, cap), np.float64)


def _noisy_prior_episode(cfg: Config, truth, key, rng: np.random.Generator, max_steps: int) -> tuple:

    ctrl = controller.ControllerConfig()
    mpc = controller.make_planner(cfg, ctrl)
    opts = ctrl.sampling or SamplingOptions()
    env = controller.env_for(cfg, "native")
    model = prior.make_prior(massdist.voxel_masses(truth, cfg.box), None, cfg.box, cfg.gripper)
    key_reset, key_plan = jax.random.split(key)
    state = env.reset(key_reset, truth)
    rows, actions = [state], []
    sig_v, sig_p = rng.uniform(*rules.NOISE_SPEED), rng.uniform(*rules.NOISE_POSITION)
    scales = np.array([sig_v, sig_v, sig_p, sig_p])
    cap = opts.speed_cap or cfg.gripper.belt_speed_limit

    def obs():
        w = np.stack([np.asarray(r.s) for r in rows[-planning.MIN_WINDOW :]])
        w = np.concatenate([np.repeat(w[:1], planning.MIN_WINDOW - len(w), axis=0), w])
        return planning.observation(w, np.asarray(state.belt_speed), state.target_yaw)

    plan_state = mpc.init(obs())
    while not bool(state.done) and len(actions) < max_steps:
        key_plan, k = jax.random.split(key_plan)
        a, plan_state, _ = mpc.optimize(k, model, obs(), plan_state)
        a = perturb(cfg, rng, np.asarray(a, np.float64), scales, cap)
        state = env.step(state, a)
        rows.append(state)
        actions.append(a)
    return _arrays(rows, actions), state.summary()["failed_reason"]


def random_drive(cfg: Config, rng: np.random.Generator, target, left: int, s, b) -> tuple:
    """One step of the random drive (module docstring; the rule `baseline_device.random_action` follows on
    the device): (action (4,), target (2,), steps left) from the drive's target and steps left, the planar
    state `s` and the belt speeds `b`."""
    g = cfg.gripper
    dvmax = g.belt_accel_limit * g.control_dt
    vmax = 0.8 * g.belt_speed_limit
    hi = np.array([rules.RANDOM_SPEED, rules.RANDOM_SPEED, g.max_position_step, g.max_position_step])
    if left <= 0 or (abs(s[geometry.X]) > rules.X_TURN_BACK and target[0] * s[geometry.X] > 0):
        mode = rng.choice(list(rules.MODES), p=list(rules.MODE_P))
        v = rng.uniform(rules.SPEED_MIN, vmax)
        if mode == "turn":
            target = np.array([v, -v]) * rng.choice([-1, 1]) + rng.normal(0, rules.TURN_SPREAD, 2)
        elif mode == "translate":
            sign = -np.sign(s[geometry.X]) if abs(s[geometry.X]) > rules.X_CENTRE else rng.choice([-1, 1])
            target = np.full(2, sign * min(v, rules.TRANSLATE_CAP))
        elif mode == "stop":
            target = np.zeros(2)
        else:
            target = rng.uniform(-vmax, vmax, 2)
        left = int(rng.integers(*rules.HOLD))
    left -= 1
    a = np.concatenate([b + np.clip(target - b, -dvmax, dvmax), np.zeros(2)])
    bal = s[geometry.Y] - 0.5 * (s[geometry.P1] + s[geometry.P2])
    if abs(bal) > rules.BALANCE_CORRECT:
        a[2 + int(rng.integers(2))] = np.sign(bal) * rng.uniform(rules.STEP_MIN, g.max_position_step)
    if rng.random() < rules.P_RANDOM_DRIVE:
        a = rng.uniform(-hi, hi)
    return a, target, left


def _random_episode(cfg: Config, truth, key, rng: np.random.Generator, max_steps: int) -> tuple:

    env = controller.env_for(baseline_device.free_world(cfg), "native")
    state = env.reset(key, truth)
    rows, actions = [state], []
    target, left = np.zeros(2), 0
    while not bool(state.done) and len(actions) < max_steps:
        s, b = np.asarray(state.s, np.float64), np.asarray(state.belt_speed, np.float64)
        a, target, left = random_drive(cfg, rng, target, left, s, b)
        state = env.step(state, a)
        rows.append(state)
        actions.append(a)
    return _arrays(rows, actions), state.summary()["failed_reason"]


def _arrays(rows, actions) -> dict:
    return {
        "s": np.stack([np.asarray(r.s, np.float64) for r in rows]),
        "belt_speed": np.stack([np.asarray(r.belt_speed, np.float64) for r in rows]),
        "actions": np.asarray(actions, np.float64).reshape(-1, 4),
    }


def collect(
    cfg: Config,
    truth,
    n_episodes: int,
    seed: int = 0,
    progress: bool = True,
    backend: str = "native",
    max_steps: int | None = None,
) -> list[dict]:
    """`n_episodes` episodes on box `truth` (module docstring), simulated with native MuJoCo one at a time
    (`backend="native"`) or on MJX in batches on the device (`"mjx"`, `training.baseline_device`). Each:
    dict with s, belt_speed, actions, kind, outcome ("success" or the failure reason), explore (bool).
    `max_steps`: the step cap (default the task's).

    Raises:
      ValueError: an unknown backend.
    """
    if backend not in ("native", "mjx"):
        raise ValueError(f"unknown backend {backend!r}; choose 'native' or 'mjx'")
    keys = jax.random.split(jax.random.PRNGKey(seed), n_episodes)
    bar = _tqdm(n_episodes, f"W data (episodes, {backend})", progress)
    if backend == "mjx":
        out = baseline_device.collect(cfg, truth, keys, bar.update, max_steps)
        bar.close()
        return out
    rng = np.random.default_rng(seed)
    cap = cfg.task.max_steps if max_steps is None else max_steps
    out = []
    for i in range(n_episodes):
        kind = KINDS[i % len(KINDS)]
        if kind == "prior":
            explore = i % 2 == 0
            res = controller.run_episode(
                cfg, truth, keys[i], ctrl=controller.ControllerConfig(explore=explore), max_steps=cap
            )
            out.append(baseline_device.prior_episode(res, explore))
        else:
            episode = _noisy_prior_episode if kind == "prior-noisy" else _random_episode
            data, why = episode(cfg, truth, keys[i], rng, cap)
            out.append({**data, "kind": kind, "outcome": why or "success", "explore": False})
        bar.update(1)
    bar.close()
    return out


def transitions_of(episodes: list[dict]) -> dict:
    """All valid transitions of `episodes` (baseline.episode_transitions), concatenated, with `episode`
    (N,) the episode index of each."""
    parts = []
    for i, ep in enumerate(episodes):
        tr = baseline.episode_transitions(ep)
        if ep["outcome"] in _DROP and tr["action"].shape[0]:
            tr = {k: v[:-1] for k, v in tr.items()}
        ok = np.all(np.isfinite(tr["window"]), axis=(1, 2)) & np.all(np.isfinite(tr["s_next"]), axis=1)
        tr = {k: v[ok] for k, v in tr.items()}
        tr["episode"] = np.full(tr["action"].shape[0], i, np.int32)
        parts.append(tr)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def split(tr: dict, holdout_every: int = 10) -> tuple[dict, dict]:
    """(train, held-out) by episode: one in `holdout_every` episodes is held out, episode i when
    i % k == (i // k) % k (k = holdout_every), so the held-out set cycles through all episode kinds."""
    k = holdout_every
    held = tr["episode"] % k == (tr["episode"] // k) % k
    return {k: v[~held] for k, v in tr.items()}, {k: v[held] for k, v in tr.items()}


def train(
    train_tr: dict, config: baseline.BaselineConfig, seed: int, cfg: Config = DEFAULT, progress: bool = True
) -> tuple[baseline.BlackBoxModel, list]:
    """W trained on `train_tr` (AdamW, cosine decay over config.epochs); returns (model, epoch losses)."""
    X, Y = baseline.batch_features(train_tr, cfg.gripper)
    model = baseline.init_model(jax.random.PRNGKey(seed), config, cfg.gripper, baseline.normalisation(X, Y))
    Xn, Yn = baseline.standardise(model, X, Y)
    n = Xn.shape[0]
    nb = max(1, -(-n // config.batch))
    sched = optax.cosine_decay_schedule(config.lr, config.epochs * nb, alpha=0.02)
    opt = optax.adamw(sched, weight_decay=config.weight_decay)
    bar = _tqdm(config.epochs * nb, "W training (batches)", progress)
    model, _, losses = baseline.run_epochs(
        model,
        Xn,
        Yn,
        opt,
        opt.init(model.params),
        config.epochs,
        config.batch,
        np.random.default_rng(seed),
        bar,
    )
    bar.close()
    return model, losses


def compare_errors(model, tr: dict, truth, cfg: Config = DEFAULT) -> dict:
    """One-step errors on the same transitions: W, the physics prior with the true masses (default
    variant "slip"), constant velocity (median / p90 / mean, mm and degrees)."""
    pm = prior.make_prior(massdist.voxel_masses(truth, cfg.box), None, cfg.box, cfg.gripper)
    return {
        "blackbox": baseline.summarise_errors(baseline.one_step_errors(model, tr)),
        "prior": baseline.summarise_errors(baseline.one_step_errors(pm, tr, chunk=1024)),
        "constant_velocity": baseline.summarise_errors(baseline.constant_velocity_errors(tr)),
        "transitions": int(tr["action"].shape[0]),
    }


def train_baseline(
    cfg: Config = DEFAULT,
    distribution: str = "A",
    n_episodes: int = 200,
    seed: int = 0,
    out: str | None = None,
    config: baseline.BaselineConfig | None = None,
    progress: bool = True,
    data: str | None = None,
    backend: str = "native",
) -> dict:
    """Collect, train, score, save. Writes OUT/baseline.npz, OUT/dataset.npz and OUT/report.json when
    `out` is given; returns the report (plain data). `data`: the dataset.npz of an earlier run to train
    on instead of collecting (its `data_s` is then the load time, and "data_from" names the file);
    `backend`: how the episodes are collected (`collect`)."""
    if n_episodes < 2:
        raise ValueError(f"--episodes must be >= 2 (one is held out), got {n_episodes}")
    config = config or baseline.BaselineConfig()
    truth = massdist.named(distribution, cfg.box)
    t0 = time.perf_counter()
    if data is None:
        episodes = collect(cfg, truth, n_episodes, seed, progress, backend)
        tr = transitions_of(episodes)
        tr["episode_kind"] = np.array([e["kind"] for e in episodes])
        tr["episode_outcome"] = np.array([e["outcome"] for e in episodes])
    else:
        tr = load_dataset(data)
        if len(tr["episode_kind"]) != n_episodes:
            raise ValueError(f"{data} holds {len(tr['episode_kind'])} episodes, not --episodes {n_episodes}")
    t_data = time.perf_counter() - t0
    episodes = [
        {"kind": k, "outcome": o}
        for k, o in zip(tr.pop("episode_kind"), tr.pop("episode_outcome"), strict=True)
    ]
    holdout_every = 10 if n_episodes >= 10 else n_episodes
    train_tr, held = split(tr, holdout_every)
    if held["action"].shape[0] == 0:
        train_tr, held = split(tr, 2)
    t1 = time.perf_counter()
    model, losses = train(train_tr, config, seed, cfg, progress)
    jax.block_until_ready(model.params)
    t_train = time.perf_counter() - t1
    errors = compare_errors(model, held, truth, cfg)
    t2 = time.perf_counter()
    tr_err = compare_errors(model, {k: v[: min(len(v), 20000)] for k, v in train_tr.items()}, truth, cfg)
    kinds = {k: sum(e["kind"] == k for e in episodes) for k in dict.fromkeys(KINDS)}
    success = {k: sum(e["kind"] == k and e["outcome"] == "success" for e in episodes) for k in kinds}
    report = {
        "command": "train-baseline",
        "distribution": distribution,
        "episodes": n_episodes,
        "seed": seed,
        "episodes_by_kind": kinds,
        "successful_episodes_by_kind": success,
        "transitions": int(tr["action"].shape[0]),
        "train_transitions": int(train_tr["action"].shape[0]),
        "heldout_transitions": int(held["action"].shape[0]),
        "n_params": baseline.n_params(model),
        "config": config.to_dict(),
        "epoch_losses": [float(x) for x in losses],
        "heldout_errors": errors,
        "train_errors_first_20000": tr_err,
        "data_from": data or "collected",
        "backend": None if data else backend,
        "data_s": t_data,
        "train_s": t_train,
        "eval_s": time.perf_counter() - t2,
    }
    if out:
        os.makedirs(out, exist_ok=True)
        info = {
            k: report[k]
            for k in (
                "distribution",
                "episodes",
                "transitions",
                "train_transitions",
                "episodes_by_kind",
                "backend",
            )
        }
        info["heldout_errors"] = {m: errors[m] for m in ("blackbox", "prior", "constant_velocity")}
        report["weights"] = baseline.save(os.path.join(out, "baseline.npz"), model, seed, info)
        arrays = {
            **tr,
            "episode_kind": np.array([e["kind"] for e in episodes]),
            "episode_outcome": np.array([e["outcome"] for e in episodes]),
        }
        with atomic_path(os.path.join(out, "dataset.npz"), suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)
        report["dataset"] = os.path.join(out, "dataset.npz")
        with atomic_path(os.path.join(out, "report.json"), suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(report, f, indent=1)
    report["total_s"] = time.perf_counter() - t0
    return report


def load_dataset(path) -> dict:
    """The transitions (and episode_kind, episode_outcome) of a `train_baseline` dataset.npz."""

    arrays = read_npz(path, ValueError, "W dataset")
    need = ("window", "belt_speed", "action", "s_next", "episode", "episode_kind", "episode_outcome")
    missing = [k for k in need if k not in arrays]
    if missing:
        raise ValueError(f"{path}: not a W dataset (missing {missing})")
    return arrays


# The task's reasons, for readers of `collect`'s outcomes.
OUTCOMES = ("success", *task.REASONS)
