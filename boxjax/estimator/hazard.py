"""Physical hazard decisions from H's ensemble (paper §4.2; issue 11 item 4).

The paper's hazard rule (`massdist.is_hazardous`): a box is hazardous when ALL its mass lies inside one outer
quarter U1..U4 (U1 / U2: the first / last quarter of the length, x <= -l/4 / x >= +l/4; U3 / U4: the first /
last quarter of the width, y <= -w/4 / y >= +w/4, i.e. over the left / right belt at yaw 0). H has a learned
hazard head for it, which is a black box and fails off its training distribution (boxes holding one small
item: it refused 22 of 30). This module decides from H's PHYSICAL estimate as well, so that a refusal can be
read in physical terms.

Evidence (`evidence`, pure jnp, one box; `evidence_batch` jitted over boxes). H is an ensemble of K
independently trained members (`estimator.predict` averages them); each member k predicts per-voxel
occupancy probabilities p_k. Reading p_k as the expected occupancy, the member's estimated mass sits in the
voxels in proportion to p_k (the total mass cancels in every ratio below). Per member:
  * its centre of mass c_k = sum_v p_k(v) r_v / sum_v p_k(v) (box frame, m; r_v the voxel centres);
  * its mass fraction inside each region, f_k[r] = sum_{v in U_r} p_k(v) / sum_v p_k(v) (the soft form of the
    paper's rule: the paper's hazardous box has f = 1 in its region);
  * its centre of mass's depth inside each region along the region's axis, d_k[r] = s_r c_k[a_r] - q_r
    (m, positive inside: U1 s = -1, a = x, q = l/4; U2 s = +1, a = x; U3 s = -1, a = y, q = w/4; U4 s = +1).
Across members: the mean and std of c, f and d (the std is H's own uncertainty: where the members disagree).

Decision (`decide`). The physics rule refuses when, for some region r,
  * the centre of mass lies inside U_r with its uncertainty: mean(d[r]) - k_std * std(d[r]) >= min_depth, and
  * the mass sits there, not only its centre: mean(f[r]) - k_std * std(f[r]) >= min_fraction
    (a label-safe box can have its centre of mass inside an outer quarter: 13 % of `massdist.sample`'s
    label-safe boxes have it at least as deep as a single voxel in U2 or U4, so the centre of mass alone
    would abort far too many safe boxes; the mass fraction is what separates them);
and the combined rule ("physics", the default) refuses when either the physics rule or H's hazard head does
(`estimator.predict_hazard`). `hazard_rule="head"` is the head alone (the previous behaviour).
`PhysicsRule` holds the thresholds; `DEFAULT_RULE`'s values and how they were chosen are in its comment.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist
from boxjax.config import BoxConfig
from boxjax.estimator import net as E
from boxjax.estimator.metrics import predict_hazard

HAZARD_RULES = ("physics", "head", "physics_only")
_AXIS = (0, 0, 1, 1)  # region -> box axis its boundary is normal to (x for U1 / U2, y for U3 / U4)
_SIGN = (-1.0, 1.0, -1.0, 1.0)  # region -> which side of the box centre it lies on


@dataclasses.dataclass(frozen=True)
class PhysicsRule:
    """Thresholds of the physics rule (module docstring). Lengths in m."""

    min_depth: float = 0.0  # m, centre of mass at least this far inside the region (lower bound)
    min_fraction: float = 0.9  # share of the estimated mass inside the region (lower bound)
    k_std: float = 1.0  # lower bound = ensemble mean - k_std x ensemble std


# Chosen on a development draw (scratch; 1500 label-safe, 400 gaussian-hazardous and 400 item-hazardous boxes,
# another seed than any evaluation) with the shipped H: the simplest physical statement ("the centre of mass
# is inside the quarter and >= 90 % of the mass is there, both by one ensemble std") whose false aborts stay
# under 2 %: physics alone aborted 1.7 % of the safe boxes and refused 95.8 % / 79.5 % of the gaussian / item
# hazardous ones. No (min_depth, min_fraction, k_std) on a grid did better than the head: at <= 2 % false
# aborts the best physics-only rule refused 97 % / 80.5 %, and physics-or-head 97 % / 82 % (the head alone,
# threshold re-chosen: 97.5 % / 82 %). H's evidence cannot separate these boxes better
# (docs/results/estimator-and-hazards.md), so the default "physics" rule refuses what the head refuses
# and explains it physically.
DEFAULT_RULE = PhysicsRule()


class Evidence(NamedTuple):
    """What H's ensemble says about one box (leading batch axis B under `evidence_batch`).

    com, com_std: (3,) m, mean and std over members of the members' centres of mass (box frame).
    fraction, fraction_std: (4,) mean and std over members of the estimated mass fraction inside U1..U4.
    depth, depth_std: (4,) m, mean and std over members of the centre of mass's depth inside U1..U4 along the
      region's axis (positive inside, negative: that far short of the boundary).
    head: () the hazard head's probability (mean over members, as `estimator.predict`).
    mass: () kg, the predicted total mass (mean over members, floored as `estimator.predict`).
    """

    com: jax.Array
    com_std: jax.Array
    fraction: jax.Array
    fraction_std: jax.Array
    depth: jax.Array
    depth_std: jax.Array
    head: jax.Array
    mass: jax.Array


def member_predictions(model: E.EstimatorParams, traj: jax.Array, final: jax.Array):
    """Each member's prediction for ONE trajectory (T, 11) + final (5,) (pure).

    Returns (prob (K, nx, ny, nz) occupancy probabilities, mass (K,) kg, hazard (K,) head probabilities);
    `estimator.predict` is their mean (the mass floored after averaging).
    """
    x = E._standardise(E.features(traj, final), model.norm)
    logits, mass_std, hazard_logit = jax.vmap(E._forward, in_axes=(0, None, None))(model.net, x, model.cfg)
    prob = jax.nn.sigmoid(logits).reshape((-1, *model.box.grid))
    mass = mass_std * model.norm.mass_std + model.norm.mass_mean
    return prob, mass, jax.nn.sigmoid(hazard_logit)


def evidence_from_members(prob: jax.Array, mass: jax.Array, hazard: jax.Array, box: BoxConfig) -> Evidence:
    """`Evidence` from the members' predictions (prob (K, nx, ny, nz), mass (K,), hazard (K,)); pure."""
    centres = jnp.asarray(massdist.voxel_centres(box))  # (nx, ny, nz, 3) m
    masks = jnp.asarray(massdist._region_masks(box), prob.dtype)  # (4, nx, ny, nz)
    w = prob / jnp.maximum(jnp.sum(prob, axis=(1, 2, 3), keepdims=True), 1e-12)  # (K, ...) mass shares
    com = jnp.einsum("kijl,ijlc->kc", w, centres, precision="highest")  # (K, 3)
    frac = jnp.einsum("kijl,rijl->kr", w, masks, precision="highest")  # (K, 4)
    quarter = jnp.asarray([box.size[a] / 4 for a in _AXIS], prob.dtype)
    depth = jnp.asarray(_SIGN, prob.dtype) * com[:, jnp.asarray(_AXIS)] - quarter  # (K, 4) m
    return Evidence(
        com=jnp.mean(com, 0),
        com_std=jnp.std(com, 0),
        fraction=jnp.mean(frac, 0),
        fraction_std=jnp.std(frac, 0),
        depth=jnp.mean(depth, 0),
        depth_std=jnp.std(depth, 0),
        head=jnp.mean(hazard),
        mass=jnp.maximum(jnp.mean(mass), E.MIN_MASS),
    )


def evidence(model: E.EstimatorParams, traj: jax.Array, final: jax.Array) -> Evidence:
    """`Evidence` of H's ensemble on ONE exploration trajectory (pure; see `evidence_batch`)."""
    return evidence_from_members(*member_predictions(model, traj, final), model.box)


# traj (B, T, 11), final (B, 5) -> Evidence with a leading axis B.
evidence_batch = jax.jit(jax.vmap(evidence, in_axes=(None, 0, 0)))


class Decision(NamedTuple):
    """One box's hazard decision (`decide`); numpy / Python values.

    hazardous: bool, the decision of the chosen rule. physics, head: bool, what each part said.
    region: int 0..3, the region the physics rule judged (the one where its test comes closest to passing).
    margin: float, how far that test is from refusing, in its own units: min(depth lower bound - min_depth
      (m) / 0.01 m, (fraction lower bound - min_fraction) / 0.1); >= 0 means the physics rule refuses.
    """

    hazardous: bool
    physics: bool
    head: bool
    region: int
    margin: float


def physics_margin(ev: Evidence, rule: PhysicsRule = DEFAULT_RULE) -> jax.Array:
    """(..., 4) per region: min((depth_lcb - min_depth) / 1 cm, (fraction_lcb - min_fraction) / 0.1), where
    *_lcb = mean - k_std x std over members. >= 0 in a region: the physics rule refuses. Pure; any batch."""
    depth_lcb = ev.depth - rule.k_std * ev.depth_std
    frac_lcb = ev.fraction - rule.k_std * ev.fraction_std
    return jnp.minimum((depth_lcb - rule.min_depth) / 0.01, (frac_lcb - rule.min_fraction) / 0.1)


def decide_batch(
    model: E.EstimatorParams, ev: Evidence, hazard_rule: str = "physics", rule: PhysicsRule = DEFAULT_RULE
) -> dict:
    """Decisions for a batch of evidence (leading axis B): numpy {"hazardous", "physics", "head" (B,) bool,
    "region" (B,) int, "margin" (B,) float}."""
    _check_rule(hazard_rule)
    margins = np.asarray(physics_margin(ev, rule))
    region = np.argmax(margins, axis=-1)
    margin = np.take_along_axis(margins, region[..., None], axis=-1)[..., 0]
    physics = margin >= 0
    head = np.asarray(predict_hazard(model, np.asarray(ev.head)))
    hazardous = {"physics": physics | head, "head": head, "physics_only": physics}[hazard_rule]
    return {"hazardous": hazardous, "physics": physics, "head": head, "region": region, "margin": margin}


def _check_rule(hazard_rule: str) -> None:
    if hazard_rule not in HAZARD_RULES:
        raise ValueError(f"unknown hazard rule {hazard_rule!r}; choose one of {', '.join(HAZARD_RULES)}")


def decide(
    model: E.EstimatorParams, ev: Evidence, hazard_rule: str = "physics", rule: PhysicsRule = DEFAULT_RULE
) -> Decision:
    """The decision for ONE box's evidence (host side)."""
    out = decide_batch(model, jax.tree.map(lambda a: np.asarray(a)[None], ev), hazard_rule, rule)
    return Decision(
        hazardous=bool(out["hazardous"][0]),
        physics=bool(out["physics"][0]),
        head=bool(out["head"][0]),
        region=int(out["region"][0]),
        margin=float(out["margin"][0]),
    )


def explain(
    model: E.EstimatorParams,
    ev: Evidence,
    d: Decision,
    hazard_rule: str = "physics",
    rule: PhysicsRule = DEFAULT_RULE,
) -> str:
    """One paragraph in physical terms: the estimated centre of mass and its uncertainty, the region judged,
    how deep the centre of mass lies in it and how much of the mass, and what each rule said."""
    box = model.box
    com, std = 100 * np.asarray(ev.com), 100 * np.asarray(ev.com_std)
    r = d.region
    axis = "xy"[_AXIS[r]]
    boundary = 100 * _SIGN[r] * box.size[_AXIS[r]] / 4
    depth, depth_std = 100 * float(ev.depth[r]), 100 * float(ev.depth_std[r])
    frac, frac_std = 100 * float(ev.fraction[r]), 100 * float(ev.fraction_std[r])
    where = (
        f"{depth:.1f} +- {depth_std:.1f} cm inside"
        if depth >= 0
        else f"{-depth:.1f} +- {depth_std:.1f} cm short of"
    )
    verdict = "HAZARDOUS" if d.hazardous else "not hazardous"
    who = {
        (True, True): "the physics rule and the hazard head both refuse",
        (True, False): "the physics rule refuses (the hazard head does not)",
        (False, True): "the hazard head refuses (the physics rule does not)",
        (False, False): "neither the physics rule nor the hazard head refuses",
    }[(d.physics, d.head)]
    return (
        f"{verdict} (rule {hazard_rule!r}: {who}). Estimated centre of mass (x, y, z) = "
        f"({com[0]:+.1f}, {com[1]:+.1f}, {com[2]:+.1f}) cm +- ({std[0]:.1f}, {std[1]:.1f}, {std[2]:.1f}) cm "
        f"(box frame, spread over H's {model.cfg.members} members), {where} the boundary "
        f"{axis} = {boundary:+.1f} cm "
        f"of {massdist._REGION_TEXT[r]}; {frac:.0f} +- {frac_std:.0f} % of the estimated mass lies in "
        f"{massdist.REGION_NAMES[r]} (the physics rule refuses at a centre of mass >= "
        f"{100 * rule.min_depth:.1f} cm inside and >= {100 * rule.min_fraction:.0f} % of the mass, both less "
        f"{rule.k_std:g} std); hazard head probability {float(ev.head):.2f}; estimated mass "
        f"{float(ev.mass):.2f} kg."
    )


def assess(
    model: E.EstimatorParams,
    traj,
    final,
    hazard_rule: str = "physics",
    rule: PhysicsRule = DEFAULT_RULE,
) -> dict:
    """Host side, ONE validated trajectory: {"hazardous" bool, "hazard_prob" float (the head's),
    "hazard_margin" float (`Decision.margin`), "hazard_region" str, "hazard_physics" bool, "hazard_head" bool,
    "hazard_explanation" str, "com" (3,) m, "com_std" (3,) m}. Raises ValueError on bad input (as
    `estimator.predict_checked`)."""
    _check_rule(hazard_rule)
    traj = np.asarray(traj, np.float32)
    final = np.asarray(final, np.float32)
    E._check_traj(traj, final, model.n_steps, batched=False)
    ev = jax.tree.map(lambda a: np.asarray(a)[0], evidence_batch(model, traj[None], final[None]))
    if not all(np.all(np.isfinite(a)) for a in ev):
        raise ValueError("the estimator produced a non-finite prediction (corrupt parameters?)")
    d = decide(model, ev, hazard_rule, rule)
    return {
        "hazardous": d.hazardous,
        "hazard_prob": float(ev.head),
        "hazard_margin": d.margin,
        "hazard_region": massdist.REGION_NAMES[d.region],
        "hazard_physics": d.physics,
        "hazard_head": d.head,
        "hazard_explanation": explain(model, ev, d, hazard_rule, rule),
        "com": np.asarray(ev.com),
        "com_std": np.asarray(ev.com_std),
    }
