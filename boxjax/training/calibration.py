"""Calibrating the action -> force map by simulation (paper §2.4, "Mapping controls to forces").

`collect_transitions` runs short episodes of the uniform box (massdist.named("uniform")) on the native
simulator with DISJOINT random actions: every control step changes exactly one of the four action
components, drawn as an increment,

  component 0, 1 (belt speeds): dv ~ U(-belt_accel_limit * control_dt, +...) m/s around the belt's
    current speed, sent to the simulator as the setpoint belt_speed_i + dv (the other belt's setpoint
    is its current speed, so its increment is 0);
  component 2, 3 (belt positions): dp ~ U(-max_position_step, +max_position_step) m (the other 0).

The components come in random permutations of (0, 1, 2, 3), so each gets a quarter of the steps. An
episode ends (and the next one starts from a fresh reset) after `episode_steps` control steps, when the
box nears a belt end (its footprint could reach past the belt), or when the simulator ends it (balance
or off-belt failure: `state.done`). A transition s_t -> s_{t+1} is kept when its window s_{t-2..t+1}
lies in one episode (so the first two steps of an episode only provide history) and s_{t+1} is not a
failure state.

`calibrate` then recovers each transition's force with `calibrate.recover_forces` (F = M delta(acc_c)
- F_f1 - F_f2), keeps the active component's scalar (`component_force`) against its action value
(`action_values`: dv_i = setpoint - belt speed, dp_i), and bins them with `fit_force_map` on
`default_grid`. Keys are explicit: the same key gives the same transitions and the same map.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from boxjax import massdist
from boxjax.config import Config
from boxjax.prior import force_map as calibrate
from boxjax.sim import make_env

DEFAULT_TRANSITIONS = 400
DEFAULT_EPISODE_STEPS = 60  # 3 s at 20 Hz: "short episodes"
GRID_POINTS = 9


class Transitions(NamedTuple):
    """Calibration transitions (numpy, n = number kept).

    windows: (n, 4, 5) planar states s_{t-2}, s_{t-1}, s_t, s_{t+1}; the action acted between s_t and s_{t+1}.
    actions: (n, 4) the environment actions sent (v1, v2 setpoints in m/s; dp1, dp2 in m).
    belt_speed: (n, 2) m/s, measured belt speeds at s_t (before the action).
    component: (n,) int32, the action's active component (0..3).
    episode: (n,) int32, the episode each transition came from.
    n_episodes: number of episodes run; n_steps: control steps simulated in all.
    """

    windows: np.ndarray
    actions: np.ndarray
    belt_speed: np.ndarray
    component: np.ndarray
    episode: np.ndarray
    n_episodes: int
    n_steps: int


class Calibration(NamedTuple):
    """The result of `calibrate`: the fitted map, the samples it was fitted on, and a summary."""

    force_map: calibrate.ForceMap
    component: np.ndarray  # (n,) int32
    value: np.ndarray  # (n,) the active component's action value (m/s or m)
    force: np.ndarray  # (n,) N, the recovered force of the active component
    transitions: Transitions
    info: dict


def belt_end_limit(cfg: Config) -> float:
    """m: the largest |x| of the box centre at which the box's footprint, in any yaw, stays on the belts
    (half the belt length minus half the box's planar diagonal)."""
    hx, hy, _ = cfg.box.half_size
    return cfg.gripper.belt_length / 2 - float(np.hypot(hx, hy))


def _episode_draws(key, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(components (n_steps,) int, u (n_steps,) in [-1, 1)) for one episode: components in random
    permutations of 0..3, increments uniform."""
    key_c, key_u = jax.random.split(key)
    blocks = -(-n_steps // calibrate.N_COMPONENTS)
    perms = jax.vmap(lambda k: jax.random.permutation(k, calibrate.N_COMPONENTS))(
        jax.random.split(key_c, blocks)
    )
    u = jax.random.uniform(key_u, (n_steps,), minval=-1.0, maxval=1.0)
    return np.asarray(perms).reshape(-1)[:n_steps].astype(np.int32), np.asarray(u, np.float64)


def disjoint_action(component: int, u: float, belt_speed, cfg: Config) -> np.ndarray:
    """(4,) environment action with one active component: the belt-speed setpoint belt_speed_c + u a dt
    for c in (0, 1), or the position increment u max_position_step for c in (2, 3); the other belt's
    setpoint is its current speed and the other position increment 0 (their action values are 0)."""
    g = cfg.gripper
    a = np.zeros(4)
    a[:2] = np.asarray(belt_speed, np.float64)
    if component < 2:
        a[component] += u * g.belt_accel_limit * g.control_dt
    else:
        a[component] = u * g.max_position_step
    return a


def collect_transitions(
    cfg: Config,
    key,
    n_transitions: int = DEFAULT_TRANSITIONS,
    *,
    episode_steps: int = DEFAULT_EPISODE_STEPS,
    progress: bool = True,
    env=None,
) -> Transitions:
    """Simulate disjoint random actions on the uniform box until `n_transitions` are kept (module
    docstring). `env`: a native environment for `cfg` to reuse (default: a new one).

    Raises:
      ValueError: n_transitions < 1 or episode_steps < 3.
      RuntimeError: far more steps than transitions were needed (episodes keep failing at once).
    """

    if n_transitions < 1:
        raise ValueError(f"need at least 1 transition, got {n_transitions}")
    if episode_steps < 3:
        raise ValueError(f"episode_steps must be >= 3 (two steps of history per window), got {episode_steps}")
    env = make_env(cfg, "native") if env is None else env
    dist = massdist.named("uniform", cfg.box)
    x_limit = belt_end_limit(cfg)
    max_total = 20 * n_transitions + 10 * episode_steps
    windows, actions, speeds, comps, episodes = [], [], [], [], []
    n_steps = n_episodes = 0
    bar = tqdm(total=n_transitions, desc="calibration", unit="transition", disable=not progress, leave=False)
    try:
        while len(windows) < n_transitions:
            if n_steps >= max_total:
                raise RuntimeError(
                    f"calibration kept only {len(windows)} of {n_transitions} transitions in {n_steps} "
                    "steps: episodes end too early"
                )
            key_ep = jax.random.fold_in(key, n_episodes)
            key_reset, key_draw = jax.random.split(key_ep)
            comp_seq, u_seq = _episode_draws(key_draw, episode_steps)
            state = env.reset(key_reset, dist)
            hist = [np.asarray(state.s, np.float64)]
            for t in range(episode_steps):
                c = int(comp_seq[t])
                speed = np.asarray(state.belt_speed, np.float64)
                a = disjoint_action(c, float(u_seq[t]), speed, cfg)
                state = env.step(state, a)
                n_steps += 1
                s_next = np.asarray(state.s, np.float64)
                if t >= 2 and not bool(state.done):
                    windows.append(np.stack([*hist[-3:], s_next]))
                    actions.append(a)
                    speeds.append(speed)
                    comps.append(c)
                    episodes.append(n_episodes)
                    bar.update(1)
                    if len(windows) >= n_transitions:
                        break
                hist.append(s_next)
                if bool(state.done) or abs(s_next[2]) > x_limit:
                    break
            n_episodes += 1
    finally:
        bar.close()
    return Transitions(
        windows=np.asarray(windows, np.float64).reshape(-1, 4, 5),
        actions=np.asarray(actions, np.float64).reshape(-1, 4),
        belt_speed=np.asarray(speeds, np.float64).reshape(-1, 2),
        component=np.asarray(comps, np.int32),
        episode=np.asarray(episodes, np.int32),
        n_episodes=n_episodes,
        n_steps=n_steps,
    )


def recover_samples(tr: Transitions, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """(value (n,), force (n,)): each transition's active action value and recovered force (N)."""
    masses = massdist.voxel_masses(massdist.named("uniform", cfg.box), cfg.box)
    g, box = cfg.gripper, cfg.box

    @jax.jit
    def one(window, action, speed, comp):
        f, _ = calibrate.recover_forces(window, masses, box, g)
        v = calibrate.action_values(action, speed, g)
        return v[comp], calibrate.component_force(f, comp)

    value, force = jax.vmap(one)(
        jnp.asarray(tr.windows, jnp.float32),
        jnp.asarray(tr.actions, jnp.float32),
        jnp.asarray(tr.belt_speed, jnp.float32),
        jnp.asarray(tr.component),
    )
    return np.asarray(value, np.float64), np.asarray(force, np.float64)


def calibrate_by_simulation(
    cfg: Config,
    key,
    n_transitions: int = DEFAULT_TRANSITIONS,
    *,
    episode_steps: int = DEFAULT_EPISODE_STEPS,
    grid_points: int = GRID_POINTS,
    progress: bool = True,
) -> Calibration:
    """Collect transitions, recover their forces and fit the force map on `default_grid` (module
    docstring). Same key -> same result.

    Raises:
      ValueError: bad sizes, or a component without any sample (too few transitions).
    """
    t0 = time.perf_counter()
    tr = collect_transitions(cfg, key, n_transitions, episode_steps=episode_steps, progress=progress)
    value, force = recover_samples(tr, cfg)
    fm = calibrate.fit_force_map(tr.component, value, force, calibrate.default_grid(cfg.gripper, grid_points))
    info = {
        "transitions": int(tr.component.size),
        "episodes": int(tr.n_episodes),
        "steps_simulated": int(tr.n_steps),
        "episode_steps": int(episode_steps),
        "per_component": [int(np.sum(tr.component == c)) for c in range(calibrate.N_COMPONENTS)],
        "wall_s": time.perf_counter() - t0,
    }
    return Calibration(fm, tr.component, value, force, tr, info)
