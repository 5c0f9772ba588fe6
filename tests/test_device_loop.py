"""The whole closed loop on the device (`boxjax.control.device_loop`, `evaluate --backend mjx`), on a CPU:
every episode ends with an outcome, the exploration is the guarded fixed sequence, a refused box is not
turned, the slots are refilled, the monitor's stops are stops, and what the loop cannot run (and an
MJX evaluation's replay) is refused by name. (Its
decisions are the host's: tests/test_pure_state_machines.py.)"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig, batch, device_loop, true_stability_margins
from boxjax.estimator import explore
from boxjax.experiments import evaluation as experiments
from boxjax.experiments.evaluation import outcome
from boxjax.planners.sampling import SamplingOptions
from boxjax.sim.faults import Faults

# a planner without gradient steps: it compiles in a fraction of the default's time (as tests/test_batch.py)
CTRL = ControllerConfig(sampling=SamplingOptions(gradient_steps=0))
NAMES = ("uniform", "D", "A")


@pytest.fixture(scope="module")
def episodes():
    dists = [massdist.named(n, cfg.box) for n in NAMES]
    keys = [jax.random.PRNGKey(j) for j in range(len(NAMES))]
    ended = []
    res = device_loop.run_episodes(
        cfg, dists, keys, ctrl=CTRL, slots=2, block=10, max_steps=200, progress=lambda b, r: ended.append(b)
    )
    return dists, keys, res, ended


def test_every_episode_ends_with_an_outcome_and_the_hazard_is_refused(episodes):
    dists, _, res, ended = episodes
    assert sorted(ended) == [0, 1, 2]
    outcomes = [outcome(r.summary) for r in res]
    assert outcomes[1] == "aborted" and "hazard" in res[1].summary["abort_reason"]
    assert res[1].summary["steps"] == explore.N_STEPS  # refused after exploring: never turned
    assert all(o in ("success", "aborted", "safe_stop", "unbalanced", "step_cap", "tipped") for o in outcomes)
    assert outcomes[0] == "success"  # the uniform box turns on MJX too
    for r in res:
        assert len(r.trace.s) == len(r.trace.actions) + 1 == r.summary["steps"] + 1
        assert r.summary["exploration_steps"] == explore.N_STEPS
        np.testing.assert_allclose(
            r.trace.actions[: explore.N_STEPS], explore.exploration_actions(cfg), atol=1e-6
        )
        assert not r.summary["unnoticed_crossing"]
        # the true box's stability margin along the device's states, as on the native path
        margins = true_stability_margins(cfg, r.truth, r.trace.s)
        assert r.summary["min_stability_margin_m"] == float(np.min(margins))
        turned = not r.summary["aborted"]
        assert r.summary["turn_min_stability_margin_m"] == (
            float(np.min(margins[explore.N_STEPS + 1 :])) if turned else None
        )


def test_an_mjx_evaluation_is_not_replayed(monkeypatch):
    monkeypatch.setattr(experiments, "load_boxes", lambda out_dir: ([None], {"backend": "mjx"}))
    with pytest.raises(ValueError, match="cannot be re-simulated"):
        experiments.replay(cfg, "ev/", 0)


def test_the_monitors_stops_send_stops(episodes):
    for r in episodes[2]:
        for t in r.summary.get("monitor_stop_steps", []):
            assert np.all(r.trace.actions[t, :2] == 0.0)  # a stop commands the belts to rest


def test_what_the_device_loop_cannot_run_is_refused_by_name():
    assert "faults" in device_loop.supports(CTRL, Faults(obs_noise_mm=3.0))
    assert "simulator" in device_loop.supports(ControllerConfig(planner="simulator"))
    with pytest.raises(ValueError, match="block"):
        device_loop.run_episodes(cfg, [massdist.named("A", cfg.box)], [jax.random.PRNGKey(0)], block=0)


@pytest.mark.slow
def test_mjx_worlds_behind_the_native_batch_interface_pause_and_refuse_bad_actions():
    from boxjax.sim.mjx_backend import MjxBatch

    sim = MjxBatch(cfg, [massdist.named(n, cfg.box) for n in ("A", "uniform")], [jax.random.PRNGKey(0)] * 2)
    s0 = sim.s.copy()
    sim.step(np.tile([0.1, -0.1, 0.0, 0.0], (2, 1)), np.array([True, False]))
    assert (
        sim.t.tolist() == [1, 0] and np.array_equal(sim.s[1], s0[1]) and not np.array_equal(sim.s[0], s0[0])
    )
    bad = np.zeros((2, 4))
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"worlds \[1\]"):
        sim.step(bad)
    assert sim.state(0).summary()["steps"] == 1
    with pytest.raises(ValueError, match="faults"):
        batch.run_episodes(
            cfg,
            [massdist.named("A", cfg.box)],
            [jax.random.PRNGKey(0)],
            faults=Faults(obs_noise_mm=3.0),
            backend="mjx",
        )


@pytest.mark.slow
def test_the_monitor_checks_with_its_own_prior_on_the_device(monkeypatch):
    """`MonitorConfig.prior_params` on the device: the turn's program checks with the slot's own prior
    (recorded as the program is traced), and the episode ends with an outcome."""
    from boxjax.control import monitor
    from boxjax.control.monitor import MonitorConfig
    from boxjax.prior import PriorParams

    own = PriorParams(carriage_omega=30.0, slip_eps=0.02)
    ctrl = ControllerConfig(
        sampling=SamplingOptions(gradient_steps=0), monitor=MonitorConfig(prior_params=own)
    )
    traced = []
    real = monitor.predicted_errors

    def spy(cfg_, model, *args, **kwargs):
        traced.append(model.params)
        return real(cfg_, model, *args, **kwargs)

    monkeypatch.setattr(monitor, "predicted_errors", spy)
    res = device_loop.run_episodes(
        cfg,
        [massdist.named("A", cfg.box)],
        [jax.random.PRNGKey(0)],
        ctrl=ctrl,
        slots=1,
        block=10,
        max_steps=80,
    )
    assert traced and all(p == own for p in traced)
    assert outcome(res[0].summary) is not None


def test_the_device_loops_record_names_tipping_stops():
    """The on-device events become the host monitor's record: a stop at a step of the `tip` events is a
    "tip" stop, the episode's reason the last stop's."""
    from boxjax.control import monitor

    rec = device_loop._MonitorRecord([5, 30], [12], [], [5, 6, 30], stopped=True, tips=[30])
    assert rec.stops == [(5, monitor.BALANCE), (30, monitor.TIP)] and rec.reason == monitor.TIP
    assert rec.record()["monitor_stop_reasons"] == [monitor.BALANCE, monitor.TIP]
    assert device_loop._MonitorRecord([5], [], [], [5], stopped=True).reason == monitor.BALANCE


@pytest.mark.slow
def test_the_tipping_watch_runs_on_the_device(monkeypatch):
    """`MonitorConfig.tip_stop` on the device: the turn's program asks the check for the stability margin,
    and the episode ends with an outcome."""
    from boxjax.control import monitor
    from boxjax.control.monitor import MonitorConfig

    ctrl = ControllerConfig(sampling=SamplingOptions(gradient_steps=0), monitor=MonitorConfig(tip_stop=0.015))
    asked = []
    real = monitor.predicted_errors

    def spy(*args, **kwargs):
        asked.append(kwargs.get("tip", False))
        return real(*args, **kwargs)

    monkeypatch.setattr(monitor, "predicted_errors", spy)
    box, key = massdist.named("C", cfg.box), jax.random.PRNGKey(0)
    res = device_loop.run_episodes(cfg, [box], [key], ctrl=ctrl, slots=1, block=10, max_steps=80)
    assert asked and all(asked)
    assert outcome(res[0].summary) is not None
