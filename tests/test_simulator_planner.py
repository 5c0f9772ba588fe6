"""The simulator reference planner: its rollouts are NativeEnv.step, its actions are sane and keyed."""

import jax
import numpy as np
import pytest

from boxjax import massdist, planning, prior
from boxjax.config import DEFAULT as CFG
from boxjax.estimator import explore
from boxjax.planners import simulator as simp
from boxjax.planners.sampling import SamplingOptions
from boxjax.sim import make_env

SMALL = simp.SimulatorOptions(sampling=SamplingOptions(n_samples=6, horizon=4, gradient_steps=0), nthread=2)


@pytest.fixture(scope="module")
def env_state():
    """Box C after 20 exploration steps (the belts moving, the box turning: contacts change)."""
    env = make_env(CFG, "native")
    dist = massdist.named("C", CFG.box)
    state = env.reset(jax.random.PRNGKey(0), dist)
    for a in explore.exploration_actions(CFG)[:20]:
        state = env.step(state, a)
    return env, dist, state


def _obs(state):
    window = np.tile(np.asarray(state.s, np.float32), (planning.MIN_WINDOW, 1))
    return planning.observation(window, state.belt_speed, state.target_yaw, state)


def test_rollout_equals_native_env_step(env_state):
    env, _, state = env_state
    rng = np.random.default_rng(0)
    seqs = np.concatenate(
        [rng.uniform(-0.2, 0.2, (3, 8, 2)), rng.uniform(-0.006, 0.006, (3, 8, 2))], axis=-1
    ).astype(np.float32)  # beyond the step limits in places: clipping must match too
    qpos, qvel = simp.Rollouts(CFG, 3, 8, nthread=2)(state, seqs)
    nq = state.model.nq
    for i in range(3):
        st = state
        for k in range(8):
            st = env.step(st, np.float64(seqs[i, k]))
            np.testing.assert_array_equal(qpos[i, k], st.physics[1 : 1 + nq])  # bit for bit
            np.testing.assert_array_equal(qvel[i, k], st.physics[1 + nq : 1 + nq + state.model.nv])


def test_planner_actions_finite_in_limits_and_keyed(env_state):
    env, dist, state = env_state
    model = prior.make_prior(massdist.voxel_masses(dist, CFG.box), None, CFG.box, CFG.gripper, variant="slip")
    planner = simp.make(CFG, SMALL)
    assert planner.privileged and planner.name == "simulator"
    obs = _obs(state)
    nominal = planner.init(obs)
    key = jax.random.PRNGKey(7)
    a1, n1, info = planner.optimize(key, model, obs, nominal)
    a2, n2, _ = planner.optimize(key, model, obs, nominal)
    a3, _, _ = planner.optimize(jax.random.PRNGKey(8), model, obs, nominal)
    g = CFG.gripper
    assert a1.shape == (4,) and np.all(np.isfinite(a1))
    assert np.all(np.abs(a1[:2]) <= min(SMALL.sampling.speed_cap, g.belt_speed_limit) + 1e-7)
    assert np.all(np.abs(a1[2:]) <= g.max_position_step + 1e-7)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(n1, n2)
    assert not np.array_equal(a1, a3) or info.best == 0
    assert info.cost.shape == (6,) and info.states.shape == (6, 4, 5)
    # the chosen action's first simulated state is exactly what the env then does
    np.testing.assert_allclose(env.step(state, np.float64(a1)).s, info.states[info.best, 0], atol=0)
    with pytest.raises(ValueError, match="obs.sim"):
        planner.optimize(key, model, obs._replace(sim=None), nominal)


def test_cli_refuses_simulator_with_learned_estimator(capsys):
    from boxjax.cli import main

    assert main(["evaluate", "--boxes", "1", "--planner", "simulator", "--estimator", "learned"]) == 2
    assert "simulator" in capsys.readouterr().err
