"""The one planner interface and the model slot: every planner through init / optimize, the drift observer."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import massdist, planning, prior
from boxjax.config import DEFAULT
from boxjax.control.config import ControllerConfig
from boxjax.planners import paper as planner
from boxjax.planners import sampling as sp
from boxjax.planners.registry import make_planner

CFG = DEFAULT
S0 = jnp.array([-0.10, 0.10, 0.0, 0.0, 0.0], jnp.float32)
OBS = planning.observation(planning.initial_window(S0), jnp.zeros(2), jnp.pi / 2)


def _model(name="A"):
    return prior.make_prior(
        massdist.voxel_masses(massdist.named(name, CFG.box), CFG.box), None, CFG.box, CFG.gripper
    )


def test_paper_planner_through_the_interface_is_the_paper_planner():
    mpc = planner.make(CFG, n_samples=50, rule="random")
    direct = planner.make_planner(CFG, n_samples=50, rule="random")
    key, model = jax.random.PRNGKey(2), _model()
    a, state, info = mpc.optimize(key, model, OBS, mpc.init(OBS))
    b, _ = direct(key, model, OBS.window, OBS.belt_speed, OBS.target_yaw)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert state == () and not mpc.privileged


def test_sampling_planner_state_is_the_shifted_nominal():
    o = sp.SamplingOptions(n_samples=8, horizon=4, gradient_steps=0)
    mpc = sp.make(CFG, o)
    st0 = mpc.init(OBS)
    assert st0.shape == (4, 4)
    a, st1, info = mpc.optimize(jax.random.PRNGKey(0), _model(), OBS, st0)
    np.testing.assert_array_equal(np.asarray(st1), np.asarray(sp.shift_nominal(info.nominal)))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(info.nominal[0]))


def test_controller_builds_each_planner_by_name():
    for name in ("sampling", "paper"):
        mpc = make_planner(CFG, ControllerConfig(planner=name))
        assert mpc.name == name


def test_drift_corrected_model_adds_k_times_the_drift_and_the_observer_integrates():
    model = _model()
    drift = jnp.array([1e-3, -2e-3, 0.01], jnp.float32)
    acts = jnp.tile(jnp.array([[0.05, -0.05, 0.0, 0.0]]), (3, 1))
    base = np.asarray(model.rollout_sequence(OBS.window, OBS.belt_speed, acts))
    corr = np.asarray(
        planning.DriftCorrected(model, drift).rollout_sequence(OBS.window, OBS.belt_speed, acts)
    )
    np.testing.assert_allclose(corr[:, :2], base[:, :2])
    np.testing.assert_allclose(corr[:, 2:] - base[:, 2:], np.outer([1, 2, 3], np.asarray(drift)), atol=1e-6)
    first = planning.predict_first(model, OBS.window, OBS.belt_speed, acts[0])
    np.testing.assert_allclose(np.asarray(first), base[0], atol=1e-6)
    observed = base[0] + np.array([0, 0, 4e-3, 0, 0.02])
    new = planning.update_drift(jnp.zeros(3), base[0], observed, 0.5)
    np.testing.assert_allclose(np.asarray(new), [2e-3, 0.0, 0.01], atol=1e-6)
    assert np.asarray(model.stability_margin(S0)) == np.asarray(
        planning.DriftCorrected(model, drift).stability_margin(S0)
    )


def test_ensemble_of_priors_particles_follow_their_members():
    """An Ensemble of deterministic models (priors of two boxes, as H's ensemble will give): one particle
    per member, each the member's own rollout and stability margin; the plain slot is their mean."""
    ens = planning.Ensemble(planning.stack([_model("A"), _model("C")]))
    assert ens.n_particles == 2 and planning.n_particles(ens) == 2
    acts = jnp.tile(jnp.array([[0.05, -0.05, 0.0, 0.002]]), (2, 1))

    @jax.jit  # one compilation (the prior's rollout is slow to compile)
    def run(ens):
        parts = planning.rollout_particles(ens, jax.random.PRNGKey(0), OBS.window, OBS.belt_speed, acts)
        own = planning.member(ens.members, 1)  # a plain model: its own rollout and margins
        own_states = own.rollout_sequence(OBS.window, OBS.belt_speed, acts)
        return (
            parts,
            planning.particle_margins(ens, parts),
            ens.rollout_sequence(OBS.window, OBS.belt_speed, acts),
            own_states,
            planning.particle_margins(own, own_states[None])[0],
        )

    parts, margins, mean, own_states, own_margins = run(ens)
    assert parts.shape == (2, 2, 5) and margins.shape == (2, 2)
    np.testing.assert_allclose(parts[1], own_states, atol=1e-6)  # particle 1 follows member 1 (box C)
    np.testing.assert_allclose(margins[1], own_margins, atol=1e-6)
    assert not np.allclose(margins[0], margins[1])  # the centre of mass differs between A and C
    np.testing.assert_allclose(mean, parts.mean(0), atol=1e-6)


def test_mixture_of_prior_settings_particles_follow_their_members():
    """A Mixture of priors with different static settings (not stackable into an Ensemble): one particle
    per member, each the member's own rollout and margins; the plain slot is their mean."""
    a = _model("A")
    slow = a.__class__(**{**a.__dict__, "params": prior.PriorParams(carriage_omega=30.0)})
    mix = planning.Mixture((a, slow))
    assert planning.n_particles(mix) == 2
    acts = jnp.tile(jnp.array([[0.05, -0.05, 0.01, 0.0]]), (2, 1))  # a carriage step: the settings differ

    @jax.jit
    def run(mix):
        parts = planning.rollout_particles(mix, jax.random.PRNGKey(0), OBS.window, OBS.belt_speed, acts)
        own = [m.rollout_sequence(OBS.window, OBS.belt_speed, acts) for m in mix.members]
        return (
            parts,
            planning.particle_margins(mix, parts),
            mix.rollout_sequence(OBS.window, OBS.belt_speed, acts),
            own,
        )

    parts, margins, mean, own = run(mix)
    assert parts.shape == (2, 2, 5) and margins.shape == (2, 2)
    for i in range(2):
        np.testing.assert_array_equal(parts[i], own[i])
    assert not np.allclose(parts[0], parts[1])  # the slower carriage response predicts another state
    np.testing.assert_allclose(mean, parts.mean(0), atol=1e-7)
    with pytest.raises(ValueError, match="non-empty tuple"):
        planning.Mixture(())


@pytest.mark.slow  # the Mixture (`friction_set`, off by default) is planned through in the test above
def test_a_mixture_of_one_setting_twice_plans_as_that_setting_alone():
    o = sp.SamplingOptions(n_samples=8, horizon=3, gradient_steps=0)
    a = _model("A")
    key = jax.random.PRNGKey(3)
    nominal = sp.initial_nominal(CFG, o)
    plain = sp.make_sampling_planner(CFG, o)(key, a, OBS.window, OBS.belt_speed, OBS.target_yaw, nominal)
    mixed = sp.make_sampling_planner(CFG, o)(
        key, planning.Mixture((a, a)), OBS.window, OBS.belt_speed, OBS.target_yaw, nominal
    )
    np.testing.assert_allclose(mixed[0], plain[0], atol=1e-6)
    np.testing.assert_allclose(mixed[1].cost, plain[1].cost, rtol=1e-6)


def test_controller_builds_a_mixture_of_priors_and_refuses_what_cannot_use_one():
    from boxjax import control as controller
    from boxjax.experiments import evaluation as experiments

    mix = (prior.PriorParams(), prior.PriorParams(carriage_omega=30.0, slip_eps=0.02))
    ctrl = ControllerConfig(prior_params=mix)
    model = controller.planning_model(CFG, ctrl, massdist.named("A", CFG.box))
    assert isinstance(model, planning.Mixture) and [m.params for m in model.members] == list(mix)
    # an evaluation file's settings rebuild the same controller
    st = experiments.settings("oracle", ctrl, 0, "gaussian")
    assert experiments.controller_from_settings(st) == ctrl
    for bad, match in [
        (dict(prior_params=mix[:1]), "at least two"),
        (dict(prior_params=mix, planner="paper"), "sampling planner"),
        (dict(prior_params=mix, belief="ensemble"), "belief='mean'|sampling planner"),
        (dict(prior_params=(mix[0], "fast")), "tuple of them"),
        (dict(prior_params=(mix[0], prior.PriorParams(variant="paper"))), "variant"),
    ]:
        with pytest.raises(ValueError, match=match):
            ControllerConfig(**bad)
