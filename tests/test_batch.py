"""Batched episodes (boxjax.control.batch, sim.native.NativeBatch): the same physics as the one-box env bit
for
bit, the same decisions and outcomes as `controller.run_episode`, exact replays, bad input named."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import control as controller
from boxjax import massdist, prior
from boxjax.config import DEFAULT as cfg
from boxjax.control import batch
from boxjax.experiments import evaluation as experiments
from boxjax.planners.sampling import SamplingOptions
from boxjax.sim.native import NativeBatch, NativeEnv


def test_batched_worlds_step_as_the_one_box_env_bit_for_bit():
    dists = [massdist.named(n, cfg.box) for n in ("A", "C", "uniform")]
    keys = [jax.random.PRNGKey(j) for j in range(3)]
    acts = np.random.default_rng(0).uniform(-1, 1, (3, 40, 4)) * np.array([0.1, 0.1, 0.01, 0.01])
    sim = NativeBatch(cfg, dists, keys)
    for t in range(40):
        sim.step(acts[:, t], np.arange(3) != t % 3)  # one world paused each step
    env = NativeEnv(cfg)
    for b in range(3):
        st = env.reset(keys[b], dists[b])
        for t in range(40):
            if t % 3 != b:
                st = env.step(st, acts[b, t])
        assert np.array_equal(np.asarray(st.s), sim.s[b])
        assert int(st.t) == int(sim.t[b]) and int(st.reason) == int(sim.reason[b])
        assert float(st.max_balance_error) == float(sim.max_balance_error[b])


def test_batched_world_rejects_bad_actions_by_world():
    sim = NativeBatch(cfg, [massdist.named("A", cfg.box)] * 2, [jax.random.PRNGKey(0)] * 2)
    with pytest.raises(ValueError, match="shape"):
        sim.step(np.zeros((3, 4)))
    bad = np.zeros((2, 4))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"worlds \[1\]"):
        sim.step(bad)
    sim.step(bad, np.array([True, False]))  # an inactive world's row is ignored


CTRL = controller.ControllerConfig(sampling=SamplingOptions(gradient_steps=0))


@pytest.fixture(scope="module")
def episodes():
    """The uniform box and hazardous D, batched, and the same boxes one at a time (a planner without
    gradient steps: it compiles in a fraction of the default's time and turns these boxes as well)."""
    dists = [massdist.named(n, cfg.box) for n in ("uniform", "D")]
    keys = [jax.random.PRNGKey(j) for j in range(2)]
    res = batch.run_episodes(cfg, dists, keys, ctrl=CTRL, slots=1)
    single = [controller.run_episode(cfg, d, k, ctrl=CTRL) for d, k in zip(dists, keys, strict=True)]
    return dists, keys, res, single


def test_batched_episodes_decide_and_end_as_the_one_box_path(episodes):
    dists, keys, res, single = episodes
    for r, s in zip(res, single, strict=True):
        assert set(r.summary) == set(s.summary)
        for k in ("success", "aborted", "abort_reason", "exploration_steps", "lost_exploring"):
            assert r.summary[k] == s.summary[k], k
        # The exploration is open loop: bit for bit the same states.
        n = r.summary["exploration_steps"]
        assert n == 45 and np.array_equal(r.trace.s[: n + 1], s.trace.s[: n + 1])
    u, d = res
    assert u.summary["success"] and d.summary["aborted"] and d.summary["steps"] == 45
    # Slip makes the closed loop chaotic: the MPC phase agrees to within some steps, not exactly.
    assert abs(u.summary["steps"] - single[0].summary["steps"]) <= 0.2 * single[0].summary["steps"]
    assert len(u.plan_ms) == u.summary["steps"] - 45 - 1  # one planner call per MPC step (first untimed)


def test_the_true_box_s_smallest_stability_margin_is_the_exact_one_along_its_true_states(episodes):
    """`min_stability_margin_m`: the min over the episode's TRUE states of the exact stability margin of the
    TRUE box, each state's computed alone (no padding), on both paths; the uniform box is never near
    tipping, D (refused after its exploration) has its exploration's."""
    dists, _, res, single = episodes
    alone = jax.jit(lambda model, x: model.stability_margin(x))  # one state per call
    for d, r, s in zip(dists, res, single, strict=True):
        exact = prior.make_prior(
            massdist.voxel_masses(d, cfg.box), None, cfg.box, cfg.gripper, margin="exact"
        )
        for out in (r, s):
            margins = np.array([float(alone(exact, jnp.asarray(x, jnp.float32))) for x in out.trace.s])
            assert out.summary["min_stability_margin_m"] == pytest.approx(margins.min(), abs=1e-6)
            turn = out.summary["turn_min_stability_margin_m"]  # the states the turn's actions reached
            n = out.summary["exploration_steps"]
            if out.summary["aborted"]:
                assert turn is None
            else:
                assert turn == pytest.approx(float(margins[n + 1 :].min()), abs=1e-6)
                assert turn >= out.summary["min_stability_margin_m"]
    assert res[0].summary["min_stability_margin_m"] > 0.02
    assert res[1].summary["aborted"] and np.isfinite(res[1].summary["min_stability_margin_m"])


def test_a_box_waiting_for_a_slot_runs_when_one_frees_longest_first():
    dists = [massdist.named(n, cfg.box) for n in ("uniform", "A", "B")]
    keys = [jax.random.PRNGKey(j) for j in range(3)]
    given = batch.run_episodes(cfg, dists, keys, ctrl=CTRL, slots=1, max_steps=50, order="given")
    for r in given:  # 45 exploration steps, then 5 MPC steps each, one box at a time
        assert r.summary["steps"] == 50 and r.summary["failed_reason"] == "step_cap"
        assert len(r.plan_ms) == 4
    assert given[0].summary["wall_s"] < given[1].summary["wall_s"] < given[2].summary["wall_s"]
    # By default the box whose centre of mass lies farthest off-centre (B, then A, then uniform) gets
    # the slot first; when a box runs does not change its episode.
    lengths = [batch.expected_length(cfg, d) for d in dists]
    assert lengths[0] < 1e-6 < lengths[1] < lengths[2]
    res = batch.run_episodes(cfg, dists, keys, ctrl=CTRL, slots=1, max_steps=50)
    assert res[2].summary["wall_s"] < res[1].summary["wall_s"] < res[0].summary["wall_s"]
    for r, g in zip(res, given, strict=True):
        assert np.array_equal(r.trace.actions, g.trace.actions) and np.array_equal(r.trace.s, g.trace.s)


def test_replay_re_simulates_a_batched_episode_exactly(episodes):
    dists, keys, res, _ = episodes
    for j in (0, 1):
        rep = batch.replay_episode(cfg, dists[j], keys[j], res[j].trace.actions)
        assert np.array_equal(rep.trace.s, res[j].trace.s)
        keys_ = ("success", "aborted", "abort_reason", "failed_reason", "steps", "max_balance_error_m")
        for k in (*keys_, "min_stability_margin_m", "turn_min_stability_margin_m"):
            assert rep.summary[k] == res[j].summary[k], k
    # another box: its exploration is not the one these actions sent, or the actions outlast it
    with pytest.raises(ValueError, match="ended at step|exploration.s"):
        batch.replay_episode(cfg, massdist.named("B", cfg.box), keys[0], np.tile([0.2, 0.2, 0, 0], (400, 1)))


def test_unsupported_controllers_and_bad_arguments_are_named():
    d, k = [massdist.named("A", cfg.box)], [jax.random.PRNGKey(0)]
    with pytest.raises(ValueError, match="simulator"):
        batch.run_episodes(cfg, d, k, ctrl=controller.ControllerConfig(planner="simulator"))
    with pytest.raises(ValueError, match="observer"):
        batch.run_episodes(cfg, d, k, ctrl=controller.ControllerConfig(observer_gain=0.3))
    with pytest.raises(ValueError, match="adapt_every >= 1"):
        batch.run_episodes(cfg, d, k, adapter=lambda m, data: m)
    with pytest.raises(ValueError, match="one key per box"):
        batch.run_episodes(cfg, d, k * 2)
    with pytest.raises(ValueError, match="slots"):
        batch.run_episodes(cfg, d, k, slots=0)
    with pytest.raises(ValueError, match="unknown order"):
        batch.run_episodes(cfg, d, k, order="shortest_first")
    with pytest.raises(ValueError, match="slots"):
        experiments.evaluate(cfg, 1, batched=False, slots=4, progress=False)


SHARDED = """
import json, jax
from boxjax import control as controller
from boxjax import massdist, prior
from boxjax.control import batch
from boxjax.config import DEFAULT as cfg
from boxjax.planners.sampling import SamplingOptions
assert batch.use_host_devices(2) == 2
ctrl = controller.ControllerConfig(sampling=SamplingOptions(gradient_steps=0))
dists = [massdist.named(n, cfg.box) for n in ("uniform", "A", "D")]
keys = [jax.random.PRNGKey(j) for j in range(3)]
res = batch.run_episodes(cfg, dists, keys, ctrl=ctrl, slots=2, max_steps=55)
print(json.dumps([[r.summary["steps"], r.summary["aborted"], len(r.plan_ms)] for r in res]))
"""


def test_batched_planner_shards_boxes_over_forced_host_devices():
    """Two host devices (jax_num_cpu_devices, as `boxjax evaluate` asks for one per core): the boxes of
    a planner call are split over both, and the episodes run as on one device."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", SHARDED], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = json.loads(out.stdout.strip().splitlines()[-1])
    assert rows == [[55, False, 9], [55, False, 9], [45, True, 0]]


def test_sharding_splits_the_box_axis_when_there_are_several_devices():
    put, n = batch.box_sharding()
    assert n == len(jax.local_devices())
    x = put(np.zeros((2 * n, 3)))
    assert np.asarray(x).shape == (2 * n, 3)


def _small_w():
    """A small random W predicting about constant velocity (residuals of ~1 mm)."""
    from boxjax.blackbox import baseline

    small = baseline.BaselineConfig(hidden=(32, 32), adapt_batch=16, adapt_lr=1e-3)
    stats = {"x_mean": np.zeros(22), "x_std": np.ones(22), "y_mean": np.zeros(5), "y_std": np.full(5, 1e-3)}
    return baseline.init_model(jax.random.PRNGKey(0), small, cfg.gripper, stats)


def test_a_black_box_in_the_slot_adapts_each_box_on_its_own_episode():
    """W in the model slot with online adaptation, batched: every box adapts its own copy of the model,
    on its own episode so far, on the one-box path's schedule (a small random W: the plumbing, not W's
    skill, is tested here)."""
    from boxjax.blackbox import baseline

    w = _small_w()
    real = baseline.make_adapter(1)
    calls = []

    def adapter(model, data):
        calls.append({k: v.copy() for k, v in data.items()})
        return real(model, data)

    ctrl = controller.ControllerConfig(
        explore=False, adapt_every=10, sampling=SamplingOptions(gradient_steps=0)
    )
    dists = [massdist.named(n, cfg.box) for n in ("A", "C")]
    keys = [jax.random.PRNGKey(j) for j in range(2)]
    res = batch.run_episodes(cfg, dists, keys, ctrl=ctrl, model=w, adapter=adapter, max_steps=25, slots=2)
    single = [
        controller.run_episode(cfg, d, k, ctrl=ctrl, model=w, adapter=real, max_steps=25)
        for d, k in zip(dists, keys, strict=True)
    ]
    assert not np.array_equal(res[0].trace.s[11], res[1].trace.s[11])  # the boxes' episodes differ
    for r, s in zip(res, single, strict=True):
        assert r.summary["steps"] == 25 and r.summary["exploration_steps"] == 0
        assert r.summary["adaptations"] == s.summary["adaptations"] == 2  # after MPC steps 10 and 20
        assert set(r.summary) == set(s.summary)
    assert sorted(len(c["actions"]) for c in calls) == [10, 10, 20, 20]
    for c in calls:  # each call saw exactly one box's own episode so far
        n = len(c["actions"])
        owners = [
            b
            for b, r in enumerate(res)
            if np.array_equal(c["s"], r.trace.s[: n + 1])
            and np.array_equal(c["actions"], r.trace.actions[:n])
        ]
        assert len(owners) == 1
    # The adapted models are the one-box path's: the same actions (bit for bit on this CPU today; the
    # tolerance leaves room for XLA vectorising the batched call differently).
    for r, s in zip(res, single, strict=True):
        np.testing.assert_allclose(r.trace.actions, s.trace.actions, atol=1e-4)


def test_batched_black_box_rows_are_the_one_at_a_time_rows():
    from boxjax.experiments import comparison

    w, jobs = _small_w(), [("A", 0), ("C", 1)]
    kw = dict(adapt_every=10, ctrl=CTRL, max_steps=22)
    rows = comparison.blackbox_episodes(cfg, jobs, w, slots=2, **kw)
    single = [comparison.blackbox_episode(cfg, b, s, w, **kw) for b, s in jobs]
    for r, s in zip(rows, single, strict=True):
        assert r["batched"] and (r["box"], r["seed"]) == (s["box"], s["seed"])
        for k in ("outcome", "steps", "adaptations", "method"):
            assert r[k] == s[k], k
    assert [r["adaptations"] for r in rows] == [2, 2]
    observer = controller.ControllerConfig(observer_gain=0.3)
    with pytest.raises(ValueError, match="black boxes' episodes: the drift observer"):
        comparison.compare(cfg, ("A",), 1, ("blackbox",), model=w, ctrl=observer, batch_black_boxes=True)
