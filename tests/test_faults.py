"""Faults and mismatch (boxjax.sim.faults), the controller's pose filter (control.state_estimate) and the
world around one episode (control.world): each fault does what it says, replays from the key, and with no
fault nothing changes."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from boxjax import geometry, massdist, prior
from boxjax.config import DEFAULT, ConfigError
from boxjax.control import true_stability_margins
from boxjax.control.state_estimate import FilterConfig, PoseFilter, make_filter
from boxjax.control.world import World
from boxjax.sim import faults as F
from boxjax.sim import model as sim_model

CFG = DEFAULT


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"obs_noise_mm": -1.0}, "obs_noise_mm"),
        ({"obs_noise_deg": float("nan")}, "obs_noise_deg"),
        ({"obs_latency": -1}, "obs_latency"),
        ({"obs_latency": 1.5}, "obs_latency"),
        ({"action_latency": 99}, "action_latency"),
        ({"drop_rate": 1.0}, "drop_rate"),
        ({"drop_rate": -0.1}, "drop_rate"),
        ({"friction": 0.0}, "friction"),
        ({"friction": 0.4, "friction_belt": "left"}, "friction_belt"),
        ({"friction_belt": "1"}, "friction_belt"),
        ({"carriage_gain": 0.0}, "carriage_gain"),
        ({"mass_shift_kg": -1.0}, "mass_shift_kg"),
        ({"mass_shift_steps": (50, 10)}, "mass_shift_steps"),
    ],
)
def test_a_fault_out_of_range_is_refused_by_name(kwargs, name):
    with pytest.raises(ConfigError, match=name):
        F.Faults(**kwargs)


def test_faults_round_trip_as_a_dict_and_unknown_fields_are_named():
    f = F.Faults(obs_noise_mm=3, obs_latency=2, friction=0.4, friction_belt="2", mass_shift_steps=(10, 20))
    assert F.Faults.from_dict(f.to_dict()) == f
    with pytest.raises(ConfigError, match="obs_noise"):
        F.Faults.from_dict({"obs_noise": 3})
    assert not F.NONE.any and f.any and f.observation and f.plant


def _sensor(**kw):
    return F.Sensor(F.Faults(**kw), F.rng(jax.random.PRNGKey(3)))


def test_latency_returns_the_state_k_steps_old():
    sensor = _sensor(obs_latency=3)
    states = [np.array([-0.1, 0.1, 0.01 * t, 0.0, 0.0]) for t in range(10)]
    seen = [sensor.observe(s, np.zeros(2)) for s in states]
    for t, (s, _, age, fresh) in enumerate(seen):
        assert fresh and age == min(t, 3)
        np.testing.assert_array_equal(s, states[max(0, t - 3)])


def test_dropped_frames_hold_the_last_one_and_say_how_old_it_is():
    sensor = _sensor(drop_rate=0.5)
    states = [np.array([-0.1, 0.1, 0.01 * t, 0.0, 0.0]) for t in range(400)]
    seen = [sensor.observe(s, np.zeros(2)) for s in states]
    fresh = np.array([f for *_, f in seen])
    assert 0.4 < 1 - fresh[1:].mean() < 0.6  # about half the frames lost
    for t in range(1, 400):
        s, _, age, f = seen[t]
        if f:
            np.testing.assert_array_equal(s, states[t])
        else:  # the last delivered frame, age counted
            np.testing.assert_array_equal(s, seen[t - 1][0])
            assert age == seen[t - 1][2] + 1


def test_noise_has_the_stated_spread_and_levels_share_their_draws():
    truth = np.array([-0.1, 0.1, 0.02, -0.01, 0.3])
    out = {}
    for mm, deg in ((1.0, 0.5), (3.0, 1.5)):
        sensor = _sensor(obs_noise_mm=mm, obs_noise_deg=deg)
        out[mm] = np.stack([sensor.observe(truth, np.zeros(2))[0] for _ in range(4000)]) - truth
        np.testing.assert_allclose(out[mm][:, geometry.X].std(), 1e-3 * mm, rtol=0.06)
        np.testing.assert_allclose(out[mm][:, geometry.YAW].std(), np.radians(deg), rtol=0.06)
        assert np.all(out[mm][:, [geometry.P1, geometry.P2]] == 0)  # encoders: not noisy
    np.testing.assert_allclose(out[3.0], 3 * out[1.0], atol=1e-12)  # the same path, scaled


def test_action_latency_applies_each_action_k_steps_late():
    act = F.Actuator(F.Faults(action_latency=2))
    sent = [np.full(4, float(t)) for t in range(1, 6)]
    applied = [act.send(a) for a in sent]
    np.testing.assert_array_equal(applied[0], np.zeros(4))  # nothing has arrived yet: stand still
    np.testing.assert_array_equal(applied[1], np.zeros(4))
    for t in range(2, 5):
        np.testing.assert_array_equal(applied[t], sent[t - 2])


def test_world_model_changes_the_friction_of_one_belt_and_the_servo_gains():
    m = sim_model.box_model(CFG, massdist.named("A", CFG.box))
    before = (m.pair_friction.copy(), m.actuator_gainprm.copy(), m.actuator_biasprm.copy())
    F.world_model(m, F.Faults(friction=0.35, friction_belt="2", carriage_gain=0.5, belt_gain=2.0))
    assert m.pair_friction[0, 0] == before[0][0, 0] == CFG.gripper.friction  # belt 1 untouched
    assert m.pair_friction[1, 0] == m.pair_friction[1, 1] == 0.35
    assert m.geom("belt2").id in (m.pair_geom1[1], m.pair_geom2[1])
    np.testing.assert_allclose(m.actuator_gainprm[2:, 0], 0.5 * before[1][2:, 0])
    np.testing.assert_allclose(m.actuator_biasprm[2:, 1:3], 0.5 * before[2][2:, 1:3])
    np.testing.assert_allclose(m.actuator_gainprm[:2, 0], 2.0 * before[1][:2, 0])
    np.testing.assert_allclose(m.actuator_biasprm[:2, 2], 2.0 * before[2][:2, 2])


def test_the_simulators_friction_follows_coulomb_law_closed_form():
    """Both belts accelerate along +x at the limit (0.6 m/s^2) for 0.4 s. With mu = 0.5 the box follows
    them (mu g = 4.9 m/s^2 > 0.6): x = a t^2 / 2 = 48 mm. With the simulator's friction set to mu = 0.05
    (the controller's config unchanged) it slides behind at mu g = 0.49 m/s^2: x = 39 mm."""
    from boxjax.sim import make_env

    env = make_env(CFG)
    x = {}
    for mu in (0.05, 0.5):
        state = env.reset(jax.random.PRNGKey(0), massdist.named("uniform", CFG.box))
        F.world_model(state.model, F.Faults(friction=mu))
        x0 = float(state.s[geometry.X])
        for _ in range(8):
            state = env.step(state, [0.24, 0.24, 0.0, 0.0])
        x[mu] = float(state.s[geometry.X]) - x0
    g, t = CFG.gripper.gravity, 8 * CFG.gripper.control_dt
    np.testing.assert_allclose(x[0.5], 0.5 * 0.6 * t**2, rtol=0.1)
    np.testing.assert_allclose(x[0.05], 0.5 * 0.05 * g * t**2, rtol=0.15)


def test_a_mass_shift_keeps_the_mass_and_moves_the_centre_of_mass_where_it_slid():
    dist = massdist.named("uniform", CFG.box)
    props = massdist.mass_properties(dist, CFG.box)
    f = F.Faults(mass_shift_kg=1.0, mass_shift_m=0.10)
    shifts = [F.mass_shift(dist, CFG, f, F.rng(jax.random.PRNGKey(k))) for k in range(20)]
    for sh in shifts:
        assert f.mass_shift_steps[0] <= sh.step <= f.mass_shift_steps[1]
        np.testing.assert_allclose(sh.mass, float(props.mass), rtol=1e-6)
        d = sh.com[:2] - np.asarray(props.com[:2])
        # at most the slid fraction times the slide, in the direction drawn (rounded to the voxel grid)
        frac = 1.0 / float(props.mass)
        assert np.linalg.norm(d) <= frac * 0.10 * 1.5 + 1e-9
        if np.linalg.norm(d) > 1e-4:
            assert np.cos(np.arctan2(d[1], d[0]) - sh.direction) > 0.5
        assert np.all(np.linalg.eigvalsh(sh.inertia) > 0)
        moved = massdist.mass_properties_from_masses(sh.masses, CFG.box)  # the slid voxels give them
        np.testing.assert_allclose(np.asarray(moved.com), sh.com, atol=1e-6)
    assert len({sh.step for sh in shifts}) > 5  # the step is drawn
    assert F.mass_shift(dist, CFG, F.NONE, F.rng(jax.random.PRNGKey(0))) is None


def test_the_mass_shift_is_written_into_the_native_model():
    dist = massdist.named("A", CFG.box)
    m = sim_model.box_model(CFG, dist)
    body = sim_model.ids(m).box_body
    sh = F.mass_shift(dist, CFG, F.Faults(mass_shift_kg=2.0), F.rng(jax.random.PRNGKey(1)))
    sh.apply(m, body)
    np.testing.assert_allclose(m.body_ipos[body], sh.com, atol=1e-9)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)  # MuJoCo's own centre of mass of the box, in the world
    R = d.xmat[body].reshape(3, 3)
    np.testing.assert_allclose(d.xipos[body] - d.xpos[body], R @ sh.com, atol=1e-9)
    np.testing.assert_allclose(m.body_mass[body], sh.mass, rtol=1e-6)
    assert sh.done


def test_the_true_stability_margin_follows_the_slid_mass_after_its_step():
    """`control.true_stability_margins`: the states up to the shift's step are the drawn box's, those
    after it the slid masses' (the slide applied before that step's action), each the exact margin."""
    dist = massdist.named("A", CFG.box)
    sh = F.mass_shift(dist, CFG, F.Faults(mass_shift_kg=2.0, mass_shift_m=0.15), F.rng(jax.random.PRNGKey(1)))
    sh.step = 2
    s = np.tile([-0.1, 0.1, 0.0, 0.0, 0.3], (6, 1))  # P1, P2 at rest, the box centred, turned 0.3 rad
    before = true_stability_margins(CFG, dist, s)
    assert np.allclose(true_stability_margins(CFG, dist, s, sh), before)  # not applied: no change
    sh.done = True
    after = true_stability_margins(CFG, dist, s, sh)
    np.testing.assert_array_equal(after[:3], before[:3])
    slid = prior.make_prior(sh.masses, None, CFG.box, CFG.gripper, margin="exact")
    np.testing.assert_allclose(
        after[3:], float(slid.stability_margin(jnp.asarray(s[0], jnp.float32))), atol=1e-6
    )
    assert abs(after[3] - before[3]) > 1e-3  # 2 kg slid 15 cm moves the centre of mass, and the margin


def test_the_filter_tracks_a_moving_box_through_noise_and_latency():
    dt, lat = CFG.gripper.control_dt, 2
    f = F.Faults(obs_noise_mm=3.0, obs_noise_deg=1.5, obs_latency=lat)
    v, w = 0.05, 0.4  # m/s along x, rad/s yaw
    for compensation, lag in (("constant_velocity", 0), ("model", lat)):
        filt = make_filter(FilterConfig(compensation=compensation), f, dt)
        sensor = F.Sensor(f, F.rng(jax.random.PRNGKey(0)))
        raw_err, est_err = [], []
        for t in range(400):
            truth = np.array([-0.1, 0.1, v * dt * t, 0.0, w * dt * t])
            s, _, _, fresh = sensor.observe(truth, np.zeros(2))
            est = filt.step(s, fresh)
            if t > 40:
                raw_err.append(s[geometry.X] - truth[geometry.X])
                est_err.append(est[geometry.X] - v * dt * (t - lag))
        raw_err, est_err = np.array(raw_err), np.array(est_err)
        # the raw observation is late by lat steps: 5 mm behind. The estimate is predicted to the present
        # by the filter (constant velocity), or is the measurement time's (the model predicts it forward)
        np.testing.assert_allclose(raw_err.mean(), -v * lat * dt, atol=1e-3)
        assert abs(est_err.mean()) < 1e-3, compensation
        assert np.sqrt(np.mean(est_err**2)) < np.sqrt(np.mean((raw_err + v * lag * dt) ** 2))
    # its stated uncertainty: about the measurement noise reduced by the averaging, growing over a latency
    filt = make_filter(FilterConfig(compensation="model"), f, dt)
    cv = make_filter(FilterConfig(compensation="constant_velocity"), f, dt)
    for _ in range(50):
        z = np.array([-0.1, 0.1, 0.0, 0.0, 0.0])
        filt.step(z), cv.step(z)
    assert 0.3e-3 < filt.y_std() < 3e-3 and cv.y_std() > filt.y_std()


def test_no_filter_with_a_perfect_sensor_unless_asked():
    assert make_filter(FilterConfig(), F.NONE, 0.05) is None
    assert isinstance(make_filter(FilterConfig(enabled=True), F.NONE, 0.05), PoseFilter)
    assert make_filter(FilterConfig(enabled=False), F.Faults(obs_noise_mm=3), 0.05) is None
    with pytest.raises(ConfigError, match="accel_std"):
        FilterConfig(accel_std=0.0)
    with pytest.raises(ConfigError, match="compensation='model'"):
        FilterConfig(motion="model", compensation="constant_velocity")
    with pytest.raises(ConfigError, match="model_std_mm"):
        FilterConfig(model_std_mm=0.0)


def test_with_no_fault_the_world_is_the_identity_and_draws_nothing():
    w = World(CFG, F.NONE, FilterConfig(), jax.random.PRNGKey(0), massdist.named("A", CFG.box))
    s, b = np.arange(5, dtype=np.float32), np.ones(2, np.float32)
    s2, b2 = w.observe(s, b)
    assert s2 is not None and np.array_equal(s2, s) and np.array_equal(b2, b)
    a = np.array([0.1, -0.1, 0.0, 0.01])
    assert w.send(a) is a and not w.before_step(100, None, 0)


def test_run_episode_with_faults_replays_and_a_perfect_world_is_unchanged():
    from boxjax import ControllerConfig, run_episode
    from boxjax.planners.sampling import SamplingOptions

    ctrl = ControllerConfig(sampling=SamplingOptions(gradient_steps=0))
    box, key = massdist.named("A", CFG.box), jax.random.PRNGKey(2)
    plain = run_episode(CFG, box, key, ctrl=ctrl, max_steps=80)
    none = run_episode(CFG, box, key, ctrl=ctrl, max_steps=80, faults=F.Faults())
    np.testing.assert_array_equal(plain.trace.s, none.trace.s)
    realistic = F.Faults(obs_noise_mm=3, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.05, friction=0.4)
    a = run_episode(CFG, box, key, ctrl=ctrl, max_steps=80, faults=realistic)
    b = run_episode(CFG, box, key, ctrl=ctrl, max_steps=80, faults=realistic)
    np.testing.assert_array_equal(a.trace.s, b.trace.s)  # drawn from the key: it replays
    assert not np.array_equal(a.trace.s, plain.trace.s)
    late = run_episode(CFG, box, key, ctrl=ctrl, max_steps=60, faults=F.Faults(action_latency=3))
    np.testing.assert_array_equal(late.trace.actions[:3], np.zeros((3, 4)))  # applied 3 steps late
    with pytest.raises(ValueError, match="native"):
        run_episode(CFG, box, key, ctrl=ctrl, max_steps=5, backend="mjx", faults=realistic)


def test_faults_are_hashable_settings():
    f = F.Faults(obs_noise_mm=1.0)
    assert hash(f) == hash(dataclasses.replace(f))


def test_a_gripper_at_rest_holds_the_box_still_in_the_estimate():
    """The zero-velocity update: with the gripper known at rest the filter's velocity is zero and its
    estimate averages frames, so a stopped box's estimate is steadier than the free filter's."""
    dt = CFG.gripper.control_dt
    f = F.Faults(obs_noise_mm=3.0)
    free, still = make_filter(FilterConfig(), f, dt), make_filter(FilterConfig(), f, dt)
    gen = np.random.default_rng(0)
    err_free, err_still = [], []
    for t in range(300):
        z = np.array([-0.1, 0.1, 0.0, 0.02, 0.0])
        z[2:4] += 3e-3 * gen.standard_normal(2)
        a, b = free.step(z), still.step(z, still=True)
        if t > 50:
            err_free.append(a[geometry.Y] - 0.02)
            err_still.append(b[geometry.Y] - 0.02)
    assert np.all(still.x[:, 1] == 0.0)
    assert np.std(err_still) < 0.7 * np.std(err_free)
    assert still.y_std() < free.y_std()


def test_the_world_knows_the_gripper_is_still_only_after_rest_was_sent_over_the_delay():
    f = F.Faults(obs_noise_mm=3.0, obs_latency=2)
    w = World(CFG, f, FilterConfig(), jax.random.PRNGKey(0), massdist.named("A", CFG.box))
    rest, move = np.zeros(4), np.array([0.1, -0.1, 0.0, 0.0])
    w.send(move)
    assert not w.rest.still(np.zeros(2))
    for _ in range(w.delay + 1):
        w.send(rest)
        assert not w.rest.still(np.zeros(2))
    w.send(rest)
    assert w.rest.still(np.zeros(2)) and not w.rest.still(np.array([0.02, 0.0]))


def test_replay_with_faults_re_simulates_the_episode_and_the_controllers_view():
    from boxjax import ControllerConfig, run_episode
    from boxjax.control.batch import replay_episode
    from boxjax.planners.sampling import SamplingOptions

    ctrl = ControllerConfig(sampling=SamplingOptions(gradient_steps=0))
    faults = F.Faults(obs_noise_mm=3, obs_latency=2, action_latency=1, friction=0.4, mass_shift_kg=1.0,
                      mass_shift_steps=(50, 60))  # fmt: skip
    box, key = massdist.named("B", CFG.box), jax.random.PRNGKey(4)
    ep = run_episode(CFG, box, key, ctrl=ctrl, max_steps=80, faults=faults)
    again = replay_episode(CFG, box, key, ep.trace.actions, ctrl=ctrl, faults=faults)
    np.testing.assert_array_equal(again.trace.s, ep.trace.s)
    assert again.summary["aborted"] == ep.summary["aborted"]


def test_a_box_at_rest_is_averaged_to_the_noise_over_the_square_root_of_the_frames():
    """At rest nothing moves the box, so the filter adds no process noise: after n frames its estimate's
    error is the sensor's noise / sqrt(n) (the mean of n frames), and the variance it states says so."""
    dt, noise = CFG.gripper.control_dt, 3e-3
    f = F.Faults(obs_noise_mm=1e3 * noise)
    errs, stds = [], []
    for seed in range(200):
        flt = make_filter(FilterConfig(), f, dt)
        gen = np.random.default_rng(seed)
        for _ in range(100):
            z = np.array([-0.1, 0.1, 0.0, 0.02, 0.0])
            z[3] += noise * gen.standard_normal()
            est = flt.step(z, still=True)
        errs.append(est[geometry.Y] - 0.02)
        stds.append(flt.y_std())
    expect = noise / np.sqrt(100)
    assert np.std(errs) == pytest.approx(expect, rel=0.15)
    assert np.mean(stds) == pytest.approx(expect, rel=0.15)


def test_the_model_driven_filter_reaches_the_random_walk_riccati_solution():
    """With the model's prediction as its motion, each axis's position is a random walk of the model's
    one-step error q observed with noise r: the filter's variance converges to the scalar Riccati
    solution P = (-q + sqrt(q^2 + 4 q r)) / 2 (after the update), and its error to that spread."""
    dt, noise = CFG.gripper.control_dt, 3e-3
    settings = FilterConfig(model_std_mm=1.0)
    q, r = 1e-6, noise**2
    p_ss = (-q + np.sqrt(q * q + 4 * q * r)) / 2
    errs = []
    for seed in range(100):
        flt = make_filter(settings, F.Faults(obs_noise_mm=3.0), dt)
        gen = np.random.default_rng(seed)
        y = 0.0
        for t in range(80):
            y += 1e-3 * gen.standard_normal()  # the truth moves by the model's error
            z = np.array([-0.1, 0.1, 0.0, y + noise * gen.standard_normal(), 0.0])
            predicted = None if t == 0 else np.array([-0.1, 0.1, 0.0, flt.x[1, 0], 0.0])  # the model: no move
            flt.step(z, predicted=predicted)
        errs.append(flt.x[1, 0] - y)
    np.testing.assert_allclose(flt.P[1, 0, 0], p_ss, rtol=1e-3)
    np.testing.assert_allclose(np.std(errs), np.sqrt(p_ss), rtol=0.2)
    # and a model that knows the motion (to 0.3 mm a step) gives the window smooth velocities where
    # constant velocity cannot
    gen = np.random.default_rng(1)
    f = F.Faults(obs_noise_mm=3.0)
    model_f, cv_f = make_filter(FilterConfig(model_std_mm=0.3), f, dt), make_filter(FilterConfig(), f, dt)
    vel_err = {"model": [], "cv": []}
    prev = {"model": None, "cv": None}
    for t in range(300):
        y = 0.03 * np.sin(2 * np.pi * t * dt)  # carried sideways, known to the model
        z = np.array([-0.1, 0.1, 0.0, y + 3e-3 * gen.standard_normal(), 0.0])
        predicted = None if t == 0 else np.array([-0.1, 0.1, 0.0, y, 0.0])
        out = {"model": model_f.step(z, predicted=predicted), "cv": cv_f.step(z)}
        for k, o in out.items():
            if prev[k] is not None and t > 50:
                v_true = 0.03 * 2 * np.pi * np.cos(2 * np.pi * (t - 0.5) * dt)
                vel_err[k].append((o[geometry.Y] - prev[k]) / dt - v_true)
            prev[k] = o[geometry.Y]
    rms = {k: np.sqrt(np.mean(np.square(v))) for k, v in vel_err.items()}
    assert rms["model"] < 0.5 * rms["cv"], rms


def test_the_filter_is_told_the_action_that_moved_the_box_between_its_frames():
    """`World.applied_next` aligns the model's prediction with the frames under sensor and action
    latency: the prediction of the next frame, made from the window at the newest frame's measurement
    time, lies within the prior's one-step error of MuJoCo's state at that time, and closer to it than to
    the states a step before or after (an alignment off by one)."""
    from boxjax import ControllerConfig, run_episode
    from boxjax.control import world as world_mod
    from boxjax.planners.sampling import SamplingOptions

    faults = F.Faults(obs_noise_mm=0.1, obs_noise_deg=0.05, obs_latency=2, action_latency=1)
    truth: list = []  # MuJoCo's states, one per observation
    pairs: list = []  # (the model's prediction of a frame, the index of that frame's observation)
    expect, observe = world_mod.World.expect, world_mod.World.observe

    def spy_expect(self, predicted):
        pairs.append([np.asarray(predicted, np.float64), None])
        return expect(self, predicted)

    def spy_observe(self, s, b):
        truth.append(np.asarray(s, np.float64))
        if pairs and pairs[-1][1] is None:
            pairs[-1][1] = len(truth) - 1
        return observe(self, s, b)

    ctrl = ControllerConfig(
        sampling=SamplingOptions(gradient_steps=0), pose_filter=FilterConfig(motion="model")
    )
    world_mod.World.expect, world_mod.World.observe = spy_expect, spy_observe
    try:
        run_episode(CFG, massdist.named("A", CFG.box), jax.random.PRNGKey(3), ctrl=ctrl, max_steps=120,
                    faults=faults)  # fmt: skip
    finally:
        world_mod.World.expect, world_mod.World.observe = expect, observe
    assert len(pairs) > 40
    xy = [geometry.X, geometry.Y]

    def err(shift):  # observation i shows the true state of observation i - latency
        i0 = faults.obs_latency - shift
        return np.median([np.linalg.norm(p[xy] - truth[i - i0][xy]) for p, i in pairs[5:-2]])

    assert err(0) < 1.5e-3, err(0)
    assert err(0) < 0.7 * min(err(-1), err(1)), (err(-1), err(0), err(1))


def test_the_state_window_gives_the_planner_the_filters_velocity_not_differences_of_noisy_frames():
    """`FilterConfig(window="state")`: the planner's window is the line through the newest estimate along
    the filter's velocity, so the velocity the prior takes from it (the last difference) is the filter's
    estimate, steadier than the difference of two noisy estimates; the carriages stay as measured, and a
    perfect sensor's window is untouched."""
    v = np.array([0.05, -0.02])  # m/s in x, y
    f = F.Faults(obs_noise_mm=3.0, obs_noise_deg=1.5)
    dt = CFG.gripper.control_dt
    errs = {"frames": [], "state": []}
    for kind in errs:
        world = World(CFG, f, FilterConfig(window=kind), jax.random.PRNGKey(5), massdist.named("A", CFG.box))
        seen = []
        for t in range(300):
            truth = np.array([-0.1 + 1e-4 * t, 0.1, v[0] * dt * t, v[1] * dt * t, 0.0])
            seen.append(world.observe(truth, np.zeros(2))[0])
            if t > 50:
                w = world.planner_window(seen[-3:])
                errs[kind].append(
                    (w[-1, [geometry.X, geometry.Y]] - w[-2, [geometry.X, geometry.Y]]) / dt - v
                )
                np.testing.assert_allclose(w[:, geometry.P1], [s[geometry.P1] for s in seen[-3:]], atol=1e-7)
                np.testing.assert_allclose(w[-1], seen[-1], atol=1e-6)  # the newest estimate itself
    rms = {k: float(np.sqrt(np.mean(np.square(e)))) for k, e in errs.items()}
    assert rms["state"] < 0.7 * rms["frames"], rms
    perfect = World(
        CFG, F.NONE, FilterConfig(window="state"), jax.random.PRNGKey(0), massdist.named("A", CFG.box)
    )
    frames = [np.arange(5, dtype=np.float32) + k for k in range(3)]
    np.testing.assert_array_equal(perfect.planner_window(frames), np.stack(frames))


def test_by_default_the_state_window_is_used_for_a_noisy_sensor_only():
    box, key = massdist.named("A", CFG.box), jax.random.PRNGKey(0)
    for faults, expected in (
        (F.Faults(obs_noise_mm=1.0), True),
        (F.Faults(obs_noise_deg=0.5), True),
        (F.Faults(obs_latency=2), False),  # exact frames, late: their differences carry the acceleration
        (F.Faults(friction=0.4), False),
        (F.NONE, False),
    ):
        assert World(CFG, faults, FilterConfig(), key, box).state_window is expected, faults
    assert World(CFG, F.Faults(obs_latency=2), FilterConfig(window="state"), key, box).state_window
    assert not World(CFG, F.Faults(obs_noise_mm=3), FilterConfig(window="frames"), key, box).state_window
    with pytest.raises(ConfigError, match="window"):
        FilterConfig(window="line")


@pytest.mark.slow
def test_batched_episodes_give_the_model_driven_filter_its_prediction_every_mpc_step():
    """The batched path (`batch.run_episodes`) makes the filter's model predictions in one call per step,
    for every live box, as `run_episode` does per box. (Slow: the model-driven filter is off by default;
    the one-box loop's is in the default suite.)"""
    from boxjax import ControllerConfig
    from boxjax.control import batch
    from boxjax.control import world as world_mod
    from boxjax.planners.sampling import SamplingOptions

    calls: list = []
    expect = world_mod.World.expect

    def spy(self, predicted):
        calls.append(np.asarray(predicted))
        return expect(self, predicted)

    ctrl = ControllerConfig(
        sampling=SamplingOptions(gradient_steps=0), pose_filter=FilterConfig(motion="model")
    )
    boxes = [massdist.named(n, CFG.box) for n in ("A", "B")]
    world_mod.World.expect = spy
    try:
        keys = [jax.random.PRNGKey(i) for i in range(2)]
        faults = F.Faults(obs_noise_mm=2.0, obs_latency=1)
        res = batch.run_episodes(CFG, boxes, keys, ctrl=ctrl, max_steps=80, faults=faults)
    finally:
        world_mod.World.expect = expect
    mpc_steps = sum(len(r.trace.actions) - r.summary["exploration_steps"] for r in res)  # a plan per MPC step
    assert mpc_steps > 0 and len(calls) == mpc_steps
    assert all(c.shape == (5,) and np.all(np.isfinite(c)) for c in calls)


def test_a_carriage_move_adds_its_unknown_drag_to_the_y_variance_and_the_filter_stays_consistent():
    """A carriage moved under the box drags it by an unknown fraction of the travel (the encoders give
    the travel): with `carriage_drag_std` s the predicted y variance grows by s^2 times each carriage's
    squared travel (a held frame carries none, the next fresh one all of it). Kalman consistency: with the
    true drag fraction drawn with that spread, after a box averaged at rest is dragged, the errors' spread
    matches the variance the filter states; without it the filter holds its rest estimate and its stated
    std is a fraction of its error (the overconfidence that let a 10 mm sensor's monitor resume a box
    that was 1 cm further out than it believed, docs/results/faults.md)."""
    dt, noise, s = CFG.gripper.control_dt, 10e-3, 0.3
    f = F.Faults(obs_noise_mm=1e3 * noise)
    rest = np.array([-0.1, 0.1, 0.0, 0.02, 0.0])
    # closed form: a still predict adds nothing but the drag, sum of both carriages' squared travel
    flt = make_filter(FilterConfig(carriage_drag_std=s), f, dt)
    flt.step(rest, still=True)
    flt.step(rest, still=True)  # the zero-velocity update: no velocity variance left
    p0 = flt.P[1, 0, 0]
    moved = rest + np.array([-0.01, 0.004, 0.0, 0.0, 0.0])
    flt.step(moved, fresh=False, still=True)
    np.testing.assert_allclose(flt.P[1, 0, 0], p0 + s**2 * (0.01**2 + 0.004**2), rtol=1e-9)
    flt.step(moved, fresh=False, still=True)  # held again: no new travel
    np.testing.assert_allclose(flt.P[1, 0, 0], p0 + s**2 * (0.01**2 + 0.004**2), rtol=1e-9)

    def dragged(drag_std: float, seed: int) -> tuple[float, float]:
        gen = np.random.default_rng(seed)
        flt = make_filter(FilterConfig(carriage_drag_std=drag_std), f, dt)
        y = 0.02
        for _ in range(40):  # at rest: averaged to noise / sqrt(40)
            z = rest.copy()
            z[3] = y + noise * gen.standard_normal()
            flt.step(z, still=True)
        travel = 0.01
        y += s * travel * gen.standard_normal()  # the world's drag, spread s
        z = rest + np.array([0.0, -travel, 0.0, 0.0, 0.0])
        z[3] = y + noise * gen.standard_normal()
        est = flt.step(z, still=True)
        return est[geometry.Y] - y, flt.y_std()

    for drag_std, consistent in ((s, True), (0.0, False)):
        errs, stds = zip(*(dragged(drag_std, seed) for seed in range(400)), strict=True)
        ratio = np.std(errs) / np.sqrt(np.mean(np.square(stds)))
        if consistent:
            assert ratio == pytest.approx(1.0, abs=0.12), ratio
        else:
            assert ratio > 1.5, ratio
