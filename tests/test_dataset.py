"""Exploration datasets: what `generate` returns, that it is seeded, and that files round-trip and are
checked on load."""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest
from npz_util import rewrite

from boxjax import massdist
from boxjax.config import DEFAULT, BoxConfig
from boxjax.estimator import explore
from boxjax.training import dataset

CFG = DEFAULT
N = 8


@pytest.fixture(scope="module")
def data():
    return dataset.generate(jax.random.key(3), N, CFG, p_hazardous=0.5, progress=False)


def test_generate_shapes_and_content(data):
    nx, ny, nz = CFG.box.grid
    assert data["traj"].shape == (N, 45, 11) and data["traj"].dtype == np.float32
    assert data["final"].shape == (N, 5)
    assert data["occupancy"].shape == (N, nx, ny, nz) and data["total_mass"].shape == (N,)
    assert data["hazardous"].dtype == bool and data["clipped"].dtype == bool
    assert np.all(np.isfinite(data["traj"])) and not data["clipped"].any()
    assert set(np.unique(data["occupancy"])) <= {0.0, 1.0}
    lo, hi = CFG.box.mass_range
    assert np.all((data["total_mass"] >= lo) & (data["total_mass"] <= hi))
    # Every box starts at rest at the nominal pose; the applied actions are the exploration's.
    np.testing.assert_allclose(data["traj"][:, 0, :5], np.tile([-0.1, 0.1, 0, 0, 0], (N, 1)), atol=1e-6)
    np.testing.assert_allclose(
        data["traj"][:, :, 5:9], np.broadcast_to(explore.applied_actions(CFG), (N, 45, 4)), atol=1e-6
    )
    # Labels agree with the grids; the balance error is that of the stored states.
    labels = jax.vmap(lambda o, m: massdist.is_hazardous(massdist.MassDistribution(o, m), CFG.box))(
        data["occupancy"], data["total_mass"]
    )
    np.testing.assert_array_equal(np.asarray(labels), data["hazardous"])
    s = np.concatenate([data["traj"][:, :, :5], data["final"][:, None]], axis=1)
    bal = np.abs(s[..., 3] - 0.5 * (s[..., 0] + s[..., 1])).max(axis=1)
    np.testing.assert_allclose(data["max_balance_error"], bal, atol=1e-6)


def test_boxes_are_seeded_and_the_hazard_share_is_controlled():
    a = dataset.sample_boxes(jax.random.key(1), 400, CFG, p_hazardous=0.25)
    b = dataset.sample_boxes(jax.random.key(1), 400, CFG, p_hazardous=0.25)
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    haz = np.asarray(jax.vmap(lambda d: massdist.is_hazardous(d, CFG.box))(a))
    assert 0.20 < haz.mean() < 0.37  # expected 0.25 + 0.75 x 0.042 = 0.28
    all_haz = dataset.sample_boxes(jax.random.key(2), 400, CFG, p_hazardous=1.0)  # same shape: no recompile
    assert np.all(np.asarray(jax.vmap(lambda d: massdist.is_hazardous(d, CFG.box))(all_haz)))
    with pytest.raises(ValueError, match="p_hazardous"):
        dataset.sample_boxes(jax.random.key(0), 4, CFG, p_hazardous=1.5)


def test_generate_is_deterministic_by_key(data):
    again = dataset.generate(jax.random.key(3), N, CFG, p_hazardous=0.5, progress=False, chunk=3)
    for k in dataset.ARRAYS:
        np.testing.assert_array_equal(again[k], data[k], err_msg=k)  # chunking does not change anything


def test_save_load_round_trip(data, tmp_path):
    path = tmp_path / "d.npz"
    dataset.save(path, data, dataset.make_meta(CFG, 3, 0.5, "native", seconds=1.0))
    assert os.listdir(tmp_path) == ["d.npz"]  # no temporary file left behind
    loaded, meta = dataset.load(path, CFG)
    for k in dataset.ARRAYS:
        np.testing.assert_array_equal(loaded[k], data[k])
    assert meta["seed"] == 3 and meta["p_hazardous"] == 0.5 and meta["backend"] == "native"
    assert meta["config"]["box"]["grid"] == list(CFG.box.grid)
    assert np.allclose(meta["exploration_actions"], explore.exploration_actions(CFG))
    with pytest.raises(ValueError, match="lacks"):
        dataset.save(path, data, {"seed": 1})


def test_load_rejects_bad_files(data, tmp_path):
    good = tmp_path / "good.npz"
    dataset.save(good, data, dataset.make_meta(CFG, 3, 0.5, "native"))
    with pytest.raises(dataset.DatasetError, match="no such"):
        dataset.load(tmp_path / "missing.npz")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[:2000])
    with pytest.raises(dataset.DatasetError, match="corrupt|truncated"):
        dataset.load(cut)
    other = CFG.replace(box=BoxConfig(grid=(12, 12, 4)))
    with pytest.raises(dataset.DatasetError, match="box config.*grid"):
        dataset.load(good, other)
    shape = tmp_path / "shape.npz"
    rewrite(good, shape, lambda a, m: a.update(traj=a["traj"][:, :44]))
    with pytest.raises(dataset.DatasetError, match="traj.*shape"):
        dataset.load(shape)
    seq = tmp_path / "seq.npz"
    rewrite(good, seq, lambda a, m: m["exploration_actions"][0].__setitem__(0, 0.2))
    with pytest.raises(dataset.DatasetError, match="exploration sequence"):
        dataset.load(seq)
    nan = tmp_path / "nan.npz"
    rewrite(good, nan, lambda a, m: a["final"].__setitem__((0, 0), np.nan))
    with pytest.raises(dataset.DatasetError, match="NaN"):
        dataset.load(nan)
    ver = tmp_path / "ver.npz"
    rewrite(good, ver, lambda a, m: m.update(version=99))
    with pytest.raises(dataset.DatasetError, match="version 99"):
        dataset.load(ver)


def test_summary(data):
    s = dataset.summary(data)
    assert s["boxes"] == N and s["transitions"] == N * 45
    assert 0 <= s["hazardous_fraction"] <= 1 and s["any_clipped"] is False


@pytest.mark.slow
def test_mjx_backend_gives_the_same_dataset():
    """Both backends simulate the same model, but a slipping box is chaotic and MJX runs in float32 (native
    in float64): even the uniform box drifts apart by ~1 degree and a few mm over the phase. So: identical
    layout and labels, the same first steps, and the same trajectory within a loose band
    (slow: MJX compiles for ~1 minute on a 2-core CPU)."""
    dists = massdist.MassDistribution(
        *(
            np.stack(x)
            for x in zip(massdist.named("uniform", CFG.box), massdist.named("C", CFG.box), strict=True)
        )
    )
    nat = dataset.simulate(CFG, dists, backend="native", progress=False)
    mjx = dataset.simulate(CFG, dists, backend="mjx", progress=False)
    for k in ("occupancy", "total_mass", "hazardous", "clipped"):
        np.testing.assert_array_equal(mjx[k], nat[k])
    # The measured belt speeds differ by up to ~1 mm/s from the first steps on (the contact solvers
    # differ), the poses of the uniform box by far less (an off-centre box, C, separates within steps).
    np.testing.assert_allclose(mjx["traj"][0, :4, :9], nat["traj"][0, :4, :9], atol=1e-4)
    np.testing.assert_allclose(mjx["traj"][:, :4, 9:], nat["traj"][:, :4, 9:], atol=2e-3)
    diff = np.abs(mjx["traj"][0] - nat["traj"][0]).max(axis=0)
    assert diff[:2].max() < 1e-3 and diff[2:4].max() < 0.01 and diff[4] < np.radians(3.0)
