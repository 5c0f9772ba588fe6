"""The runtime safety monitor (boxjax.control.monitor) and the latency compensation (planning.compensate):
the stop it issues, its state machine, the crossing bookkeeping, and that it stops a turn the simulated
world would lose, whatever model is in the planner's slot."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import geometry, massdist, planning
from boxjax.config import DEFAULT, ConfigError
from boxjax.control import monitor
from boxjax.control.monitor import BALANCE, STALE, TIP, Monitor, MonitorConfig
from boxjax.prior import make_prior

CFG = DEFAULT
LIMIT = CFG.task.balance_limit
STEP = CFG.gripper.max_position_step


def _state(p1=-0.10, p2=0.10, x=0.0, y=0.0, yaw=0.0):
    return jnp.asarray([p1, p2, x, y, yaw], jnp.float32)


@pytest.mark.parametrize("y", [0.035, -0.022, 0.004, 0.0])
def test_the_stop_rests_the_belts_and_brings_the_carriages_under_the_box(y):
    stop = np.asarray(monitor.backup_actions(CFG, _state(y=y), 10))
    assert stop.shape == (10, 4)
    np.testing.assert_array_equal(stop[:, :2], 0.0)  # belts to rest (the drives ramp at their limit)
    assert np.all(np.abs(stop[:, 2:]) <= STEP + 1e-7)  # never faster than a carriage may move
    np.testing.assert_allclose(stop[:, 2], stop[:, 3], atol=1e-6)  # together: the belts' gap is kept
    np.testing.assert_allclose(stop[:, 2].sum(), y, atol=1e-6)  # the midline ends under the box's centre
    assert np.all(np.sign(stop[:, 2]) * np.sign(y) >= 0)  # towards it, never away


def test_the_stop_keeps_the_carriages_in_their_ranges():
    p1_lo, p1_hi = CFG.gripper.p1_range
    s = _state(p1=p1_hi - 0.005, p2=0.15, y=0.10)  # the box far to +y; belt 1 is 5 mm from its inner end
    stop = np.asarray(monitor.backup_actions(CFG, s, 10))
    p1 = float(s[geometry.P1]) + np.cumsum(stop[:, 2])
    p2 = float(s[geometry.P2]) + np.cumsum(stop[:, 3])
    assert p1.max() <= p1_hi + 1e-6 and p2.max() <= CFG.gripper.p2_range[1] + 1e-6
    assert stop[:, 3].sum() > stop[:, 2].sum()  # the free carriage keeps moving the midline


def _check(go, stop_plan=((0.0, 0.0, 0.0, 0.0),), *, now=None, end=None, go_stop=None) -> monitor.Check:
    """A check whose action and stop are both predicted `go` (m), with the stop `stop_plan`; by default
    the box is predicted to stay where it is (`now`, `end`: go's present and settled error)."""
    stop_plan = np.asarray(stop_plan, np.float64).reshape(-1, 4)
    now = go if now is None else now
    end = now if end is None else end
    go_stop = np.zeros_like(stop_plan) if go_stop is None else go_stop
    return monitor.Check(*(np.asarray(x) for x in (go, go, now, go, end, stop_plan, go_stop)))


def _decide(m: Monitor, t: int, go: float, *, sigma=0.0, stale=0, belt=(0.2, -0.2)):
    planned = np.array([0.2, -0.2, 0.0, 0.0])
    stop = np.array([0.0, 0.0, 0.01, 0.01])
    out = m.decide(t, planned, _check(go, stop), sigma, stale, np.asarray(belt))
    return "go" if np.array_equal(out, planned) else "stop"


def test_the_monitor_stops_before_the_threshold_and_resumes_only_at_rest_and_well_inside():
    m = Monitor(CFG, MonitorConfig(stop_at=0.75, resume_below=0.5, k_sigma=2.0))
    assert _decide(m, 0, 0.74 * LIMIT) == "go"
    assert _decide(m, 1, 0.70 * LIMIT, sigma=0.05 * LIMIT) == "stop"  # 0.7 + 2 x 0.05 >= 0.75
    assert m.stops == [(1, BALANCE)] and m.stopped
    assert _decide(m, 2, 0.2 * LIMIT, belt=(0.1, -0.1)) == "stop"  # belts still running: no resume
    assert _decide(m, 3, 0.6 * LIMIT, belt=(0.0, 0.0)) == "stop"  # at rest, but not inside resume_below
    assert _decide(m, 4, 0.4 * LIMIT, belt=(0.0, 0.0)) == "go"  # at rest and well inside: resume
    assert m.resumes == [4] and not m.stopped
    assert m.stopping_steps == {1, 2, 3}


def test_the_last_allowed_stop_is_final_and_ends_at_rest():
    m = Monitor(CFG, MonitorConfig(max_stops=2))
    t = 0
    for _ in range(2):
        assert _decide(m, t, LIMIT) == "stop"
        t += 1
        if not m.final:
            assert _decide(m, t, 0.1 * LIMIT, belt=(0, 0)) == "stop"  # the stop's carriage step in the loop
            assert _decide(m, t + 1, 0.1 * LIMIT, belt=(0, 0)) == "go"  # known at rest: resume
            t += 2
    assert m.final and not m.ended
    assert _decide(m, t, 0.0, belt=(0.1, 0.1)) == "stop" and not m.ended  # final: no resume; not at rest
    assert _decide(m, t + 1, 0.0, belt=(0.0, 0.0)) == "stop" and m.ended  # at rest: the episode ends
    assert m.record()["monitor_stops"] == 2


def test_a_stop_that_cannot_resume_times_out_into_a_final_stop():
    m = Monitor(CFG, MonitorConfig(stop_timeout=5))
    assert _decide(m, 0, LIMIT) == "stop"
    for t in range(1, 7):
        _decide(m, t, 0.9 * LIMIT, belt=(0, 0))
    assert m.final and m.ended and m.resumes == []


def test_stale_observations_stop_the_belts_until_fresh_frames_return():
    m = Monitor(CFG, MonitorConfig(stale_steps=2))
    assert _decide(m, 0, 0.0, stale=2) == "go"
    assert _decide(m, 1, 0.0, stale=3) == "stop" and m.reason == STALE
    assert _decide(m, 2, 0.0, stale=4, belt=(0.1, 0.1)) == "stop"
    assert _decide(m, 3, 0.0, stale=0, belt=(0.1, 0.1)) == "go"  # fresh again: it need not wait for rest
    assert m.balance_stops == 0  # stale stops do not count toward max_stops


def test_monitor_settings_are_validated_by_name():
    for kwargs, name in (
        ({"stop_at": 1.5}, "stop_at"),
        ({"resume_below": 0.9}, "resume_below"),
        ({"horizon": 0}, "horizon"),
        ({"k_sigma": -1.0}, "k_sigma"),
        ({"max_stops": 0}, "max_stops"),
        ({"miss_sigmas": -1.0}, "miss_sigmas"),
        ({"k_delay": -1.0}, "k_delay"),
        ({"miss_window": 0}, "miss_window"),
    ):
        with pytest.raises(ConfigError, match=name):
            MonitorConfig(**kwargs)


def test_crossings_are_noticed_only_when_a_stop_was_under_way():
    errors = np.array([0.0, 0.01, 0.03, 0.045, 0.05])  # crosses at index 3, after action 2
    assert monitor.crossing(errors, LIMIT, set()) == (True, True)
    assert monitor.crossing(errors, LIMIT, {2}) == (True, False)
    assert monitor.crossing(errors, LIMIT, {0}) == (True, True)  # an earlier stop that resumed: unnoticed
    assert monitor.crossing(errors, LIMIT, set(), guard_steps=[2]) == (True, False)
    assert monitor.crossing(errors[:3], LIMIT, set()) == (False, False)


def test_the_check_predicts_with_the_model_in_the_slot():
    prior = make_prior(massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box))
    window = planning.initial_window(_state(y=0.02))
    belt = jnp.zeros(2)
    rest = jnp.zeros(4)
    c = monitor.check(CFG, prior, window, belt, rest, 10)
    assert float(c.now) == pytest.approx(0.02, abs=1e-6)
    assert float(c.go) >= 0.02 - 1e-6 and float(c.stop) >= 0.02 - 1e-6  # both include the present error
    assert float(c.go_end) <= float(c.go_ahead)
    np.testing.assert_array_equal(np.asarray(c.go_stop), 0.0)  # a recovery's stop holds the carriages
    assert c.stop_plan.shape == (10, 4) and c.go_stop.shape == (10, 4)  # the stops' plans
    centring = monitor.check(CFG, prior, window, belt, rest, 10, "recentre").stop_plan
    np.testing.assert_allclose(np.asarray(centring)[0, 2:], STEP, rtol=1e-5)  # first step: 1 cm to the box
    # a batch of boxes gives each box's own check
    stacked = planning.stack([prior, prior])
    cb = monitor.check_batch(
        CFG, stacked, jnp.stack([window, window]), jnp.stack([belt, belt]), jnp.stack([rest, rest]), 10
    )
    for one, field in zip(monitor.to_host(cb, 0), monitor.to_host(c), strict=True):
        np.testing.assert_allclose(one, field, atol=1e-6)


def test_the_tipping_check_is_the_smallest_stability_margin_of_the_action_and_its_stop():
    """`tip=True`: `go_tip` is the prior's `stability_margin` at the present and along the action's
    rollout (the action, then the stop `go` was predicted with), the smallest; a box whose centre of mass
    sits over the gap with the belts spread has less than one on the belts' middle; not asked: +inf."""
    prior = make_prior(massdist.voxel_masses(massdist.named("C", CFG.box), CFG.box))
    belt, turn = jnp.zeros(2), jnp.asarray([0.1, -0.1, -STEP, STEP], jnp.float32)
    spread = planning.initial_window(_state(p1=-0.2, p2=0.2, yaw=1.2))
    narrow = planning.initial_window(_state(p1=-0.1, p2=0.1))
    assert np.isinf(float(monitor.check(CFG, prior, narrow, belt, turn, 10).go_tip))
    c = monitor.check(CFG, prior, spread, belt, turn, 10, "hold", tip=True)
    states = jax.jit(prior.rollout_sequence)(spread, belt, jnp.concatenate([turn[None], c.go_stop[:-1]]))
    margin = jax.jit(prior.stability_margin)  # one program for every state below (eager: op by op)
    margins = [margin(spread[-1])] + [margin(s) for s in states]
    np.testing.assert_allclose(float(c.go_tip), float(min(margins)), atol=1e-6)
    on_middle = monitor.check(CFG, prior, narrow, belt, turn, 10, "hold", tip=True)
    assert float(c.go_tip) < float(on_middle.go_tip)
    # the batched check gives each box its own
    cb = monitor.check_batch(
        CFG, planning.stack([prior, prior]), jnp.stack([spread, narrow]), jnp.stack([belt, belt]),
        jnp.stack([turn, turn]), 10, "hold", tip=True,
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(cb.go_tip), [float(c.go_tip), float(on_middle.go_tip)], atol=1e-6)
    # the slope: how fast the margin falls with the pose where it is smallest, against central differences
    # (a box at rest, nothing sent: every predicted state is the present)
    rest = jnp.zeros(4, jnp.float32)
    at_rest = monitor.check(CFG, prior, spread, belt, rest, 2, "hold", tip="slope")  # 2 steps: compiles fast
    np.testing.assert_array_equal(np.asarray(c.go_tip_slope), 0)  # the margin alone: no slope computed
    assert float(at_rest.go_tip) == pytest.approx(float(margin(spread[-1])), abs=1e-4)
    assert (
        monitor.tip_watch(MonitorConfig(tip_uncertainty="y")) is True
        and monitor.tip_watch(MonitorConfig(tip_stop=0.0)) is False
    )
    assert monitor.tip_watch(MonitorConfig(tip_uncertainty="pose")) == "slope"
    s0, h = np.asarray(spread[-1], np.float64), 1e-4
    fd = []
    for i in (geometry.X, geometry.Y, geometry.YAW):
        up, down = s0.copy(), s0.copy()
        up[i], down[i] = s0[i] + h, s0[i] - h
        m_up, m_down = (float(margin(jnp.asarray(z, jnp.float32))) for z in (up, down))
        fd.append(abs(m_up - m_down) / (2 * h))
    np.testing.assert_allclose(np.asarray(at_rest.go_tip_slope), fd, rtol=0.05, atol=0.02)
    assert float(np.max(at_rest.go_tip_slope)) > 0.1  # the margin does move with the pose here
    np.testing.assert_array_equal(
        np.asarray(monitor.check(CFG, prior, narrow, belt, turn, 10).go_tip_slope), 0
    )


def test_the_tipping_watch_can_count_how_fast_the_margin_falls_with_the_pose():
    """tip_uncertainty="pose": the estimate's margin times the margin's slopes in x and y, and k_delay
    `tip_yaw_std` per square-root step of delay times its slope in yaw, in quadrature; "y": the
    margin alone, 1:1. Known at rest, the yaw's delay term is dropped."""
    planned, belts = np.array([0.2, -0.2, 0.0, 0.0]), np.array([0.2, -0.2])

    def tip(slope):
        return monitor.Check(*_check(0.01)[:7], np.asarray(0.03), np.asarray(slope, np.float64))

    steep = (0.0, 3.0, 0.0)  # the margin falls 3 mm per mm of y: 0.03 - 3 x 0.008 under 0.008
    assert np.array_equal(
        Monitor(CFG, MonitorConfig(tip_uncertainty="y")).decide(0, planned, tip(steep), 0.008, 0, belts),
        planned,
    )
    pose = Monitor(CFG, MonitorConfig(tip_uncertainty="pose"))
    assert not np.array_equal(pose.decide(0, planned, tip(steep), 0.008, 0, belts), planned)
    assert pose.stops == [(0, TIP)]
    flat = Monitor(CFG, MonitorConfig(tip_uncertainty="pose"))  # slope 0.5: less than 1:1
    assert np.array_equal(flat.decide(0, planned, tip((0.5, 0.5, 0.0)), 0.008, 0, belts), planned)
    # yaw over 4 steps of delay: k_delay 2 x 0.01 rad x 2 = 0.04 rad, times 0.6 m/rad = 24 mm
    m = MonitorConfig(tip_uncertainty="pose", tip_yaw_std=0.01, k_sigma=0.0, delay_std=0.0)
    late = Monitor(CFG, m, delay=4)
    assert not np.array_equal(late.decide(0, planned, tip((0.0, 0.0, 0.6)), 0.0, 0, belts), planned)
    c = tip((1.0, 2.0, 0.6))
    want = math.sqrt(0.005**2 + (2 * 0.005) ** 2 + (0.6 * 2 * 0.01 * 2) ** 2)
    assert monitor.tip_margin(m, c, 0.005, 4, False) == pytest.approx(want)
    assert monitor.tip_margin(m, c, 0.005, 4, True) == pytest.approx(math.sqrt(5) * 0.005)  # at rest
    assert monitor.tip_margin(MonitorConfig(tip_uncertainty="y"), c, 0.005, 4, False) == 0.005
    for bad, match in (
        ({"tip_uncertainty": "xy"}, "tip_uncertainty"),
        ({"tip_uncertainty": "pose", "tip_yaw_std": -1.0}, "tip_yaw_std"),
    ):
        with pytest.raises(ConfigError, match=match):
            MonitorConfig(**bad)


def test_the_sigma_watch_sees_a_cliff_that_the_slope_cannot():
    """Adversarial: box C at rest on belts spread far apart, 28 mm to one side. The margin is 82 mm (the
    box's own edge: a plateau, its slope zero), so the "pose" watch subtracts nothing; 6 mm further to the
    side the far belt's patch is gone and the centre of mass is outside the support. tip_uncertainty
    "sigma" evaluates the margin at the spread's sigma points (the smallest of them, recomputed here
    one by one) and stops; with no spread it is the plain margin."""
    prior = make_prior(massdist.voxel_masses(massdist.named("C", CFG.box), CFG.box))
    s = _state(p1=-0.1747, p2=0.1685, x=-0.0479, y=-0.0284, yaw=0.0108)
    window, belt, rest = planning.initial_window(s), jnp.zeros(2), jnp.zeros(4, jnp.float32)
    spread = np.array([0.006, 0.006, math.radians(1.5), 0.42], np.float32)  # at rest: no carriage travel
    slope = monitor.check(CFG, prior, window, belt, rest, 2, "hold", tip="slope")
    sigma = monitor.check(CFG, prior, window, belt, rest, 2, "hold", tip="sigma", tip_spread=spread)
    none = monitor.check(CFG, prior, window, belt, rest, 2, "hold", tip="sigma", tip_spread=np.zeros(4))
    assert float(none.go_tip) == pytest.approx(float(slope.go_tip), abs=1e-6) and float(slope.go_tip) > 0.05
    assert float(np.max(slope.go_tip_slope)) < 1e-3  # on the plateau
    points = [np.asarray(s, np.float64) + np.r_[0.0, 0.0, p * spread[:3]] for p in monitor.SIGMA_POINTS]
    direct = min(float(prior.stability_margin(jnp.asarray(z, jnp.float32))) for z in points)
    assert direct < 0  # a box that far off tips
    assert float(sigma.go_tip) == pytest.approx(direct, abs=1e-4)  # at rest: every state is the present
    assert monitor.tip_watch(MonitorConfig(tip_uncertainty="sigma")) == "sigma"
    with pytest.raises(ValueError, match="tip_spread"):
        monitor.check(CFG, prior, window, belt, rest, 2, "hold", tip="sigma")
    # the decisions: "pose" lets the box go, "sigma" stops it (nothing more subtracted: counted already)
    planned, belts = np.array([0.1, -0.1, 0.0, 0.0]), np.zeros(2)
    pose = Monitor(CFG, MonitorConfig(tip_uncertainty="pose"))
    assert np.array_equal(pose.decide(0, planned, monitor.to_host(slope), 0.006, 0, belts), planned)
    sig = Monitor(CFG, MonitorConfig(tip_uncertainty="sigma"))
    assert monitor.tip_margin(sig.m, monitor.to_host(sigma), 0.006, 0, False) == 0
    assert not np.array_equal(sig.decide(0, planned, monitor.to_host(sigma), 0.006, 0, belts), planned)
    assert sig.stops == [(0, TIP)]
    # the batched check gives each box its own spread's
    cb = monitor.check_batch(
        CFG, planning.stack([prior, prior]), jnp.stack([window, window]), jnp.stack([belt, belt]),
        jnp.stack([rest, rest]), 2, "hold", tip="sigma", tip_spread=np.stack([spread, np.zeros(4)]),
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(cb.go_tip), [float(sigma.go_tip), float(none.go_tip)], atol=1e-6)
    # a carriage move: its drag is uncertain, so y spreads further state by state with the travel (the
    # squared per-carriage sums of the moves so far), recomputed here along the rollout of the action
    # and its stop
    move = jnp.asarray([0.0, 0.0, 0.005, 0.005], jnp.float32)
    c = monitor.check(CFG, prior, window, belt, move, 2, "hold", tip="sigma", tip_spread=spread)
    states = np.asarray(prior.rollout_sequence(window, belt, jnp.stack([move, rest])), np.float64)
    want = []
    for z, travel in ((np.asarray(s, np.float64), 0.0), (states[0], 5e-5), (states[1], 5e-5)):
        per = np.array([spread[0], math.sqrt(spread[1] ** 2 + spread[3] ** 2 * travel), spread[2]])
        want += [
            float(prior.stability_margin(jnp.asarray(z + np.r_[0, 0, p * per], jnp.float32)))
            for p in monitor.SIGMA_POINTS
        ]
    assert float(c.go_tip) == pytest.approx(min(want), abs=1e-4)


def test_the_tip_spread_is_the_margin_decide_counts_and_changes_nothing():
    """`Monitor.tip_spread` before a step's `decide`: in x and y the balance check's margin that decide
    then adds (a stop exactly where go + that margin reaches stop_at, with the prediction's misses over the
    delay counted), in yaw k_sigma of the estimate's yaw std and k_delay `tip_yaw_std` per square-root
    step of delay (only the estimate's once known at rest); previewing changes no decision."""
    m = MonitorConfig(tip_uncertainty="sigma", miss_sigmas=1.0)
    planned, moving = np.array([0.2, -0.2, 0.0, 0.0]), np.array([0.2, -0.2])
    a, b = Monitor(CFG, m, delay=2), Monitor(CFG, m, delay=2)
    for t in range(6):  # the model misses by 3-8 mm a step over the delay
        measured = _state(y=0.001 * t)
        predicted = _state(y=0.001 * t + 0.003 + 0.001 * t)
        spread = a.tip_spread(0.002, moving, measured, predicted, yaw_sigma=0.01)
        k = m.k_sigma if m.k_delay is None else m.k_delay
        assert spread[2] == pytest.approx(
            math.hypot(m.k_sigma * 0.01, k * m.tip_yaw_std * math.sqrt(2)), rel=1e-5
        )
        assert spread[0] == spread[1] >= m.k_sigma * 0.002  # nothing in flight moved a carriage
        assert spread[3] == pytest.approx(k * m.tip_drag_std)
        go = m.stop_at * LIMIT - float(spread[0])
        for mon in (a, b):  # just under the threshold: both go, the previewed one and the other
            sent = mon.decide(t, planned, _check(go - 1e-5), 0.002, 0, moving, measured, predicted)
            assert np.array_equal(sent, planned), t
    assert spread[0] > 0.006  # the misses widened it
    c = Monitor(CFG, m, delay=2)
    for t in range(6):  # the same steps, just over the threshold at the last (its misses counted)
        measured, predicted = _state(y=0.001 * t), _state(y=0.002 * t + 0.003)
        go = m.stop_at * LIMIT - float(c.tip_spread(0.002, moving, measured, predicted)[0])
        c.decide(t, planned, _check(go + (1e-5 if t == 5 else -1e-5)), 0.002, 0, moving, measured, predicted)
    assert c.stops == [(5, BALANCE)]
    rest = Monitor(CFG, m, delay=2)
    for t in range(4):
        rest.decide(t, np.zeros(4), _check(0.0), 0.002, 0, np.zeros(2))
    at_rest = rest.tip_spread(0.002, np.zeros(2), yaw_sigma=0.01)
    np.testing.assert_allclose(at_rest[:3], [0.002, 0.002, 0.01], rtol=1e-5)
    # carriage travel in flight widens y by k_delay tip_drag_std of it: 6 + 2 mm on carriage 1 -> 8 mm
    flying = Monitor(CFG, m, delay=2)
    for t, p1 in enumerate((0.006, 0.002)):
        flying.decide(t, np.array([0.2, -0.2, p1, 0.0]), _check(0.0), 0.002, 0, moving)
    wide = flying.tip_spread(0.002, moving)
    assert wide[1] == pytest.approx(math.hypot(wide[0], wide[3] * 0.008), rel=1e-5) and wide[1] > wide[0]


def test_a_predicted_tip_stops_and_the_stop_holds_until_the_margin_is_back():
    """`tip_stop` 1.5 cm, watch "y": an action whose margin (less the estimate's std) falls under it is
    stopped (reason "tip", counted toward max_stops); at rest it neither resumes nor recovers while the
    planner's action still would; once an action keeps the margin it resumes. Off (`tip_stop` 0): the
    same action goes."""
    planned = np.array([0.2, -0.2, 0.0, 0.0])
    tip = lambda go_tip: monitor.Check(*_check(0.01)[:7], np.asarray(go_tip))  # noqa: E731
    m = Monitor(CFG, MonitorConfig(tip_stop=0.015, tip_uncertainty="y"))
    assert np.array_equal(m.decide(0, planned, tip(0.03), 0.002, 0, np.array([0.2, -0.2])), planned)
    assert not np.array_equal(m.decide(1, planned, tip(0.016), 0.002, 0, np.array([0.2, -0.2])), planned)
    assert m.stops == [(1, TIP)] and m.balance_stops == 1
    for t in (2, 3):  # at rest, the action still predicted to tip: held
        np.testing.assert_array_equal(m.decide(t, planned, tip(0.010), 0.002, 0, np.zeros(2)), 0.0)
    assert m.resumes == [] and m.recoveries == []
    assert np.array_equal(m.decide(4, planned, tip(0.02), 0.002, 0, np.zeros(2)), planned)
    assert m.resumes == [4]
    assert MonitorConfig().tip_stop > 0  # on by default
    off = Monitor(CFG, MonitorConfig(tip_stop=0.0))
    assert np.array_equal(off.decide(0, planned, tip(0.0), 0.002, 0, np.array([0.2, -0.2])), planned)
    with pytest.raises(ConfigError, match="tip_stop"):
        MonitorConfig(tip_stop=-0.01)


def test_compensation_moves_the_window_over_the_actions_in_flight():
    prior = make_prior(massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box))
    window = planning.initial_window(_state())
    belt = jnp.zeros(2)
    same = planning.compensate(prior, window, belt, jnp.zeros((0, 4)))
    assert same[0] is window and same[1] is belt
    acts = jnp.asarray([[0.1, 0.1, 0.01, 0.01]] * 3, jnp.float32)
    w, b = planning.compensate(prior, window, belt, acts)
    np.testing.assert_allclose(np.asarray(w[-3:]), np.asarray(prior.rollout_sequence(window, belt, acts)))
    np.testing.assert_allclose(np.asarray(w[: len(window) - 3]), np.asarray(window[3:]))
    dv = CFG.gripper.belt_accel_limit * CFG.gripper.control_dt
    np.testing.assert_allclose(np.asarray(b), min(0.1, 3 * dv), atol=1e-6)  # the drives ramp at their limit
    assert w.shape == window.shape
    # every model of the slot compensates, wrappers included (an ensemble, a mixture, the drift observer)
    for wrapped in (
        planning.Ensemble(planning.stack([prior, prior])),
        planning.Mixture((prior, prior)),
        planning.DriftCorrected(prior, jnp.zeros(3)),
    ):
        w2, b2 = jax.jit(planning.compensate)(wrapped, window, belt, acts)
        np.testing.assert_allclose(np.asarray(w2), np.asarray(w), atol=1e-6)
        np.testing.assert_allclose(np.asarray(b2), np.asarray(b), atol=1e-7)


def test_a_box_the_controller_loses_is_never_lost_unnoticed_with_the_monitor():
    """Adversarial: development box 56 (`scripts/monitor_study.py`'s set, never the fault table's) crosses
    the 4 cm limit without the monitor with 4 steps of latency (and with no fault, not run here). With the
    monitor the crossing is noticed (a stop under way) or prevented (a safe stop)."""
    from boxjax.control.config import ControllerConfig
    from boxjax.control.episode import run_episode
    from boxjax.experiments.evaluation import sample_safe
    from boxjax.sim.faults import Faults

    box = sample_safe(jax.random.PRNGKey(1000), 57, CFG)[56]
    key = jax.random.fold_in(jax.random.PRNGKey(1001), 56)
    # The exploration guard's lead refuses this box during the carriage probes (its trend includes the
    # commanded midline moves); with the present-value guard it reaches the turn, which is what is tested.
    guard = {"explore_guard_lead": 0}
    for faults in (Faults(obs_latency=4),):  # the harder case; with no fault the box is lost the same way
        off = run_episode(
            CFG, box, key, ctrl=ControllerConfig(monitor=monitor.OFF, **guard), faults=faults, max_steps=90
        )
        assert off.summary["crossing"] and off.summary["unnoticed_crossing"], faults
        on = run_episode(CFG, box, key, ctrl=ControllerConfig(**guard), faults=faults, max_steps=150).summary
        assert not on["unnoticed_crossing"] and on["monitor_stops"] >= 1, faults
        assert on["safe_stop"] or on["success"] or on["crossing"]


def test_the_hold_stop_rests_the_belts_and_keeps_the_carriages():
    stops = np.asarray(monitor.backup_set(CFG, _state(y=0.03), 10, "hold"))
    assert stops.shape == (1, 10, 4)
    np.testing.assert_array_equal(stops, 0.0)
    both = np.asarray(monitor.backup_set(CFG, _state(y=0.03), 10, "best"))
    assert both.shape == (2, 10, 4)
    np.testing.assert_array_equal(both[0], 0.0)
    np.testing.assert_allclose(both[1], np.asarray(monitor.backup_actions(CFG, _state(y=0.03), 10)))


def test_best_is_the_safer_of_the_two_stops_by_the_models_prediction():
    """With one carriage at its stop the re-centring moves the other alone, which drags the box on its
    belt; the check's stop and go errors are the smaller of the two stops', and the stop it issues is
    the one predicted safer."""
    prior = make_prior(massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box))
    p2_hi = CFG.gripper.p2_range[1]
    for s in (_state(p1=-0.19, p2=p2_hi, y=0.03), _state(y=0.025), _state(y=-0.01)):
        window, belt = planning.initial_window(s), jnp.asarray([0.1, -0.1], jnp.float32)
        act = jnp.asarray([0.1, -0.1, 0.0, 0.0], jnp.float32)
        each = {b: monitor.check(CFG, prior, window, belt, act, 10, b) for b in monitor.BACKUPS}
        c = monitor.check(CFG, prior, window, belt, act, 10, "best")
        for field in ("go", "stop"):
            best = min(float(getattr(e, field)) for e in each.values())
            assert float(getattr(c, field)) == pytest.approx(best, abs=1e-6)
        chosen = [
            b for b in each if np.allclose(np.asarray(c.stop_plan), np.asarray(each[b].stop_plan), atol=1e-7)
        ]
        assert chosen, c.stop_plan  # one of the two stops
        assert min(float(each[b].stop) for b in chosen) <= float(c.stop) + 1e-6  # the safer one


@pytest.mark.parametrize("name", ["uniform", "A", "C"])
def test_moving_one_carriage_drags_the_box_along_in_mujoco(name):
    """Why the stop may hold its carriages: a carriage moved under a box at rest drags the box with it
    (MuJoCo's contact friction, a reference nobody here wrote), so re-centring with one carriage (the
    other at its stop) gains on the box by less than half the carriage's travel. The prior the monitor
    chooses with predicts the drag's direction, not its size (a fifth of the simulator's for a uniform
    box, 2-3x for boxes heavy over the moving belt: scripts/carriage_drag.py), so its choice between
    holding and re-centring is only as good as that prediction."""
    from boxjax.control.episode import env_for

    box = massdist.named(name, CFG.box)
    env = env_for(CFG, "native")
    for j, sign in ((geometry.P1, -1.0), (geometry.P2, 1.0)):  # each carriage outward by 5 x 1 cm
        state = env.reset(jax.random.PRNGKey(0), box)
        for _ in range(5):  # settle
            state = env.step(state, np.zeros(4))
        s0 = np.asarray(state.s, np.float64)
        move = np.zeros(4)
        move[2 + j] = sign * STEP
        for _ in range(5):
            state = env.step(state, move)
        s1 = np.asarray(state.s, np.float64)
        travel, dy = s1[j] - s0[j], s1[geometry.Y] - s0[geometry.Y]
        assert travel == pytest.approx(5 * sign * STEP, abs=1e-3)
        assert 0.0 < dy / travel < 0.5, (name, j, dy, travel)  # dragged along, by less than half
        prior = make_prior(massdist.voxel_masses(box, CFG.box))
        w = planning.initial_window(jnp.asarray(s0, jnp.float32))
        seq = jnp.tile(jnp.asarray(move, jnp.float32), (5, 1))
        pred = float(prior.rollout_sequence(w, jnp.zeros(2), seq)[-1, geometry.Y]) - s0[geometry.Y]
        assert -1e-4 <= pred / travel < 1.0  # C rests on belt 2: the prior drags it not at all


def test_at_rest_the_prediction_over_the_delay_adds_no_uncertainty():
    """2 cm predicted + 2 x 8 mm of prediction error over 4 steps of delay passes the 3 cm threshold
    while the gripper moves; after delay + 1 steps of rest sent with the belts at rest, the prediction
    over the delay is exact and the same 2 cm does not stop it."""
    settings = MonitorConfig(stop_at=0.75, k_sigma=2.0, delay_std=0.004)
    go, calm = _check(0.5 * LIMIT), _check(0.0)
    for first, expect in ((np.zeros(4), False), (np.array([0.05, 0.05, 0.0, 0.0]), True)):
        m = Monitor(CFG, settings, delay=4)
        for t in range(5):
            m.decide(t, first, calm, 0.0, 0, np.zeros(2))
        m.decide(5, np.array([0.1, -0.1, 0.0, 0.0]), go, 0.0, 0, np.zeros(2))
        assert m.stopped == expect


def test_a_stop_follows_its_plan_then_rests_and_resumes_only_once_rest_is_observed():
    """The stop issued is the plan the check predicted safest, sent step by step, then rest; with a
    delay of d steps it may resume only after d + 1 steps of rest sent (its own carriage moves are then
    in the observations, not only in the prediction)."""
    m = Monitor(CFG, MonitorConfig(), delay=2)
    planned = np.array([0.1, -0.1, 0.0, 0.0])
    plan = np.array([[0.0, 0.0, 0.01, 0.01], [0.0, 0.0, 0.005, 0.005]])
    out = [m.decide(0, planned, _check(LIMIT, plan), 0.0, 0, np.array([0.1, -0.1]))]
    for t in range(1, 8):
        out.append(m.decide(t, planned, _check(0.0, plan * 0), 0.0, 0, np.zeros(2)))
    np.testing.assert_array_equal(out[0], plan[0])
    np.testing.assert_array_equal(out[1], plan[1])
    for t in range(2, 5):  # rest: 3 = delay + 1 steps of it before the gripper counts as known at rest
        np.testing.assert_array_equal(out[t], 0.0)
    assert m.resumes == [5]
    np.testing.assert_array_equal(out[5], planned)


def test_a_prediction_that_misses_what_then_arrived_widens_the_margin():
    """With 2 steps of delay, the offset predicted at step t for when its action applies is compared with
    the estimate that arrives at t + 2 (of that time). While the predictions come true the margin is
    `delay_std`'s; a 1.5 cm miss (the box slipped) is far beyond it, and for `miss_window` steps it is the
    prediction's std: the same 2 cm predicted error now stops the turn. With miss_sigmas = 0 it does not."""
    planned = np.array([0.2, -0.2, 0.0, 0.0])
    go = _check(0.5 * LIMIT)  # 2 cm
    moving = np.array([0.2, -0.2])

    def run(miss_sigmas: float, slip: float) -> list[bool]:
        m = Monitor(
            CFG, MonitorConfig(stop_at=0.8, k_sigma=2.0, miss_sigmas=miss_sigmas, miss_window=3), delay=2
        )
        stopped = []
        for t in range(10):
            truth = 0.001 * t + (slip if t >= 5 else 0.0)  # the box's offset; it jumps at t = 5
            measured = np.asarray(_state(y=truth - 0.002))  # the estimate is of 2 steps ago
            predicted = np.asarray(_state(y=0.001 * t))  # the model foresaw no slip
            m.decide(t, planned, go, 0.001, 0, moving, measured=measured, predicted=predicted)
            stopped.append(m.stopped)
        return stopped, m.log

    calm, log = run(3.0, 0.0)
    assert not any(calm) and max(row[4] for row in log) < 1e-6  # the predictions came true: no miss
    assert log[1][4] == 0.0  # nothing to compare before `delay` steps have passed
    slipped, log = run(3.0, 0.015)
    assert slipped.index(True) == 5 and log[5][4] == pytest.approx(0.015, abs=1e-6)
    assert not any(run(0.0, 0.015)[0])  # off: delay_std's margin alone


def test_the_estimates_and_the_delays_uncertainty_have_their_own_multipliers():
    """margin = sqrt((k_sigma sigma)^2 + k_delay^2 delay delay_std^2), with 2.4 cm predicted, 3 mm of estimate
    noise and 4 steps of delay at 2 mm per square-root step (4 mm), against a 3.2 cm threshold: (2, None):
    2.4 + 1.0 stops; (1, 2): 2.4 + 0.85 stops; (1, 1.5): 2.4 + 0.67 goes on; (0, 2.2): 2.4 + 0.88 stops."""
    go = _check(0.024)
    for k_sigma, k_delay, stops in ((2.0, None, True), (1.0, 2.0, True), (1.0, 1.5, False), (0.0, 2.2, True)):
        m = Monitor(
            CFG, MonitorConfig(stop_at=0.8, k_sigma=k_sigma, k_delay=k_delay, delay_std=0.002), delay=4
        )
        m.decide(0, np.array([0.2, -0.2, 0.0, 0.0]), go, 0.003, 0, np.array([0.2, -0.2]))
        assert m.stopped == stops, (k_sigma, k_delay)


def test_a_resume_and_a_recovery_from_rest_count_their_own_multiple_of_the_estimates_std():
    """`resume_k_sigma`: at rest, 2.2 cm predicted with a 2.5 mm std against resume_below's 2.6 cm, a
    resume counting one std (2.45 cm) goes, one counting two (2.7 cm) waits; a recovery predicted to pass
    2.9 cm on the way is under stop_at's 3.2 cm with one std (3.15), not with two (3.4). The stop while
    running keeps k_sigma: 2.9 cm predicted goes on with either (2.9 + 0.25 < 3.2)."""
    sigma, planned = 0.0025, np.array([0.2, -0.2, 0.0, 0.0])
    for k_resume, resumes in ((None, True), (1.0, True), (2.0, False)):
        m = Monitor(CFG, MonitorConfig(resume_k_sigma=k_resume))
        assert _decide(m, 0, 0.029, sigma=sigma) == "go"  # running: k_sigma's margin only
        assert _decide(m, 1, LIMIT) == "stop"
        assert _decide(m, 2, 0.022, sigma=sigma, belt=(0, 0)) == "stop"  # the stop's step in the loop
        assert (_decide(m, 3, 0.022, sigma=sigma, belt=(0, 0)) == "go") == resumes, k_resume
    for k_resume, recovers in ((None, True), (2.0, False)):
        m = Monitor(CFG, MonitorConfig(resume_k_sigma=k_resume))
        m.decide(0, planned, _check(LIMIT), sigma, 0, np.array([0.2, -0.2]))
        m.decide(1, planned, _check(0.029), sigma, 0, np.zeros(2))
        ahead = _check(0.029, now=0.029, end=0.027)
        out = m.decide(2, planned, ahead, sigma, 0, np.zeros(2))
        assert np.array_equal(out, planned) == recovers and bool(m.recoveries) == recovers, k_resume


def test_a_box_at_rest_between_the_thresholds_is_recovered_by_actions_predicted_to_centre_it():
    """A balance stop whose box came to rest at 2.9 cm (above `resume_below`'s 2.6, under `stop_at`'s 3.2)
    cannot resume; it sends the planner's action when the model predicts that, with its stop, it brings
    the box at least `recover_gain` closer to the middle without passing 3.2 cm, then that stop, then
    rest; an action predicted to gain too little, or to pass the threshold on the way, is not sent. A
    crossing a recovery leads to is not a stop's: `stopping_steps` leaves the recovery's steps out."""
    planned = np.array([0.05, -0.05, 0.004, 0.0])
    then = np.array([[0.0, 0.0, 0.002, 0.0], [0.0, 0.0, 0.001, 0.0], [0.0, 0.0, 0.0, 0.0]])
    m = Monitor(CFG, MonitorConfig(recover_gain=0.001), delay=1)
    rest, moving = np.zeros(2), np.array([0.1, -0.1])
    assert not np.array_equal(m.decide(0, planned, _check(0.034), 0.0, 0, moving), planned)  # stop
    for t in (1, 2):  # rest sent; at rest from t = 2 (delay + 1 steps of it)
        m.decide(t, planned, _check(0.029), 0.0, 0, rest)
    m.recoveries.clear()
    assert m.stopped and not m.resumes
    # too little gain (0.5 mm), or 3.3 cm on the way: kept at rest
    for c in (
        _check(0.029, end=0.0285),
        monitor.Check(
            *_check(0.033, now=0.029, end=0.020)[:3],
            np.asarray(0.033),
            *_check(0.033, now=0.029, end=0.020)[4:],
        ),
    ):
        np.testing.assert_array_equal(m.decide(3, planned, c, 0.0, 0, rest), 0.0)
    assert m.recoveries == []
    # predicted 2.9 -> 2.7 cm, never above 3.0: sent, then the stop it was checked with, then rest
    good = _check(0.030, now=0.029, end=0.027, go_stop=np.vstack([then, np.zeros((1, 4))]))
    out = [m.decide(4, planned, good, 0.0, 0, rest)]
    out += [m.decide(t, planned, _check(0.029), 0.0, 0, moving) for t in (5, 6, 7)]
    np.testing.assert_array_equal(out[0], planned)
    np.testing.assert_array_equal(np.stack(out[1:]), then)
    assert m.recoveries == [4] and m.stopped and not m.resumes
    assert not {4, 5, 6, 7} & m.stopping_steps  # the recovery and its stop: not a stop's steps
    assert m.record()["monitor_recoveries"] == 1
    # once at rest again inside resume_below, the turn resumes as after any stop
    for t in (8, 9):
        m.decide(t, planned, _check(0.025), 0.0, 0, rest)
    assert m.resumes == [9] and not m.stopped
    # off: the same box waits out the timeout
    off = Monitor(CFG, MonitorConfig(recover=False, stop_timeout=6), delay=1)
    off.decide(0, planned, _check(0.034), 0.0, 0, moving)
    sent = [off.decide(t, planned, good, 0.0, 0, rest) for t in range(1, 8)]
    assert not any(np.array_equal(a, planned) for a in sent) and off.final and off.ended


def test_recoveries_end_once_one_leaves_the_box_further_out():
    """A box at rest at 3.0 cm, recovered by an action predicted to take it to 2.7 cm, that comes to rest
    at 3.05 cm instead: the model has the direction wrong there, so no further recovery is sent in the
    episode however much it predicts (`recover_until_worse`), and the stop times out. One that came to
    rest at 2.95 cm (closer, if by less than predicted), or further by no more than the estimate's
    k_sigma std (1 mm here), is followed by the next. Off: recoveries go on while a gain is predicted."""
    planned = np.array([0.05, -0.05, 0.004, 0.0])
    rest, moving = np.zeros(2), np.array([0.1, -0.1])
    good = _check(0.030, now=0.030, end=0.027)
    assert monitor.recovery_worse(0.030, 0.0305, 0.0) and not monitor.recovery_worse(0.030, 0.0305, 0.001)
    for until_worse, landed, sigma, again in (
        (True, 0.0305, 0.0, False),
        (True, 0.0295, 0.0, True),
        (True, 0.0305, 0.001, True),
        (False, 0.0305, 0.0, True),
    ):
        m = Monitor(CFG, MonitorConfig(recover_until_worse=until_worse, stop_timeout=30), delay=0)
        m.decide(0, planned, _check(0.034), sigma, 0, moving)  # stop
        for t in (1, 2):
            m.decide(t, planned, _check(0.030), sigma, 0, rest)
        np.testing.assert_array_equal(m.decide(3, planned, good, sigma, 0, rest), planned)  # recovery
        for t in (4, 5):  # its stop, the box seen at `landed`
            m.decide(t, planned, _check(landed), sigma, 0, moving)
        nxt = _check(0.029, now=landed, end=landed - 0.003)
        sent = [m.decide(t, planned, nxt, sigma, 0, rest) for t in range(6, 40)]
        assert m.recovery_failed != again, (until_worse, landed, sigma)
        assert (m.recoveries[1:2] == [6]) == again, m.recoveries
        if not again:
            assert not any(np.array_equal(a, planned) for a in sent) and m.final and m.ended


def test_carriage_travel_in_flight_widens_the_margin_by_the_drags_uncertainty():
    """With 2 steps of delay, two 1 cm moves of carriage 1 in flight (2 cm, summed: the prior's drag error
    is the same fraction for every move of that carriage under that box) add drag_std x 2 cm to the
    prediction's std over the delay: 2.6 cm predicted + 2 x 0.2 x 2 cm = 3.4 cm stops at 3.2 cm; moves
    that cancel (+1, -1 cm) add nothing, and with drag_std 0 neither stops."""
    move = np.array([0.0, 0.0, STEP, 0.0])
    for drag_std, second, stops in ((0.2, move, True), (0.2, -move, False), (0.0, move, False)):
        m = Monitor(
            CFG, MonitorConfig(stop_at=0.8, k_sigma=1.0, k_delay=2.0, delay_std=0.0, drag_std=drag_std), 2
        )
        moving = np.array([0.1, -0.1])
        m.decide(0, move, _check(0.0), 0.0, 0, moving)
        m.decide(1, second, _check(0.0), 0.0, 0, moving)
        m.decide(2, np.zeros(4), _check(0.026), 0.0, 0, moving)
        assert m.stopped == stops, (drag_std, second)
        assert m.log[2][5] == pytest.approx((STEP + second[2]) ** 2)


def test_the_held_compensation_keeps_the_box_where_the_carriage_moves_would_have_dragged_it():
    """`planning.compensate_held`: the same present as `compensate` for the carriages and the belts, the
    box predicted without the drag of the carriage steps in flight: with both carriages stepping the same
    way under a box at rest, the model drags the box along, the held prediction leaves it (the drag is all
    the box's motion here), and with no carriage step in flight the two are the same window."""
    prior = make_prior(massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box))
    window = planning.initial_window(_state(y=0.01))
    belt = jnp.zeros(2)
    acts = jnp.asarray([[0.0, 0.0, -STEP, -STEP]] * 2, jnp.float32)
    w, _ = planning.compensate(prior, window, belt, acts)
    held = planning.compensate_held(prior, window, belt, acts, w)
    np.testing.assert_allclose(np.asarray(held[:, :2]), np.asarray(w[:, :2]))  # the carriages moved
    assert float(w[-1, geometry.P1]) == pytest.approx(-0.10 - 2 * STEP, abs=2e-3)
    dragged = float(w[-1, geometry.Y]) - 0.01
    assert dragged < -0.3 * 2 * STEP  # the model has the box follow the carriages
    assert float(held[-1, geometry.Y]) == pytest.approx(0.01, abs=1e-4)  # held: the box stays
    # so the box's offset from the middle is larger held: the carriages' middle moved away from it
    assert float(geometry.balance_error(held[-1])) > float(geometry.balance_error(w[-1])) + 0.005
    half = planning.compensate_held(prior, window, belt, acts, w, 0.5)  # half the drag withheld
    np.testing.assert_allclose(
        float(half[-1, geometry.Y]), 0.5 * float(w[-1, geometry.Y] + held[-1, geometry.Y])
    )
    belts_only = acts.at[:, 2:].set(0.0).at[:, :2].set(0.1)  # no carriage step: the same window
    w2, _ = planning.compensate(prior, window, belt, belts_only)
    np.testing.assert_allclose(
        np.asarray(planning.compensate_held(prior, window, belt, belts_only, w2)), np.asarray(w2), atol=1e-7
    )
    assert planning.compensate_held(prior, window, belt, jnp.zeros((0, 4)), window) is window


def test_the_drag_bound_checks_the_worse_of_the_dragged_and_the_held_present():
    """`MonitorConfig.drag_bound`: the check from two windows is the worse of the two checks, field by
    field, and from the same window twice it is the one-window check."""
    prior = make_prior(massdist.voxel_masses(massdist.named("A", CFG.box), CFG.box))
    belt = jnp.zeros(2)
    action = jnp.asarray([0.1, -0.1, 0.0, 0.0], jnp.float32)
    dragged = planning.initial_window(_state(y=0.01))
    held = planning.initial_window(_state(y=0.025))  # the carriages' middle moved away from the box
    one = monitor.to_host(monitor.check(CFG, prior, dragged, belt, action, 10))
    other = monitor.to_host(monitor.check(CFG, prior, held, belt, action, 10))
    both = monitor.to_host(monitor.check(CFG, prior, dragged, belt, action, 10, held=held))
    assert float(both.now) == pytest.approx(0.025, abs=1e-6)
    assert float(both.go) == pytest.approx(max(float(one.go), float(other.go)), abs=1e-6)
    assert float(both.go) > float(one.go) + 0.01
    assert float(both.stop) >= max(float(one.stop), float(other.stop)) - 1e-6
    same = monitor.to_host(monitor.check(CFG, prior, dragged, belt, action, 10, held=dragged))
    for a, b in zip(same, one, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-7)
    stacked = planning.stack([prior, prior])  # batched: each box's own
    two = lambda x: jnp.stack([x, x])  # noqa: E731
    cb = monitor.check_batch(CFG, stacked, two(dragged), two(belt), two(action), 10, held=two(held))
    for a, b in zip(monitor.to_host(cb, 1), both, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


def _spy_checks(monkeypatch) -> tuple[list, list]:
    """Record what the one-box and the batched loops give the check: (window, held present) or None per
    call, and the tipping watch's spread (N, 4)."""
    seen, spreads = [], []

    def spy(real):
        def check(
            cfg, model, window, belt, action, horizon, backup="best", held=None, tip=False, tip_spread=None
        ):
            seen.append(None if held is None else (np.asarray(window), np.asarray(held)))
            spreads.append(np.asarray(tip_spread).reshape(-1, 4))
            return real(cfg, model, window, belt, action, horizon, backup, held, tip, tip_spread)

        return check

    monkeypatch.setattr(monitor, "check", spy(monitor.check))
    monkeypatch.setattr(monitor, "check_batch", spy(monitor.check_batch))
    return seen, spreads


def _both_loops(ctrl, late):
    from boxjax.control import batch, episode

    box, key = massdist.named("A", CFG.box), jax.random.PRNGKey(3)
    return (
        lambda: episode.run_episode(CFG, box, key, ctrl=ctrl, max_steps=52, faults=late),
        lambda: batch.run_episodes(CFG, [box], [key], ctrl=ctrl, max_steps=52, faults=late),
    )


def test_the_one_box_and_the_batched_loops_give_the_check_the_pose_spread(monkeypatch):
    """With the default tipping watch ("sigma") `run_episode` and the batched `run_episodes` both give the
    check the pose's spread (`tip_spread`): nothing off with a perfect sensor and no delay, and over a
    delay in x, y and yaw; always the drag's per m of carriage travel. Without `drag_bound`, from the
    model's present alone."""
    from boxjax.control.config import ControllerConfig
    from boxjax.planners.sampling import SamplingOptions
    from boxjax.sim.faults import Faults

    seen, spreads = _spy_checks(monkeypatch)
    settings = MonitorConfig()
    assert settings.tip_uncertainty == "sigma" and not settings.drag_bound
    ctrl = ControllerConfig(sampling=SamplingOptions(gradient_steps=0))
    for late in (Faults(obs_latency=2), Faults()):
        for run in _both_loops(ctrl, late):
            seen.clear()
            spreads.clear()
            run()
            assert seen and all(s is None for s in seen), "the monitor checked nothing, or a held present"
            assert all(np.all(s[:, 3] == np.float32(monitor.tip_drag(settings))) for s in spreads)
            if late.obs_latency:
                assert all(np.all(s[:, :3] > 0) for s in spreads)  # moving, late
            else:
                np.testing.assert_array_equal(np.concatenate(spreads)[:, :3], 0.0)


@pytest.mark.slow
def test_the_one_box_and_the_batched_loops_give_the_check_the_held_present(monkeypatch):
    """With `drag_bound` and a late loop, `run_episode` and the batched `run_episodes` both check from the
    held present as well (the carriages where the model's present has them); with no delay, from the
    model's alone. (Slow: `drag_bound` is off by default; the spread they give the check is the test
    above.)"""
    from boxjax.control.config import ControllerConfig
    from boxjax.planners.sampling import SamplingOptions
    from boxjax.sim.faults import Faults

    seen, _ = _spy_checks(monkeypatch)
    ctrl = ControllerConfig(sampling=SamplingOptions(gradient_steps=0), monitor=MonitorConfig(drag_bound=1.0))
    for late in (Faults(obs_latency=2), Faults()):
        for run in _both_loops(ctrl, late):
            seen.clear()
            run()
            assert seen, "the monitor checked nothing"
            if not late.obs_latency:
                assert all(s is None for s in seen)
                continue
            for window, held in seen:
                w, h = window.reshape(-1, *window.shape[-2:]), held.reshape(-1, *held.shape[-2:])
                np.testing.assert_array_equal(h[:, :, :2], w[:, :, :2])  # the same carriages
            assert any(not np.allclose(h, w) for w, h in seen)  # and somewhere another box pose


def test_the_monitor_can_predict_with_its_own_prior_on_the_planners_belief(monkeypatch):
    """`MonitorConfig.prior_params`: the check runs with a prior of those settings on the belief the
    planner's prior is built on (here the robot loop's; the one-box and the batched loops: the slow test
    below; the on-device loop: the slow test in tests/test_device_loop.py); a model given as it is (a
    black box) has no belief, and the robot loop's PlannerStep is given it: each said before any work."""
    from boxjax import prior as prior_mod
    from boxjax.control import batch, device_loop, episode
    from boxjax.control.config import ControllerConfig
    from boxjax.control.models import monitor_model, planning_model
    from boxjax.planners.sampling import SamplingOptions
    from boxjax.robot import PlannerStep

    own = prior_mod.PriorParams(carriage_omega=30.0, slip_eps=0.02)
    ctrl = ControllerConfig(
        sampling=SamplingOptions(gradient_steps=0), monitor=MonitorConfig(prior_params=own)
    )
    box = massdist.named("A", CFG.box)
    planner_prior = planning_model(CFG, ctrl, box)
    mine = monitor_model(CFG, ctrl, box, planner_prior)
    assert mine.params == own and planner_prior.params == prior_mod.PriorParams()
    np.testing.assert_array_equal(np.asarray(mine.masses), np.asarray(planner_prior.masses))  # one belief
    assert monitor_model(CFG, ControllerConfig(), box, planner_prior) is planner_prior

    used, spy = _spy_params()
    key = jax.random.PRNGKey(3)
    with pytest.raises(ValueError, match="black box"):
        episode.run_episode(CFG, box, key, ctrl=ctrl, model=planner_prior)
    with pytest.raises(ValueError, match="black box"):
        batch.run_episodes(CFG, [box], [key], ctrl=ctrl, model=planner_prior)
    assert device_loop.supports(ctrl) is None
    rest = planning.Planner("rest", lambda obs: None, lambda k, m, obs, st: (np.zeros(4), st, None))
    with pytest.raises(ValueError, match="monitor_model"):  # the robot loop's: given its model
        PlannerStep(rest, planner_prior, key, monitor=ctrl.monitor)
    from boxjax.robot import loop as robot_loop

    monkeypatch.setattr(robot_loop, "monitor_check", spy(robot_loop.monitor_check))
    step = PlannerStep(rest, planner_prior, key, monitor=ctrl.monitor, monitor_model=mine)
    step(planning.observation(planning.initial_window(_state()), jnp.zeros(2), 1.57))
    assert used == [own]
    with pytest.raises(ConfigError, match="prior_params"):
        MonitorConfig(prior_params={"carriage_omega": 30.0})


def _spy_params():
    """(list of the models' PriorParams the wrapped checks were given, the wrapper)."""
    used = []

    def spy(real):
        def check(cfg, model, *args, **kwargs):
            used.append(model.params)
            return real(cfg, model, *args, **kwargs)

        return check

    return used, spy


@pytest.mark.slow
def test_the_one_box_and_the_batched_loops_check_with_the_monitors_own_prior(monkeypatch):
    """`MonitorConfig.prior_params` in `run_episode` and the batched `run_episodes`: every check is made
    with the monitor's prior (slow: the option is off by default; the robot loop's: the test above)."""
    from boxjax import prior as prior_mod
    from boxjax.control import batch, episode
    from boxjax.control.config import ControllerConfig
    from boxjax.planners.sampling import SamplingOptions
    from boxjax.sim.faults import Faults

    own = prior_mod.PriorParams(carriage_omega=30.0, slip_eps=0.02)
    ctrl = ControllerConfig(
        sampling=SamplingOptions(gradient_steps=0), monitor=MonitorConfig(prior_params=own)
    )
    box, key, late = massdist.named("A", CFG.box), jax.random.PRNGKey(3), Faults(obs_latency=2)
    used, spy = _spy_params()
    monkeypatch.setattr(monitor, "check", spy(monitor.check))
    monkeypatch.setattr(monitor, "check_batch", spy(monitor.check_batch))
    episode.run_episode(CFG, box, key, ctrl=ctrl, max_steps=50, faults=late)
    batch.run_episodes(CFG, [box], [key], ctrl=ctrl, max_steps=50, faults=late)
    assert used and all(p == own for p in used)


def test_the_compensation_error_script_summarises_per_square_root_step_and_refuses_bad_input(
    tmp_path, capsys
):
    """scripts/compensation_error.py (what `delay_std` and `tip_yaw_std` were measured with): its summary
    of known errors, and an evaluation without recorded actions or a bad count refused with status 2."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import compensation_error

    rng = np.random.default_rng(0)
    e = rng.normal(0, 1, (20000, 3)) * np.array([0.002, 0.004, math.radians(0.8)])
    out = compensation_error.summary({4: e})["4"]
    assert out["samples"] == 20000
    assert out["std_per_sqrt_step"]["y_mm"] == pytest.approx(2.0, rel=0.03)
    assert out["std_per_sqrt_step"]["yaw_deg"] == pytest.approx(0.4, rel=0.03)
    assert out["p99_abs"]["x_mm"] == pytest.approx(2 * 2.576, rel=0.05)
    (tmp_path / "evaluation.json").write_text('{"rows": []}')
    for argv, msg in (([str(tmp_path)], str(tmp_path)), ([str(tmp_path), "--boxes", "0"], "must be >= 1")):
        with pytest.raises(SystemExit) as exc:
            compensation_error.main(argv)
        assert exc.value.code == 2 and msg in capsys.readouterr().err
