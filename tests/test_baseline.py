"""The black-box baseline W (boxjax/baseline.py): learning, adaptation, the model slot, checkpoints, CLI."""

from __future__ import annotations

import dataclasses
import os

import jax
import numpy as np
import pytest

from boxjax import cli, massdist, planning, prior
from boxjax.blackbox import baseline as B
from boxjax.config import DEFAULT
from boxjax.planners import sampling as sp
from boxjax.training import baseline as T

SMALL = B.BaselineConfig(hidden=(64, 64), epochs=40, batch=64, lr=3e-3, adapt_lr=1e-3, adapt_batch=32)
G = DEFAULT.gripper


def linear_episode(rng, n: int, damping: float = 0.9, gain=None) -> dict:
    """A known linear system in W's coordinates: s_{t+1} = s_t + damping (s_t - s_{t-1}) + K u, u = (dv,
    dp) the belt-speed change and the position steps (inside the hardware limits, so no clipping)."""
    gain = (
        np.array([[0, 0, 1.0, 0], [0, 0, 0, 1.0], [0.05, 0.05, 0, 0], [0, 0, 0.3, 0.3], [0.4, -0.4, 0, 0]])
        if gain is None
        else gain
    )
    s = [np.array([-0.1, 0.1, 0.0, 0.0, 0.0])] * 2
    b = [np.zeros(2)]
    acts = []
    for _ in range(n):
        dv = rng.uniform(-0.02, 0.02, 2)
        dp = rng.uniform(-0.004, 0.004, 2)
        a = np.concatenate([b[-1] + dv, dp])
        s.append(s[-1] + damping * (s[-1] - s[-2]) + gain @ np.concatenate([dv, dp]))
        b.append(b[-1] + dv)
        acts.append(a)
    return {"s": np.stack(s[1:]), "belt_speed": np.stack(b), "actions": np.stack(acts)}


def _norm_mse(model, tr) -> float:
    X, Y = B.batch_features(tr, G)
    Xn, Yn = B.standardise(model, X, Y)
    pred = jax.vmap(B.mlp.apply, in_axes=(None, 0))(model.params, Xn)
    return float(np.mean(np.square(np.asarray(pred) - np.asarray(Yn))))


@pytest.fixture(scope="module")
def linear_model():
    rng = np.random.default_rng(0)
    eps = [
        {**linear_episode(rng, 150), "kind": "random", "outcome": "step_cap", "explore": False}
        for _ in range(6)
    ]
    tr = T.transitions_of(eps)
    model, losses = T.train(tr, SMALL, seed=0, progress=False)
    return model, tr, losses


def test_learns_a_known_linear_system(linear_model):
    model, tr, losses = linear_model
    assert losses[-1] < 0.05 * losses[0]
    test = T.transitions_of([{**linear_episode(np.random.default_rng(1), 200), "outcome": "step_cap"}])
    # one-step state error, relative to the spread of the one-step change
    err = B.one_step_errors(model, test)
    cv = B.constant_velocity_errors(test)
    assert np.median(err["position_mm"]) < 0.25 * np.median(cv["position_mm"])
    assert np.median(err["yaw_deg"]) < 0.25 * np.median(cv["yaw_deg"])
    assert _norm_mse(model, test) < 0.1  # of the standardised target variance


def test_adaptation_changes_params_and_lowers_the_episode_error(linear_model):
    model, _, _ = linear_model
    other = np.array(
        [[0, 0, 1.0, 0], [0, 0, 0, 1.0], [0.1, -0.05, 0, 0], [0, 0, 0.1, 0.5], [0.2, -0.6, 0, 0]]
    )
    ep = linear_episode(np.random.default_rng(2), 120, damping=0.8, gain=other)
    tr = B.episode_transitions(ep)
    before = _norm_mse(model, tr)
    adapted = B.make_adapter(epochs=3)(model, ep)
    changed = [
        not np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(model.params), jax.tree.leaves(adapted.params), strict=True)
    ]
    assert all(changed)
    assert _norm_mse(adapted, tr) < 0.8 * before
    np.testing.assert_array_equal(adapted.x_mean, model.x_mean)  # normalisation is kept
    again = B.make_adapter(epochs=3)(model, ep)  # pure in (model, data)
    np.testing.assert_array_equal(again.params[0]["w"], adapted.params[0]["w"])


def test_model_slot_interface_and_no_margin(linear_model):
    model, _, _ = linear_model
    window = planning.initial_window(np.array([-0.1, 0.1, 0.0, 0.0, 0.0]))
    acts = np.zeros((4, 4), np.float32)
    acts[:, :2] = [0.03, -0.03]
    states = model.rollout_sequence(window, np.zeros(2), acts)
    assert states.shape == (4, 5) and np.all(np.isfinite(states))
    # each prediction is fed back: the second state equals predict on the shifted window
    s1 = model.predict(window, np.zeros(2), acts[0])
    np.testing.assert_allclose(states[0], s1, atol=1e-6)
    assert float(model.stability_margin(states[0])) == planning.NO_MARGIN
    assert jax.vmap(model.stability_margin)(states).shape == (4,)


def test_same_action_for_same_model_and_key_whichever_model(linear_model):
    w_model, _, _ = linear_model
    p_model = prior.make_prior(massdist.voxel_masses(massdist.named("A")), None)
    # Without gradient steps: the slot, not the refinement, is tested here (the same plan per key with
    # gradient steps: W and PETS in tests/test_pets.py); the gradient through the prior took 20 s to compile.
    pl = sp.make(DEFAULT, sp.SamplingOptions(n_samples=8, horizon=3, gradient_steps=0))
    obs = planning.observation(
        planning.initial_window(np.array([-0.1, 0.1, 0.0, 0.0, 0.0])), np.zeros(2), np.pi / 2
    )
    key = jax.random.PRNGKey(3)
    for model in (w_model, p_model):
        st = pl.init(obs)
        a1, st1, _ = pl.optimize(key, model, obs, st)
        a2, st2, _ = pl.optimize(key, model, obs, st)
        np.testing.assert_array_equal(a1, a2)
        np.testing.assert_array_equal(st1, st2)
        assert a1.shape == (4,) and np.all(np.isfinite(a1))


def test_nan_window_gets_a_named_error(linear_model):
    model, _, _ = linear_model
    w = np.zeros((3, 5))
    w[1, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        B.rollout(model, w, np.zeros(2), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="actions"):
        B.rollout(model, np.zeros((3, 5)), np.zeros(2), np.full((2, 4), np.nan))
    with pytest.raises(ValueError, match="NaN"):
        B.adapt(
            model, {"s": np.full((4, 5), np.nan), "belt_speed": np.zeros((4, 2)), "actions": np.zeros((3, 4))}
        )


def test_checkpoint_round_trip_and_refusals(linear_model, tmp_path):
    model, _, _ = linear_model
    path = B.save(tmp_path / "w.npz", model, seed=7, info={"note": "test"})
    back, meta = B.load(path, expected_config=SMALL, with_meta=True)
    assert meta["seed"] == 7 and meta["config"]["hidden"] == [64, 64]
    np.testing.assert_array_equal(back.params[1]["w"], model.params[1]["w"])
    np.testing.assert_array_equal(back.y_std, model.y_std)
    with pytest.raises(B.BaselineCheckpointError, match="configuration differs"):
        B.load(path, expected_config=B.BaselineConfig())
    with pytest.raises(B.BaselineCheckpointError, match=r"another gripper .*gripper.control_dt"):
        B.load(path, gripper=dataclasses.replace(G, control_dt=0.1, timestep=0.002))
    # how MJX finds contacts is not the gripper (like the backend); a field the file lacks is its default
    B.load(path, gripper=dataclasses.replace(G, mjx_box_contacts="polygon"))
    assert B.gripper_mismatches({k: v for k, v in meta["gripper"].items() if k != "friction"}, G) == []
    assert B.gripper_mismatches(None, G) == ["gripper"]
    with pytest.raises(B.BaselineCheckpointError, match="no such"):
        B.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(B.BaselineCheckpointError, match="not a boxjax"):
        B.load(bad)
    # arrays of another shape than the configuration in the metadata says
    wrong = dataclasses.replace(
        model,
        params=[{"w": p["w"][:, :32] if i == 0 else p["w"], "b": p["b"]} for i, p in enumerate(model.params)],
    )
    B.save(tmp_path / "wrong.npz", wrong, seed=0)
    with pytest.raises(B.BaselineCheckpointError, match="layer0_w has shape"):
        B.load(tmp_path / "wrong.npz")


@pytest.mark.skipif(not os.path.exists(B.shipped_path()), reason="no shipped W")
def test_shipped_weights_load_with_paper_size():
    model, meta = B.load(B.shipped_path(), expected_config=B.BaselineConfig(), with_meta=True)
    assert 2.0e6 < B.n_params(model) < 3.0e6
    assert meta["info"]["distribution"] == "A"
    assert os.path.getsize(B.shipped_path()) <= 10 * 2**20
    from boxjax.experiments import comparison

    t2 = comparison.table2()
    assert t2[1]["transitions"] == meta["info"]["transitions"] and t2[1]["zero_shot"] is False
    assert t2[0]["zero_shot"] is True


@pytest.mark.parametrize(
    "argv",
    [
        ["rotate", "--model", "prior", "--adapt-every", "20"],
        ["rotate", "--adapt-epochs", "1"],
        ["rotate", "--model", "blackbox", "--model-weights", "/nonexistent/w.npz"],
        ["rotate", "--model", "blackbox", "--estimator", "learned"],
        ["rotate", "--model", "blackbox", "--adapt-every", "-1"],
        ["train-baseline", "--episodes", "1", "--out", "/tmp/boxjax-test-never-written"],
    ],
)
def test_cli_bad_input_exits_2(argv, capsys):
    assert cli.main(argv) == 2
    assert "error" in capsys.readouterr().err


def test_cli_refuses_a_wrong_checkpoint(linear_model, tmp_path, capsys):
    model, _, _ = linear_model
    path = B.save(tmp_path / "w.npz", model, seed=0)
    with open(tmp_path / "corrupt.npz", "wb") as f:
        f.write(b"not a zip")
    assert cli.main(["rotate", "--model", "blackbox", "--model-weights", str(tmp_path / "corrupt.npz")]) == 2
    assert "W checkpoint" in capsys.readouterr().err
    del path


def test_comparison_table_aggregates_rows():
    from boxjax.experiments import comparison

    def row(method, box, seed, outcome, steps, adapt=0.0, n_adapt=0):
        s = {
            "success": outcome == "success",
            "aborted": outcome == "refused",
            "failed_reason": None,
            "steps": steps,
            "wall_s": 2.0,
            "adapt_s": adapt,
            "adaptations": n_adapt,
            "max_balance_error_m": 0.01 * (seed + 1),
            "plan_ms_median": 5.0,
        }
        if outcome not in ("success", "refused"):
            s["failed_reason"] = outcome
        return comparison._row(method, box, seed, s)

    rows = [
        row("blackbox", "A", 0, "success", 100, 1.0, 4),
        row("blackbox", "A", 1, "tipped", 300, 3.0, 6),
        row("prior", "D", 0, "refused", 45),
    ]
    t = {(r["box"], r["method"]): r for r in comparison.table(rows)}
    a = t[("A", "blackbox")]
    assert a["success_ratio"] == 0.5 and a["mean_steps_successes"] == 100
    assert a["outcomes"] == {"success": 1, "tipped": 1} and a["adapt_epoch_s_median"] == 0.375
    assert a["paper_success"] == 1.0 and a["worst_balance_m"] == 0.02
    d = t[("D", "prior")]
    assert d["refused"] == 1 and d["worst_balance_m"] is None and d["paper_success"] == "aborts"
    md = comparison.format_table(comparison.table(rows))
    assert "| A | blackbox | 1/2 |" in md and "(refused 1)" in md


def test_cli_compare_runs_w_in_the_model_slot(tmp_path, capsys):
    """`boxjax compare --methods blackbox` loads the shipped W and turns a box with it (one episode)."""
    import json

    argv = ["compare", "--seeds", "1", "--boxes", "A", "--methods", "blackbox", "--adapt-every", "0"]
    assert cli.main([*argv, "--out", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (row,) = out["rows"]
    assert row["method"] == "blackbox" and row["box"] == "A" and row["steps"] > 0
