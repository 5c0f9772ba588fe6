"""Predictive sampling over action sequences (sampling_planner): consistency with the prior's own rollout,
the cost's barriers, the receding-horizon bookkeeping, determinism, limits and bad input."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import geometry, massdist, planning, prior
from boxjax.blackbox import baseline
from boxjax.config import DEFAULT
from boxjax.planners import sampling as sp
from boxjax.planners import terms

CFG = DEFAULT
G = CFG.gripper
OPTS = sp.SamplingOptions(n_samples=16, horizon=6, gradient_steps=0)


def _model(name="uniform"):
    return prior.make_prior(massdist.voxel_masses(massdist.named(name, CFG.box), CFG.box), None, CFG.box, G)


S0 = jnp.array([-0.10, 0.10, 0.0, 0.0, 0.0], jnp.float32)
WINDOW = planning.initial_window(S0)
PLAN = sp.make_sampling_planner(CFG, OPTS)


def test_rollout_sequence_feeds_predictions_back_step_by_step():
    """prior.rollout_sequence (used for every rollout) equals the one-step prediction applied step by step
    on the window shifted by each prediction, with belt speeds from next_belt_speed: from the second step
    on, starting from the velocity and friction the previous step ended with (carry_velocity, default),
    or re-derived from the window (carry_velocity=False: exactly `predict` step by step)."""
    acts = jnp.array([[0.12, -0.08, 0.0, 0.004], [0.1, -0.1, 0.0, 0.0], [0.0, 0.0, -0.01, 0.0]], jnp.float32)
    explain, predict = jax.jit(prior.explain), jax.jit(prior.predict)  # one step at a time, compiled
    for carry in (True, False):
        model = prior.make_prior(
            massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box),
            None,
            CFG.box,
            G,
            carry_velocity=carry,
        )
        seq = np.asarray(prior.rollout_sequence(model, WINDOW, jnp.zeros(2), acts))
        w, b, u, f = WINDOW, jnp.zeros(2), None, None
        for k, a in enumerate(acts):
            s, info = explain(model, w, b, a, u, f)
            if carry:
                u, f = info["velocity"], info["friction"]
            else:
                np.testing.assert_allclose(np.asarray(s), np.asarray(predict(model, w, b, a)), atol=1e-7)
            np.testing.assert_allclose(seq[k], np.asarray(s), atol=1e-5)  # m, rad: float32 (scan vs eager)
            w, b = jnp.concatenate([w[1:], s[None]]), planning.next_belt_speed(model, b, a)
        np.testing.assert_allclose(
            seq[0], np.asarray(predict(model, WINDOW, jnp.zeros(2), acts[0])), atol=1e-6
        )
        held = prior.rollout(model, WINDOW, jnp.zeros(2), acts[0], 2, brake_steps=1)
        np.testing.assert_allclose(np.asarray(held[0]), seq[0], atol=1e-6)


def test_cost_barrier_starts_at_safe_fraction_of_the_balance_limit():
    lim = CFG.task.balance_limit
    o = sp.SamplingOptions(
        w_yaw=0.0, w_balance=0.0, w_effort=0.0, w_barrier=1.0, safe_fraction=0.5, horizon=1
    )
    acts = jnp.zeros((1, 4))

    def cost_at(balance):
        s = S0.at[geometry.Y].set(balance)[None]
        return float(sp.rollout_cost(_model(), s, acts, 0.0, CFG, o))

    assert cost_at(0.4 * lim) == 0.0
    np.testing.assert_allclose(cost_at(0.75 * lim), 0.25**2, rtol=1e-5)  # relu(0.75 - 0.5)^2
    # Beyond the belt ends (x) the same barrier applies, in units of the balance limit.
    over = S0.at[geometry.X].set(G.belt_length / 2 - CFG.box.half_size[0] + 0.01)[None]  # 1 cm over
    np.testing.assert_allclose(
        float(sp.rollout_cost(_model(), over, acts, 0.0, CFG, o)), ((0.01 + o.x_margin) / lim) ** 2, rtol=1e-4
    )


def test_cost_tip_barrier_is_the_stability_margin_shortfall():
    """Below `tip_margin` the cost grows with the square of the shortfall of `prior.stability_margin`
    (in units of the balance limit); belts spread until box C's centre of mass nears the support's edge."""
    lim = CFG.task.balance_limit
    o = sp.SamplingOptions(
        w_yaw=0.0, w_balance=0.0, w_effort=0.0, w_barrier=1.0, horizon=1, support_margin=-1.0, x_margin=-1.0
    )
    model = _model("C")
    acts = jnp.zeros((1, 4))
    spread = jnp.array([[-0.20, 0.20, 0.0, 0.0, 0.41]])
    margin = float(prior.stability_margin(model, spread[0]))
    assert margin < o.tip_margin
    np.testing.assert_allclose(
        float(sp.rollout_cost(model, spread, acts, 0.0, CFG, o)),
        ((o.tip_margin - margin) / lim) ** 2,
        rtol=1e-4,
    )
    assert float(sp.rollout_cost(model, S0[None], acts, 0.0, CFG, o)) == 0.0  # margin 8 cm at rest


def test_plans_from_rest_turn_the_box_the_right_way_and_respect_limits():
    """From rest, the plans towards yaw + pi/2 turn the box counter-clockwise (paper Fig. 1): after six
    receding-horizon iterations the predicted yaw grows for every key, and on average over the keys the
    plan runs belt 1 (left, y < 0) faster forwards (+x) than belt 2. One plan alone may lean on the
    carriages instead (keys 0-11, 2026-12-06: belt 1 - belt 2 from -0.04 to 0.11 m/s, mean 0.046; predicted
    yaw 0.02-0.10 rad): a round-off change in the gradient flipped key 0's. Every action is within the
    limits. (The planner and model the controller uses, built as `run_episode` builds them: the same
    compiled program, which the session's compilation cache then shares with the episode tests.)"""
    from boxjax.control import ControllerConfig
    from boxjax.control.models import planning_model
    from boxjax.planners.registry import make_planner

    ctrl = ControllerConfig()
    o = sp.SamplingOptions()
    assert (ctrl.sampling or o) == o
    mpc = make_planner(CFG, ctrl)
    model = planning_model(CFG, ctrl, massdist.named("uniform", CFG.box))
    obs = planning.observation(WINDOW, jnp.zeros(2), jnp.pi / 2)
    differences = []
    for seed in range(8):
        nominal = mpc.init(obs)
        key = jax.random.PRNGKey(seed)
        for _ in range(6):  # receding-horizon iterations on the same state
            key, k = jax.random.split(key)
            a, nominal, info = mpc.optimize(k, model, obs, nominal)  # the nominal comes back shifted
        a, states, plan_seq = np.asarray(a), np.asarray(info.states), np.asarray(info.nominal)
        differences.append(np.mean(plan_seq[:, 0] - plan_seq[:, 1]))  # m/s, over the planned 0.5 s
        assert states[-1, geometry.YAW] > 0.01, (seed, states[-1])  # rad, turning the right way
        assert np.all(np.abs(a[:2]) <= o.speed_cap + 1e-7)
        assert np.all(np.abs(a[2:]) <= G.max_position_step + 1e-7)
        assert float(info.yaw_error) < 0  # still short of the target after 0.5 s from rest
        assert info.states.shape == (o.horizon, 5) and info.cost.shape == (o.n_samples,)
    assert np.mean(differences) > 0.02, differences


def test_plan_keeps_the_best_and_is_deterministic_per_key():
    model = _model("C")
    nominal = sp.initial_nominal(CFG, OPTS)
    a1, i1 = PLAN(jax.random.PRNGKey(3), model, WINDOW, jnp.zeros(2), jnp.pi / 2, nominal)
    a2, i2 = PLAN(jax.random.PRNGKey(3), model, WINDOW, jnp.zeros(2), jnp.pi / 2, nominal)
    np.testing.assert_array_equal(np.asarray(a1), np.asarray(a2))
    cost = np.asarray(i1.cost)
    assert cost[int(i1.best)] == cost.min() <= cost[0]  # the old nominal (row 0) is never lost
    np.testing.assert_array_equal(np.asarray(i1.nominal[0]), np.asarray(a1))


def test_shift_nominal_and_bad_input():
    n = jnp.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(np.asarray(sp.shift_nominal(n)), np.asarray(jnp.stack([n[1], n[2], n[2]])))
    with pytest.raises(ValueError, match="nominal must have shape"):
        PLAN(jax.random.PRNGKey(0), _model(), WINDOW, jnp.zeros(2), 1.0, jnp.zeros((3, 4)))
    with pytest.raises(ValueError, match="n_samples"):
        sp.SamplingOptions(n_samples=1)


def test_support_deficit_hand_computed():
    """Box 0.30 m wide at yaw 0 spans y +-0.15; a 0.10 m belt at P1 = -0.10 lies fully under it."""
    np.testing.assert_allclose(float(sp.support_deficit(S0, CFG, 0.04)), 0.04 - 0.10, atol=1e-6)
    spread = S0.at[geometry.P1].set(-0.19)  # belt 1 covers [-0.24, -0.14]: 1 cm under the box
    np.testing.assert_allclose(float(sp.support_deficit(spread, CFG, 0.04)), 0.03, atol=1e-6)
    turned = S0.at[geometry.YAW].set(jnp.pi / 2).at[geometry.P1].set(-0.19)  # now spans y +-0.20
    np.testing.assert_allclose(float(sp.support_deficit(turned, CFG, 0.04)), 0.04 - 0.06, atol=1e-6)


@pytest.mark.parametrize(
    "update, extra",
    [
        # MPPI and CEM are options, not the default: slow (11 s each), to keep the suite under 10 min
        pytest.param("mppi", {"gradient_steps": 0}, marks=pytest.mark.slow),
        pytest.param("cem", {"iterations": 2, "gradient_steps": 0}, marks=pytest.mark.slow),
        # knots are an option too; gradient refinement's gain is tested by
        # test_gradient_refinement_lowers_the_cost_of_a_poor_sequence in the default suite (24 s here)
        pytest.param("best", {"gradient_steps": 3, "n_knots": 3}, marks=pytest.mark.slow),
    ],
)
def test_planner_updates_never_lose_the_nominal_and_are_deterministic(update, extra):
    """MPPI, CEM (two rounds) and gradient refinement: the plan's cost under the model is never above the
    old nominal's (row 0 of the first round), the action is within the limits, the same key gives the
    same action."""
    o = sp.SamplingOptions(n_samples=16, horizon=6, update=update, **extra)
    plan = sp.make_sampling_planner(CFG, o)
    model = _model("C")
    nominal = sp.initial_nominal(CFG, o)
    a1, i1 = plan(jax.random.PRNGKey(1), model, WINDOW, jnp.zeros(2), jnp.pi / 2, nominal)
    a2, _ = plan(jax.random.PRNGKey(1), model, WINDOW, jnp.zeros(2), jnp.pi / 2, nominal)
    np.testing.assert_array_equal(np.asarray(a1), np.asarray(a2))
    chosen = float(sp.rollout_cost(model, i1.states, i1.nominal, jnp.pi / 2, CFG, o))
    assert chosen <= float(i1.cost[0]) * (1 + 1e-5)
    assert np.all(np.abs(np.asarray(a1)[:2]) <= o.speed_cap + 1e-6)
    assert np.all(np.abs(np.asarray(a1)[2:]) <= G.max_position_step + 1e-6)


def test_gradient_refinement_lowers_the_cost_of_a_poor_sequence():
    """From a sequence that turns the wrong way, Adam steps through the prior lower its cost. (The prior
    with one substep and one friction iteration: what is tested is the descent, and its backward pass
    compiles in a fraction of the default's time.)"""
    o = sp.SamplingOptions(n_samples=4, horizon=6, gradient_steps=8, gradient_lr=1.0)
    model = dataclasses.replace(_model("uniform"), params=prior.PriorParams(n_substeps=1, n_iterations=1))
    bad = jnp.tile(jnp.array([[-0.08, 0.08, 0.0, 0.0]]), (6, 1))
    c0 = float(
        sp.rollout_cost(model, model.rollout_sequence(WINDOW, jnp.zeros(2), bad), bad, jnp.pi / 2, CFG, o)
    )
    seq, c = jax.jit(lambda x: sp.refine_gradient(model, WINDOW, jnp.zeros(2), jnp.pi / 2, x, CFG, o))(bad)
    assert float(c) < 0.99 * c0
    assert np.all(np.abs(np.asarray(seq)[:, :2]) <= o.speed_cap + 1e-6)


def test_knot_matrix_interpolates_between_knots():
    m = sp.knot_matrix(5, 3)
    np.testing.assert_allclose(m.sum(axis=1), 1.0)
    np.testing.assert_allclose(m[[0, 2, 4]], np.eye(3))
    np.testing.assert_array_equal(sp.knot_matrix(4, None), np.eye(4))
    with pytest.raises(ValueError, match="n_knots"):
        sp.SamplingOptions(horizon=4, n_knots=5)
    with pytest.raises(ValueError, match="update"):
        sp.SamplingOptions(update="annealing")


def test_pose_cost_l1_and_quadratic_hand_computed():
    """At a 5 degree yaw error: quadratic e^2, L1 sqrt(e^2 + d^2) - d with d the 2 degree tolerance; the
    L1 term keeps pulling near the target (its slope there is ~5x the quadratic's)."""
    e, d = np.radians(5.0), CFG.task.yaw_tolerance
    s = S0.at[geometry.YAW].set(np.pi / 2 - e)[None]
    acts = jnp.zeros((1, 4))
    base = dict(w_balance=0.0, w_effort=0.0, w_barrier=0.0, horizon=1)
    q = float(
        sp.rollout_cost(_model(), s, acts, np.pi / 2, CFG, sp.SamplingOptions(pose_cost="quadratic", **base))
    )
    l1 = float(sp.rollout_cost(_model(), s, acts, np.pi / 2, CFG, sp.SamplingOptions(pose_cost="l1", **base)))
    np.testing.assert_allclose(q, e**2, rtol=1e-4)
    np.testing.assert_allclose(l1, np.sqrt(e**2 + d**2) - d, rtol=1e-4)
    assert e / np.sqrt(e**2 + d**2) > 4 * (2 * e)  # slopes at 5 degrees: L1 0.93, quadratic 0.17
    with pytest.raises(ValueError, match="pose_cost"):
        sp.SamplingOptions(pose_cost="cubic")


def _long_box():
    """Mass in the last three of the eight voxel columns along x: centre of mass 12.5 cm along the length
    (label-safe: not all of it in the outer quarter)."""
    occ = np.zeros(CFG.box.grid, np.float32)
    occ[5:] = 1.0
    return massdist.MassDistribution(jnp.asarray(occ), jnp.float32(4.0))


def test_turn_end_excess_hand_computed_and_invariant_under_a_turn_about_the_centre_of_mass():
    """A centre of mass 12 cm along the length, box at y = 0, yaw 0: turned by pi/2 about it, the
    geometric centre ends at y = -12 cm, 6 cm beyond the -7 cm + 1 cm margin reach. The same box
    already turned part of the way about its centre of mass gives the same end; without an offset the
    end is where the box is."""
    com = jnp.array([0.12, 0.0])
    s = jnp.array([-0.10, 0.10, 0.0, 0.0, 0.0], jnp.float32)
    target = jnp.float32(np.pi / 2)
    np.testing.assert_allclose(float(sp.turn_end_excess(s, com, target, CFG, 0.01)), 0.06, atol=1e-6)
    for th in (0.3, 0.9, 1.4):  # y_com = 0 stays put: y = -(sin th * 0.12)
        turned = s.at[geometry.YAW].set(th).at[geometry.Y].set(-np.sin(th) * 0.12)
        np.testing.assert_allclose(float(sp.turn_end_excess(turned, com, target, CFG, 0.01)), 0.06, atol=1e-6)
    off = s.at[geometry.Y].set(0.03)
    np.testing.assert_allclose(
        float(sp.turn_end_excess(off, jnp.zeros(2), target, CFG, 0.01)),
        float(terms.y_excess(off, CFG, 0.01)),
        atol=1e-7,
    )


def test_turn_end_term_adds_its_barrier_and_needs_a_centre_of_mass():
    """w_reach * relu(excess / limit)^2 on the last state, with the model's own centre of mass (the prior
    and every wrapper of it pass it on); 0 for a box whose turn ends in reach, and no term at all for a
    model that knows no centre of mass (W)."""
    lim = CFG.task.balance_limit
    model = prior.make_prior(massdist.voxel_masses(_long_box(), CFG.box), None, CFG.box, G)
    com = np.asarray(massdist.mass_properties(_long_box(), CFG.box).com[:2])
    np.testing.assert_allclose(np.asarray(planning.planar_com(model)), com, atol=1e-6)
    for wrapped in (
        planning.DriftCorrected(model, jnp.zeros(3)),
        planning.Mixture((model, model)),
        planning.Ensemble(planning.stack([model, model])),
    ):
        np.testing.assert_allclose(np.asarray(planning.planar_com(wrapped)), com, atol=1e-6)
    acts = jnp.zeros((2, 4))
    states = jnp.stack([S0, S0])
    o0 = sp.SamplingOptions(horizon=2, w_reach=0.0)
    o1 = sp.SamplingOptions(horizon=2, w_reach=50.0)
    excess = float(sp.turn_end_excess(S0, jnp.asarray(com), jnp.float32(np.pi / 2), CFG, o1.y_margin))
    assert excess > 0.05
    c0 = float(sp.rollout_cost(model, states, acts, np.pi / 2, CFG, o0))
    c1 = float(sp.rollout_cost(model, states, acts, np.pi / 2, CFG, o1))
    np.testing.assert_allclose(c1 - c0, 50.0 * (excess / lim) ** 2, rtol=1e-4)
    uniform = _model("uniform")  # centre of mass near the middle: the turn ends in reach
    assert float(sp.rollout_cost(uniform, states, acts, np.pi / 2, CFG, o1)) == pytest.approx(
        float(sp.rollout_cost(uniform, states, acts, np.pi / 2, CFG, o0))
    )
    w = baseline.init_model(jax.random.PRNGKey(0), baseline.BaselineConfig(hidden=(8,)), G)
    assert planning.planar_com(w) is None
    assert float(sp.rollout_cost(w, states, acts, np.pi / 2, CFG, o1)) == float(
        sp.rollout_cost(w, states, acts, np.pi / 2, CFG, o0)
    )
