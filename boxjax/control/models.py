"""The model in the planner's slot, built from the controller's belief: the physics prior on the estimate,
an ensemble of priors over H's members, a mixture of prior settings, or the prior with a learned residual.
"""

from __future__ import annotations

import dataclasses

from boxjax import massdist, planning, prior
from boxjax.config import Config
from boxjax.control.config import ControllerConfig
from boxjax.prior import residual
from boxjax.prior.force_map import default_force_map


def planning_model(
    cfg: Config, ctrl: ControllerConfig, belief: massdist.MassDistribution, force_map=None, est=None
):
    """The model the planners plan with: the physics prior (`ctrl.variant`) on the belief, or with
    `ctrl.belief == "ensemble"` a `planning.Ensemble` of one prior per member of the estimate
    (`est["members"]`, the learned H's ensemble), with a tuple of `ctrl.prior_params` a
    `planning.Mixture` of one prior per setting on the belief, or with `ctrl.friction_set` a
    `planning.Mixture` of one prior per belt friction coefficient."""
    if ctrl.variant == "paper" and force_map is None:
        force_map = default_force_map(cfg)

    settings = ctrl.prior_settings()

    def on(dist, params):
        return prior.make_prior(massdist.voxel_masses(dist, cfg.box), force_map, cfg.box, cfg.gripper, params)

    if isinstance(settings, tuple):  # the per-box quantities do not depend on the settings: built once
        base = on(belief, settings[0])
        return planning.Mixture(tuple(dataclasses.replace(base, params=p) for p in settings))
    if ctrl.friction_set is not None:  # robust planning: one prior per belt friction, built once
        base = on(belief, settings)
        return planning.Mixture(
            tuple(dataclasses.replace(base, gripper=dataclasses.replace(base.gripper, friction=float(mu)))
                  for mu in ctrl.friction_set)
        )  # fmt: skip
    if ctrl.belief == "mean":
        if ctrl.residual is not None:
            net, rcfg, _ = residual.load_cached(ctrl.residual)
            return residual.Residual(on(belief, settings), net, rcfg)
        return on(belief, settings)
    members = (est or {}).get("members")
    if not members:
        raise ValueError(
            "belief='ensemble' needs an estimator that gives ensemble members (the learned H); "
            "the oracle's one true distribution has none"
        )
    return planning.Ensemble(planning.stack([on(massdist.validate(m, cfg.box), settings) for m in members]))


def refuse_own_prior_without_belief(ctrl: ControllerConfig, model) -> None:
    """Raise ValueError when the monitor's own prior (`MonitorConfig.prior_params`) is asked for beside
    a model given as it is (a black box in the planner's slot): such a model has no belief to put it on."""
    if model is not None and ctrl.monitor.enabled and ctrl.monitor.prior_params is not None:
        raise ValueError(
            "the monitor's own prior (MonitorConfig.prior_params) needs a belief; a model given as it is "
            "(a black box) has none"
        )


def monitor_model(cfg: Config, ctrl: ControllerConfig, belief, model, force_map=None, est=None):
    """The model the runtime safety monitor predicts with: `model` (the planner's; None where the caller
    keeps it), or with `ctrl.monitor.prior_params` a physics prior of those settings on the same belief."""
    params = ctrl.monitor.prior_params
    if params is None:
        return model
    if belief is None:
        raise ValueError(
            "the monitor's own prior (MonitorConfig.prior_params) needs a belief; a black box has none"
        )
    own = dataclasses.replace(ctrl, prior_params=params, friction_set=None, residual=None)
    return planning_model(cfg, own, belief, force_map, est)
