"""W's training episodes on the device (`boxjax train-baseline --backend mjx`): the episode kinds of
`training.baseline` (its module docstring) collected in MJX worlds, vmapped over episodes and scanned over
control steps, with no host round trip per control step.

- "prior": the physics-prior pipeline as `controller.run_episode` runs it (oracle, default controller;
  with the exploration for even i, without for odd i), through the on-device closed loop
  (`control.device_loop.run_episodes`).
- "prior-noisy": the default planner on the true prior, its action perturbed as the host's
  `training.baseline.perturb` does (`noisy_action`: gaussian noise of a per-episode std, a uniformly random
  action with probability 0.1), from rest.
- "random": the host's random drive (`random_action`, the rule of `training.baseline.random_drive`), with the
  success rule off.

The two perturbed kinds run in one program each: `block` control steps of every episode per call
(`run_block`), the host stopping when every episode has ended or reached the step cap. Their rules are
the host's (`training.baseline_rules`; tests/test_baseline_device.py checks that the two draw from the same
distributions, state by state); their random draws are JAX's (per-episode keys from the same
`jax.random.split(PRNGKey(seed), n)` as the host's), and MJX's contact solver is not native MuJoCo's: the
episodes are of the same kinds, not the same episodes (the report and W's checkpoint record the backend).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning, prior
from boxjax.config import Config
from boxjax.control import ControllerConfig, batch, device_loop
from boxjax.planners.registry import make_planner
from boxjax.planners.sampling import SamplingOptions, clip_actions
from boxjax.sim import core, mjx_backend
from boxjax.training import baseline_rules as rules

BLOCK = 50  # control steps per program call (the host checks between calls whether every episode ended)


class Drive(NamedTuple):
    """The random drive's memory: its belt-speed target (2,) and the steps it is held for ()."""

    target: jax.Array
    left: jax.Array


def free_world(cfg: Config) -> Config:
    """The random drive's world (both backends): the success rule off (the box may keep turning)."""
    return cfg.replace(task=dataclasses.replace(cfg.task, target_yaw_delta=1e4))


def noise_scales(cfg: Config, key) -> jax.Array:
    """(4,) the per-episode std of the noise on (v1, v2, dp1, dp2) (the host's draw)."""
    kv, kp = jax.random.split(key)
    sv = jax.random.uniform(kv, (), minval=rules.NOISE_SPEED[0], maxval=rules.NOISE_SPEED[1])
    sp = jax.random.uniform(kp, (), minval=rules.NOISE_POSITION[0], maxval=rules.NOISE_POSITION[1])
    return jnp.stack([sv, sv, sp, sp])


def noisy_action(cfg: Config, key, planned, scales, cap: float) -> jax.Array:
    """The planned action plus gaussian noise of `scales`, or with probability `rules.P_RANDOM_NOISY` a
    uniformly random action within (cap, cap, max step, max step); clipped to the planner's limits."""
    g = cfg.gripper
    k_pick, k_uniform, k_noise = jax.random.split(key, 3)
    hi = jnp.array([cap, cap, g.max_position_step, g.max_position_step], jnp.float32)
    uniform = jax.random.uniform(k_uniform, (4,), minval=-hi, maxval=hi)
    noisy = planned + jax.random.normal(k_noise, (4,)) * scales
    a = jnp.where(jax.random.uniform(k_pick) < rules.P_RANDOM_NOISY, uniform, noisy)
    return clip_actions(a, cfg, cap)


def random_action(cfg: Config, key, drive: Drive, s, belt_speed) -> tuple[jax.Array, Drive]:
    """One step of the random drive (the rule of `training.baseline.random_drive`, pure): a belt-speed
    target (turn, translate, stop or any pair) held rules.HOLD steps, replaced early when it drives the box
    further out past rules.X_TURN_BACK, approached at the belts' acceleration limit; a carriage step against a
    balance error past rules.BALANCE_CORRECT; a uniformly random action with probability rules.P_RANDOM_DRIVE.
    Returns (action (4,), the drive's new memory)."""
    g = cfg.gripper
    ks = jax.random.split(key, 10)
    x = s[geometry.X]
    vmax = 0.8 * g.belt_speed_limit
    renew = (drive.left <= 0) | ((jnp.abs(x) > rules.X_TURN_BACK) & (drive.target[0] * x > 0))
    mode = jax.random.choice(ks[0], len(rules.MODES), p=jnp.asarray(rules.MODE_P))
    v = jax.random.uniform(ks[1], (), minval=rules.SPEED_MIN, maxval=vmax)
    side = jnp.where(jax.random.bernoulli(ks[2]), 1.0, -1.0)
    turn = jnp.array([v, -v]) * side + rules.TURN_SPREAD * jax.random.normal(ks[3], (2,))
    back = jnp.where(jnp.abs(x) > rules.X_CENTRE, -jnp.sign(x), side)
    translate = jnp.full(2, back * jnp.minimum(v, rules.TRANSLATE_CAP))
    anything = jax.random.uniform(ks[4], (2,), minval=-vmax, maxval=vmax)
    new_target = jnp.stack([turn, translate, jnp.zeros(2), anything])[mode]
    target = jnp.where(renew, new_target, drive.target)
    left = jnp.where(renew, jax.random.randint(ks[5], (), rules.HOLD[0], rules.HOLD[1]), drive.left) - 1

    dv = g.belt_accel_limit * g.control_dt
    a = jnp.concatenate([belt_speed + jnp.clip(target - belt_speed, -dv, dv), jnp.zeros(2)])
    bal = s[geometry.Y] - 0.5 * (s[geometry.P1] + s[geometry.P2])
    step = jnp.sign(bal) * jax.random.uniform(ks[6], (), minval=rules.STEP_MIN, maxval=g.max_position_step)
    which = jax.random.randint(ks[7], (), 0, 2)
    a = jnp.where((jnp.abs(bal) > rules.BALANCE_CORRECT) & (jnp.arange(4) == 2 + which), step, a)
    hi = jnp.array([rules.RANDOM_SPEED, rules.RANDOM_SPEED, g.max_position_step, g.max_position_step])
    uniform = jax.random.uniform(ks[8], (4,), minval=-hi, maxval=hi)
    a = jnp.where(jax.random.uniform(ks[9]) < rules.P_RANDOM_DRIVE, uniform, a)
    return a.astype(jnp.float32), Drive(target, left.astype(jnp.int32))


class Episode(NamedTuple):
    """One episode of a perturbed kind during the program (a pytree; stacked over episodes)."""

    state: core.State
    window: jax.Array  # (MIN_WINDOW, 5) the planner's window (prior-noisy)
    plan: Any  # the planner's state (prior-noisy; () for random)
    drive: Drive  # the random drive's memory (random)
    scales: jax.Array  # (4,) the noise's std (prior-noisy)
    key: jax.Array


@lru_cache(maxsize=4)
def _programs(cfg: Config, kind: str, block: int):
    """(start, run_block): the jitted programs of `kind` ("prior-noisy" or "random")."""
    ctrl = ControllerConfig()
    opts = ctrl.sampling or SamplingOptions()
    cap = opts.speed_cap or cfg.gripper.belt_speed_limit
    env = mjx_backend.env_for(free_world(cfg) if kind == "random" else cfg)
    mpc = make_planner(cfg, ctrl) if kind == "prior-noisy" else None

    def start(params, key):
        k_reset, k_scales, k_run = jax.random.split(key, 3)
        state = env.pure_init(params, k_reset)
        window = jnp.repeat(state.s[None], planning.MIN_WINDOW, axis=0)
        plan = ()
        if mpc is not None:
            plan = mpc.init(planning.observation(window, state.belt_speed, state.target_yaw))
        drive = Drive(jnp.zeros(2, jnp.float32), jnp.zeros((), jnp.int32))
        return Episode(state, window, plan, drive, noise_scales(cfg, k_scales), k_run)

    def run_block(ep: Episode, model, max_steps):
        def body(ep: Episode, _):
            key, k_plan, k_act = jax.random.split(ep.key, 3)
            plan, drive = ep.plan, ep.drive
            if mpc is not None:
                obs = planning.observation(ep.window, ep.state.belt_speed, ep.state.target_yaw)
                planned, plan, _ = mpc.optimize(k_plan, model, obs, ep.plan)
                a = noisy_action(cfg, k_act, planned, ep.scales, cap)
            else:
                a, drive = random_action(cfg, k_act, ep.drive, ep.state.s, ep.state.belt_speed)
            live = ~ep.state.done & (ep.state.t < max_steps)
            state = env.pure_step(ep.state, a)
            window = jnp.concatenate([ep.window[1:], state.s[None]])
            new = Episode(state, window, plan, drive, ep.scales, key)
            rec = {"s": state.s, "belt_speed": state.belt_speed, "action": a, "live": live}
            return jax.tree.map(lambda a, b: jnp.where(live, a, b), new, ep), rec

        return jax.lax.scan(body, ep, None, length=block)

    return (
        jax.jit(jax.vmap(start)),
        jax.jit(jax.vmap(run_block, in_axes=(0, None, None)), donate_argnums=0),
    )


def perturbed_episodes(
    cfg: Config,
    truth,
    keys,
    kind: str,
    slots: int | None = None,
    block: int = BLOCK,
    max_steps: int | None = None,
    progress=None,
) -> list[tuple[dict, str | None]]:
    """Episodes of `kind` ("prior-noisy" or "random") on box `truth`, one per key, on MJX: per episode
    ({"s": (T+1, 5), "belt_speed": (T+1, 2), "actions": (T, 4)}, failure reason or None), as the host's
    `_noisy_prior_episode` / `_random_episode` return.

    Args:
      slots: episodes per program call (default `device_loop.default_slots`).
      max_steps: the step cap (default the task's; an argument of the programs, not compiled in).
      progress: optional callable(number of episodes ended) after each call.
    Raises:
      ValueError: an unknown kind, slots or block < 1, more slots per CPU device than MJX can batch there.
    """
    if kind not in ("prior-noisy", "random"):
        raise ValueError(f"unknown perturbed episode kind {kind!r}; choose 'prior-noisy' or 'random'")
    if block < 1 or (slots is not None and slots < 1):
        raise ValueError(f"slots and block must be >= 1, got {slots} and {block}")
    n = len(keys)
    if n == 0:
        return []
    put, n_dev = batch.box_sharding()
    width = device_loop.default_slots(n_dev) if slots is None else slots
    width = -(-min(width, n) // n_dev) * n_dev
    if jax.default_backend() == "cpu" and width // n_dev > mjx_backend.CPU_CHUNK:
        raise ValueError(f"at most {mjx_backend.CPU_CHUNK * n_dev} slots on this CPU, got {width}")
    start, run_block = _programs(cfg, kind, block)
    env_cfg = free_world(cfg) if kind == "random" else cfg
    params = mjx_backend.env_for(env_cfg).box_params(truth)
    model = prior.make_prior(massdist.voxel_masses(truth, cfg.box), None, cfg.box, cfg.gripper)
    max_steps = cfg.task.max_steps if max_steps is None else max_steps
    cap = jnp.asarray(max_steps, jnp.int32)
    out: list[tuple[dict, str | None]] = []
    for lo in range(0, n, width):
        idx = list(range(lo, min(lo + width, n)))
        pad = idx + [idx[0]] * (width - len(idx))
        stacked = mjx_backend.stack([params] * width)
        ep = start(put(stacked), put(jnp.stack([batch.as_key(keys[i]) for i in pad])))
        s0, belt0 = np.asarray(ep.state.s), np.asarray(ep.state.belt_speed)
        recs = []
        while True:
            ep, rec = run_block(ep, model, cap)
            recs.append(jax.tree.map(np.asarray, rec))
            done = np.asarray(ep.state.done) | (np.asarray(ep.state.t) >= max_steps)
            if progress is not None:
                progress(len(out) + int(done[: len(idx)].sum()))
            if done.all():
                break
        rec = {k: np.concatenate([r[k] for r in recs], axis=1) for k in recs[0]}
        final = jax.tree.map(np.asarray, ep.state._replace(physics=None, model=None))
        for k in range(len(idx)):
            live = rec["live"][k]
            data = {
                "s": np.concatenate([s0[k][None], rec["s"][k][live]]).astype(np.float64),
                "belt_speed": np.concatenate([belt0[k][None], rec["belt_speed"][k][live]]).astype(np.float64),
                "actions": rec["action"][k][live].astype(np.float64).reshape(-1, 4),
            }
            out.append((data, jax.tree.map(lambda x, k=k: x[k], final).summary()["failed_reason"]))
    return out


def prior_episode(result, explore: bool) -> dict:
    """W's episode dict of a "prior" kind episode (an EpisodeResult of either backend's closed loop)."""
    s = result.summary
    data = {"s": result.trace.s, "belt_speed": result.trace.belt_speed, "actions": result.trace.actions}
    outcome = "success" if s["success"] else (s["failed_reason"] or "success")
    return {**data, "kind": "prior", "outcome": outcome, "explore": explore}


def collect(cfg: Config, truth, keys, progress=None, max_steps: int | None = None) -> list[dict]:
    """W's episodes on box `truth`, one per key, episode i of kind `rules.KINDS[i % 5]` (as the host's
    `training.baseline.collect`): the "prior" ones through `device_loop.run_episodes` (with the exploration
    for even i), the perturbed ones through `perturbed_episodes`. `progress`: optional callable(k) called
    with each k episodes ended; `max_steps`: the step cap (default the task's). Returns the host's episode
    dicts, in order."""
    n = len(keys)
    kinds = [rules.KINDS[i % len(rules.KINDS)] for i in range(n)]
    out: list[dict | None] = [None] * n
    tick = progress or (lambda k: None)
    for explore in (True, False):
        idx = [i for i in range(n) if kinds[i] == "prior" and (i % 2 == 0) == explore]
        if not idx:
            continue
        res = device_loop.run_episodes(
            cfg, [truth] * len(idx), [keys[i] for i in idx], ctrl=ControllerConfig(explore=explore),
            max_steps=max_steps, progress=lambda b, r: tick(1),
        )  # fmt: skip
        for i, r in zip(idx, res, strict=True):
            out[i] = prior_episode(r, explore)
    for kind in ("prior-noisy", "random"):
        idx = [i for i in range(n) if kinds[i] == kind]
        ended = [0]

        def step(k, ended=ended):
            tick(k - ended[0])
            ended[0] = k

        eps = perturbed_episodes(cfg, truth, [keys[i] for i in idx], kind, max_steps=max_steps, progress=step)
        for i, (data, why) in zip(idx, eps, strict=True):
            out[i] = {**data, "kind": kind, "outcome": why or "success", "explore": False}
    return out  # type: ignore[return-value]
