"""The physics prior's static tipping criterion (`prior.stability_margin`) against MuJoCo: boxes placed at
rest on the belts and held still (`sim.statics.hold`). The full measurement: scripts/tip_calibration.py."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist, prior
from boxjax.config import DEFAULT
from boxjax.sim import model, statics

CFG = DEFAULT
TIPPED = math.radians(10.0)


def _prior(dist, margin="exact"):
    masses = massdist.voxel_masses(dist, CFG.box)
    return prior.make_prior(masses, None, CFG.box, CFG.gripper, prior.PriorParams(margin=margin))


def test_a_uniform_box_on_both_belts_stays_up_and_one_on_a_single_belt_edge_tips():
    """Closed form: the uniform box at yaw 0 on belts at -+0.10 m rests on its whole footprint, the centre
    of mass 0.15 m from its long edges, and MuJoCo's contacts span it; moved +4 cm with the belts at their
    stops (-+0.20) it rests on belt 2's 4 cm strip alone, its centre of mass 11 cm outside: it falls."""
    uniform = massdist.named("uniform", CFG.box)
    m = model.box_model(CFG, uniform)
    on_both = np.array([-0.10, 0.10, 0.0, 0.0, 0.0])
    held = statics.hold(CFG, m, on_both, seconds=1.0)
    assert held.peak_tilt < math.radians(0.5)
    np.testing.assert_allclose(held.hull_margin, 0.15, atol=1e-3)
    np.testing.assert_allclose(
        float(prior.stability_margin(_prior(uniform), jnp.asarray(on_both))), 0.15, atol=1e-5
    )
    off = np.array([-0.20, 0.20, 0.0, 0.04, 0.0])
    assert float(prior.stability_margin(_prior(uniform), jnp.asarray(off))) < -0.1
    held = statics.hold(CFG, m, off, seconds=1.0)
    assert held.hull_margin < -0.1 and held.peak_tilt > TIPPED


def test_the_exact_static_criterion_is_mujocos():
    """Adversarial: off-centre (hazardous) random boxes placed at random states near the edge of their
    support. MuJoCo's box-belt contacts span exactly the prior's overlap polygons (the hull margin equals
    the exact one); a box 2-6 mm inside by the exact margin stays up and one 2-20 mm outside falls. The
    "sampled" margin (the default before "refined") over-estimates several of these placements by
    millimetres."""
    rng = np.random.default_rng(0)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    margin = jax.jit(jax.vmap(prior.stability_margin, in_axes=(None, 0)))
    checked, over = {"inside": 0, "outside": 0}, []
    for key in keys:
        dist = massdist.sample_hazardous(key, CFG.box)
        m = model.box_model(CFG, dist)
        s = statics.random_states(rng, 400, CFG)
        exact = np.asarray(margin(_prior(dist), jnp.asarray(s)))
        sampled = np.asarray(margin(_prior(dist, "sampled"), jnp.asarray(s)))
        for kind, sel in (
            ("inside", (exact >= 0.002) & (exact < 0.006)),
            ("outside", (exact <= -0.002) & (exact > -0.02)),
        ):
            for k in np.flatnonzero(sel)[:2]:
                held = statics.hold(CFG, m, s[k], seconds=1.0)
                np.testing.assert_allclose(held.hull_margin, exact[k], atol=1e-4)
                assert (held.peak_tilt > TIPPED) == (kind == "outside"), (kind, exact[k], s[k].tolist())
                checked[kind] += 1
                over.append(sampled[k] - exact[k])
    assert checked == {"inside": 6, "outside": 6}
    assert min(over) > -1e-6 and max(over) > 0.002
