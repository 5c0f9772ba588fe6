"""The fixed exploration phase: its shape and limits, what the simulator applies, and what it does to the
named boxes (turns and shifts them a little, safely)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from boxjax import geometry, massdist
from boxjax.config import DEFAULT
from boxjax.estimator import explore
from boxjax.sim import make_env
from boxjax.sim.native import rollout

CFG = DEFAULT
NAMES = ("uniform", "A", "B", "C", "D")


@pytest.fixture(scope="module")
def named_rollout():
    dists = [massdist.named(n, CFG.box) for n in NAMES]
    return rollout(CFG, dists, explore.exploration_actions(CFG))


DESIGNED_CFG = CFG.replace(task=dataclasses.replace(CFG.task, exploration="designed"))
GENTLE_CFG = CFG.replace(task=dataclasses.replace(CFG.task, exploration="gentle"))


@pytest.mark.parametrize("cfg", [CFG, DESIGNED_CFG, GENTLE_CFG], ids=["fixed", "designed", "gentle"])
def test_fifteen_vectors_held_three_steps_within_limits(cfg):
    """Every sequence keeps the same rules (the designed one was searched within them)."""
    a = explore.exploration_actions(cfg)
    assert a.shape == (45, 4) == (explore.N_STEPS, 4) and a.dtype == np.float32
    assert explore.N_VECTORS == 15 and explore.HOLD == 3
    np.testing.assert_array_equal(a.reshape(15, 3, 4), np.repeat(a[::3][:, None], 3, axis=1))
    g = CFG.gripper
    assert np.all(np.abs(a[:, :2]) <= g.belt_speed_limit)
    assert np.all(np.abs(a[:, 2:]) <= g.max_position_step + 1e-9)
    # Every setpoint is reachable within its 3-step hold under the acceleration limit.
    v = np.concatenate([np.zeros((1, 2)), explore.vectors(cfg)[:, :2]])
    assert np.all(np.abs(np.diff(v, axis=0)) <= explore.HOLD * g.belt_accel_limit * g.control_dt + 1e-9)
    # Belts end where they started, at rest (the designed carriages within 0.1 mm: its vectors are
    # rounded to 10 um); both carriages stay inside their ranges all along.
    np.testing.assert_allclose(a[:, 2:].sum(axis=0), 0.0, atol=1e-4)
    np.testing.assert_array_equal(a[-1, :2], 0.0)
    p = np.asarray(g.belt_y0) + np.cumsum(a[:, 2:], axis=0)
    assert np.all((p[:, 0] >= g.p1_range[0]) & (p[:, 0] <= g.p1_range[1]))
    assert np.all((p[:, 1] >= g.p2_range[0]) & (p[:, 1] <= g.p2_range[1]))


def test_applied_actions_match_the_simulator(named_rollout):
    applied = explore.applied_actions(CFG)
    assert applied.shape == (45, 4)
    for b in range(len(NAMES)):
        np.testing.assert_allclose(named_rollout["actions"][b], applied, atol=1e-6)
    assert not named_rollout["clipped"].any()
    # Speeds reach each vector's setpoint by the end of its hold; position increments are as commanded.
    np.testing.assert_allclose(applied[2::3, :2], explore.VECTORS[:, :2], atol=1e-6)
    np.testing.assert_allclose(applied[:, 2:], explore.exploration_actions(CFG)[:, 2:], atol=1e-7)


def test_turns_and_shifts_a_uniform_box_slightly_and_safely(named_rollout):
    s = named_rollout["s"]
    bal = np.abs(s[..., geometry.Y] - 0.5 * (s[..., geometry.P1] + s[..., geometry.P2]))
    d = s[:, -1] - s[:, 0]
    u = NAMES.index("uniform")
    yaw = np.degrees(s[u, :, geometry.YAW] - s[u, 0, geometry.YAW])
    assert 5.0 < yaw.max() < 30.0  # a small counter-clockwise turn ...
    assert 0.0 < yaw[-1] < 0.5 * yaw.max()  # ... mostly undone by the end
    assert np.hypot(d[u, geometry.X], d[u, geometry.Y]) < 0.05
    assert bal[u].max() < 0.02
    for name in ("A", "B", "C", "D"):  # typical boxes and the hazardous D: well inside the 4 cm limit
        assert bal[NAMES.index(name)].max() < 0.02, name
    # The belts are back where they started.
    np.testing.assert_allclose(s[:, -1, :2], np.tile(CFG.gripper.belt_y0, (len(NAMES), 1)), atol=1e-3)


def test_different_boxes_leave_different_trajectories(named_rollout):
    """What the estimator needs: the phase tells the boxes apart (final poses differ by centimetres or
    degrees between the named boxes)."""
    final = named_rollout["s"][:, -1, 2:]
    for i in range(len(NAMES)):
        for j in range(i + 1, len(NAMES)):
            gap = np.abs(final[i] - final[j])
            assert gap[:2].max() > 0.003 or gap[2] > np.radians(0.5), (NAMES[i], NAMES[j])


def test_trajectory_layout():
    s = np.arange(3 * 5, dtype=np.float32).reshape(3, 5)
    w = np.arange(3 * 2, dtype=np.float32).reshape(3, 2) + 100
    a = np.arange(2 * 4, dtype=np.float32).reshape(2, 4) + 50
    traj, final = explore.trajectory(s, w, a)
    assert traj.shape == (2, explore.N_TRAJ_COLUMNS) and final.shape == (5,)
    np.testing.assert_array_equal(traj[:, :5], s[:2])
    np.testing.assert_array_equal(traj[:, 5:9], a)
    np.testing.assert_array_equal(traj[:, 9:], w[1:])  # belt speeds measured at the END of each step
    np.testing.assert_array_equal(final, s[2])
    batched = jax.vmap(explore.trajectory)(s[None], w[None], a[None])
    np.testing.assert_array_equal(batched[0][0], traj)


def test_run_on_one_env_matches_the_batched_rollout(named_rollout):
    env = make_env(CFG, "native")
    u = NAMES.index("uniform")
    state = env.reset(jax.random.PRNGKey(0), massdist.named("uniform", CFG.box))
    state, traj, final = explore.run(env, state)
    assert traj.shape == (45, 11) and not bool(state.done)
    ref, ref_final = explore.trajectory(
        named_rollout["s"][u], named_rollout["belt_speed"][u], named_rollout["actions"][u]
    )
    np.testing.assert_allclose(traj, ref, atol=2e-4)
    np.testing.assert_allclose(final, ref_final, atol=2e-4)


def test_describe_effect_reports_every_named_box():
    eff = explore.describe_effect(CFG, names=("uniform", "D"))
    assert set(eff) == {"uniform", "D"}
    assert set(eff["uniform"]) == {"dx_cm", "dy_cm", "dyaw_deg", "max_balance_error_cm", "clipped"}
    assert eff["uniform"]["clipped"] is False


def _guard_trace(guard, ys):
    """Feed a guard states whose box centre sits at ys (m) between belts at -0.1 / +0.1 m; the step at
    which it tripped (None: never)."""
    for t, y in enumerate(ys):
        s = np.array([-0.1, 0.1, 0.0, y, 0.0])
        guard.next(s, abs(y))
        if guard.tripped:
            return t
    return None


def test_guard_lead_trips_on_the_trend_before_the_threshold():
    swing = [0.001, 0.005, 0.011, 0.020, 0.030, 0.041]  # ~1 cm per step: an end-heavy box's first turn
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875), swing) == 5  # past 3.5 cm only once beyond 4 cm
    lead = explore.Guarded(DEFAULT, 0.875, lead=3)
    assert _guard_trace(lead, swing) == 3  # 2.0 cm + 3 x 0.6 cm/step (the smaller change) > 3.5 cm
    assert "expected 3 steps ahead" in lead.why()
    # Coming back towards the midline, or steady, never trips below the threshold.
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3), swing[::-1][1:]) is None
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3), [0.03] * 10) is None
    # Noise about a resting box: one large change alone (a frame off by 5 mm) does not trip it.
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3), [0.028, 0.028, 0.033, 0.028, 0.028]) is None
    # A stated pose noise of 3 mm: two frames' difference counts only beyond 2 sqrt(2) x 3 mm, so a resting
    # box seen jumping by 5 mm twice running does not trip it; the 1 cm-per-step swing is then mostly
    # within the allowance, so the guard trips no earlier than on the present value.
    jumpy = [0.020, 0.025, 0.030, 0.030, 0.030]
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3), jumpy) == 2
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3, noise=0.003), jumpy) is None
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3, noise=0.003), swing) == 5
    assert _guard_trace(explore.Guarded(DEFAULT, 0.875, lead=3, noise=0.001), swing) == 4
    with pytest.raises(ValueError, match="lead must be >= 0"):
        explore.Guarded(DEFAULT, 0.875, lead=-1)


def test_the_exploration_is_chosen_by_the_config():
    np.testing.assert_array_equal(explore.vectors(CFG), explore.VECTORS)
    np.testing.assert_array_equal(explore.vectors(DESIGNED_CFG), explore.DESIGNED)
    np.testing.assert_allclose(
        explore.exploration_actions(DESIGNED_CFG), np.repeat(explore.DESIGNED, 3, 0), atol=1e-7
    )
    with pytest.raises(ValueError, match="exploration must be one of"):
        dataclasses.replace(CFG.task, exploration="spiral")


def test_designed_exploration_keeps_the_named_boxes_balanced():
    """The designed sequence on the named boxes (native): no clipping, every box within 1.5 cm of the
    midline (fixed: within 1.1 cm), and it moves them (it is not a sequence that shows nothing)."""
    effect = explore.describe_effect(DESIGNED_CFG)
    for name, e in effect.items():
        assert not e["clipped"], name
        assert e["max_balance_error_cm"] < 1.5, (name, e)
    assert max(abs(e["dyaw_deg"]) for e in effect.values()) > 2.0


def test_the_gentle_exploration_is_the_fixed_one_with_a_slower_first_turn():
    """Its first turn (vectors 1-3) at half the belt speeds, everything after it the fixed sequence's; on the
    named boxes it turns them about half as far during that turn."""
    np.testing.assert_array_equal(explore.vectors(GENTLE_CFG)[:3, :2], 0.5 * explore.VECTORS[:3, :2])
    np.testing.assert_array_equal(explore.vectors(GENTLE_CFG)[:3, 2:], explore.VECTORS[:3, 2:])
    np.testing.assert_array_equal(explore.vectors(GENTLE_CFG)[3:], explore.VECTORS[3:])
    dists = [massdist.named(n, CFG.box) for n in ("uniform", "A")]
    turn = slice(0, 3 * explore.HOLD + 1)
    yaw = {
        name: np.abs(rollout(CFG, dists, explore.exploration_actions(c)[: 3 * explore.HOLD])["s"][:, turn, 4])
        for name, c in (("fixed", CFG), ("gentle", GENTLE_CFG))
    }
    assert np.all(yaw["gentle"].max(1) < 0.7 * yaw["fixed"].max(1))
    assert np.all(yaw["gentle"].max(1) > 0.2 * yaw["fixed"].max(1))  # it still turns the box


def test_models_trained_on_another_exploration_are_refused():
    """The shipped H was trained on the fixed sequence: with the designed one it is refused by name (a
    model saved before the field existed counts as made with its default, the fixed sequence)."""
    from boxjax import config_io
    from boxjax.estimator import CheckpointError, shipped

    shipped.default_estimator(CFG)  # the default config still loads it
    with pytest.raises(CheckpointError, match="task.exploration = 'designed'"):
        shipped.default_estimator(DESIGNED_CFG)
    with pytest.raises(CheckpointError, match="train-estimator --exploration gentle"):
        shipped.default_estimator(GENTLE_CFG)
    stored = CFG.to_dict()
    del stored["task"]["exploration"]
    assert config_io.field_mismatches(stored, CFG.to_dict(), ["task.exploration"]) == []
    assert config_io.field_mismatches(stored, DESIGNED_CFG.to_dict(), ["task.exploration"]) == [
        ("task.exploration", config_io.MISSING, "designed")
    ]


@pytest.mark.parametrize("stop", explore.STOPS)
def test_guard_stop_after_a_trip(stop):
    """Once tripped, the guard sends GUARD_STEPS steps of its stop and ends: both stop the belts; a
    re-centring steps both carriages towards the box (at most one position step), a hold keeps them still."""
    guard = explore.Guarded(DEFAULT, 0.875, stop=stop)
    s = np.array([-0.1, 0.1, 0.0, 0.037, 0.0])  # 3.7 cm off the midline: past 3.5 cm
    sent = []
    while (a := guard.next(s, 0.037)) is not None:
        sent.append(a)
    assert guard.tripped and len(sent) == explore.GUARD_STEPS
    sent = np.array(sent)
    np.testing.assert_array_equal(sent[:, :2], 0.0)  # belts to rest
    step = DEFAULT.gripper.max_position_step
    np.testing.assert_allclose(sent[:, 2:], step if stop == "recentre" else 0.0)
    assert ("re-centred under it" in guard.why()) == (stop == "recentre")
    assert ("held still" in guard.why()) == (stop == "hold")
    with pytest.raises(ValueError, match="stop must be one of"):
        explore.Guarded(DEFAULT, 0.875, stop="brake")


def test_the_offline_guard_study_trips_where_the_guard_does():
    """`scripts/guard_trend_study.py` judges guard rules on unguarded records: its version of the guard's own
    rule must trip at the very step `explore.Guarded` does on the same seen poses, or its table is wrong."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "scripts" / "guard_trend_study.py"
    spec = importlib.util.spec_from_file_location("guard_trend_study", path)
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    rng = np.random.default_rng(0)
    n, boxes = 40, 60
    seen = np.cumsum(rng.normal(0, 0.004, (boxes, n)), axis=1)  # wandering offsets, some past the guard
    seen[: boxes // 2, 10:] += 0.008 * np.arange(n - 10)  # half swing away ~8 mm a step from step 10
    for noise in (0.0, 0.003):
        offline = study.trip_frames(seen, 3, noise, 0.875 * DEFAULT.task.balance_limit)
        for i in range(boxes):
            guard = explore.Guarded(DEFAULT, 0.875, lead=3, noise=noise)
            tripped_at = -1
            for t, y in enumerate(seen[i]):
                guard.next(np.array([-0.1, 0.1, 0.0, y, 0.0]), abs(y))
                if guard.tripped:
                    tripped_at = t
                    break
            assert offline[i] == tripped_at, (noise, i)
        assert (offline >= 0).sum() > boxes // 2  # the test trips (the swings at least)
