"""The on-device loop's state machines (`control.monitor_pure`, `estimator.guard_pure`) against the host
ones they port (`monitor.Monitor`, `explore.Guarded`): fed the same inputs, the same actions and decisions,
step by step, on random sequences built to visit every branch (stops, resumes, recoveries, time-outs,
final stops; trips, re-centring, the rest after the sequence)."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax.config import DEFAULT
from boxjax.control import monitor, monitor_pure
from boxjax.control.monitor import Check, MonitorConfig
from boxjax.estimator import explore, guard_pure

CFG = DEFAULT
LIMIT = CFG.task.balance_limit


def _stop_plan(rng, horizon):
    """A stop's actions: belts 0, carriage moves that end (then zeros), as `monitor.backup_actions`."""
    plan = np.zeros((horizon, 4), np.float32)
    n = rng.integers(0, horizon)
    plan[:n, 2:] = rng.uniform(-0.01, 0.01, (n, 1))
    return plan


def _checks(rng, n, horizon):
    x = np.zeros(n)  # mean-reverting, so that the predicted error wanders across both thresholds
    for t in range(1, n):
        x[t] = 0.8 * x[t - 1] + rng.normal(0, 0.004)
    go = np.clip(0.028 + x, 0.0, 0.05)
    for t in range(n):
        now = go[t] * rng.uniform(0.6, 1.0)
        yield Check(
            go=np.float32(go[t]),
            stop=np.float32(go[t] * rng.uniform(0.8, 1.1)),
            now=np.float32(now),
            go_ahead=np.float32(go[t] * rng.uniform(0.7, 1.0)),
            go_end=np.float32(now + rng.normal(0, 0.002)),
            stop_plan=_stop_plan(rng, horizon),
            go_stop=_stop_plan(rng, horizon),
            go_tip=np.float32(rng.uniform(0.005, 0.05)),  # the smallest stability margin (m)
            go_tip_slope=rng.uniform(0.0, 4.0, 3).astype(np.float32),  # and how fast it falls with the pose
        )


@pytest.mark.parametrize(
    "settings,seed,visits",
    [
        # a recovery that left the box further out ends the recoveries (`recover_until_worse`)
        (MonitorConfig(), 0, ("stops", "resumes", "recoveries", "recovery_failed")),
        (MonitorConfig(max_stops=3, stop_timeout=12), 1, ("stops", "ended")),  # final: timed out
        # (these two without the tipping watch, whose random margins would hold their stops)
        (MonitorConfig(recover=False, stop_timeout=20, k_sigma=2.0, tip_stop=0.0), 2, ("stops", "resumes")),
        # a resume and a recovery from rest count more of the estimate's std than the running stop
        (MonitorConfig(resume_k_sigma=3.0, tip_stop=0.0), 1, ("stops", "resumes", "recoveries")),
        # tipping stops, held while the action would tip
        (MonitorConfig(tip_stop=0.012), 0, ("stops", "resumes", "recoveries", "tip_stops")),
        # ... counting how fast the margin falls with the pose (no delay on the device: x and y alone)
        (MonitorConfig(tip_uncertainty="pose"), 1, ("stops", "resumes", "tip_stops")),
        # final: the max_stops-th stop
        (
            MonitorConfig(horizon=4, max_stops=3, stop_timeout=60, recover_gain=0.0),
            3,
            ("resumes", "recoveries", "ended"),
        ),
    ],
)
def test_pure_monitor_decides_as_the_host_monitor(settings, seed, visits):
    rng = np.random.default_rng(seed)
    host = monitor.Monitor(CFG, settings, 0)
    st = monitor_pure.init(settings)
    decide = jax.jit(partial(monitor_pure.decide, CFG, settings))
    sigma = 0.0 if seed % 2 == 0 else 0.001
    stopping, n_steps = [], 400
    for t, check in enumerate(_checks(rng, n_steps, settings.horizon)):
        action = np.zeros(4) if rng.random() < 0.25 else rng.uniform(-0.1, 0.1, 4)
        belts = rng.uniform(-0.02, 0.02, 2) if rng.random() < 0.5 else rng.uniform(-0.2, 0.2, 2)
        sent_host = host.decide(t, action, check, sigma, 0, belts)
        st, sent, ev = decide(
            st, jnp.asarray(action, jnp.float32), Check(*map(jnp.asarray, check)), sigma, jnp.asarray(belts)
        )
        np.testing.assert_allclose(np.asarray(sent), sent_host, atol=1e-7, err_msg=f"step {t}")
        assert bool(ev.stop) == (bool(host.stops) and host.stops[-1][0] == t), t
        assert bool(ev.tip) == (bool(ev.stop) and host.stops[-1][1] == monitor.TIP), t
        assert bool(ev.resume) == (bool(host.resumes) and host.resumes[-1] == t), t
        assert bool(ev.recovery) == (bool(host.recoveries) and host.recoveries[-1] == t), t
        assert bool(st.ended) == host.ended and bool(st.stopped) == host.stopped, t
        assert bool(st.recovery_failed) == host.recovery_failed, t
        if bool(ev.stopping):
            stopping.append(t)
    assert set(stopping) == host.stopping_steps
    assert int(st.balance_stops) == host.balance_stops
    host.tip_stops = [t for t, why in host.stops if why == monitor.TIP]
    assert all(getattr(host, what) for what in visits)  # the sequence visits what it is for


def test_pure_monitor_refuses_what_it_does_not_model():
    with pytest.raises(ValueError, match="shadow"):
        monitor_pure.check_supported(MonitorConfig(shadow=True))
    with pytest.raises(ValueError, match="delay"):
        monitor_pure.check_supported(MonitorConfig(), delay=2)


def _states(rng, n, swing_at):
    """Planar states whose balance offset wanders, then (from `swing_at`) swings away ~8 mm a step."""
    s = np.zeros((n, 5))
    s[:, 0], s[:, 1] = -0.1 + rng.normal(0, 0.001, n), 0.1 + rng.normal(0, 0.001, n)
    offset = np.cumsum(rng.normal(0, 0.002, n))
    offset[swing_at:] += 0.008 * np.arange(n - swing_at)
    s[:, 3] = offset + 0.5 * (s[:, 0] + s[:, 1])
    return s


@pytest.mark.parametrize(
    "guard,settle,lead,noise,swing_at,stop",
    [
        (0.875, 0, 3, 0.0, 30, "recentre"),
        (0.875, 2, 3, 0.003, 200, "recentre"),
        (0.875, 0, 0, 0.0, 10, "recentre"),
        (None, 3, 3, 0.0, 5, "recentre"),
        (0.875, 2, 3, 0.003, 30, "hold"),
    ],
)
def test_pure_guard_sends_what_the_host_guard_sends(guard, settle, lead, noise, swing_at, stop):
    rng = np.random.default_rng(swing_at)
    host = explore.Guarded(CFG, guard, settle=settle, lead=lead, noise=noise, stop=stop)
    st = guard_pure.init()
    step = jax.jit(
        partial(guard_pure.step, CFG, guard=guard, settle=settle, lead=lead, noise=noise, stop=stop)
    )
    for t, s in enumerate(_states(rng, 120, swing_at)):
        bal = abs(s[3] - 0.5 * (s[0] + s[1]))
        expected = host.next(s, bal)
        st, action, over = step(st, jnp.asarray(s, jnp.float32), jnp.float32(bal))
        assert bool(over) == (expected is None), t
        if expected is None:
            break
        np.testing.assert_allclose(np.asarray(action), expected, atol=1e-6, err_msg=f"step {t}")
    assert bool(over)
    assert bool(st.tripped) == host.tripped == (guard is not None and swing_at < 45)
    assert int(st.k) == host.k
    if host.tripped:
        np.testing.assert_allclose([float(st.worst), float(st.judged)], [host.worst, host.judged], atol=1e-6)
        text = explore.guard_explanation(
            CFG, int(st.k), float(st.worst), float(st.judged), lead, host.threshold, stop
        )
        assert text == host.why()
