"""The estimator H: features, training on a learnable synthetic dataset, early stopping, checkpoints,
input validation and metrics against hand-computed values."""

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from npz_util import rewrite

from boxjax import estimator as E
from boxjax.config import BoxConfig, ConfigError
from boxjax.massdist import MassDistribution

BOX = BoxConfig(grid=(4, 4, 2))  # small grid: 32 voxels
T = 45


def synthetic(
    seed: int, n: int, box: BoxConfig = BOX, learnable: bool = True, hazardous_share: float = 0.0
) -> dict:
    """Boxes whose occupancy (any non-empty union of the four xy quadrants, all layers) and mass are a
    deterministic function of the trajectory: each step's state change is a fixed linear map of
    (quadrant bits, standardised mass), plus 1e-4 noise. With learnable=False the targets are shuffled
    against the trajectories, so nothing generalises (for early stopping). A share `hazardous_share` of
    the boxes instead fills only the first x-slice of voxels (region U1, hazardous), marked in the
    trajectory by a response of its own."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = box.grid
    bits = rng.integers(0, 2, (n, 4))
    bits[bits.sum(1) == 0, 0] = 1
    occ = np.zeros((n, nx, ny, nz), np.float32)
    hx, hy = nx // 2, ny // 2
    quadrants = [
        (slice(0, hx), slice(0, hy)),
        (slice(0, hx), slice(hy, None)),
        (slice(hx, None), slice(0, hy)),
        (slice(hx, None), slice(hy, None)),
    ]
    for q, (sx, sy) in enumerate(quadrants):
        occ[:, sx, sy, :] = bits[:, q, None, None, None]
    hazardous = rng.random(n) < hazardous_share
    bits[hazardous] = 0
    occ[hazardous] = 0.0
    occ[hazardous, 0] = 1.0
    mass = rng.uniform(1, 10, n).astype(np.float32)
    fixed = np.random.default_rng(1234)  # the same "physics" and exploration actions for every dataset
    actions = fixed.uniform(-0.2, 0.2, (T, 4)).astype(np.float32)
    actions[:, 2:] *= 0.05
    response = fixed.normal(0, 0.01, (T, 5, 5))
    p = np.concatenate([bits, ((mass - 5.5) / 4.5)[:, None]], 1)
    if not learnable:
        p = rng.permutation(p)
    ds = np.einsum("tij,bj->bti", response, p) + rng.normal(0, 1e-4, (n, T, 5))
    ds += hazardous[:, None, None] * fixed.normal(0, 0.01, (T, 5))[None]
    s0 = np.array([-0.1, 0.1, 0, 0, 0]) + rng.normal(0, 1e-3, (n, 5))
    s = s0[:, None] + np.concatenate([np.zeros((n, 1, 5)), np.cumsum(ds, 1)], 1)
    # Measured belt speeds: the commanded ones, slowed in proportion to the mass (as a belt servo would be).
    belt = actions[None, :, :2] - 1e-4 * p[:, None, 4:5]
    traj = np.concatenate([s[:, :T], np.broadcast_to(actions, (n, T, 4)), belt], -1).astype(np.float32)
    return {"traj": traj, "final": s[:, T].astype(np.float32), "occupancy": occ, "total_mass": mass}


CFG = E.EstimatorConfig(hidden=(64, 64), learning_rate=3e-3, batch_size=32, max_epochs=60, patience=60)


@pytest.fixture(scope="module")
def trained():
    model, history = E.train(jax.random.key(0), synthetic(0, 300), CFG, box=BOX, progress=False)
    return model, history


# ------------------------------------------------------------------------------------------------ features


def test_features_shape_and_hand_values():
    traj = np.zeros((2, E.N_TRAJ_COLUMNS), np.float32)
    traj[0, :5] = (-0.1, 0.1, 0.0, 0.0, 3.1)
    traj[0, 5:9] = (0.1, -0.1, 0.002, 0.0)
    traj[0, 9:] = (0.0995, -0.0990)  # measured belt speeds at the end of step 0
    traj[1, :5] = (-0.099, 0.1, 0.0, 0.0, -3.1)  # yaw crossed +-pi: a small positive turn
    traj[1, 5:9] = (0.0, 0.0, -0.001, 0.0)
    traj[1, 9:] = (0.0, 0.0)
    final = np.array([-0.1, 0.1, 0.01, 0.0, -3.1], np.float32)  # moved +1 cm along world x
    f = np.asarray(E.features(jnp.asarray(traj), jnp.asarray(final))).reshape(2, E.N_STEP_FEATURES)
    assert E.features(jnp.asarray(traj), jnp.asarray(final)).shape == (2 * E.N_STEP_FEATURES,)
    np.testing.assert_allclose(f[0, :5], [0.001, 0, 0, 0, 2 * np.pi - 6.2], atol=1e-5)  # wrapped dyaw
    np.testing.assert_allclose(f[0, 7:9], [-0.1, 0.1], atol=1e-6)  # belts relative to the box centre
    np.testing.assert_allclose(f[0, 9:11], [0.001 - 0.002, 0.0], atol=1e-6)  # carriage 1 lags 1 mm
    np.testing.assert_allclose(f[1, 9:11], [-0.001, 0.0], atol=1e-6)  # still 1 mm behind after step 1
    np.testing.assert_allclose(f[0, 11:13], [0.0005, -0.0010], atol=1e-6)  # belt speed lag v - w
    np.testing.assert_allclose(f[0, 13:16], [0, 0, 2 * np.pi - 6.2], atol=1e-5)  # pose after step 0
    np.testing.assert_allclose(f[1, 13:16], [0.01, 0, 2 * np.pi - 6.2], atol=1e-5)  # ... after step 1
    np.testing.assert_allclose(f[0, 16:], traj[0, 5:9])
    # Step 1 at yaw ~ -pi: a world +x move is a box-frame -x move.
    np.testing.assert_allclose(f[1, 5:7], [0.01 * np.cos(-3.1), -0.01 * np.sin(-3.1)], atol=1e-6)
    assert f[1, 5] < 0


# ------------------------------------------------------------------------------------------------ training


@pytest.fixture(scope="module")
def evaluation(trained):
    return E.evaluate(trained[0], synthetic(1, 200))


def test_learns_synthetic_dataset(trained, evaluation):
    model, history = trained
    test = evaluation
    assert test["boxes"] == 200
    assert test["iou_median"] > 0.95 and test["iou_mean"] > 0.9
    assert test["mass_rel_error_median"] < 0.1
    assert test["com_error_cm_median"] < 1.0
    assert history["val_loss"][history["best_epoch"]] < history["val_loss"][0] / 5
    assert len(history["train_index"]) + len(history["val_index"]) == 300
    assert not set(history["train_index"]) & set(history["val_index"])
    n_in = T * E.N_STEP_FEATURES
    assert E.mlp.n_params(model.net) == (n_in + 1) * 64 + 65 * 64 + 65 * BOX.n_voxels + 65 + 65


def test_train_deterministic_by_key():
    cfg = dataclasses.replace(CFG, max_epochs=3)  # same compiled functions as the fixture's run
    data = synthetic(3, 300)
    a, ha = E.train(jax.random.key(7), data, cfg, box=BOX, progress=False)
    b, hb = E.train(jax.random.key(7), data, cfg, box=BOX, progress=False)
    jax.tree.map(np.testing.assert_array_equal, a.net, b.net)
    assert ha["val_loss"] == hb["val_loss"]
    np.testing.assert_array_equal(ha["val_index"], hb["val_index"])


def test_early_stopping_restores_best_params():
    # Targets unrelated to the inputs: the net memorises the training boxes and the validation loss rises.
    data = synthetic(2, 300, learnable=False)
    cfg = dataclasses.replace(CFG, max_epochs=300, patience=6)
    model, history = E.train(jax.random.key(1), data, cfg, box=BOX, progress=False)
    assert history["stopped_early"]
    assert history["epochs_run"] == history["best_epoch"] + 1 + cfg.patience < cfg.max_epochs
    best = history["val_loss"][history["best_epoch"]]
    assert best == min(history["val_loss"]) < history["val_loss"][-1]
    val = {k: v[history["val_index"]] for k, v in data.items()}
    assert E.losses(model, val)["loss"] == pytest.approx(best, rel=1e-4)


def test_train_rejects_bad_dataset():
    data = synthetic(0, 10)
    with pytest.raises(ValueError, match="grid"):
        E.train(None, data, CFG, box=BoxConfig(), progress=False)
    bad = dict(data, traj=data["traj"].copy())
    bad["traj"][3, 4, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        E.train(None, bad, CFG, box=BOX, progress=False)
    with pytest.raises(ValueError, match="total_mass"):
        E.train(None, {k: v for k, v in data.items() if k != "total_mass"}, CFG, box=BOX, progress=False)


def test_config_validation_and_dict_round_trip():
    with pytest.raises(ConfigError):
        E.EstimatorConfig(val_fraction=1.0)
    with pytest.raises(ConfigError):
        E.EstimatorConfig(hidden=())
    with pytest.raises(ConfigError):
        E.EstimatorConfig(activation="swish")
    cfg = E.EstimatorConfig(hidden=(8, 4), seed=3)
    assert E.EstimatorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


# ------------------------------------------------------------------------------------------------ prediction


def test_predict_checked_matches_predict_and_validates(trained):
    model, _ = trained
    data = synthetic(5, 3)
    prob, mass, hazard = E.predict_checked(model, data["traj"][0], data["final"][0])
    assert prob.shape == BOX.grid and mass.shape == () and hazard.shape == ()
    assert np.all((prob > 0) & (prob < 1)) and mass > 0 and 0 < hazard < 1
    probs, masses, hazards = E.predict_checked(model, data["traj"], data["final"])
    assert probs.shape == (3, *BOX.grid) and masses.shape == (3,) and hazards.shape == (3,)
    np.testing.assert_allclose(probs[0], prob, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(masses[0], mass, rtol=1e-5)
    np.testing.assert_allclose(hazards[0], hazard, rtol=1e-5, atol=1e-6)

    with pytest.raises(ValueError, match="44 steps"):
        E.predict_checked(model, data["traj"][0, :44], data["final"][0])
    with pytest.raises(ValueError, match="shape"):
        E.predict_checked(model, data["traj"][0, :, :9], data["final"][0])
    with pytest.raises(ValueError, match="final state"):
        E.predict_checked(model, data["traj"][0], data["final"][0, :4])
    with pytest.raises(ValueError, match="shape"):
        E.predict_checked(model, data["traj"][0].reshape(-1), data["final"][0])
    bad = data["traj"][0].copy()
    bad[10, 3] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        E.predict_checked(model, bad, data["final"][0])
    with pytest.raises(ValueError, match="NaN or inf"):
        E.predict_checked(model, data["traj"][0], np.full(5, np.nan))


def test_to_distribution_threshold_and_fallback():
    prob = jnp.zeros((4, 4, 2)).at[1, 2, 0].set(0.3).at[0, 0, 1].set(0.2)
    d = E.to_distribution(prob, jnp.asarray(2.0))
    assert float(d.occupancy.sum()) == 1.0 and float(d.occupancy[1, 2, 0]) == 1.0  # argmax fallback
    prob = prob.at[3, 3, 1].set(0.9).at[2, 2, 1].set(0.6)
    d = E.to_distribution(prob, jnp.asarray(2.0))
    assert float(d.occupancy.sum()) == 2.0 and float(d.occupancy[3, 3, 1]) == float(d.occupancy[2, 2, 1]) == 1
    assert d.occupancy.dtype == jnp.float32 and float(d.total_mass) == 2.0
    assert float(E.to_distribution(prob, jnp.asarray(2.0), threshold=0.1).occupancy.sum()) == 4.0


# ------------------------------------------------------------------------------------------------ metrics


def test_iou_hand_made():
    a = np.zeros((2, 2, 1), np.float32)
    b = np.zeros((2, 2, 1), np.float32)
    a[0, 0, 0] = a[0, 1, 0] = 1  # {(0,0), (0,1)}
    b[0, 1, 0] = b[1, 1, 0] = 1  # {(0,1), (1,1)}: intersection 1, union 3
    assert float(E.iou(a, b)) == pytest.approx(1 / 3)
    assert float(E.iou(a, a)) == 1.0
    assert float(E.iou(np.zeros_like(a), np.zeros_like(a))) == 1.0
    assert float(E.iou(a, 1 - a)) == 0.0


def test_mass_and_com_errors_hand_made():
    assert float(E.mass_rel_error(jnp.asarray(3.0), jnp.asarray(2.0))) == pytest.approx(0.5)
    np.testing.assert_allclose(E.mass_rel_error(jnp.array([1.0, 4.0]), jnp.array([2.0, 4.0])), [0.5, 0.0])
    box = BoxConfig()  # voxel 5 x 3.75 x 3.75 cm
    a = jnp.zeros(box.grid).at[0, 0, 0].set(1.0)
    b = jnp.zeros(box.grid).at[1, 0, 0].set(1.0)
    c = jnp.zeros(box.grid).at[1, 1, 0].set(1.0)
    m = jnp.asarray(5.0)  # kg: the 1e-5 kg eps per voxel moves the COM by ~ 1e-3 cm
    com_error_cm = jax.jit(E.com_error_cm, static_argnums=2)
    err = com_error_cm(MassDistribution(a, m), MassDistribution(b, m), box)
    assert float(err) == pytest.approx(5.0, abs=1e-2)
    err = com_error_cm(MassDistribution(a, m), MassDistribution(c, m), box)
    assert float(err) == pytest.approx(math.hypot(5.0, 3.75), abs=1e-2)


def test_hazard_precision_recall_hand_made():
    pred = np.array([1, 1, 1, 0, 0, 0], bool)
    true = np.array([1, 0, 0, 1, 0, 0], bool)  # TP 1, FP 2, FN 1, TN 2
    precision, recall = E.hazard_precision_recall(pred, true)
    assert float(precision) == pytest.approx(1 / 3) and float(recall) == pytest.approx(1 / 2)
    precision, recall = E.hazard_precision_recall(np.zeros(3, bool), np.zeros(3, bool))
    assert math.isnan(float(precision)) and math.isnan(float(recall))


def test_evaluate_hazard_undefined_without_hazards(evaluation):
    """On the (4, 4, 2) grid the hazard slabs are one voxel column / row wide and no quadrant union fits
    in one, so no box is hazardous: precision and recall are undefined (NaN), not 0 or 1."""
    result = evaluation
    assert result["hazard_true"] == result["hazard_pred"] == 0
    assert math.isnan(result["hazard_precision"]) and math.isnan(result["hazard_recall"])


# ------------------------------------------------------------------------------------------------ checkpoints


def test_checkpoint_round_trip(trained, tmp_path):
    model, _ = trained
    path = tmp_path / "h.npz"
    E.save(path, model)
    assert os.listdir(tmp_path) == ["h.npz"]  # no temporary file left behind
    with np.load(path, allow_pickle=False) as npz:  # plain arrays, no pickle
        assert "__meta__" in npz.files
    loaded = E.load(path, expected_box_config=BOX)
    assert loaded.cfg == model.cfg and loaded.box == model.box and loaded.n_steps == T
    assert loaded.provenance == model.provenance and loaded.provenance["n_boxes"] == 300
    data = synthetic(6, 5)
    a = E.predict_batch(model, jnp.asarray(data["traj"]), jnp.asarray(data["final"]))
    b = E.predict_batch(loaded, jnp.asarray(data["traj"]), jnp.asarray(data["final"]))
    jax.tree.map(np.testing.assert_array_equal, a, b)
    E.save(path, loaded)  # overwriting an existing checkpoint is atomic too
    assert os.listdir(tmp_path) == ["h.npz"]


@pytest.fixture(scope="module")
def checkpoint(trained, tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "h.npz"
    E.save(path, trained[0])
    return path


def test_load_rejects_non_npz(tmp_path):
    path = tmp_path / "h.npz"
    path.write_text("this is not a checkpoint\n")
    with pytest.raises(E.CheckpointError, match="not a boxjax checkpoint"):
        E.load(path)
    np.save(tmp_path / "a.npy", np.zeros(3))
    with pytest.raises(E.CheckpointError, match="not a boxjax checkpoint"):
        E.load(tmp_path / "a.npy")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(E.CheckpointError, match="not a boxjax checkpoint"):
        E.load(tmp_path / "other.npz")
    with pytest.raises(E.CheckpointError, match="no such"):
        E.load(tmp_path / "missing.npz")


@pytest.mark.parametrize("keep", [0.5, 0.99])
def test_load_rejects_truncated_file(checkpoint, tmp_path, keep):
    raw = checkpoint.read_bytes()
    path = tmp_path / "cut.npz"
    path.write_bytes(raw[: int(len(raw) * keep)])
    with pytest.raises(E.CheckpointError, match="corrupt|truncated"):
        E.load(path)


def test_load_rejects_damaged_member(checkpoint, tmp_path):
    raw = bytearray(checkpoint.read_bytes())
    start = len(raw) // 3
    raw[start : start + 64] = bytes(64)  # zero bytes inside a compressed member; the zip directory survives
    path = tmp_path / "damaged.npz"
    path.write_bytes(bytes(raw))
    with pytest.raises(E.CheckpointError):
        E.load(path)


def test_load_rejects_other_grid(checkpoint):
    with pytest.raises(E.CheckpointError, match=r"\(4, 4, 2\).*\(8, 8, 4\)"):
        E.load(checkpoint, expected_box_config=BoxConfig())
    E.load(checkpoint)  # no expectation: fine


def test_load_rejects_wrong_version(checkpoint, tmp_path):
    path = tmp_path / "v99.npz"
    rewrite(checkpoint, path, lambda arrays, meta: meta.update(version=99))
    with pytest.raises(E.CheckpointError, match="version 99"):
        E.load(path)


def test_load_rejects_missing_and_misshapen_arrays(checkpoint, tmp_path):
    path = tmp_path / "missing.npz"
    rewrite(checkpoint, path, lambda arrays, meta: arrays.pop("net.occ.0.b"))
    with pytest.raises(E.CheckpointError, match=r"missing arrays \['net.occ.0.b'\]"):
        E.load(path)
    path = tmp_path / "shape.npz"
    rewrite(checkpoint, path, lambda arrays, meta: arrays.update({"norm.feat_std": np.ones(7, np.float32)}))
    with pytest.raises(E.CheckpointError, match="norm.feat_std.*shape"):
        E.load(path)
    path = tmp_path / "nan.npz"
    rewrite(checkpoint, path, lambda arrays, meta: arrays["net.trunk.0.w"].__setitem__((0, 0), np.nan))
    with pytest.raises(E.CheckpointError, match="NaN"):
        E.load(path)


# ------------------------------------------------------------------------------------------------ decisions


def test_calibrate_thresholds_round_trip_and_estimate(trained, tmp_path):
    model, _ = trained
    held_out = synthetic(8, 100)
    calibrated, info = E.calibrate(model, held_out)
    assert 0.1 <= calibrated.occupancy_threshold <= 0.9
    best = max(info["iou_median_by_threshold"].values())
    assert info["iou_median_by_threshold"][calibrated.occupancy_threshold] == best
    assert calibrated.hazard_threshold == 0.5 and info["hazardous_boxes"] == 0  # none on this grid: kept
    assert E.evaluate(calibrated, held_out)["iou_median"] == pytest.approx(best)
    path = tmp_path / "h.npz"
    E.save(path, dataclasses.replace(calibrated, hazard_threshold=0.7))
    loaded = E.load(path)
    assert loaded.occupancy_threshold == calibrated.occupancy_threshold and loaded.hazard_threshold == 0.7

    out = E.estimate(loaded, held_out["traj"][0], held_out["final"][0])
    assert set(out) == {"prob", "distribution", "members", "total_mass", "hazard_prob", "hazardous"}
    assert len(out["members"]) == loaded.cfg.members
    assert out["hazardous"] == (out["hazard_prob"] > 0.7)
    np.testing.assert_array_equal(
        np.asarray(out["distribution"].occupancy), out["prob"] > loaded.occupancy_threshold
    )
    assert out["total_mass"] > 0 and isinstance(out["hazardous"], bool)
    bad = held_out["traj"][0].copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        E.estimate(loaded, bad, held_out["final"][0])


def test_occupancy_hazard_rule():
    """Hazardous iff no voxel outside one region U1..U4 is more probable than the threshold."""
    box = BoxConfig()
    prob = jnp.full(box.grid, 0.01).at[:, 6:, :].set(0.9)  # U4 (last quarter of the width) only
    assert bool(E.occupancy_hazard(prob, 0.6, box))
    assert bool(E.occupancy_hazard(prob.at[3, 3, 0].set(0.55), 0.6, box))  # below the threshold: still U4
    assert not bool(E.occupancy_hazard(prob.at[3, 3, 0].set(0.65), 0.6, box))  # a confident voxel outside


def test_predict_hazard_thresholds_the_head():
    model = E.EstimatorParams(net={}, norm=None, cfg=CFG, box=BoxConfig(), n_steps=T, hazard_threshold=0.6)
    np.testing.assert_array_equal(
        E.predict_hazard(model, jnp.array([0.1, 0.59, 0.61, 0.99])), [False, False, True, True]
    )


def test_hazard_head_learns_and_calibrates():
    """Boxes with all mass in U1 among quadrant boxes: the head separates them on held-out boxes, and
    calibrate picks a threshold on its probability that reaches the recall target."""
    cfg = dataclasses.replace(CFG, max_epochs=40, patience=40)
    data = synthetic(11, 300, hazardous_share=0.3)
    labels = np.asarray(E.hazard_labels(BOX, jnp.asarray(data["occupancy"])))
    assert 0.2 < labels.mean() < 0.4  # the U1 boxes and only they are hazardous on this grid
    model, history = E.train(jax.random.key(2), data, cfg, box=BOX, progress=False)
    assert history["val_hazard_bce"][history["best_epoch"]] < history["val_hazard_bce"][0] / 5
    held_out = synthetic(12, 200, hazardous_share=0.3)
    model, info = E.calibrate(model, held_out, hazard_recall_target=0.99)
    assert info["hazardous_boxes"] > 40
    m = E.evaluate(model, held_out)
    assert m["hazard_recall"] >= 0.99 and m["hazard_precision"] >= 0.95


def test_ensemble_averages_its_members(tmp_path):
    cfg = dataclasses.replace(CFG, members=2, max_epochs=3)
    data = synthetic(9, 120)
    model, history = E.train(jax.random.key(4), data, cfg, box=BOX, progress=False)
    assert all(leaf.shape[0] == 2 for leaf in jax.tree_util.tree_leaves(model.net))
    assert len(history["member_best_epochs"]) == 2
    one = [
        dataclasses.replace(model, net=jax.tree.map(lambda a, i=i: a[i : i + 1], model.net), cfg=CFG)
        for i in range(2)
    ]
    traj, final = jnp.asarray(data["traj"][:4]), jnp.asarray(data["final"][:4])
    probs, masses, hazards = zip(*(E.predict_batch(m, traj, final) for m in one), strict=True)
    prob, mass, hazard = pred = E.predict_batch(model, traj, final)
    np.testing.assert_allclose(prob, (probs[0] + probs[1]) / 2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(mass, (masses[0] + masses[1]) / 2, rtol=1e-5)
    np.testing.assert_allclose(hazard, (hazards[0] + hazards[1]) / 2, rtol=1e-5, atol=1e-7)
    assert not np.allclose(probs[0], probs[1])  # the members differ
    E.save(tmp_path / "ens.npz", model)
    loaded = E.load(tmp_path / "ens.npz", expected_box_config=BOX)
    assert loaded.cfg.members == 2
    jax.tree.map(np.testing.assert_array_equal, E.predict_batch(loaded, traj, final), pred)


def test_hazard_curve_matches_precision_recall_per_threshold():
    prob = np.array([0.05, 0.2, 0.4, 0.6, 0.8, 0.95])
    true = np.array([False, True, False, True, True, True])
    curve = E.hazard_curve(prob, true, (0.1, 0.5, 0.9, 0.99))
    assert [c[0] for c in curve] == [0.1, 0.5, 0.9, 0.99]
    np.testing.assert_allclose([c[1:] for c in curve][:3], [(0.8, 1.0), (1.0, 0.75), (1.0, 0.25)])
    assert math.isnan(curve[3][1]) and curve[3][2] == 0.0  # nothing flagged: precision undefined
    for t, p, r in curve[:3]:
        ref = E.hazard_precision_recall(jnp.asarray(prob > t), jnp.asarray(true))
        np.testing.assert_allclose((p, r), np.asarray(ref, np.float64), rtol=1e-6)
    assert all(math.isnan(c[2]) for c in E.hazard_curve(prob, np.zeros(6, bool)))  # no hazardous box


def test_choose_hazard_threshold_hand_computed():
    """Highest precision among thresholds reaching the recall target (ties: the lower threshold); when
    none reaches it, the highest recall. NaN precision (nothing flagged) never wins."""
    curve = [(0.1, float("nan"), 0.0), (0.2, 0.9, 0.97), (0.3, 0.8, 0.99), (0.4, 0.8, 1.0), (0.5, 0.6, 1.0)]
    assert E.choose_hazard_threshold(curve, 0.98) == 0.3
    assert E.choose_hazard_threshold(curve, 0.95) == 0.2
    assert E.choose_hazard_threshold(curve[:2], 0.98) == 0.2
