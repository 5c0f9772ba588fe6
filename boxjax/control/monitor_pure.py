"""The runtime safety monitor's state machine as a pure function (jnp, one box; vmap for batches), for
closed loops that run on the device (`boxjax.control.device_loop`): no host round trip per control step.

It makes the decisions `monitor.Monitor.decide` makes (a test feeds both the same checks and compares every
action sent, stop, resume and recovery), for the world the on-device loop simulates: fresh frames every
step and no loop delay (no sensor or action latency, so nothing is predicted over a delay and no frame is
stale). The thresholds, the committed stop plan, the rest watch, the recovery, `max_stops` and
`stop_timeout` are the host monitor's; see `boxjax.control.monitor` for what each means.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from boxjax.config import Config
from boxjax.control.monitor import Check, MonitorConfig, recovery_worse, tip_margin


class MonitorState(NamedTuple):
    """One box's monitor between control steps (a pytree; stack for a batch)."""

    stopped: jax.Array  # () bool: mode STOP (a balance stop: no stale frames here)
    stopped_for: jax.Array  # () int32 control steps since the stop was issued
    balance_stops: jax.Array  # () int32
    final: jax.Array  # () bool: the stop will not resume
    ended: jax.Array  # () bool: final and the gripper at rest: the episode ends `safe_stop`
    recovering: jax.Array  # () bool: a recovery sent, the gripper not yet known at rest again
    plan: jax.Array  # (horizon, 4) the committed stop's actions
    plan_i: jax.Array  # () int32 next action of `plan` to send
    plan_n: jax.Array  # () int32 actions in `plan` (then rest)
    rest_run: jax.Array  # () int32 rest actions (all zeros) sent in a row up to now
    judging: jax.Array  # () bool: a recovery not yet judged (`recover_until_worse`)
    recovered_from: jax.Array  # () float32 the balance error it was sent at (m)
    recovery_failed: jax.Array  # () bool: a recovery left the box further out: no more recoveries


class Events(NamedTuple):
    """What one `decide` did (each () bool): for the episode's record (`Monitor.record`)."""

    stop: jax.Array  # a stop was issued at this step
    resume: jax.Array
    recovery: jax.Array
    stopping: jax.Array  # the action sent is a stop's (`Monitor.stopping_steps`)
    tip: jax.Array  # the stop issued at this step is a tipping stop (`MonitorConfig.tip_stop`)


def check_supported(settings: MonitorConfig, delay: int = 0) -> None:
    """Raise ValueError naming what the pure monitor does not model (the host `Monitor` does)."""
    if settings.shadow:
        raise ValueError("the on-device monitor does not run in shadow mode (use the host loop)")
    if delay:
        raise ValueError(
            f"the on-device monitor runs with fresh frames and no loop delay, not {delay} steps of delay "
            "(faults run on the native backend)"
        )


def init(settings: MonitorConfig) -> MonitorState:
    """A monitor that has sent nothing yet (running)."""
    f, i = jnp.zeros((), bool), jnp.zeros((), jnp.int32)
    plan = jnp.zeros((settings.horizon, 4), jnp.float32)
    return MonitorState(f, i, i, f, f, f, plan, i, i, i, f, jnp.zeros((), jnp.float32), f)


def decide(
    cfg: Config, settings: MonitorConfig, st: MonitorState, action, check: Check, sigma, belt_speed
) -> tuple[MonitorState, jax.Array, Events]:
    """(state, the action to send (4,), events) at one control step: `Monitor.decide` with no delay and
    fresh frames. `check`: `monitor.predicted_errors` for the planner's `action` (one box); `sigma`: the
    std of the estimate's y (m)."""
    m = settings
    limit = cfg.task.balance_limit
    stop_at, resume_below = m.stop_at * limit, m.resume_below * limit
    action = jnp.asarray(action, jnp.float32)
    # known at rest: the last action sent was rest (delay 0: a window of one) and the belts are at rest
    still = (st.rest_run >= 1) & jnp.all(jnp.abs(belt_speed) <= m.standstill_speed)
    recovering = st.recovering & ~still
    margin = m.k_sigma * jnp.asarray(sigma, jnp.float32)  # no delay: the estimate's margin alone
    # the last recovery played out: judged
    judged = still & st.judging
    failed = st.recovery_failed | (judged & recovery_worse(st.recovered_from, check.now, margin))
    go_error = check.go + margin
    k_resume = m.k_sigma if m.resume_k_sigma is None else m.resume_k_sigma
    resume_margin = k_resume * jnp.asarray(sigma, jnp.float32)  # from rest: what a resume or recovery counts
    running = ~st.stopped
    # the action and its stop predicted to bring the centre of mass near the support's edge
    tip = tip_margin(m, check, margin, 0, still)  # no delay on the device
    tipping = (check.go_tip - tip < m.tip_stop) if m.tip_stop > 0 else jnp.zeros((), bool)

    # running: a stop when the action and a stop after it are predicted too close to the limit, or to tip
    balance = go_error >= stop_at
    stop_now = running & (balance | tipping)
    balance_stops = st.balance_stops + stop_now
    final = jnp.where(stop_now, balance_stops >= m.max_stops, st.final)
    # stopped: resume, recover, or time out
    stopped_for = jnp.where(running, 0, st.stopped_for + 1)
    active = st.stopped & ~st.final
    resume = active & still & (check.go + resume_margin < resume_below) & ~tipping
    recovers = (
        ~failed & (check.go_ahead + resume_margin < stop_at) & (check.go_end <= check.now - m.recover_gain)
    )
    recovery = active & ~resume & still & m.recover & recovers & ~tipping
    timeout = active & ~resume & ~recovery & (stopped_for >= m.stop_timeout)
    final = final | timeout
    ended = st.ended | (st.stopped & ~recovery & final & still & (stopped_for >= 2))
    recovering = recovering | recovery
    judging = (st.judging & ~judged) | (recovery & m.recover_until_worse)
    recovered_from = jnp.where(recovery, check.now, st.recovered_from)
    stopped = (st.stopped | stop_now) & ~resume

    # the committed plan: a new stop's, a recovery's (its stop without the last step), else as it was
    plan = jnp.where(stop_now, check.stop_plan, jnp.where(recovery, check.go_stop, st.plan))
    plan_n = jnp.where(stop_now, m.horizon, jnp.where(recovery, m.horizon - 1, st.plan_n))
    plan_i = jnp.where(stop_now | recovery, 0, st.plan_i)
    pop = stopped & ~recovery  # a stop's action is sent (a recovery sends the planner's own)
    has_plan = plan_i < plan_n
    from_plan = jnp.where(has_plan, plan[jnp.minimum(plan_i, plan.shape[0] - 1)], jnp.zeros(4, jnp.float32))
    sent = jnp.where(pop, from_plan, action)
    plan_i = plan_i + (pop & has_plan)
    rest_run = jnp.where(jnp.all(sent == 0), st.rest_run + 1, 0)
    new = MonitorState(
        stopped, stopped_for, balance_stops, final, ended, recovering, plan, plan_i, plan_n, rest_run,
        judging, recovered_from, failed,
    )  # fmt: skip
    events = Events(
        stop=stop_now, resume=resume, recovery=recovery, stopping=pop & ~recovering, tip=stop_now & ~balance
    )
    return new, sent, events
