"""Run one closed-loop episode on either backend and keep its trace."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from boxjax.sim.core import State


class EpisodeTrace(NamedTuple):
    """What happened in an episode (numpy, T = control steps taken).

    time: (T+1,) s.  s: (T+1, 5) planar states.  belt_speed: (T+1, 2) m/s.  actions: (T, 4) as commanded.
    balance_error: (T+1,) m.  clipped: (T,) bool.  wall_s: seconds of wall time for the whole episode.
    """

    time: np.ndarray
    s: np.ndarray
    belt_speed: np.ndarray
    actions: np.ndarray
    balance_error: np.ndarray
    clipped: np.ndarray
    wall_s: float

    @classmethod
    def from_lists(cls, control_dt, s, belt_speed, actions, balance_error, clipped, wall_s) -> EpisodeTrace:
        """A trace from a host loop's per-step lists: T+1 states, belt speeds and balance errors, T actions
        and clipped flags."""
        return cls(
            time=np.arange(len(s)) * control_dt,
            s=np.stack(s),
            belt_speed=np.stack(belt_speed),
            actions=np.asarray(actions, np.float64).reshape(-1, 4),
            balance_error=np.asarray(balance_error),
            clipped=np.asarray(clipped, bool),
            wall_s=wall_s,
        )

    @classmethod
    def from_states(
        cls, states: list[State], actions: list, control_dt: float, wall_s: float
    ) -> EpisodeTrace:
        """Build a trace from the T+1 states visited and the T actions sent."""
        return cls(
            time=np.arange(len(states)) * control_dt,
            s=np.stack([np.asarray(r.s) for r in states]),
            belt_speed=np.stack([np.asarray(r.belt_speed) for r in states]),
            actions=np.asarray(actions, dtype=np.float64).reshape(-1, 4),
            balance_error=np.asarray([float(r.balance_error) for r in states]),
            clipped=np.asarray([bool(r.clipped) for r in states[1:]], dtype=bool),
            wall_s=wall_s,
        )


Policy = Callable[[State, jax.Array], np.ndarray]  # (state, key) -> action (4,)


def run_episode(env, state: State, policy: Policy, key, max_steps: int) -> tuple[State, EpisodeTrace]:
    """Step `env` with `policy` until the episode ends or `max_steps` control steps were taken."""
    step = env.step
    rows = [state]
    actions = []
    t0 = time.perf_counter()
    for _ in range(max_steps):
        if bool(state.done):
            break
        key, key_act = jax.random.split(key)
        a = np.asarray(policy(state, key_act), dtype=np.float64)
        state = step(state, a)
        actions.append(a)
        rows.append(state)
    trace = EpisodeTrace.from_states(rows, actions, env.cfg.gripper.control_dt, time.perf_counter() - t0)
    return state, trace


def naive_policy(speed: float) -> Policy:
    """The non-adaptive rotation of paper §2: belts in opposite directions at constant speed, no position
    control. Left belt +x, right belt -x turns the box counter-clockwise (yaw increasing)."""
    a = np.array([speed, -speed, 0.0, 0.0])
    return lambda state, key: a


def random_policy(cfg) -> Policy:
    """Uniformly random actions within the hardware limits (belt speeds and position steps)."""
    g = cfg.gripper
    hi = np.array([g.belt_speed_limit, g.belt_speed_limit, g.max_position_step, g.max_position_step])

    def policy(state, key):
        return np.asarray(jax.random.uniform(key, (4,), minval=-hi, maxval=hi))

    return policy
