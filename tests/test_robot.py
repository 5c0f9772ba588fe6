"""boxjax.robot: the robot's messages without ROS; every sign, unit and frame convention, the stops, a
replay of a simulated episode through the messages, and a property test of the outgoing commands."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from boxjax.robot import (
    ROBOT_MAX_ACCELERATION,
    ROBOT_MAX_VELOCITY,
    STOP_REASONS,
    AdapterConfig,
    JointState,
    Quaternion,
    RobotLoop,
    TrackingFeedback,
    VelocityControl,
    action_from_commands,
    carriage_targets,
    commands_from_action,
    messages_from_observation,
    observation_from_messages,
)

CFG = AdapterConfig()


def tracking(x=0.0, y=0.0, q=(0.0, 0.0, 0.0, 1.0), stamp=10.0, frame="gripper_surface_tip_link"):
    qx, qy, qz, qw = q
    return TrackingFeedback.from_dict(
        {
            "header": {"stamp": stamp, "frame_id": frame},
            "items_in_manipulator": [
                {
                    "pose": {
                        "position": {"x": x, "y": y, "z": 0.075},
                        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
                    }
                }
            ],
        }
    )


def joints(right=0.10, left=0.10, v_right=0.0, v_left=0.0, stamp=10.0):
    return JointState.from_dict(
        {
            "header": {"stamp": stamp, "frame_id": ""},
            "name": [
                "gripper_y_left",
                "conveyor_belt_left",
                "wrist",
                "conveyor_belt_right",
                "gripper_y_right",
            ],
            "position": [left, 0.0, math.nan, 0.0, right],
            "velocity": [0.0, v_left, math.nan, v_right, 0.0],
            "effort": [],
        }
    )


def test_box_at_plus_y_lies_towards_belt_2_the_left_belt():
    s, v, stamp = observation_from_messages(tracking(0.0, 0.05), joints(right=0.12, left=0.15))
    np.testing.assert_allclose(s, [-0.12, 0.15, 0.0, 0.05, 0.0])
    assert s[0] < 0 < s[1] and stamp == 10.0
    # the tip link's planar pose in the conveyor frame: rotate, then offset
    cfg = AdapterConfig(tip_in_conveyor=(0.02, -0.01, math.pi / 2))
    s, _, _ = observation_from_messages(tracking(0.05, 0.0), joints(), cfg)
    np.testing.assert_allclose(s[2:], [0.02, 0.04, math.pi / 2], atol=1e-12)


def test_quaternion_is_ros_order_and_yaw_is_about_z():
    h = math.radians(15)
    s, _, _ = observation_from_messages(tracking(q=(0.0, 0.0, math.sin(h), math.cos(h))), joints())
    assert s[4] == pytest.approx(math.radians(30))
    s, _, _ = observation_from_messages(tracking(q=(0.0, 0.0, -math.sin(h), math.cos(h))), joints())
    assert s[4] == pytest.approx(math.radians(-30))
    assert Quaternion.from_yaw(math.radians(30)).xyzw() == pytest.approx((0, 0, math.sin(h), math.cos(h)))
    assert Quaternion.from_dict([0.0, 0.0, math.sin(h), math.cos(h)]).w == pytest.approx(math.cos(h))
    with pytest.raises(ValueError, match="ROS order"):  # (w, x, y, z) read as (x, y, z, w)
        observation_from_messages(tracking(q=(math.cos(h), 0.0, 0.0, math.sin(h))), joints())
    with pytest.raises(ValueError, match="norm"):
        observation_from_messages(tracking(q=(0.0, 0.0, 0.0, 0.0)), joints())


def test_yaw_is_continuous_given_the_previous_one():
    q = Quaternion.from_yaw(-3.0).xyzw()
    s, _, _ = observation_from_messages(tracking(q=q), joints(), prev_yaw=3.0)
    assert s[4] == pytest.approx(2 * math.pi - 3.0)


def test_carriage_distances_both_ways():
    s, _, _ = observation_from_messages(tracking(), joints(right=0.12, left=0.15))
    assert (s[0], s[1]) == pytest.approx((-0.12, 0.15))  # gripper_y_right = -P1, gripper_y_left = +P2
    _, car, _ = commands_from_action([0, 0, 0.0, 0.0], [-0.12, 0.15], 10.0, 10.0)
    assert car.joint_names == ("gripper_y_right", "gripper_y_left")
    assert car.positions == pytest.approx((0.12, 0.15))
    cfg = AdapterConfig(carriage_offset=(-0.05, -0.05))  # robot value = sign * P + offset
    _, car, _ = commands_from_action([0, 0, 0.0, 0.0], [-0.12, 0.15], 10.0, 10.0, cfg)
    assert car.positions == pytest.approx((0.07, 0.10))
    np.testing.assert_allclose(carriage_targets(car, cfg), [-0.12, 0.15])
    with pytest.raises(ValueError, match="gripper_y_right"):  # a negative distance: the wrong side
        observation_from_messages(tracking(), joints(right=-0.1))
    with pytest.raises(ValueError, match="units"):  # mm instead of m
        observation_from_messages(tracking(), joints(left=100.0))


def test_joints_are_matched_by_name():
    s, v, _ = observation_from_messages(tracking(), joints(right=0.11, left=0.13, v_right=0.1, v_left=-0.05))
    np.testing.assert_allclose(s[:2], [-0.11, 0.13])
    np.testing.assert_allclose(v, [0.1, -0.05])  # belt 1 = conveyor_belt_right
    d = joints().to_dict()
    d["name"][4] = "gripper_y_rigth"
    with pytest.raises(ValueError, match="gripper_y_right"):
        observation_from_messages(tracking(), d)
    d = joints().to_dict()
    d["velocity"] = []
    with pytest.raises(ValueError, match="velocity"):
        observation_from_messages(tracking(), d)
    with pytest.raises(ValueError, match="one per name"):
        JointState(name=("a", "b"), position=(1.0,))
    with pytest.raises(ValueError, match="more than once"):
        JointState(name=("a", "a"))
    with pytest.raises(ValueError, match="sequence"):
        JointState.from_dict({"header": {"stamp": 0.0}, "name": "gripper_y_left"})


def test_belt_velocities_signs_and_acceleration_never_zero():
    vel, _, st_ = commands_from_action([0.1, -0.05, 0, 0], [-0.1, 0.1], 10.0, 10.0)
    assert vel.joint_names == ("conveyor_belt_right", "conveyor_belt_left")
    assert vel.target_velocities == (0.1, -0.05)
    assert vel.target_accelerations == (0.6, 0.6) and not st_["safe_stop"]
    vel, _, _ = commands_from_action(
        [0.1, -0.05, 0, 0], [-0.1, 0.1], 10.0, 10.0, AdapterConfig(belt_sign=(-1.0, 1.0))
    )
    assert vel.target_velocities == (-0.1, -0.05)
    vel, car, st_ = commands_from_action([math.nan, 0, 0, 0], [-0.1, 0.1], 10.0, 10.0)  # a stop
    assert st_["reason"] == "non_finite_action" and vel.target_velocities == (0.0, 0.0)
    assert vel.target_accelerations == (0.6, 0.6)
    for bad in ({"target_accelerations": [0.0, 0.6]}, {"target_accelerations": [0.61, 0.6]},
                {"target_velocities": [0.25, 0.0]}, {"target_velocities": [math.nan, 0.0]}):  # fmt: skip
        d = {"joint_names": ["a", "b"], "target_velocities": [0.0, 0.0], "target_accelerations": [0.6, 0.6]}
        with pytest.raises(ValueError, match="VelocityControl"):
            VelocityControl.from_dict({**d, **bad})


def test_clipping_to_the_limits():
    vel, car, st_ = commands_from_action([1.0, -1.0, 0.5, -0.5], [-0.195, 0.065], 10.0, 10.0)
    assert vel.target_velocities == (0.247, -0.247) and st_["clipped"]
    np.testing.assert_allclose(carriage_targets(car), [-0.185, 0.06])


def test_stale_observation_stops():
    vel, car, st_ = commands_from_action([0.1, 0.1, 0.01, 0.0], [-0.1, 0.1], 10.11, 10.0)
    assert st_["safe_stop"] and st_["reason"] == "stale_observation"
    assert vel.target_velocities == (0.0, 0.0) and vel.target_accelerations == (0.6, 0.6)
    np.testing.assert_allclose(carriage_targets(car), [-0.1, 0.1])  # held
    vel, car, st_ = commands_from_action([0.1, 0.1, 0.01, 0.0], [-0.1, 0.1], 10.09, 10.0)
    assert not st_["safe_stop"] and vel.target_velocities == (0.1, 0.1)
    np.testing.assert_allclose(carriage_targets(car), [-0.09, 0.1])
    assert commands_from_action([0] * 4, [-0.1, 0.1], 9.8, 10.0)[2]["reason"] == "future_observation"
    assert commands_from_action([0] * 4, [-0.1, 0.1], math.nan, 10.0)[2]["reason"] == "invalid_stamp"


def test_messages_round_trip_through_dicts():
    t, j = tracking(0.01, 0.02), joints()
    assert TrackingFeedback.from_dict(t.to_dict()) == t and JointState.from_dict(j.to_dict()) == j
    d = t.to_dict()
    d["header"]["stamp"] = {"sec": 1, "nanosec": 500_000_000}
    assert TrackingFeedback.from_dict(d).header.stamp == pytest.approx(1.5)
    with pytest.raises(ValueError, match="unknown"):
        JointState.from_dict({**j.to_dict(), "speed": []})
    with pytest.raises(ValueError, match="frame_id"):
        observation_from_messages(tracking(frame="base_link"), joints())
    with pytest.raises(ValueError, match=r"position\.x"):
        observation_from_messages(tracking(x=math.nan), joints())
    with pytest.raises(ValueError, match="empty"):
        observation_from_messages({"header": {"stamp": 1.0}, "items_in_manipulator": []}, joints())


def test_messages_from_observation_inverts_with_any_convention():
    cfg = AdapterConfig(
        belt_sign=(-1.0, 1.0), carriage_offset=(0.01, -0.02), tip_in_conveyor=(0.03, -0.02, 0.4),
        item_centre_offset=(0.2, 0.15), belt_state_scale=2.0,
    ).sides_swapped()  # fmt: skip
    s = np.array([-0.11, 0.14, 0.02, 0.01, 1.2])
    t, j = messages_from_observation(s, [0.1, -0.2], 3.0, cfg)
    s2, v2, stamp = observation_from_messages(t, j, cfg)
    np.testing.assert_allclose(s2, s, atol=1e-12)
    np.testing.assert_allclose(v2, [0.1, -0.2], atol=1e-12)
    assert cfg.carriage_joints == ("gripper_y_left", "gripper_y_right") and stamp == 3.0


def test_config_is_checked():
    with pytest.raises(ValueError, match="carriage_sign"):
        AdapterConfig(carriage_sign=(0.5, 1.0))
    with pytest.raises(ValueError, match="four different"):
        AdapterConfig(belt_joints=("gripper_y_left", "conveyor_belt_left"))


def test_robot_loop_keeps_the_controllers_window_and_stops():
    seen = []

    def plan(obs):
        seen.append(np.asarray(obs.window))
        return np.array([0.1, -0.1, -0.01, 0.0])

    loop = RobotLoop(plan)
    vel, car, st_ = loop.step(tracking(q=(0, 0, 0, 0)), joints(), 10.0)  # nothing valid yet
    assert st_["reason"] == "invalid_observation" and car is None and vel.target_accelerations == (0.6, 0.6)
    for k in range(3):
        vel, car, st_ = loop.step(
            tracking(x=0.01 * k, stamp=10 + 0.05 * k), joints(stamp=10 + 0.05 * k), 10 + 0.05 * k
        )
        assert not st_["safe_stop"]
    np.testing.assert_allclose(seen[0][:, 2], [0, 0, 0])  # the first state repeated
    np.testing.assert_allclose(seen[2][:, 2], [0, 0.01, 0.02], atol=1e-7)
    assert loop.target_yaw == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(loop.p_target, [-0.13, 0.1])  # the targets accumulate the steps
    _, car, st_ = loop.step(tracking(stamp=10.1), joints(stamp=10.1), 10.25)  # 0.15 s old
    assert st_["reason"] == "stale_observation" and len(seen) == 3
    np.testing.assert_allclose(carriage_targets(car), [-0.13, 0.1])
    tilted = Quaternion(math.sin(0.3), 0.0, 0.0, math.cos(0.3)).xyzw()  # 34 degrees: tipped
    assert (
        loop.step(tracking(q=tilted, stamp=10.3), joints(stamp=10.3), 10.3)[2]["reason"]
        == "invalid_observation"
    )


@pytest.fixture(scope="module")
def episode():
    from boxjax import DEFAULT, massdist, run_episode

    return run_episode(DEFAULT, massdist.named("A"), jax.random.PRNGKey(0), estimator="oracle", max_steps=80)


def test_replay_of_an_episode_through_the_messages(episode):
    tr = episode.trace
    assert len(tr.actions) > 45  # the exploration and some MPC steps
    g = CFG.gripper
    prev = None
    for t, (s, v) in enumerate(zip(tr.s.astype(np.float64), tr.belt_speed.astype(np.float64), strict=True)):
        stamp = 100.0 + 0.05 * t
        yaw = s[4]
        tk = tracking(s[2], s[3], (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), stamp)
        js = joints(right=-s[0], left=s[1], v_right=v[0], v_left=v[1], stamp=stamp)
        s2, v2, st2 = observation_from_messages(tk, js, CFG, prev_yaw=prev)
        prev = s2[4]
        np.testing.assert_allclose(s2, s, atol=1e-9)
        np.testing.assert_allclose(v2, v, atol=1e-12)
        if t == len(tr.actions):
            break
        a = tr.actions[t]
        vel, car, status = commands_from_action(a, s[:2], stamp + 0.03, st2, CFG)
        assert not status["safe_stop"]
        dp = np.clip(a[2:], -g.max_position_step, g.max_position_step)
        target = np.clip(s[:2] + dp, CFG.p_low, CFG.p_high)
        expected = [*np.clip(a[:2], -g.belt_speed_limit, g.belt_speed_limit), *(target - s[:2])]
        np.testing.assert_allclose(action_from_commands(vel, car, s[:2], CFG), expected, atol=1e-12)
        if not status["clipped"]:
            np.testing.assert_allclose(
                action_from_commands(vel.to_dict(), car.to_dict(), s[:2]), a, atol=1e-12
            )
        assert vel.target_velocities == pytest.approx(tuple(expected[:2]))
        assert car.positions == pytest.approx((-target[0], target[1]))


ANY = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=200, deadline=None)
@given(
    action=st.lists(ANY, min_size=4, max_size=4),
    p=st.lists(ANY, min_size=2, max_size=2),
    now=ANY,
    stamp=ANY,
    belt_sign=st.tuples(st.sampled_from([1.0, -1.0]), st.sampled_from([1.0, -1.0])),
    offset=st.floats(-0.1, 0.1),
)
def test_no_bad_command_ever_leaves(action, p, now, stamp, belt_sign, offset):
    """Any floats in the action and stamps: a valid command. ValueError only for non-finite state_p."""
    cfg = AdapterConfig(belt_sign=belt_sign, carriage_offset=(offset, -offset))
    if not all(math.isfinite(x) for x in p):
        with pytest.raises(ValueError, match="state_p"):
            commands_from_action(action, p, now, stamp, cfg)
        return
    vel, car, status = commands_from_action(action, p, now, stamp, cfg)
    v = np.array(vel.target_velocities)
    acc = np.array(vel.target_accelerations)
    assert np.all(np.isfinite(v)) and np.all(
        np.abs(v) <= min(ROBOT_MAX_VELOCITY, cfg.gripper.belt_speed_limit)
    )
    assert np.all(acc > 0) and np.all(acc <= ROBOT_MAX_ACCELERATION)
    target = carriage_targets(car, cfg)
    assert np.all(np.isfinite(car.positions))
    assert np.all(target >= cfg.p_low - 1e-12) and np.all(target <= cfg.p_high + 1e-12)
    assert VelocityControl.from_dict(vel.to_dict()) == vel
    if status["safe_stop"]:
        assert status["reason"] in STOP_REASONS and np.all(v == 0)


@settings(max_examples=200, deadline=None)
@given(vals=st.lists(ANY, min_size=11, max_size=11))
def test_any_incoming_values_give_a_checked_state_or_a_value_error(vals):
    x, y, qx, qy, qz, qw, right, left, vr, vl, stamp = vals
    try:
        s, v, st_ = observation_from_messages(
            tracking(x, y, (qx, qy, qz, qw), stamp), joints(right, left, vr, vl)
        )
    except ValueError:
        return
    assert np.all(np.isfinite(s)) and np.all(np.isfinite(v)) and math.isfinite(st_)
    assert s[0] < 0 < s[1]


def test_the_planner_step_runs_the_runtime_safety_monitor_with_its_model():
    from typing import NamedTuple

    import jax.numpy as jnp

    from boxjax import planning
    from boxjax.control.monitor import MonitorConfig
    from boxjax.robot import PlannerStep

    class Drifting(NamedTuple):  # a model (a pytree) predicting the box sliding 1 cm per step sideways
        def rollout_sequence(self, window, belt_speed, actions):
            k = jnp.arange(1, actions.shape[0] + 1, dtype=jnp.float32)[:, None]
            return window[-1] + k * jnp.array([0.0, 0.0, 0.0, 0.01, 0.0])

        def stability_margin(self, s):
            return jnp.float32(1.0)

    turn = np.array([0.2, -0.2, 0.0, 0.0])
    planner = planning.Planner("fixed", lambda obs: None, lambda key, model, obs, st: (turn, st, None))
    obs = planning.observation(np.tile([-0.1, 0.1, 0.0, 0.0, 0.0], (3, 1)), np.zeros(2), 1.57)
    on = PlannerStep(planner, Drifting(), jax.random.PRNGKey(0))
    a = on(obs)
    assert on.stopped and np.array_equal(a[:2], [0.0, 0.0])  # the stop, not the turn
    off = PlannerStep(planner, Drifting(), jax.random.PRNGKey(0), monitor=MonitorConfig(enabled=False))
    assert np.array_equal(off(obs), turn) and not off.stopped


def test_given_the_pose_noise_the_loop_estimates_the_pose_as_the_controller_does():
    """With the tracking's noise stated, the loop filters the poses and the planner's window is the line
    along the filter's velocity (`control.state_estimate`, as the simulated controller under a noisy
    sensor): the velocity the prior takes from the window's last difference is steadier than the
    difference of two noisy poses. Without it the window holds the poses as received."""
    dt, v = 0.05, 0.04  # s, m/s along the tracking frame's x
    gen = np.random.default_rng(0)
    errs: dict = {"raw": [], "filtered": []}
    loops = {
        "raw": RobotLoop(lambda obs: np.zeros(4)),
        "filtered": RobotLoop(lambda obs: np.zeros(4), pose_noise=(3.0, 1.5)),
    }
    for k in range(200):
        t = 10 + dt * k
        x = v * dt * k + 3e-3 * gen.standard_normal()
        for name, loop in loops.items():
            assert loop.observe(tracking(x=x, stamp=t), joints(stamp=t)) in ("first", "new")
            if k > 40:
                w = loop.window
                errs[name].append(abs((w[-1, 2] - w[-2, 2]) / dt - v))
    rms = {k: float(np.sqrt(np.mean(np.square(e)))) for k, e in errs.items()}
    assert rms["filtered"] < 0.5 * rms["raw"], rms
    # the raw loop's window is what came in
    assert loops["raw"].window[-1, 2] == pytest.approx(x, abs=1e-7)
    with pytest.raises(ValueError, match="pose_noise"):
        RobotLoop(lambda obs: np.zeros(4), pose_noise=(-1.0, 0.0))
    with pytest.raises(ValueError, match="pose_noise"):
        RobotLoop(lambda obs: np.zeros(4), pose_noise=(0.0, 0.0))


def test_given_a_model_the_loop_predicts_over_the_pipelines_latency(episode):
    """Poses that arrive 3 control steps late (stamped when measured): with the planner's model the loop
    predicts the window to the present through the actions it sent (`planning.compensate`), so the state
    the planner is given is nearer the box's true present state than the late pose (by about half: over
    episode keys 0-3 with the prior's step looped and unrolled the median error was 0.38-0.57 of the late
    pose's, 1.8-2.2 mm against 3.1-5.1 mm; the slipping episode, not the prediction, sets the spread)."""
    from boxjax import DEFAULT, massdist
    from boxjax.control.config import ControllerConfig
    from boxjax.control.models import planning_model

    tr, lag, dt = episode.trace, 3, CFG.gripper.control_dt
    model = planning_model(DEFAULT, ControllerConfig(), massdist.named("A"))
    s_true = tr.s.astype(np.float64)
    errors: dict = {"late": [], "predicted": []}
    for name, loop_model in (("late", None), ("predicted", model)):
        given = []

        def plan(obs, given=given):
            given.append(np.asarray(obs.window[-1]))
            return tr.actions[lag + len(given) - 1]

        loop = RobotLoop(plan, AdapterConfig(max_observation_age=0.3), latency_model=loop_model)
        for t in range(lag, len(tr.actions)):  # one latency throughout: one compilation
            f = t - lag  # the newest frame that has arrived
            s, v = s_true[f], tr.belt_speed[f].astype(np.float64)
            tk = tracking(s[2], s[3], (0.0, 0.0, math.sin(s[4] / 2), math.cos(s[4] / 2)), 100.0 + dt * f)
            js = joints(right=-s[0], left=s[1], v_right=v[0], v_left=v[1], stamp=100.0 + dt * f)
            _, _, status = loop.step(tk, js, 100.0 + dt * t + 1e-3)
            assert not status["safe_stop"] and status["predicted_steps"] == (
                0 if loop_model is None else t - f
            )
        for k, t in enumerate(range(lag, len(tr.actions))):
            errors[name].append(np.abs(given[k][2:4] - s_true[t][2:4]).max())
    late, predicted = np.median(errors["late"]), np.median(errors["predicted"])
    assert predicted < 0.65 * late, (predicted, late)  # key 0, unrolled step: 2.1 mm against 4.0 mm


def test_the_monitor_of_a_loop_with_pose_noise_assumes_its_filters_uncertainty():
    """A PlannerStep given no sigma, in a loop told the tracking's noise: its monitor's sigma is the
    filter's y std each step (the stated 3 mm before the first frame, less once frames are averaged), and
    its yaw sigma (the "sigma" tipping watch's) the filter's yaw std."""
    from boxjax import planning
    from boxjax.control.monitor import MonitorConfig
    from boxjax.robot import PlannerStep

    planner = planning.Planner("rest", lambda obs: None, lambda key, model, obs, st: (np.zeros(4), st, None))
    step = PlannerStep(planner, None, jax.random.PRNGKey(0), monitor=MonitorConfig(enabled=False))
    loop = RobotLoop(step, pose_noise=(3.0, 1.5))
    assert step.sigma() == pytest.approx(0.003)
    for k in range(20):
        loop.observe(tracking(stamp=10 + 0.05 * k), joints(stamp=10 + 0.05 * k))
    assert 0 < step.sigma() < 0.003 and step.sigma() == loop.y_std()
    assert 0 < step.yaw_sigma() < math.radians(1.5) and step.yaw_sigma() == loop.yaw_std()  # and its yaw
    fixed = PlannerStep(planner, None, jax.random.PRNGKey(0), sigma=0.002)
    RobotLoop(fixed, pose_noise=(3.0, 1.5))
    assert fixed.sigma == 0.002  # a sigma given is kept
    assert RobotLoop(lambda obs: np.zeros(4)).y_std() == 0.0


def test_a_loop_late_by_two_steps_bounds_the_drag_its_model_counts_on():
    """Carriages moved away from a box, frames two steps late, and a world that does not drag the box
    (friction lower than the model's): a model in which the box follows the carriages predicts it
    centred, so without the bound the monitor stops only once the late frames show the box at the limit;
    with `drag_bound` the loop gives the monitor the present without that drag too (`RobotLoop.held`),
    and it stops before 3.2 cm."""
    from typing import NamedTuple

    import jax.numpy as jnp

    from boxjax import DEFAULT, planning
    from boxjax.control.monitor import MonitorConfig
    from boxjax.robot import PlannerStep

    class Following(NamedTuple):  # a model whose box follows the carriages' middle exactly
        def rollout_sequence(self, window, belt_speed, actions):
            dp = jnp.cumsum(actions[:, 2:], axis=0)
            move = jnp.concatenate([dp, jnp.zeros((len(dp), 1)), dp.mean(1, keepdims=True), 0 * dp[:, :1]], 1)
            return window[-1] + move

        def stability_margin(self, s):
            return jnp.float32(1.0)

        @property
        def gripper(self):
            return CFG.gripper

    step_m, lag, dt = CFG.gripper.max_position_step, 2, CFG.gripper.control_dt
    away = np.array([0.0, 0.0, -step_m, -step_m])
    planner = planning.Planner("away", lambda obs: None, lambda key, model, obs, st: (away, st, None))
    first_stop = {}
    for bound in (0.0, 1.0):
        plan = PlannerStep(
            planner, Following(), jax.random.PRNGKey(0), delay=lag, monitor=MonitorConfig(drag_bound=bound)
        )
        loop = RobotLoop(plan, AdapterConfig(max_observation_age=0.3), latency_model=Following())
        p = [np.array([-0.10, 0.10])] * lag  # the carriages' true positions, frame by frame
        for t in range(lag, 60):
            f = t - lag
            s = p[f]
            tk = tracking(0.0, 0.0, stamp=100.0 + dt * f)  # the box stays at y = 0
            js = joints(right=-s[0], left=s[1], stamp=100.0 + dt * f)
            _, _, status = loop.step(tk, js, 100.0 + dt * t + 1e-3)
            offset = -0.5 * p[-1].sum()  # the box's true offset from the middle as this action applies
            if plan.stopped:
                first_stop[bound] = offset
                break
            p.append(p[-1] + np.asarray(status["action"])[2:])
    limit = DEFAULT.task.balance_limit
    assert first_stop[0.0] > limit - 1e-9, first_stop  # the stop comes once the late frames show it: lost
    assert first_stop[1.0] < 0.8 * limit, first_stop  # bounded: stopped while the stop can still save it
