"""The simulator reference planner: its rollouts are NativeEnv.step, its actions are sane and keyed."""

import dataclasses

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


def test_planar_start_keeps_the_robot_and_flattens_the_box(env_state):
    """From the planar window of a moving box: the box flat at rest height at the observed pose with the
    window's velocities; belts, carriages and warm start exactly the simulator's; one control step from
    it lands near the exact step (the box's small tilt and bounce are all that was dropped)."""
    env, dist, state = env_state
    window = [np.asarray(state.s)]
    st = state
    for a in explore.exploration_actions(CFG)[20:22]:
        st = env.step(st, a)
        window.append(np.asarray(st.s))
    window = np.stack(window).astype(np.float64)
    phys = simp.planar_start(CFG, st, window)
    m = st.model
    idx = simp.model.ids(m)
    nq, nv = m.nq, m.nv
    q, v = phys[1 : 1 + nq], phys[1 + nq : 1 + nq + nv]
    q0, v0 = st.physics[1 : 1 + nq], st.physics[1 + nq : 1 + nq + nv]
    b, bv = idx.box_qpos, idx.box_dof
    keep_q = np.setdiff1d(np.arange(nq), np.arange(b, b + 7))
    keep_v = np.setdiff1d(np.arange(nv), np.arange(bv, bv + 6))
    np.testing.assert_array_equal(q[keep_q], q0[keep_q])
    np.testing.assert_array_equal(v[keep_v], v0[keep_v])
    np.testing.assert_array_equal(phys[1 + nq + nv :], st.physics[1 + nq + nv :])  # act, warm start
    np.testing.assert_allclose(q[b : b + 2], window[-1, 2:4])
    assert q[b + 2] == CFG.box.half_size[2]
    yaw = window[-1, 4]
    np.testing.assert_allclose(q[b + 3 : b + 7], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], atol=1e-12)
    fd = (3 * window[-1] - 4 * window[-2] + window[-3]) / (2 * CFG.gripper.control_dt)
    np.testing.assert_allclose(v[[bv, bv + 1, bv + 5]], fd[2:5], rtol=1e-6, atol=1e-9)
    assert np.all(v[bv + 2 : bv + 5] == 0)  # no vertical or tilting motion
    assert abs(q0[b + 2] - q[b + 2]) < 2e-3  # the simulator's box sinks < 2 mm into its belts
    # One control step from either start: what the dropped state (tilt, bounce, the velocity within the
    # step that finite differences smear) is worth here.
    a = np.asarray(explore.exploration_actions(CFG)[22], np.float64)
    exact, flat = env.step(st, a), env.step(st._replace(physics=phys), a)
    np.testing.assert_allclose(flat.s[2:4], exact.s[2:4], atol=1e-3)
    assert abs(flat.s[4] - exact.s[4]) < np.radians(0.1)

    # The two halves apart: "flat" keeps the exact planar velocities, "velocity" the exact 3-D pose.
    def vel_world(ph):  # the box's (linear, angular) velocity in world axes
        q, v = ph[1 : 1 + nq], ph[1 + nq : 1 + nq + nv]
        return np.concatenate([v[bv : bv + 3], simp._rotation(q[b + 3 : b + 7]) @ v[bv + 3 : bv + 6]])

    exact_v = vel_world(st.physics)
    flat = simp.planar_start(CFG, st, window, start="flat")
    np.testing.assert_array_equal(flat[1 : 1 + b + 7], phys[1 : 1 + b + 7])  # the same flat pose
    np.testing.assert_allclose(vel_world(flat)[[0, 1, 5]], exact_v[[0, 1, 5]], atol=1e-12)
    assert np.all(vel_world(flat)[2:5] == 0)
    vel = simp.planar_start(CFG, st, window, start="velocity")
    np.testing.assert_array_equal(vel[1 : 1 + nq], st.physics[1 : 1 + nq])  # the exact pose, tilt included
    np.testing.assert_allclose(vel_world(vel)[[0, 1, 5]], fd[2:5], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(vel_world(vel)[2:5], exact_v[2:5], atol=1e-12)  # tilting motion kept
    with pytest.raises(ValueError, match="window"):
        simp.planar_start(CFG, st, window[:2])
    with pytest.raises(ValueError, match="start"):
        simp.planar_start(CFG, st, window, start="exact")
    with pytest.raises(ValueError, match="start"):
        simp.SimulatorOptions(start="tilted")


def test_belief_model_simulates_the_believed_box():
    """model="belief": the rollouts' box has the belief's mass and centre of mass, not the truth's."""
    belief = massdist.named("A", CFG.box)
    assert simp.belief_model(CFG, None, belief) is None
    assert simp.belief_model(CFG, simp.SimulatorOptions(), belief) is None  # "truth": the env's own
    m = simp.belief_model(CFG, simp.SimulatorOptions(start="planar", model="belief"), belief)
    props = massdist.mass_properties(belief, CFG.box)
    body = m.body("box")
    np.testing.assert_allclose(body.mass[0], float(props.mass), rtol=1e-5)
    np.testing.assert_allclose(body.ipos, np.asarray(props.com), atol=1e-6)
    with pytest.raises(ValueError, match="model"):
        simp.SimulatorOptions(model="estimate")
    with pytest.raises(ValueError, match="no belief"):
        simp.belief_model(CFG, simp.SimulatorOptions(model="belief"), None)


@pytest.mark.parametrize("box_model", ["truth", "belief"])
def test_episode_hands_the_simulator_the_believed_box(box_model, monkeypatch):
    """In a closed loop, model="belief" rolls out the estimator's box (here a fixed belief: uniform) and
    "truth" the true one (box C); from the planar start the box's pose comes from the window either way."""
    from boxjax.control.config import ControllerConfig
    from boxjax.control.episode import run_episode

    seen = []
    call = simp.Rollouts.__call__

    def spy(self, state, seqs):
        seen.append(np.array(state.model.body("box").ipos))
        return call(self, state, seqs)

    monkeypatch.setattr(simp.Rollouts, "__call__", spy)
    truth, belief = massdist.named("C", CFG.box), massdist.named("uniform", CFG.box)
    opts = dataclasses.replace(SMALL, start="planar", model=box_model)
    ctrl = ControllerConfig(planner="simulator", simulator=opts)
    n_explore = len(explore.exploration_actions(CFG))
    est = lambda exploration: {"distribution": belief, "hazardous": False}  # noqa: E731
    res = run_episode(CFG, truth, jax.random.PRNGKey(0), estimator=est, ctrl=ctrl, max_steps=n_explore + 2)
    assert len(seen) == 2 and res.summary["steps"] == n_explore + 2
    want = belief if box_model == "belief" else truth
    np.testing.assert_allclose(seen[-1], np.asarray(massdist.mass_properties(want, CFG.box).com), atol=1e-6)
