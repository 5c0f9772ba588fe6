"""Box families beyond the gaussian mixtures; the moments estimator (boxjax.estimator.moments, issue 30)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.estimator import moments as M
from boxjax.training import moments as TM
from boxjax.training import wide

BOX = DEFAULT.box
KEYS = jax.random.split(jax.random.key(11), 200)


def _draw(family, hazardous):
    return jax.jit(jax.vmap(functools.partial(massdist.sampler(family, hazardous), box=BOX)))(KEYS)


@pytest.mark.parametrize("family", massdist.FAMILIES)
def test_every_family_hazardous_form_is_hazardous_and_free_form_mixes(family):
    haz = _draw(family, True)
    labels = np.asarray(jax.vmap(lambda d: massdist.is_hazardous(d, BOX))(haz))
    assert labels.all()
    free = _draw(family, False)
    occ = np.asarray(free.occupancy)
    assert occ.sum(axis=(1, 2, 3)).min() >= 1  # never empty
    assert set(np.unique(occ)) <= {0.0, 1.0}
    mass = np.asarray(free.total_mass)
    assert mass.min() >= BOX.mass_range[0] and mass.max() <= BOX.mass_range[1]
    labels = np.asarray(jax.vmap(lambda d: massdist.is_hazardous(d, BOX))(free))
    assert 0 < labels.mean() < 0.5  # the free forms hold both safe and hazardous boxes


def test_unknown_family_is_refused_by_name():
    with pytest.raises(ValueError, match="unknown box family 'rods'"):
        massdist.sampler("rods", True)


def test_wide_mixture_holds_the_shares_and_never_the_held_out_family():
    d, source = wide.sample_wide(jax.random.key(0), 400)
    counts = np.bincount(source, minlength=len(wide.WIDE_SHARES))
    np.testing.assert_array_equal(counts, [160, 60, 60, 60, 60])
    assert wide.HELD_OUT not in {f for f, *_ in wide.WIDE_SHARES}
    assert np.asarray(d.occupancy).shape == (400, *BOX.grid)


def test_true_moments_of_a_full_box_are_the_solid_cuboid_closed_form():
    full = massdist.named("uniform", BOX)
    q = np.asarray(M.true_moments(full, BOX))
    l, w, h = BOX.size
    mass = 5.0 + BOX.voxel_eps * np.prod(BOX.grid)
    np.testing.assert_allclose(q[0], mass, rtol=1e-6)
    np.testing.assert_allclose(q[1:4], 0.0, atol=1e-7)
    # A solid uniform cuboid: spread along an axis = side / sqrt(12); I_zz / M = (l^2 + w^2) / 12.
    np.testing.assert_allclose(q[4:7], np.array([l, w, h]) / np.sqrt(12), rtol=1e-5)
    np.testing.assert_allclose(q[7], np.sqrt((l * l + w * w) / 12), rtol=1e-5)


def test_gyration_is_the_planar_sum_of_the_spreads_and_matches_the_inertia():
    d = _draw("items", False)
    q = np.asarray(jax.vmap(lambda x: M.true_moments(x, BOX))(d))
    np.testing.assert_allclose(q[:, 7] ** 2, q[:, 4] ** 2 + q[:, 5] ** 2, rtol=1e-4)
    mp = jax.vmap(lambda x: massdist.mass_properties(x, BOX))(d)
    np.testing.assert_allclose(q[:, 7] ** 2 * q[:, 0], np.asarray(mp.inertia)[:, 2, 2], rtol=1e-4)


def test_coverage_and_calibration_of_gaussian_draws():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(20000, M.N_Q))
    est = M.Moments(np.zeros_like(truth), np.full_like(truth, 1.0))
    cov = M.coverage(est, truth)
    for level, row in cov.items():
        for v in row.values():
            assert abs(v - float(level)) < 0.015
    # A std stated twice too wide is scaled by one half.
    wide_est = M.Moments(est.mean, 2 * est.std)
    np.testing.assert_allclose(M.calibration_scale(wide_est, truth), 0.5, rtol=0.03)
    # Heavy tails: the factor is set by the 95 % level, so both levels cover at least their share.
    t = rng.standard_t(3, size=(20000, M.N_Q))
    scale = M.calibration_scale(est, t)
    cov = M.coverage(M.Moments(est.mean, est.std * scale), t)
    assert min(cov["0.683"].values()) >= 0.68 and min(cov["0.95"].values()) >= 0.949


def test_mixture_adds_the_members_disagreement():
    members = M.Moments(jnp.array([[0.0] * M.N_Q, [2.0] * M.N_Q]), jnp.ones((2, M.N_Q)))
    m = M.mixture(members)
    np.testing.assert_allclose(m.mean, 1.0)
    np.testing.assert_allclose(m.std, np.sqrt(1.0 + 1.0))


def test_hazard_posterior_follows_the_library_weights():
    safe = massdist.named("A", BOX)
    haz = massdist.named("D", BOX)  # all mass in U4
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), safe, haz)
    lib = M.make_library(both, BOX)
    np.testing.assert_array_equal(np.asarray(lib.region), [-1, 3])
    sharp = jnp.full(M.N_Q, 1e-3)
    p = M.hazard_posterior(M.Moments(lib.q[1], sharp), lib)
    assert float(p.hazardous) > 0.999 and int(np.argmax(p.region)) == 3
    p = M.hazard_posterior(M.Moments(lib.q[0], sharp), lib)
    assert float(p.hazardous) < 1e-3
    # An estimate that resolves nothing leaves the library's prior: one box in two.
    p = M.hazard_posterior(M.Moments(lib.q[0], jnp.full(M.N_Q, 1e3)), lib)
    np.testing.assert_allclose(float(p.hazardous), 0.5, atol=1e-3)
    np.testing.assert_allclose(float(p.n_eff), 2.0, atol=1e-3)
    assert "U4" in M.explain(
        M.Moments(lib.q[1], sharp), M.hazard_posterior(M.Moments(lib.q[1], sharp), lib), BOX
    )


def _fake_data(n: int, seed: int = 0) -> dict:
    """Explorations whose features carry the box's centre of mass (a stand-in for the simulation)."""
    d, _ = wide.sample_wide(jax.random.key(seed), n)
    q = M.true_moments_batch(d, BOX)
    rng = np.random.default_rng(seed)
    traj = rng.normal(size=(n, 45, 11)).astype(np.float32) * 0.01
    traj[:, :, 2:5] += q[:, None, 1:4]  # the pose columns hold the centre of mass
    final = traj[:, -1, :5]
    return {
        "traj": traj,
        "final": final,
        "occupancy": np.asarray(d.occupancy),
        "total_mass": np.asarray(d.total_mass),
    }


@pytest.mark.slow  # 12 s compiling the training step; loading the shipped file is tested below
def test_training_learns_what_the_features_show_and_round_trips(tmp_path):
    data = _fake_data(400)
    model, report = TM.train(
        jax.random.key(0), data, BOX, members=2, hidden=(16,), epochs=4, log=lambda s: None
    )
    nll = [np.mean(h["val_nll"]) for h in report["history"]]
    assert nll[-1] < nll[0]
    path = M.save(tmp_path / "m.npz", model, {"note": "test"})
    again, meta = M.load(path, BOX)
    assert meta["note"] == "test"
    test = _fake_data(50, seed=1)
    a = M.predict_batch(model, jnp.asarray(test["traj"]), jnp.asarray(test["final"]))
    b = M.predict_batch(again, jnp.asarray(test["traj"]), jnp.asarray(test["final"]))
    np.testing.assert_array_equal(np.asarray(a.mean), np.asarray(b.mean))
    assert np.all(np.asarray(a.std) > 0)


def test_load_refuses_another_file_by_name(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(M.MomentsError, match="not a boxjax moments checkpoint"):
        M.load(bad)
    with pytest.raises(M.MomentsError):
        M.load(tmp_path / "missing.npz")


def test_a_config_the_shipped_moments_do_not_fit_runs_without_them():
    from boxjax.config import BoxConfig
    from boxjax.estimator import shipped

    other = DEFAULT.replace(box=BoxConfig(size=(0.5, 0.3, 0.15)))
    model, why = shipped.moments_for(other)
    assert model is None and "0.5" in why and "train-moments" in why
    assert shipped.moments_for(DEFAULT)[0] is not None
