"""The simulated gripper against references nobody here wrote: MuJoCo's own computations, closed-form
mechanics, symmetry; plus the Env API's contracts and its errors."""

from __future__ import annotations

import dataclasses

import jax
import mujoco
import numpy as np
import pytest

from boxjax import massdist, task
from boxjax.config import DEFAULT, ConfigError, GripperConfig
from boxjax.sim import make_env, model
from boxjax.sim.episode import naive_policy, run_episode
from boxjax.sim.native import rollout as native_rollout

CFG = DEFAULT
KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def env():
    return make_env(CFG, "native")


# -- the model really carries the box -------------------------------------------------------------


def test_box_model_carries_mass_properties():
    for name in ("A", "D", "uniform"):
        dist = massdist.named(name, CFG.box)
        props = massdist.mass_properties(dist, CFG.box)
        m = model.box_model(CFG, dist)
        b = model.ids(m).box_body
        assert m.body_mass[b] == pytest.approx(float(props.mass), rel=1e-6)
        np.testing.assert_allclose(m.body_ipos[b], props.com, atol=1e-7)
        # full inertia tensor from MuJoCo's principal representation
        r = np.zeros(9)
        mujoco.mju_quat2Mat(r, m.body_iquat[b])
        r = r.reshape(3, 3)
        np.testing.assert_allclose(r @ np.diag(m.body_inertia[b]) @ r.T, props.inertia, rtol=1e-5, atol=1e-9)
        # mj_setConst recomputes body_sameframe: 0 whenever the inertial frame is not the body frame.
        off_centre = np.abs(np.asarray(props.com)).max() > 1e-6
        assert m.body_sameframe[b] == (0 if off_centre else 1)
        assert m.body_subtreemass[b] == pytest.approx(float(props.mass), rel=1e-6)


def _numeric_fields(m):
    out = {}
    for name in dir(m):
        if name.startswith("_"):
            continue
        try:
            v = getattr(m, name)
        except Exception:  # noqa: BLE001 - some attributes are not readable on a model
            continue
        if isinstance(v, np.ndarray) and v.dtype.kind in "fiub":
            out[name] = v
    for name in ("meaninertia", "meanmass", "meansize", "extent", "center"):
        out[f"stat.{name}"] = np.asarray(getattr(m.stat, name))
    return out


def test_box_fields_cover_everything_that_changes():
    """Every model field that differs between two boxes travels per world in MJX
    (docs/design.md#simulation-pitfalls)."""
    a = _numeric_fields(model.box_model(CFG, massdist.named("A", CFG.box)))
    c = _numeric_fields(model.box_model(CFG, massdist.named("C", CFG.box)))
    changed = {k for k in a if a[k].shape != c[k].shape or not np.array_equal(a[k], c[k])}
    travelling = set(model.BOX_FIELDS) | {f"stat.{f}" for f in model.STAT_FIELDS}
    assert "body_ipos" in changed and "dof_invweight0" in changed
    # The rest may stay shared only if MJX's simulation code never reads them.
    import pathlib

    import mujoco.mjx._src as mjx_src

    src = "".join(
        p.read_text()
        for p in pathlib.Path(mjx_src.__path__[0]).glob("*.py")
        if p.name not in ("types.py", "io.py") and not p.name.endswith("_test.py")
    )
    read_by_mjx = {f for f in changed - travelling if f.split(".")[-1] in src}
    assert not read_by_mjx, f"box-dependent fields MJX reads but that do not travel per world: {read_by_mjx}"


def test_different_distribution_gives_different_trajectory(env):
    """Guards the body_sameframe pitfall: the mass distribution must change the motion."""
    finals = {}
    for name in ("uniform", "A", "C"):
        s = env.reset(KEY, massdist.named(name, CFG.box))
        for _ in range(20):
            s = env.step(s, [0.15, -0.15, 0.0, 0.0])
        finals[name] = np.asarray(s.s)
    assert np.abs(finals["uniform"] - finals["A"]).max() > 1e-3
    assert np.abs(finals["A"] - finals["C"]).max() > 1e-3


# -- closed-form mechanics ---------------------------------------------------------------------------


def test_box_on_moving_belts_accelerates_at_mu_g():
    """Belts already running at v under a box at rest: kinetic friction accelerates the box at mu * g
    until it reaches the belt speed, then it rides along."""
    v = 0.2
    m = model.box_model(CFG, massdist.named("uniform", CFG.box))
    idx = model.ids(m)
    d = mujoco.MjData(m)
    d.qpos[:] = model.initial_qpos(CFG, m)
    d.ctrl[:] = [0.0, 0.0, *CFG.gripper.belt_y0]
    mujoco.mj_forward(m, d)
    for _ in range(50):  # let the box settle onto the belts
        mujoco.mj_step(m, d)
    d.qvel[:] = 0
    d.act[:] = v
    for k in idx.belt_dof:
        d.qvel[k] = v
    dt = m.opt.timestep
    vx = []
    for _ in range(int(0.1 / dt)):
        mujoco.mj_step(m, d)
        vx.append(d.qvel[idx.box_dof])
    vx = np.asarray(vx)
    t = dt * np.arange(1, len(vx) + 1)
    slipping = vx < 0.8 * v
    accel = np.polyfit(t[slipping][2:], vx[slipping][2:], 1)[0]
    mu_g = CFG.gripper.friction * CFG.gripper.gravity
    assert accel == pytest.approx(mu_g, rel=0.05)
    assert vx[-1] == pytest.approx(v, abs=0.003)  # then it rides with the belt


def test_uniform_box_turns_quarter_turn_without_drift(env):
    """Symmetry: a uniform box between opposite belts turns by pi/2 and its centre stays put."""
    state = env.reset(KEY, massdist.named("uniform", CFG.box))
    state, trace = run_episode(env, state, naive_policy(0.15), KEY, 200)
    assert state.reason == task.SUCCESS
    assert abs(float(state.s[4]) - np.pi / 2) <= CFG.task.yaw_tolerance
    assert np.abs(trace.s[:, 2:4]).max() < 0.01  # centre drift < 1 cm
    assert trace.balance_error.max() < 0.01


def test_a_belts_only_turn_swings_the_box_about_a_pivot_near_its_centre_of_mass(env):
    """The premise of the sampling planner's turn-end term (`sampling_planner.turn_end_excess`): belts
    push along x only, so while they turn a box whose centre of mass lies 12.5 cm along its length, the
    geometric centre swings sideways and the centre of mass's y stays nearly put (MuJoCo's contact
    dynamics, no carriage move)."""
    occ = np.zeros(CFG.box.grid, np.float32)
    occ[5:] = 1.0
    dist = massdist.MassDistribution(occ, np.float32(4.0))
    cx, cy = np.asarray(massdist.mass_properties(dist, CFG.box).com[:2])
    state = env.reset(KEY, dist)
    state, trace = run_episode(env, state, naive_policy(0.15), KEY, 15)
    s = trace.s
    y, yaw = s[:, 3], s[:, 4]
    y_com = y + np.sin(yaw) * cx + np.cos(yaw) * cy
    assert np.degrees(yaw[-1]) > 15.0
    assert abs(y[-1] - y[0]) > 0.03  # the geometric centre swings 3+ cm to the side ...
    assert abs(y_com[-1] - y_com[0]) < 0.35 * abs(y[-1] - y[0])  # ... the centre of mass a third of that


def test_naive_rotation_fails_on_hazardous_D(env):
    """D (all mass over one belt) cannot be turned by the non-adaptive policy; uniform can."""
    state = env.reset(KEY, massdist.named("D", CFG.box))
    state, trace = run_episode(env, state, naive_policy(0.15), KEY, 300)
    assert state.done and not state.success
    assert task.REASONS[int(state.reason)] in ("unbalanced", "off_belts", "tipped")
    assert abs(float(state.s[4])) < 0.5  # the box barely turned: the loaded belt carries it away


def test_belt_speed_and_acceleration_limits(env):
    """A step command beyond the limits: the belt ramps at the acceleration limit to the speed limit."""
    state = env.reset(KEY, massdist.named("uniform", CFG.box))
    g = CFG.gripper
    speeds = []
    for _ in range(12):
        state = env.step(state, [1.0, -1.0, 0.0, 0.0])
        assert bool(state.clipped)
        speeds.append(np.asarray(state.belt_speed))
    speeds = np.asarray(speeds)
    dv = np.diff(np.concatenate([[[0.0, 0.0]], speeds]), axis=0)
    assert np.abs(dv).max() <= g.belt_accel_limit * g.control_dt * 1.05
    assert np.abs(speeds).max() <= g.belt_speed_limit * 1.01
    np.testing.assert_allclose(np.abs(speeds[-1]), g.belt_speed_limit, rtol=0.01)


def test_position_steps_are_clipped_and_tracked(env):
    state = env.reset(KEY, massdist.named("uniform", CFG.box))
    state = env.step(state, [0.0, 0.0, -0.05, 0.0])  # beyond max_position_step
    assert bool(state.clipped)
    assert float(state.p_target[0]) == pytest.approx(CFG.gripper.belt_y0[0] - CFG.gripper.max_position_step)
    assert float(state.s[0]) == pytest.approx(float(state.p_target[0]), abs=2e-3)
    for _ in range(15):
        state = env.step(state, [0.0, 0.0, -0.01, 0.0])
    assert float(state.p_target[0]) == pytest.approx(CFG.gripper.p1_range[0])  # range limit


# -- backends and batches ----------------------------------------------------------------------------


def test_native_rollout_matches_env_steps(env):
    """mujoco.rollout batches (threads) give the same trajectories as stepping the Env one by one."""
    dists = [massdist.named(n, CFG.box) for n in ("uniform", "A", "C")]
    acts = np.zeros((10, 4))
    acts[:, 0], acts[:, 1] = 0.15, -0.15
    acts[5:, 2] = -0.005
    out = native_rollout(CFG, dists, acts, nthread=2)
    assert out["s"].shape == (3, 11, 5)
    for b, dist in enumerate(dists):
        s = env.reset(KEY, dist)
        for t in range(10):
            s = env.step(s, acts[t])
        np.testing.assert_allclose(out["s"][b, -1], np.asarray(s.s), atol=2e-4)


# -- bad input ------------------------------------------------------------------------------------


def test_bad_actions_raise(env):
    state = env.reset(KEY, massdist.named("uniform", CFG.box))
    with pytest.raises(ValueError, match="shape"):
        env.step(state, [0.1, 0.1])
    with pytest.raises(ValueError, match="non-finite.*v2"):
        env.step(state, [0.1, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="non-finite"):
        env.step(state, [0.1, 0.0, np.inf, 0.0])


def test_bad_distributions_raise(env):
    empty = massdist.MassDistribution(np.zeros(CFG.box.grid, np.float32), np.float32(3.0))
    with pytest.raises(massdist.DistributionError, match="no"):
        env.reset(KEY, empty)
    wrong = massdist.MassDistribution(np.ones((4, 4, 2), np.float32), np.float32(3.0))
    with pytest.raises(massdist.DistributionError, match="shape"):
        env.reset(KEY, wrong)
    with pytest.raises(ValueError, match="uniform"):
        massdist.named("E", CFG.box)


def test_limits_beyond_hardware_raise():
    with pytest.raises(ConfigError, match="belt_speed_limit"):
        GripperConfig(belt_speed_limit=0.5)
    with pytest.raises(ConfigError, match="belt_accel_limit"):
        GripperConfig(belt_accel_limit=2.0)
    with pytest.raises(ConfigError, match="carriage travel"):
        GripperConfig(p1_range=(-0.4, -0.06))
    with pytest.raises(ConfigError, match="carriage speed"):
        GripperConfig(max_position_step=0.05)
    with pytest.raises(ValueError, match="unknown backend"):
        make_env(CFG, "bullet")


def test_config_is_hashable_and_replaceable():
    cfg = CFG.replace(gripper=dataclasses.replace(CFG.gripper, friction=0.4))
    assert hash(cfg) != hash(CFG)
    assert cfg.gripper.n_substeps == 25
