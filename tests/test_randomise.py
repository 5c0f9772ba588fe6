"""Domain randomisation of H's training data (boxjax.training.randomise): the view it trains on is the
view the controller's estimator is given at run time, through the same sensor draws."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT as CFG
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import run_episode
from boxjax.estimator import explore
from boxjax.sim.faults import Faults
from boxjax.training.randomise import SensorRandomisation, seen_exploration, sensor_view


def _episode_view(faults: Faults, key, ctrl: ControllerConfig = ControllerConfig()):  # noqa: B008 (frozen)
    """Explore box B through `faults` with an estimator that records what it is given."""
    given = {}

    def estimator(exploration):
        given.update(exploration)
        return {"distribution": massdist.named("B", CFG.box), "hazardous": True}  # refuse: no turn

    ep = run_episode(CFG, massdist.named("B", CFG.box), key, estimator=estimator, ctrl=ctrl, faults=faults,
                     max_steps=60)  # fmt: skip
    n = explore.N_STEPS
    traj, final = explore.trajectory(ep.trace.s[: n + 1], ep.trace.belt_speed[: n + 1], ep.trace.actions[:n])
    return given, np.asarray(traj), np.asarray(final)


@pytest.mark.parametrize(
    "faults", [Faults(obs_noise_mm=3, obs_noise_deg=1.5, drop_rate=0.2), Faults(drop_rate=0.3)]
)
def test_the_training_view_is_what_the_estimator_is_given_in_an_episode(faults):
    key = jax.random.PRNGKey(3)
    given, traj, final = _episode_view(faults, key)
    view_traj, view_final = seen_exploration(CFG, traj, final, faults, key)
    expect, expect_final = explore.trajectory(given["s"], given["belt_speed"], traj[:, 5:9])
    np.testing.assert_allclose(view_traj, np.asarray(expect), atol=1e-6)
    np.testing.assert_allclose(view_final, np.asarray(expect_final), atol=1e-6)
    assert not np.allclose(view_traj[:, :5], traj[:, :5], atol=1e-4)  # the sensor did change it
    # and it is told the sensor (the learned estimator chooses its H by it)
    assert given["sensor"] == {"obs_noise_mm": faults.obs_noise_mm, "drop_rate": faults.drop_rate}


def test_the_estimator_is_told_the_sensor_the_controller_states():
    """The filter's stated noise, when set, is what the estimator is told; a perfect sensor tells nothing
    (the learned estimator reads that as a perfect one)."""
    import dataclasses

    from boxjax.control.state_estimate import FilterConfig

    key = jax.random.PRNGKey(3)
    perfect, _, _ = _episode_view(Faults(), key)
    assert "sensor" not in perfect
    ctrl = dataclasses.replace(ControllerConfig(), pose_filter=FilterConfig(noise_mm=2.0))
    given, _, _ = _episode_view(Faults(obs_noise_mm=3, obs_noise_deg=1.5), key, ctrl)
    assert given["sensor"] == {"obs_noise_mm": 2.0, "drop_rate": 0.0}


def test_dropped_frames_are_bridged_not_held():
    """With drops alone (no noise), a dropped frame's pose is bridged from the fresh frames around it:
    closer to the truth than the held frame a controller sees live (the carriage steps that drag the
    box sideways and the 3-step holds that swing its yaw are abrupt, so the line between frames misses
    part of them: closer, not exact)."""
    from boxjax.control.state_estimate import FilterConfig
    from boxjax.control.world import World

    key, faults = jax.random.PRNGKey(5), Faults(drop_rate=0.3)
    _, traj, final = _episode_view(Faults(), key)
    view, _ = seen_exploration(CFG, traj, final, faults, key)
    truth = np.concatenate([traj[:, :5], final[None]])
    world = World(CFG, faults, FilterConfig(), key, truth=None)  # the same draws: which frames dropped
    for t, s in enumerate(truth):
        world.observe(s, np.zeros(2))
        if t < len(traj):
            world.send(traj[t, 5:9])
    fresh = np.asarray([f for *_, f in world.frames])[: len(traj)]
    dropped = np.flatnonzero(~fresh)
    assert len(dropped) >= 5
    last_fresh = np.maximum.accumulate(np.where(fresh, np.arange(len(fresh)), 0))
    held = truth[last_fresh[dropped]]
    for axis in (2, 3, 4):  # x, y, yaw
        bridged_err = np.sqrt(np.mean((view[dropped, axis] - truth[dropped, axis]) ** 2))
        held_err = np.sqrt(np.mean((held[:, axis] - truth[dropped, axis]) ** 2))
        assert bridged_err < held_err, (axis, bridged_err, held_err)


def test_a_perfect_sensor_leaves_the_data_and_the_view_is_reproducible():
    gen = np.random.default_rng(0)
    data = {
        "traj": gen.normal(size=(6, explore.N_STEPS, 11)).astype(np.float32) * 0.01,
        "final": gen.normal(size=(6, 5)).astype(np.float32) * 0.01,
        "total_mass": np.ones(6, np.float32),
    }
    same = sensor_view(data, CFG, SensorRandomisation(p_perfect=1.0), seed=1)
    np.testing.assert_array_equal(same["traj"], data["traj"])
    a = sensor_view(data, CFG, SensorRandomisation(p_perfect=0.0), seed=1)
    b = sensor_view(data, CFG, SensorRandomisation(p_perfect=0.0), seed=1)
    np.testing.assert_array_equal(a["traj"], b["traj"])
    assert np.all(a["obs_noise_mm"] <= 5.0) and np.all(a["drop_rate"] < 0.2 + 1e-6)
    assert not np.allclose(a["traj"], data["traj"])
    with pytest.raises(ValueError, match="drop_rate"):
        SensorRandomisation(drop_rate=(0.0, 1.0))


@pytest.mark.slow  # 11 s compiling H's training; the view it trains on is tested above
def test_train_estimator_with_a_randomised_sensor_trains_on_the_view_and_says_so(tmp_path):
    from boxjax import estimator as E
    from boxjax.training import dataset as ds
    from boxjax.training.estimator import train_estimator

    tiny = E.EstimatorConfig(hidden=(16,), members=1, max_epochs=2, patience=1, batch_size=8)
    report = train_estimator(
        3, 12, tmp_path, CFG, est_cfg=tiny, progress=False, sensor=SensorRandomisation(p_perfect=0.0)
    )
    data, _ = ds.load(tmp_path / "dataset.npz")  # the exact explorations are what is kept on disk
    view = sensor_view(data, CFG, SensorRandomisation(p_perfect=0.0), 3)
    assert not np.allclose(view["traj"], data["traj"])
    model = E.load(report["weights"])
    assert model.provenance["sensor_randomisation"]["p_perfect"] == 0.0
