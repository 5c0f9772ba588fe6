"""PETS (boxjax/pets.py) and the particle mechanism of the model slot (planning.Ensemble, the sampling
planner's particle aggregation): learning and calibration, TS-inf particles, the plain path unchanged,
determinism in the key, adaptation, checkpoints."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import blackbox, planning
from boxjax.blackbox import baseline, pets
from boxjax.config import DEFAULT
from boxjax.planners import sampling as sp
from boxjax.training import baseline as T
from boxjax.training import pets as PT

CFG = DEFAULT
G = CFG.gripper
SMALL = pets.PETSConfig(
    members=3, hidden=(64, 64), particles_per_member=2, epochs=60, batch=64, lr=3e-3, adapt_lr=1e-3
)
NOISE = np.array([2e-5, 2e-5, 1e-4, 1e-4, 2e-3])  # m, m, m, m, rad: the known per-step noise std
GAIN = np.array([[0, 0, 1.0, 0], [0, 0, 0, 1.0], [0.05, 0.05, 0, 0], [0, 0, 0.3, 0.3], [0.4, -0.4, 0, 0]])
S0 = np.array([-0.1, 0.1, 0.0, 0.0, 0.0])
OBS = planning.observation(planning.initial_window(S0), np.zeros(2), np.pi / 2)


def noisy_linear_episode(rng, n: int, damping: float = 0.9, gain=GAIN, noise=NOISE) -> dict:
    """s_{t+1} = s_t + damping (s_t - s_{t-1}) + K u + noise, u = (dv, dp): in W's coordinates the target
    (the second difference) is linear in the inputs plus gaussian noise of std `noise`."""
    s = [S0] * 2
    b = [np.zeros(2)]
    acts = []
    for _ in range(n):
        # belt speeds stay inside +-0.2 m/s (below the limit, so W's features see no clipping)
        dv = np.clip(rng.uniform(-0.02, 0.02, 2), -0.2 - b[-1], 0.2 - b[-1])
        dp = rng.uniform(-0.004, 0.004, 2)
        s.append(
            s[-1] + damping * (s[-1] - s[-2]) + gain @ np.concatenate([dv, dp]) + noise * rng.normal(size=5)
        )
        b.append(b[-1] + dv)
        acts.append(np.concatenate([b[-2] + dv, dp]))
    return {"s": np.stack(s[1:]), "belt_speed": np.stack(b), "actions": np.stack(acts)}


def _transitions(seed: int, episodes: int, n: int) -> dict:
    rng = np.random.default_rng(seed)
    eps = [{**noisy_linear_episode(rng, n), "outcome": "step_cap"} for _ in range(episodes)]
    return T.transitions_of(eps)


@pytest.fixture(scope="module")
def trained():
    tr = _transitions(0, 6, 150)
    model, losses = PT.train(tr, SMALL, seed=0, progress=False)
    return model, tr, losses


def _tiny_w(seed=0):
    """A small untrained W: a single-trajectory model of the slot that compiles in a blink (the prior's
    rollout takes tens of seconds to compile on this CPU; the plain path does not depend on the model)."""
    return baseline.init_model(jax.random.PRNGKey(seed), baseline.BaselineConfig(hidden=(16,)))


def test_learns_a_noisy_linear_system_with_calibrated_variance(trained):
    model, _, losses = trained
    assert losses[-1] < losses[0] - 1.0  # NLL per output fell by more than a nat
    test = _transitions(1, 2, 200)
    err, cv = baseline.one_step_errors(model, test), baseline.constant_velocity_errors(test)
    assert np.median(err["position_mm"]) < 0.25 * np.median(cv["position_mm"])
    # yaw: down to the noise floor (the median |noise| is 0.674 std), far below constant velocity
    assert np.median(err["yaw_deg"]) < min(1.3 * 0.674 * np.degrees(NOISE[4]), 0.5 * np.median(cv["yaw_deg"]))
    # Calibrated: where the known noise dominates (x, y, yaw) the predicted std is the noise std (plus the
    # little the fit gets wrong) and matches the RMS of the errors it makes; the coverage is near gaussian.
    cal = pets.calibration(model, test)
    y_std = np.asarray(model.members.y_std[0])
    for i, k in ((2, "x"), (3, "y"), (4, "yaw")):
        assert 0.8 * NOISE[i] < cal["predicted_std_rms"][k] * y_std[i] < 1.6 * NOISE[i]
        np.testing.assert_allclose(cal["predicted_std_rms"][k], cal["error_rms"][k], rtol=0.2)
        assert 0.5 < cal["within_1_std"][k] < 0.8 and cal["within_2_std"][k] > 0.8


def test_members_differ_and_the_plain_slot_is_their_mean(trained):
    model, _, _ = trained
    acts = jnp.tile(jnp.array([[0.03, -0.03, 0.0, 0.001]]), (4, 1))
    roll = jax.jit(lambda m: m.rollout_sequence(OBS.window, OBS.belt_speed, acts))  # one compilation
    per = [roll(planning.member(model.members, i)) for i in range(3)]
    assert not np.allclose(per[0], per[1], atol=0, rtol=0)  # bootstrap + own init: different members
    np.testing.assert_allclose(roll(model), np.mean(per, 0), atol=1e-7)
    assert float(model.stability_margin(per[0][0])) == planning.NO_MARGIN
    assert pets.n_params(model) == 3 * (22 * 64 + 64 + 64 * 64 + 64 + 64 * 10 + 10 + 10)


def test_trajectory_sampling_each_particle_keeps_its_member(trained):
    model, _, _ = trained
    acts = jnp.tile(jnp.array([[0.03, -0.03, 0.0, 0.0]]), (5, 1))
    key = jax.random.PRNGKey(4)
    parts = np.asarray(model.rollout_particles(key, OBS.window, OBS.belt_speed, acts))
    assert parts.shape == (6, 5, 5) and model.n_particles == 6
    keys = jax.random.split(key, 6)
    sample = jax.jit(lambda m, k: m.rollout_sample(k, OBS.window, OBS.belt_speed, acts))
    for p in range(6):  # particle e * k + j: member e, its own key, the whole horizon (TS-inf)
        np.testing.assert_allclose(
            parts[p], sample(planning.member(model.members, p // 2), keys[p]), atol=1e-6
        )
    assert not np.allclose(parts[0], parts[1])  # sampled noise: two particles of one member differ
    np.testing.assert_array_equal(parts, model.rollout_particles(key, OBS.window, OBS.belt_speed, acts))
    assert planning.particle_margins(model, parts).shape == (6, 5)


def test_aggregation_over_particles():
    c = jnp.array([[1.0, 2.0, 6.0], [3.0, 3.0, 3.0]])
    np.testing.assert_allclose(planning.aggregate(c), [3.0, 3.0])
    np.testing.assert_allclose(planning.aggregate(c, "worst"), [6.0, 3.0])
    np.testing.assert_allclose(planning.aggregate(c, "mean_std", 2.0), [3.0 + 2 * np.std([1, 2, 6]), 3.0])
    with pytest.raises(ValueError, match="particle risk"):
        planning.aggregate(c, "cvar")
    with pytest.raises(ValueError, match="particle_risk"):
        sp.SamplingOptions(particle_risk="best")


# Planners shared by the tests below (each jitted planner compiles once per model type: ~10 s here).
O0 = sp.SamplingOptions(n_samples=8, horizon=3, gradient_steps=0)
PLAN0 = sp.make_sampling_planner(CFG, O0)
MPC = sp.make(CFG, sp.SamplingOptions(n_samples=8, horizon=3, gradient_steps=2))


def test_one_member_ensemble_plans_as_the_plain_model():
    """An Ensemble of one deterministic member (one particle) gives the plain model's costs and plan:
    the particle path aggregates to the plain path. (Without gradient steps: Adam's first step is
    +-lr per component, so float32 noise in a near-zero gradient flips it; the costs it descends agree.)"""
    pm = _tiny_w()
    one = planning.Ensemble(planning.stack([pm]))
    assert planning.n_particles(one) == 1 and planning.n_particles(pm) is None
    key, nominal = jax.random.PRNGKey(7), sp.initial_nominal(CFG, O0)
    a0, i0 = PLAN0(key, pm, OBS.window, OBS.belt_speed, OBS.target_yaw, nominal)
    a1, i1 = PLAN0(key, one, OBS.window, OBS.belt_speed, OBS.target_yaw, nominal)
    np.testing.assert_allclose(i1.cost, i0.cost, rtol=1e-5)
    np.testing.assert_allclose(a1, a0, atol=1e-6)
    np.testing.assert_allclose(i1.states, i0.states, atol=1e-6)
    seq = i0.nominal
    c0 = sp.rollout_cost(
        pm, pm.rollout_sequence(OBS.window, OBS.belt_speed, seq), seq, OBS.target_yaw, CFG, O0
    )
    c1 = sp.particle_cost(one, key, OBS.window, OBS.belt_speed, OBS.target_yaw, seq, CFG, O0)[1]
    np.testing.assert_allclose(c1, c0, rtol=1e-6)


def test_plain_path_is_predictive_sampling_as_before():
    """For a single-trajectory model the planner computes exactly what it did before particles existed:
    the nominal and the key's perturbations, clipped, rolled out by `rollout_sequence`, scored by
    `rollout_cost`, argmin (bit-identical; gradient steps off so the reference stays short). The prior
    and the shipped W were also checked bit-identical against the planner before this change, with
    gradient steps, MPPI and CEM (README, "PETS")."""
    pm, o = _tiny_w(), O0
    key, nominal = jax.random.PRNGKey(3), sp.initial_nominal(CFG, o, OBS.belt_speed)
    a, info = PLAN0(key, pm, OBS.window, OBS.belt_speed, OBS.target_yaw, nominal)

    @jax.jit
    def reference(key, model):
        sigma = jnp.array([o.speed_sigma, o.speed_sigma, o.position_sigma, o.position_sigma])
        seqs = jnp.concatenate([nominal[None], nominal[None] + sp.perturbations(key, o) * sigma])
        seqs = sp.clip_actions(seqs, CFG, o.speed_cap, o.position_deadband)
        states = jax.vmap(lambda q: model.rollout_sequence(OBS.window, OBS.belt_speed, q))(seqs)
        cost = jax.vmap(lambda s, q: sp.rollout_cost(model, s, q, OBS.target_yaw, CFG, o))(states, seqs)
        cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
        return seqs[jnp.argmin(cost)][0], cost

    a_ref, cost_ref = reference(key, pm)
    np.testing.assert_array_equal(np.asarray(info.cost), np.asarray(cost_ref))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(a_ref))
    assert planning.n_particles(planning.DriftCorrected(pm, jnp.zeros(3))) is None  # still the plain path


def test_same_action_for_same_model_and_key_whichever_model(trained):
    """The same model and key give the same plan, with PETS (gradient steps through the particles) or a
    single-trajectory model in the slot (the prior and W: test_baseline); the particles' noise comes
    from the step's key."""
    model, _, _ = trained
    key = jax.random.PRNGKey(3)
    for m in (model, _tiny_w()):
        st = MPC.init(OBS)
        a1, st1, _ = MPC.optimize(key, m, OBS, st)
        a2, st2, _ = MPC.optimize(key, m, OBS, st)
        np.testing.assert_array_equal(a1, a2)
        np.testing.assert_array_equal(st1, st2)
        assert a1.shape == (4,) and np.all(np.isfinite(a1))
    # another key: other particle noise, so another cost of the same nominal
    _, _, i1 = MPC.optimize(key, model, OBS, MPC.init(OBS))
    _, _, i3 = MPC.optimize(jax.random.PRNGKey(4), model, OBS, MPC.init(OBS))
    assert float(i3.cost[0]) != float(i1.cost[0])
    # the nominal's cost is the particles' mean, and "worst" is their max (the same particles)
    kp = jax.random.fold_in(key, planning.PARTICLE_STREAM)
    seq = sp.initial_nominal(CFG, O0, OBS.belt_speed)
    parts = model.rollout_particles(kp, OBS.window, OBS.belt_speed, seq)
    costs = [float(sp.rollout_cost(model.members, p, seq, OBS.target_yaw, CFG, O0)) for p in parts]
    np.testing.assert_allclose(float(i1.cost[0]), np.mean(costs), rtol=1e-5)
    worst = dataclasses.replace(O0, particle_risk="worst")
    c_w = sp.particle_cost(model, kp, OBS.window, OBS.belt_speed, OBS.target_yaw, seq, CFG, worst)[1]
    np.testing.assert_allclose(float(c_w), np.max(costs), rtol=1e-5)
    # under the drift observer a particle model stays one: every particle moved by k x the drift
    drift = jnp.array([1e-3, -2e-3, 0.01], jnp.float32)
    acts = jnp.zeros((3, 4))
    moved = planning.DriftCorrected(model, drift).rollout_particles(key, OBS.window, OBS.belt_speed, acts)
    base = model.rollout_particles(key, OBS.window, OBS.belt_speed, acts)
    assert planning.n_particles(planning.DriftCorrected(model, drift)) == model.n_particles
    np.testing.assert_allclose(
        moved[..., 2:] - base[..., 2:], np.outer([1, 2, 3], drift)[None].repeat(6, 0), atol=1e-6
    )


def test_adaptation_changes_params_and_lowers_the_episode_nll(trained):
    model, _, _ = trained
    other = GAIN.copy()
    other[4] = [0.2, -0.6, 0, 0]
    ep = noisy_linear_episode(np.random.default_rng(2), 120, damping=0.8, gain=other)
    tr = baseline.episode_transitions(ep)
    before = pets.calibration(model, tr)["nll_per_output"]
    adapted = pets.make_adapter(epochs=3)(model, ep)
    assert all(
        not np.array_equal(a, b)
        for a, b in zip(
            jax.tree.leaves(model.members.params), jax.tree.leaves(adapted.members.params), strict=True
        )
    )
    assert pets.calibration(adapted, tr)["nll_per_output"] < before - 0.1
    np.testing.assert_array_equal(adapted.members.x_mean, model.members.x_mean)  # normalisation kept
    again = pets.make_adapter(epochs=3)(model, ep)  # pure in (model, data)
    np.testing.assert_array_equal(again.members.params[0]["w"], adapted.members.params[0]["w"])
    wrapped = pets.make_adapter(epochs=1)(planning.DriftCorrected(model, jnp.zeros(3)), ep)
    assert pets.is_pets(wrapped.model)
    with pytest.raises(ValueError, match="NaN"):
        pets.adapt(
            model, {"s": np.full((4, 5), np.nan), "belt_speed": np.zeros((4, 2)), "actions": np.zeros((3, 4))}
        )


def test_checkpoint_round_trip_and_refusals(trained, tmp_path):
    model, _, _ = trained
    path = pets.save(tmp_path / "p.npz", model, seed=5, info={"note": "test"})
    back, meta = pets.load(path, expected_config=SMALL, with_meta=True)
    assert meta["seed"] == 5 and meta["config"]["members"] == 3 and back.particles_per_member == 2
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(model), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(pets.PETSCheckpointError, match="configuration differs.*members"):
        pets.load(path, expected_config=dataclasses.replace(SMALL, members=5))
    with pytest.raises(pets.PETSCheckpointError, match="another gripper"):
        pets.load(path, gripper=dataclasses.replace(G, control_dt=0.1, timestep=0.002))
    with pytest.raises(pets.PETSCheckpointError, match="no such"):
        pets.load(tmp_path / "missing.npz")
    # a W checkpoint is not a PETS checkpoint, and the other way round
    w = baseline.init_model(jax.random.PRNGKey(0), baseline.BaselineConfig(hidden=(8,)))
    baseline.save(tmp_path / "w.npz", w, seed=0)
    with pytest.raises(pets.PETSCheckpointError, match="format is not 'boxjax-pets'"):
        pets.load(tmp_path / "w.npz")
    with pytest.raises(baseline.BaselineCheckpointError, match="format is not"):
        baseline.load(path)

    with pytest.raises(baseline.BaselineCheckpointError, match="PETS"):
        blackbox.load_black_box("pets", str(tmp_path / "w.npz"))
    # arrays of another shape than the configuration says, refused by the array's name
    m = model.members
    wrong = dataclasses.replace(
        model,
        members=dataclasses.replace(
            m, params=[m.params[0], {"w": m.params[1]["w"][:, :, :32], "b": m.params[1]["b"]}, m.params[2]]
        ),
    )
    pets.save(tmp_path / "wrong.npz", wrong, seed=0)
    with pytest.raises(pets.PETSCheckpointError, match="layer1_w has shape"):
        pets.load(tmp_path / "wrong.npz")
    fewer = dataclasses.replace(model, members=dataclasses.replace(m, min_logvar=m.min_logvar[:2]))
    pets.save(tmp_path / "fewer.npz", fewer, seed=0)
    with pytest.raises(pets.PETSCheckpointError, match="min_logvar has shape"):
        pets.load(tmp_path / "fewer.npz")


def test_bad_config_is_refused_by_name():
    with pytest.raises(ValueError, match="activation"):
        pets.PETSConfig(activation="tanh")
    with pytest.raises(ValueError, match="particles_per_member"):
        pets.PETSConfig(particles_per_member=0)
    with pytest.raises(ValueError, match="particles_per_member"):
        planning.Ensemble(planning.stack([_tiny_w()]), 0)


# ----------------------------------------------------------------------------------------------------------
# `boxjax train-baseline --model pets` (the CLI of pets_train.train_pets)


def _tiny_dataset(path, episodes: int = 4, steps: int = 60) -> dict:
    """A W dataset file (baseline_train's format) of noisy linear episodes."""
    tr = _transitions(3, episodes, steps)
    kinds = np.array([T.KINDS[i % len(T.KINDS)] for i in range(episodes)])
    np.savez(path, **tr, episode_kind=kinds, episode_outcome=np.array(["step_cap"] * episodes))
    return tr


@pytest.mark.slow  # 9 s compiling the ensemble's training; PETS's training is tested above
def test_cli_train_baseline_model_pets_on_a_dataset(tmp_path, capsys, monkeypatch):
    import json

    from boxjax import cli

    def cheap_comparison(model, tr, truth, cfg=CFG):  # W's and the prior's errors cost ~10 s to compile
        cv = baseline.summarise_errors(baseline.constant_velocity_errors(tr))
        return {"blackbox": cv, "prior": cv, "constant_velocity": cv, "transitions": len(tr["action"])}

    monkeypatch.setattr(T, "compare_errors", cheap_comparison)
    tr = _tiny_dataset(tmp_path / "dataset.npz")
    out = tmp_path / "run"
    argv = ["train-baseline", "--model", "pets", "--data", str(tmp_path / "dataset.npz"), "--out", str(out)]
    assert cli.main([*argv, "--epochs", "2", "--members", "2", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rep["command"] == "train-baseline" and rep["model"] == "pets"
    assert rep["episodes"] == 4 and rep["transitions"] == tr["action"].shape[0]
    assert rep["train_transitions"] + rep["heldout_transitions"] == rep["transitions"]
    assert rep["config"]["epochs"] == 2 and rep["config"]["members"] == 2 and len(rep["epoch_losses"]) == 2
    model, meta = pets.load(out / "pets.npz", with_meta=True)
    assert model.n_members == 2 and meta["info"]["transitions"] == rep["transitions"]
    with open(out / PT.REPORT) as f:
        assert json.load(f)["heldout_transitions"] == rep["heldout_transitions"]
    assert not (out / "baseline.npz").exists() and not (out / "report.json").exists()  # W's files untouched
    # a second run without --force is refused, by the file's name
    assert cli.main([*argv, "--epochs", "1"]) == 2
    assert "already holds pets.npz" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra, named",
    [
        (["--members", "2"], "--members is an option of the PETS ensemble (--model pets)"),  # W has none
        (["--model", "pets", "--episodes", "3"], "--episodes does nothing with --model pets --data"),
        (["--model", "pets", "--epochs", "0"], "--epochs must be >= 1"),
        (["--model", "pets", "--members", "0"], "--members must be >= 1"),
        (["--backend", "mjx"], "--backend does nothing with --data"),  # nothing is simulated
    ],
)
def test_cli_train_baseline_refuses_an_option_the_model_does_not_use(tmp_path, capsys, extra, named):
    from boxjax import cli

    out = tmp_path / "never"
    argv = ["train-baseline", "--data", str(tmp_path / "missing.npz"), "--out", str(out), *extra]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0]
    assert not out.exists()


def test_pets_split_needs_two_episodes():
    tr = _transitions(0, 2, 20)
    train_tr, held = PT.split_episodes(tr, 2)
    assert set(np.unique(held["episode"])) == {0} and set(np.unique(train_tr["episode"])) == {1}
    with pytest.raises(ValueError, match="at least 2 episodes"):
        PT.split_episodes(tr, 1)
    with pytest.raises(ValueError, match="--episodes must be >= 2"):
        PT.train_pets(n_episodes=1, progress=False)


def test_cli_train_baseline_model_blackbox_passes_epochs_to_w(tmp_path, monkeypatch, capsys):
    from boxjax import cli

    seen = {}

    def fake_train_baseline(cfg, **kw):
        seen.update(kw)
        return {"command": "train-baseline"}

    monkeypatch.setattr(T, "train_baseline", fake_train_baseline)
    argv = ["train-baseline", "--data", "d.npz", "--out", str(tmp_path), "--epochs", "3", "--json"]
    assert cli.main(argv) == 0
    assert seen["config"] == baseline.BaselineConfig(epochs=3) and seen["data"] == "d.npz"
    assert seen["n_episodes"] == 200 and '"model": "blackbox"' in capsys.readouterr().out
    assert seen["backend"] == "native"
    argv = ["train-baseline", "--backend", "mjx", "--out", str(tmp_path), "--json"]
    assert cli.main(argv) == 0 and seen["backend"] == "mjx" and seen["data"] is None
