"""Random-shooting MPC (paper §2.3, §4): action set, Pareto front, selection rules, plan."""

from __future__ import annotations

import functools

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from boxjax import geometry, massdist, planning, prior
from boxjax.config import DEFAULT
from boxjax.planners import paper as planner
from boxjax.planners import terms

G = DEFAULT.gripper

# Scores on a coarse grid, so that ties and duplicates are common. A fixed number of rows, so the
# jitted functions compile once (small sets are covered by the hand-written cases).
scores_strategy = hnp.arrays(np.float32, (24, 2), elements=st.integers(0, 6).map(float))


def _dominated_by(s):
    """[i, j]: row j dominates row i (numpy reference)."""
    ge = np.all(s[None, :, :] >= s[:, None, :], axis=-1)
    gt = np.any(s[None, :, :] > s[:, None, :], axis=-1)
    return ge & gt


front_jit = {m: jax.jit(functools.partial(planner.pareto_front, method=m)) for m in ("pairwise", "sorted")}


@settings(max_examples=60, deadline=None)
@given(scores_strategy, st.sampled_from(["pairwise", "sorted"]))
def test_pareto_front_is_exactly_the_non_dominated_set(s, method):
    front = np.asarray(front_jit[method](jnp.asarray(s)))
    dom = _dominated_by(s)
    assert front.any()
    # No front member is dominated by anything.
    assert not np.any(dom[front])
    # Every excluded point is dominated, and by a member of the front.
    for i in np.nonzero(~front)[0]:
        assert np.any(dom[i] & front)


def test_pareto_front_ties_and_nan():
    s = jnp.array([[1.0, 1.0], [1.0, 1.0], [0.0, 2.0], [0.5, 0.5], [np.nan, np.nan], [np.nan, 3.0]])
    for method in ("pairwise", "sorted"):
        # Equal points are both on the front; NaN counts as -inf (row 5 still has the best second score).
        front = front_jit[method](s)
        assert np.asarray(front).tolist() == [True, True, True, False, False, True]
        assert np.asarray(front_jit[method](jnp.array([[3.0, 1.0]]))).tolist() == [True]


@functools.cache
def _select(rule):
    return jax.jit(functools.partial(planner.select, rule=rule, safe_balance=0.02))


@settings(max_examples=40, deadline=None)
@given(
    scores_strategy,
    st.integers(0, 2**31 - 1),
    st.sampled_from(["random", "weighted", "lexicographic", "safe-random"]),
)
def test_selection_returns_a_front_member(s, seed, rule):
    s = s + 1.0  # rewards are positive
    front = planner.pareto_front(jnp.asarray(s))
    bal = jnp.asarray(1.0 / np.sqrt(s[:, 1]))  # consistent with R2 = 1 / bal^2
    i = int(_select(rule)(jax.random.key(seed), jnp.asarray(s), front, bal))
    assert bool(front[i])


def test_lexicographic_rule_by_hand():
    # (R1, R2); balance errors in m. Safe (<= 2 cm): rows 1, 2 -> best R1 among them: row 2.
    s = jnp.array([[9.0, 1.0], [2.0, 5.0], [3.0, 4.0], [1.0, 6.0]])
    bal = jnp.array([0.05, 0.01, 0.015, 0.005])
    front = planner.pareto_front(s)
    assert int(_select("lexicographic")(jax.random.key(0), s, front, bal)) == 2
    # Nothing safe: the best balance (row 3).
    assert int(_select("lexicographic")(jax.random.key(0), s, front, bal + 0.1)) == 3


def test_safe_random_rule_by_hand():
    # Safe (<= 2 cm) front members: rows 1, 2; every key picks one of them.
    s = jnp.array([[9.0, 1.0], [2.0, 5.0], [3.0, 4.0], [1.0, 6.0]])
    bal = jnp.array([0.05, 0.01, 0.015, 0.005 + 0.1])
    front = planner.pareto_front(s)
    picks = {int(_select("safe-random")(jax.random.key(k), s, front, bal)) for k in range(20)}
    assert picks == {1, 2}
    # Nothing safe: the best balance reward (row 3).
    assert int(_select("safe-random")(jax.random.key(0), s, front, bal + 0.1)) == 3


def test_y_excess_band():
    """The belt midpoint reaches (p1_min + p2_min) / 2 .. (p1_max + p2_max) / 2 = -0.07 .. +0.07 m."""
    s = jnp.zeros(5)
    assert float(terms.y_excess(s, DEFAULT, 0.01)) == pytest.approx(-0.06, abs=1e-6)
    assert float(terms.y_excess(s.at[geometry.Y].set(0.08), DEFAULT, 0.01)) == pytest.approx(0.02, abs=1e-6)
    assert float(terms.y_excess(s.at[geometry.Y].set(-0.05), DEFAULT, 0.0)) == pytest.approx(-0.02, abs=1e-6)


def test_action_set():
    a = planner.action_set(G)
    assert a.shape == (95, 4)
    vel, p1, p2 = a[:81], a[81:88], a[88:]
    assert np.all(vel[:, 2:] == 0) and np.all(p1[:, [0, 1, 3]] == 0) and np.all(p2[:, [0, 1, 2]] == 0)
    step = G.belt_accel_limit * G.control_dt
    assert np.isclose(np.abs(vel[:, :2]).max(), step)
    assert np.isclose(np.abs(p1[:, 2]).max(), G.max_position_step)
    ab = planner.action_set(G, velocity="absolute")
    assert np.isclose(np.abs(ab[:81, :2]).max(), G.belt_speed_limit)
    assert planner.action_set(G, n_v=5, n_p=3).shape == (31, 4)
    with pytest.raises(ValueError, match="velocity mode"):
        planner.action_set(G, velocity="nope")


def test_position_actions_keep_belt_speeds():
    speed = jnp.array([0.1, -0.12])
    for mode in planner.VELOCITY_MODES:
        a = planner.action_set(G, velocity=mode)
        env = np.asarray(planner.to_env_actions(a, speed, G, mode))
        moves = np.any(a[:, 2:] != 0, axis=1)
        assert np.allclose(env[moves, :2], np.asarray(speed))  # position moves hold the belt speeds
        assert np.array_equal(env[:, 2:], a[:, 2:])
        assert np.all(np.abs(env[:, :2]) <= G.belt_speed_limit + 1e-7)
    inc = np.asarray(planner.to_env_actions(planner.action_set(G), speed, G, "increment", speed_cap=0.11))
    assert np.abs(inc[:, :2]).max() <= 0.11 + 1e-7


# ----------------------------------------------------------------------------------------------------------
# plan (one compiled planner shared by the tests).

MASSES = massdist.voxel_masses(massdist.named("A", DEFAULT.box), DEFAULT.box)
MODEL = prior.make_prior(MASSES, None, DEFAULT.box, G)
PLAN = planner.make_planner(DEFAULT, n_samples=50, rule="random")
S0 = jnp.array([-0.1, 0.1, 0.0, 0.0, 0.0])


def _moving():
    k = jnp.arange(3.0)[:, None] - 2
    return S0[None] + jnp.concatenate([jnp.zeros((3, 2)), k * 0.05 * jnp.array([0.01, -0.004, 0.3])], axis=1)


def test_plan_same_key_same_action_and_front_member():
    # (The predictions in PlanInfo are prior.predict's: see test_prior's vmap-vs-loop test.)
    w, b, target = _moving(), jnp.array([0.05, -0.05]), jnp.pi / 2
    a1, info1 = PLAN(jax.random.key(7), MODEL, w, b, target)
    a2, info2 = PLAN(jax.random.key(7), MODEL, w, b, target)
    assert np.array_equal(np.asarray(a1), np.asarray(a2))
    assert a1.shape == (4,)
    assert bool(info1.front[info1.choice])
    assert len(np.unique(np.asarray(info1.set_index))) == 50  # sampled without replacement
    assert np.array_equal(np.asarray(a1), np.asarray(info1.candidates[info1.choice]))
    # The scores are the task rewards of the predicted states.
    s = info1.predicted[info1.choice]
    assert float(info1.scores[info1.choice, 1]) == pytest.approx(
        1 / (float(geometry.balance_error(s)) ** 2 + DEFAULT.task.reward_eps), rel=1e-4
    )
    # Different keys explore different samples.
    picks = {tuple(np.asarray(PLAN(jax.random.key(k), MODEL, w, b, target)[0]).round(5)) for k in range(8)}
    assert len(picks) > 1


def test_plan_turns_towards_target_from_rest():
    # From rest the best turn towards +pi/2 drives belt 1 (y < 0) forward and belt 2 backward; the
    # front always holds that action when it was sampled (it has the best R1).
    w = planning.initial_window(S0)
    _, info = PLAN(jax.random.key(3), MODEL, w, jnp.zeros(2), jnp.pi / 2)
    best = int(jnp.argmax(info.scores[:, 0]))
    assert bool(info.front[best])
    c = np.asarray(info.candidates[best])
    assert c[0] >= 0 >= c[1] and c[0] - c[1] > 0


def test_plan_keeps_box_on_belts():
    # Box near the +x end of the belts, moving outwards with both belts: every candidate that keeps
    # pushing is infeasible, and the chosen action slows the belts.
    x = G.belt_length / 2 - 0.2 - 0.04
    s = S0.at[geometry.X].set(x)
    w = jnp.stack([s.at[geometry.X].add(-0.01), s.at[geometry.X].add(-0.005), s])
    b = jnp.array([0.1, 0.1])
    a, info = PLAN(jax.random.key(0), MODEL, w, b, jnp.pi / 2)
    assert not bool(np.all(np.asarray(info.feasible)))
    assert float(a[0] + a[1]) < float(b[0] + b[1]) + 1e-6


def test_plan_rejects_bad_options():
    w = planning.initial_window(S0)
    with pytest.raises(ValueError, match="n_samples"):
        planner.plan(jax.random.key(0), MODEL, w, jnp.zeros(2), 1.0, DEFAULT, n_samples=500)
    with pytest.raises(ValueError, match="rule"):
        planner.plan(jax.random.key(0), MODEL, w, jnp.zeros(2), 1.0, DEFAULT, rule="best")
