"""Item samplers and the physical hazard decision (boxjax.estimator.hazard; issue 11 item 4)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import control as controller
from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.estimator import hazard
from boxjax.estimator.shipped import default_estimator
from boxjax.training import dataset as ds

BOX = DEFAULT.box
KEYS = jax.random.split(jax.random.key(3), 300)


def _draw(sampler):
    return jax.jit(jax.vmap(functools.partial(sampler, box=BOX)))(KEYS)


def test_items_hazardous_inside_one_region_and_within_the_voxel_budget():
    d = _draw(massdist.sample_items_hazardous)
    occ = np.asarray(d.occupancy) > 0.5
    n = occ.sum(axis=(1, 2, 3))
    assert n.min() >= 1 and n.max() <= 16
    assert n.max() > 8  # several items do occur
    masks = massdist._region_masks(BOX)
    inside_one = np.array([any(not np.any(o & ~m) for m in masks) for o in occ])
    assert inside_one.all()
    region = np.asarray(jax.vmap(massdist.hazard_region, in_axes=(0, None))(d, BOX))
    assert set(region.tolist()) == {0, 1, 2, 3}
    mass = np.asarray(d.total_mass)
    assert mass.min() >= BOX.mass_range[0] and mass.max() <= BOX.mass_range[1]
    assert set(np.unique(np.asarray(d.occupancy)).tolist()) <= {0.0, 1.0}


def test_items_anywhere_respect_the_budget_and_are_not_all_hazardous():
    d = _draw(massdist.sample_items)
    n = np.asarray(d.occupancy).sum(axis=(1, 2, 3))
    assert n.min() >= 1 and n.max() <= 16
    haz = np.asarray(jax.jit(jax.vmap(functools.partial(massdist.is_hazardous, box=BOX)))(d))
    assert 0.05 < haz.mean() < 0.8  # a safe-or-not family
    # Same key, same box (a pure function of the key).
    again = jax.jit(functools.partial(massdist.sample_items, box=BOX))(KEYS[0])
    np.testing.assert_array_equal(np.asarray(again.occupancy), np.asarray(d.occupancy[0]))


def _members(occupancy, k=5, seed=0):
    """k fake member predictions close to an occupancy grid (probabilities 0.01..0.99, small noise)."""
    rng = np.random.default_rng(seed)
    p = 0.01 + 0.98 * np.asarray(occupancy, np.float32)
    p = np.clip(p[None] + 0.01 * rng.standard_normal((k, *p.shape)), 0.001, 0.999).astype(np.float32)
    return jnp.asarray(p), jnp.full((k,), 5.0), jnp.zeros((k,))


@pytest.fixture(scope="module")
def model():
    return default_estimator(DEFAULT)


def test_physics_rule_refuses_mass_in_U4_and_accepts_the_uniform_box(model):
    u4 = np.zeros(BOX.grid, np.float32)
    u4[:, 6:8, :] = 1.0  # the whole U4 slab (y >= +w/4, over the right belt at yaw 0)
    ev = hazard.evidence_from_members(*_members(u4), BOX)
    assert float(ev.com[1]) > BOX.size[1] / 4  # centre of mass inside U4
    d = hazard.decide(model, ev, "physics_only")
    assert d.hazardous and d.physics and not d.head and d.region == 3 and d.margin >= 0
    assert hazard.decide(model, ev, "physics").hazardous
    assert not hazard.decide(model, ev, "head").hazardous  # the head (probability 0 here) alone would not

    uni = hazard.evidence_from_members(*_members(np.ones(BOX.grid)), BOX)
    assert not hazard.decide(model, uni, "physics").hazardous
    assert float(jnp.max(jnp.abs(uni.com))) < 0.005


def test_explanation_names_the_region_and_the_centre_of_mass(model):
    u4 = np.zeros(BOX.grid, np.float32)
    u4[:, 6:8, :] = 1.0
    ev = hazard.evidence_from_members(*_members(u4), BOX)
    text = hazard.explain(model, ev, hazard.decide(model, ev))
    com_cm = 100 * np.asarray(ev.com)
    assert "HAZARDOUS" in text and "U4" in text and "centre of mass" in text
    assert f"{com_cm[1]:+.1f}" in text  # the estimated centre of mass, in cm
    assert "cm inside" in text and "% of the estimated mass" in text


def test_named_boxes_through_exploration_and_H(model):
    """End to end on simulated explorations: D (all mass in U4) refused, uniform and A accepted."""
    dists = [massdist.named(n, BOX) for n in ("D", "uniform", "A")]
    batch = jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a]), *dists)
    data = ds.simulate(DEFAULT, batch, progress=False)
    out = [hazard.assess(model, data["traj"][i], data["final"][i]) for i in range(3)]
    assert [o["hazardous"] for o in out] == [True, False, False]
    assert out[0]["hazard_region"] == "U4" and "U4" in out[0]["hazard_explanation"]
    assert out[1]["hazard_explanation"].startswith("not hazardous")


def test_learned_estimator_rejects_an_unknown_hazard_rule():
    with pytest.raises(ValueError, match="hazard rule"):
        controller.learned_estimator(DEFAULT, hazard_rule="vibes")


def test_learned_estimator_explains_its_refusal_physically():
    from boxjax.estimator import explore
    from boxjax.sim import native

    out = native.rollout(DEFAULT, [massdist.named("D", BOX)], explore.exploration_actions(DEFAULT))
    exploration = {"s": out["s"][0], "belt_speed": out["belt_speed"][0], "actions": out["actions"][0]}
    est = controller.learned_estimator(DEFAULT)(exploration)
    assert est["hazardous"] and est["hazard_rule"] == "physics" and est["hazard_region"] == "U4"
    assert "centre of mass" in est["hazard_explanation"] and "U4" in est["hazard_explanation"]
    head = controller.learned_estimator(DEFAULT, hazard_rule="head")(exploration)
    assert head["hazardous"] and "hazard_explanation" not in head
