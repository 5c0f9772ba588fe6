"""The estimator slot of the controller: what it believes about the box after the exploration, and the
refusal when that belief is hazardous (paper §4.2).

An estimator is "oracle" (the true distribution) or a callable(exploration dict) -> {"distribution",
"hazardous", ...} such as `learned_estimator(cfg)`; `decide` turns either into (estimate, belief, why).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from boxjax import massdist
from boxjax.config import Config
from boxjax.estimator import explore, hazard, moments
from boxjax.estimator.io import load
from boxjax.estimator.metrics import estimate as estimate_with
from boxjax.estimator.shipped import (
    default_estimator,
    default_moments,
    imperfect_sensor,
    moments_for,
    sensor_estimator,
)

_predict_moments = jax.jit(moments.predict)


def hazard_explanation(
    belief: massdist.MassDistribution,
    cfg: Config,
    hazardous: bool | None = None,
    probability: float | None = None,
) -> str | None:
    """None if the belief is safe to turn; else why not, in terms a person understands.

    `hazardous` overrides the paper's rule on `belief` (a learned estimator's calibrated decision), and
    `probability` is that estimator's hazard probability, quoted in the message when given.
    """
    if hazardous is None:
        hazardous = bool(massdist.is_hazardous(belief, cfg.box))
    if not hazardous:
        return None
    judged = "" if probability is None else f", estimated probability {probability:.2f}"
    return (
        f"refusing to rotate: the box is hazardous{judged} (paper §4.2: all mass in one outer quarter of "
        "the box, over one belt or one end). Estimate: " + massdist.describe(belief, cfg.box)
    )


def oracle_estimator(truth: massdist.MassDistribution, cfg: Config) -> dict:
    """The true distribution (issue 3's estimator slot)."""
    return {"distribution": truth, "hazardous": bool(massdist.is_hazardous(truth, cfg.box))}


def learned_estimator(
    cfg: Config, weights: str | None = None, hazard_rule: str = "physics", with_moments: bool | None = None
):
    """The learned H as a controller estimator: exploration dict -> {"distribution", "hazardous", ...}.

    weights: an estimator checkpoint, used for every exploration; None (default): the two shipped with
    boxjax, chosen per exploration by the sensor it was seen through (its "sensor", `World.for_estimator`):
    the H trained on exact explorations for a perfect sensor (or one with latency alone: the exploration
    is aligned for it), the H trained through randomised sensors when the pose is noisy or frames drop
    (`shipped.sensor_estimator`; trained on exact states, an H reads 3 mm of noise as a hazardous box:
    docs/results/faults.md). Raises CheckpointError for a missing, corrupt or incompatible file.
    hazard_rule: "physics" (default: refuse when H's ensemble puts the centre of mass and the mass inside
    an outer quarter, or when H's hazard head says so; `boxjax.estimator.hazard`), "head" (the hazard head
    alone, the previous rule) or "physics_only". With a physics rule the dict also holds
    "hazard_explanation" (the estimated centre of mass, its uncertainty and the region, in words),
    "hazard_margin" and "hazard_region"; "hazard_prob" stays the head's probability. "estimator_weights"
    names the H that read the exploration ("shipped", "shipped_sensor" or the path given).
    with_moments: also read the box's physical moments with their calibrated std (the shipped
    `boxjax.estimator.moments` model; "moments" {quantity: {mean, std}} and "moments_text"), for a perfect
    sensor only (the model was trained on exact explorations). None (default): when the shipped model fits
    `cfg` (else the dict says why not in "moments_skipped"); True: required (MomentsError if it does not
    fit); False: never.
    """
    if hazard_rule not in hazard.HAZARD_RULES:
        choices = ", ".join(hazard.HAZARD_RULES)
        raise ValueError(f"unknown hazard rule {hazard_rule!r}; choose one of {choices}")

    model = default_estimator(cfg) if weights is None else load(weights, expected_box_config=cfg.box)
    moments_model, moments_skipped = None, None
    if with_moments:
        moments_model = default_moments(cfg)
    elif with_moments is None:
        moments_model, moments_skipped = moments_for(cfg)
    for_sensor = sensor_estimator(cfg) if weights is None else model  # loaded now: fails before any work
    applied = explore.applied_actions(cfg)

    def estimate(exploration: dict) -> dict:
        sensor = exploration.get("sensor")  # the sensor's specification (`World.for_estimator`)
        noisy = imperfect_sensor(sensor)
        h = for_sensor if noisy else model
        used = str(weights) if weights is not None else ("shipped_sensor" if noisy else "shipped")
        if exploration["actions"].shape[0] != applied.shape[0]:
            raise ValueError(
                f"the learned estimator needs the full {applied.shape[0]}-step exploration, got "
                f"{exploration['actions'].shape[0]} steps (did the box leave the belts while exploring?)"
            )
        traj, final = explore.trajectory(exploration["s"], exploration["belt_speed"], applied)
        out = estimate_with(h, np.asarray(traj), np.asarray(final))
        if moments_model is not None and not noisy:  # trained on exact explorations: not for a noisy sensor
            m = jax.tree.map(np.asarray, _predict_moments(moments_model, traj, final))
            out.update(moments=moments.as_dict(m), moments_text=moments.describe(m))
        elif moments_skipped is not None or moments_model is not None:
            out["moments_skipped"] = moments_skipped or (
                "the moments estimator was trained on exact explorations, not for this noisy sensor"
            )
        if hazard_rule != "head":
            a = hazard.assess(h, np.asarray(traj), np.asarray(final), hazard_rule)
            keys = ("hazardous", "hazard_margin", "hazard_region", "hazard_explanation")
            out.update({k: a[k] for k in keys}, hazard_rule=hazard_rule)
        return {**out, "estimator_weights": used}

    return estimate


def decide(cfg: Config, truth: massdist.MassDistribution, exploration: dict, estimator: Any):
    """The belief after the exploration and the decision on it: (est dict, belief, why). `why` is None
    when the box is to be turned, else the refusal in words (paper §4.2, plus the physics rule's reading
    when the estimator gives one)."""
    est = oracle_estimator(truth, cfg) if estimator == "oracle" else estimator(exploration)
    belief = massdist.validate(est["distribution"], cfg.box)
    why = hazard_explanation(belief, cfg, bool(est["hazardous"]), est.get("hazard_prob"))
    if why is not None and est.get(
        "hazard_explanation"
    ):  # the physics rule's reading (boxjax.estimator.hazard)
        why = f"{why} Physics rule: {est['hazard_explanation']}"
    if why is not None and est.get("moments_text"):
        why = f"{why} Moments read from the exploration: {est['moments_text']}."
    return est, belief, why
