"""The guarded exploration as a pure function (jnp, one box; vmap for batches), for closed loops that run on
the device (`boxjax.control.device_loop`).

It sends what `explore.Guarded.next` sends, step by step (a test feeds both the same states and compares
every action and the end): the fixed sequence while the balance error, extrapolated `lead` steps along its
trend, stays within the guard; once past it, `GUARD_STEPS` steps of its stop (re-centring or a hold) and the
exploration ends tripped; after the fixed sequence, `settle` rest steps. See `explore.Guarded` for why each
rule is there.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from boxjax import geometry
from boxjax.config import Config
from boxjax.estimator.explore import GUARD_STEPS, STOPS, exploration_actions


class GuardState(NamedTuple):
    """One box's exploration between control steps (a pytree; stack for a batch)."""

    k: jax.Array  # () int32 fixed-sequence steps sent
    settled: jax.Array  # () int32 rest steps sent after the fixed sequence
    recentring: jax.Array  # () int32 re-centring steps left once tripped (-1: not tripped)
    worst: jax.Array  # () m, the balance error that tripped the guard
    judged: jax.Array  # () m, the extrapolated balance error it tripped on
    history: jax.Array  # (3,) the last three signed balance offsets seen (m), newest last
    seen: jax.Array  # () int32 states seen so far (the history's fill, capped at 3)

    @property
    def tripped(self):
        return self.recentring >= 0


def init() -> GuardState:
    i = jnp.zeros((), jnp.int32)
    z = jnp.zeros((), jnp.float32)
    return GuardState(i, i, i - 1, z, z, jnp.zeros(3, jnp.float32), i)


def step(
    cfg: Config,
    st: GuardState,
    s,
    balance_error,
    guard: float | None,
    settle: int = 0,
    lead: int = 0,
    noise: float = 0.0,
    stop: str = "recentre",
) -> tuple[GuardState, jax.Array, jax.Array]:
    """(state, action (4,), over) for the state `s` (5,) the controller sees and its balance error:
    `explore.Guarded(cfg, guard, settle, lead, noise, stop).next(s, balance_error)`, whose None is `over`
    (then the action is zeros and must not be sent)."""
    if stop not in STOPS:
        raise ValueError(f"the guard's stop must be one of {STOPS}, got {stop!r}")
    actions = jnp.asarray(exploration_actions(cfg), jnp.float32)
    threshold = math.inf if guard is None else guard * cfg.task.balance_limit
    b = jnp.abs(balance_error).astype(jnp.float32)
    h = jnp.concatenate([st.history[1:], jnp.asarray(geometry.balance_offset(s), jnp.float32)[None]])
    seen = jnp.minimum(st.seen + 1, 3)
    side = jnp.where(h[2] >= 0, 1.0, -1.0)
    away = jnp.minimum(side * (h[2] - h[1]), side * (h[1] - h[0])) - 2.0 * math.sqrt(2.0) * noise
    judged = b if lead == 0 else jnp.where(seen < 3, b, b + lead * jnp.maximum(away, 0.0))
    trip = ~st.tripped & (judged > threshold)
    recentring = jnp.where(trip, GUARD_STEPS, st.recentring)
    worst = jnp.where(trip, b, st.worst)
    judged_at_trip = jnp.where(trip, judged, st.judged)
    tripped = recentring >= 0

    # tripped: re-centre (belts stopped, both carriages one clipped step toward the box's centre) or hold
    dp = jnp.clip(h[2], -cfg.gripper.max_position_step, cfg.gripper.max_position_step)
    dp = dp if stop == "recentre" else jnp.zeros_like(dp)
    recentre = jnp.stack([0.0, 0.0, dp, dp]).astype(jnp.float32)
    fixed_left = st.k < actions.shape[0]
    over = jnp.where(tripped, recentring == 0, ~fixed_left & (st.settled >= settle))
    fixed = actions[jnp.minimum(st.k, actions.shape[0] - 1)]
    action = jnp.where(tripped, recentre, jnp.where(fixed_left, fixed, jnp.zeros(4, jnp.float32)))
    action = jnp.where(over, jnp.zeros(4, jnp.float32), action)
    live = ~over
    new = GuardState(
        k=st.k + (live & ~tripped & fixed_left),
        settled=st.settled + (live & ~tripped & ~fixed_left),
        recentring=jnp.where(tripped & live, recentring - 1, recentring),
        worst=worst,
        judged=judged_at_trip,
        history=h,
        seen=seen,
    )
    return new, action, over
