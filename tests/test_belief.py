"""Planning over H's ensemble (ControllerConfig.belief = "ensemble"): the members H averages, one prior
per member in the planners' model slot, and the combinations that cannot work refused by name."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from boxjax import control as controller
from boxjax import estimator, massdist, planning
from boxjax.config import DEFAULT as cfg
from boxjax.estimator import explore, moments
from boxjax.estimator.shipped import default_estimator
from boxjax.sim import native


@pytest.fixture(scope="module")
def exploration():
    data = native.rollout(cfg, [massdist.named("C", cfg.box)], explore.exploration_actions(cfg))
    return {k: data[k][0] for k in ("s", "belt_speed", "actions")}


def test_members_are_what_h_averages(exploration):
    model = default_estimator(cfg)
    traj, final = explore.trajectory(
        exploration["s"], exploration["belt_speed"], explore.applied_actions(cfg)
    )
    mean = estimator.predict(model, traj, final)
    mem = estimator.predict_members(model, traj, final)
    assert mem.prob.shape == (model.cfg.members, *cfg.box.grid)
    np.testing.assert_allclose(np.mean(mem.prob, axis=0), mean.prob, atol=1e-6)
    np.testing.assert_allclose(np.mean(mem.mass), mean.mass, rtol=1e-5)
    np.testing.assert_allclose(np.mean(mem.hazard), mean.hazard, atol=1e-6)


def test_ensemble_belief_puts_one_prior_per_member_in_the_slot(exploration):
    est_fn = controller.learned_estimator(cfg)
    est, belief, why = controller.decide(cfg, massdist.named("C", cfg.box), exploration, est_fn)
    assert why is None and len(est["members"]) == default_estimator(cfg).cfg.members
    ctrl = controller.ControllerConfig(belief="ensemble")
    model = controller.planning_model(cfg, ctrl, belief, est=est)
    assert isinstance(model, planning.Ensemble) and model.n_particles == len(est["members"])
    # Member e is the prior on member e's distribution.
    e = 2
    alone = controller.planning_model(cfg, controller.ControllerConfig(), est["members"][e])
    np.testing.assert_array_equal(
        np.asarray(planning.member(model.members, e).masses), np.asarray(alone.masses)
    )
    window = np.asarray(controller.first_window(exploration["s"]), np.float32)
    acts = np.tile(np.array([0.1, -0.1, 0.0, 0.0], np.float32), (5, 1))
    parts = planning.rollout_particles(
        model, jax.random.PRNGKey(0), window, exploration["belt_speed"][-1], acts
    )
    assert parts.shape == (len(est["members"]), 5, 5) and np.all(np.isfinite(parts))


def test_ensemble_belief_refused_where_it_cannot_work():
    with pytest.raises(ValueError, match="sampling planner"):
        controller.ControllerConfig(belief="ensemble", planner="paper")
    with pytest.raises(ValueError, match="unknown belief"):
        controller.ControllerConfig(belief="median")
    with pytest.raises(ValueError, match="oracle"):
        controller.planning_model(
            cfg, controller.ControllerConfig(belief="ensemble"), massdist.named("A", cfg.box), est={}
        )
    from boxjax.experiments import evaluation as experiments

    with pytest.raises(ValueError, match="oracle"):
        experiments.evaluate(cfg, 1, ctrl=controller.ControllerConfig(belief="ensemble"), progress=False)


def test_the_default_h_is_chosen_by_the_sensor_the_exploration_was_seen_through(exploration):
    """With no weights given, a perfect sensor's exploration (or one with latency alone) is read by the
    H trained on exact explorations, a noisy or dropping one's by the H trained through randomised sensors;
    given weights are used for every exploration."""
    from boxjax.estimator.metrics import estimate
    from boxjax.estimator.shipped import SHIPPED_WEIGHTS, sensor_estimator

    traj, final = explore.trajectory(
        exploration["s"], exploration["belt_speed"], explore.applied_actions(cfg)
    )
    by_exact = estimate(default_estimator(cfg), traj, final)["hazard_prob"]
    by_sensor = estimate(sensor_estimator(cfg), traj, final)["hazard_prob"]
    assert by_exact != by_sensor
    h = controller.learned_estimator(cfg)
    perfect = {"obs_noise_mm": 0.0, "drop_rate": 0.0}
    assert h(exploration)["hazard_prob"] == by_exact
    assert h({**exploration, "sensor": perfect})["hazard_prob"] == by_exact
    assert h(exploration)["estimator_weights"] == "shipped"
    for sensor in ({"obs_noise_mm": 3.0, "drop_rate": 0.0}, {"obs_noise_mm": 0.0, "drop_rate": 0.05}):
        out = h({**exploration, "sensor": sensor})
        assert out["hazard_prob"] == by_sensor and out["estimator_weights"] == "shipped_sensor"
    given = controller.learned_estimator(cfg, str(SHIPPED_WEIGHTS))
    out = given({**exploration, "sensor": {"obs_noise_mm": 3.0, "drop_rate": 0.0}})
    assert out["hazard_prob"] == by_exact and out["estimator_weights"] == str(SHIPPED_WEIGHTS)
    assert sensor_estimator(cfg).provenance["sensor_randomisation"]["p_perfect"] > 0


def test_learned_estimate_reads_the_moments_with_their_std(exploration):
    est_fn = controller.learned_estimator(cfg)
    truth = massdist.named("C", cfg.box)
    est, _, why = controller.decide(cfg, truth, exploration, est_fn)
    assert why is None and set(est["moments"]) == set(moments.QUANTITIES)
    q = np.asarray(moments.true_moments(truth, cfg.box))
    for i, name in enumerate(moments.QUANTITIES):
        m, s = est["moments"][name]["mean"], est["moments"][name]["std"]
        assert s > 0 and abs(q[i] - m) < 3 * s, (name, q[i], m, s)
    assert "planar radius of gyration" in est["moments_text"]
    # A noisy sensor: the moments model was trained on exact explorations, so it is not asked.
    noisy = {**exploration, "sensor": {"obs_noise_mm": 3.0, "drop_rate": 0.0}}
    seen_noisy = est_fn(noisy)
    assert "moments" not in seen_noisy and "noisy sensor" in seen_noisy["moments_skipped"]
    assert "moments" not in controller.learned_estimator(cfg, with_moments=False)(exploration)
