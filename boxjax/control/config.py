"""The controller's settings: how it explores, which planner and model it plans with."""

from __future__ import annotations

import dataclasses
from typing import Any

from boxjax import prior
from boxjax.control.monitor import MonitorConfig
from boxjax.control.state_estimate import FilterConfig
from boxjax.estimator import explore
from boxjax.planners import paper as planner
from boxjax.planners import registry
from boxjax.planners.registry import PLANNERS  # noqa: F401 (the built-in planner names, for the CLI)
from boxjax.planners.sampling import SamplingOptions

BELIEFS = ("mean", "ensemble")  # the planner's model: on the estimate, or on each of H's members


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """How the MPC plans (paper §2.3, §4 defaults)."""

    n_samples: int = 50  # actions scored per control step (paper N_a = 50)
    rule: str = "random"  # selection on the Pareto front (planner.RULES); the paper picks at random
    velocity: str = "increment"  # how the action set's velocity columns are read (planner.VELOCITY_MODES)
    horizon: int = 1  # prediction steps per candidate (1 = the paper's one-step prediction)
    variant: str = "slip"  # physics prior (prior.VARIANTS)
    brake_steps: int = 0  # predicted braking steps appended to each candidate's safety check
    speed_cap: float | None = None  # m/s, |belt speed| the planner may command (None: hardware limit)
    safe_balance: float | None = None  # m, for the "lexicographic" rule (None: half the balance limit)
    y_margin: float | None = None  # m, paper planner: keep the box centre inside the carriages' reach
    explore: bool = True  # run the fixed exploration phase first (always needed by a learned estimator)
    # The exploration guard (`explore.Guarded`), a fraction of the balance limit: a box whose balance error
    # passes it during the fixed exploration is stopped and refused instead of being lost. None: the
    # paper's fixed sequence whatever happens. Models given to `run_episode` (W, PETS: no refusal) always
    # explore without it. 0.875 (3.5 of 4 cm) was chosen over 0.75 on development boxes
    # (docs/results/estimator-and-hazards.md).
    explore_guard: float | None = 0.875
    # Control steps the guard looks ahead along the balance error's trend (`explore.Guarded`'s lead). A box
    # whose mass sits at one end swings its centre sideways by ~1 cm per step during the exploration's
    # first turn and passed the 3.5 cm guard within a step of crossing 4 cm. On development boxes
    # (scripts/exploration_guard.py, seeds 301-307, 1,800 boxes of four families) lead 3 left 1 box lost
    # while exploring (the present-value guard: 37; no guard: 63) for 1 of 583 label-safe gaussian boxes
    # refused (0 before; 3 with 1 mm of pose noise); lead 4 refused 6 of them. The trend discounts the
    # sensor's stated pose noise (realistic world: 92/100 turned, as with lead 0; without it 89/100).
    explore_guard_lead: int = 3
    # What the guard does once tripped (`explore.STOPS`): "recentre" the carriages under the box, "hold"
    # them still (the belts stop either way), or "auto" (default): hold when the sensor's pose is noisy or
    # late, re-centre when it is exact (`episode.guard_stop`). Re-centring on a late, noisy estimate chases
    # where the box was and drags it off: realistic world, 1,800 hazardous boxes of four families, 88 lost
    # while exploring re-centring, 61 holding; with the exact pose re-centring loses 3, holding 30
    # (docs/results/faults.md, "The guard's stop, chosen by the sensor").
    explore_guard_stop: str = "auto"
    planner: str = "sampling"  # "sampling": predictive sampling (default); "paper": one-step Pareto shooting
    sampling: Any = None  # planners.sampling.SamplingOptions (None: its defaults)
    simulator: Any = None  # planners.simulator.SimulatorOptions (None: its defaults)
    adapt_every: int = 0  # MPC steps between online adaptations of a learned model (0: none; paper: 20)
    # Gain of the drift observer (planning.DriftCorrected; 0: off): each step the model's prediction of
    # the state just reached is compared with it and the per-step drift corrected by gain x the error.
    observer_gain: float = 0.0
    # What the planner's model is built on: "mean" (default) the estimator's one belief; "ensemble" one
    # physics prior per member of H's ensemble (`estimator.predict_members`) in a `planning.Ensemble`, the
    # sampling planner scoring each candidate over the members (`SamplingOptions.particle_risk`).
    belief: str = "mean"
    # The physics prior's settings (prior.PriorParams: substeps, friction regularisation, carriage
    # response, ...; None: the defaults of `variant`). Its variant must be `variant`. A tuple of several
    # plans over a mixture of priors (`planning.Mixture`: one particle per setting, scored by
    # `SamplingOptions.particle_risk`; the sampling planner and belief="mean" only).
    prior_params: Any = None
    # Robust planning over the belt friction (the world's may not be the model's): the belt friction
    # coefficients the planner plans over, one physics prior per value in a `planning.Mixture`,
    # each candidate scored over them by `SamplingOptions.particle_risk` (mean, mean + k std, worst).
    # None: the prior with the gripper's friction. The sampling planner, belief="mean", one prior setting.
    friction_set: tuple | None = None
    # A learned residual on the physics prior (`boxjax.prior.residual`): the path of its checkpoint, or None
    # (the prior alone). The "slip" prior with belief="mean" and one prior setting only.
    residual: str | None = None
    # The controller's filter over the observed box pose (`state_estimate.FilterConfig`; used when the
    # sensor is imperfect: `boxjax.sim.faults`).
    pose_filter: FilterConfig = FilterConfig()
    # The runtime safety monitor between the planner and the gripper (`boxjax.control.monitor`; on by
    # default, `MonitorConfig(enabled=False)` or `monitor.OFF`: the paper's controller, which has none).
    monitor: MonitorConfig = MonitorConfig()
    # The loop's delay (`World.delay`: the sensor's latency the controller predicts over, plus the drives')
    # beyond which the sampling planner slows down: past `delay_reference` control steps its belt-speed and
    # carriage-step caps shrink by (1 + delay_reference) / (1 + delay) (`for_delay`), so that what the
    # gripper does before the controller can see it stays what it is at delay_reference steps. Why: at 4
    # steps (200 ms) the crossings the monitor missed came from full-speed carriage moves whose drag the
    # prior mispredicts, unseen for 4 steps; at 2 steps it noticed every one. At 4 steps: crossings 6 -> 0,
    # turned 84 -> 75 of 100, the rest at the step cap, balanced (docs/results/faults.md, "Latency: a
    # late loop slows the planner"). None: never (the paper's planner is never slowed).
    delay_reference: int | None = 2

    def __post_init__(self):
        if self.delay_reference is not None and not (
            isinstance(self.delay_reference, int) and self.delay_reference >= 0
        ):
            raise ValueError(
                "delay_reference must be a whole number of control steps >= 0 or None, got "
                f"{self.delay_reference}"
            )
        if self.explore_guard_lead < 0:
            raise ValueError(f"explore_guard_lead must be >= 0 control steps, got {self.explore_guard_lead}")
        if self.explore_guard_stop not in ("auto", *explore.STOPS):
            stops = ("auto", *explore.STOPS)
            raise ValueError(f"explore_guard_stop must be one of {stops}, got {self.explore_guard_stop!r}")
        if self.explore_guard is not None and not 0 < self.explore_guard < 1:
            raise ValueError(
                "explore_guard must be a fraction of the balance limit in (0, 1) or None, got "
                f"{self.explore_guard}"
            )
        if self.planner not in registry.available():
            raise ValueError(f"unknown planner {self.planner!r}; choose one of {registry.available()}")
        if self.rule not in planner.RULES:
            raise ValueError(f"unknown selection rule {self.rule!r}; choose one of {planner.RULES}")
        if self.belief not in BELIEFS:
            raise ValueError(f"unknown belief {self.belief!r}; choose one of {BELIEFS}")
        if self.belief == "ensemble" and self.planner != "sampling":
            raise ValueError("belief='ensemble' plans over H's members with the sampling planner only")
        if self.variant not in prior.VARIANTS:
            raise ValueError(f"unknown prior variant {self.variant!r}; choose one of {prior.VARIANTS}")
        if self.prior_params is not None:
            mixture = isinstance(self.prior_params, tuple)
            for p in self.prior_params if mixture else (self.prior_params,):
                if not isinstance(p, prior.PriorParams):
                    raise ValueError(
                        f"prior_params must be a prior.PriorParams or a tuple of them, got {type(p).__name__}"
                    )
                if p.variant != self.variant:
                    raise ValueError(
                        f"prior_params is of the {p.variant!r} variant but the controller's "
                        f"variant is {self.variant!r}"
                    )
            if mixture and (
                len(self.prior_params) < 2 or self.planner != "sampling" or self.belief != "mean"
            ):
                raise ValueError(
                    "a mixture of priors (prior_params as a tuple) needs at least two settings, the "
                    "sampling planner and belief='mean'"
                )

        if self.friction_set is not None:
            fs = self.friction_set
            if not (
                isinstance(fs, tuple)
                and len(fs) >= 2
                and all(isinstance(m, int | float) and 0 < m < 5 for m in fs)
            ):
                raise ValueError(
                    f"friction_set must be a tuple of two or more friction coefficients in (0, 5), got {fs!r}"
                )
            if self.planner != "sampling" or self.belief != "mean" or isinstance(self.prior_params, tuple):
                raise ValueError(
                    "planning over a friction set needs the sampling planner, belief='mean' and one "
                    "prior setting"
                )
            if self.residual is not None:
                raise ValueError("a friction set and a learned residual cannot be combined")
        if self.residual is not None:
            settings = self.prior_settings()
            if (
                self.variant != "slip"
                or isinstance(settings, tuple)
                or not settings.carry_velocity
                or self.belief != "mean"
                or self.planner == "simulator"
            ):
                raise ValueError(
                    "a residual on the prior needs the 'slip' variant with carry_velocity, one prior "
                    "setting, belief='mean' and a planner that plans with the model (not 'simulator')"
                )

    def prior_settings(self) -> prior.PriorParams | tuple:
        """The PriorParams the planner's prior is built with (a tuple: a mixture of priors)."""
        return self.prior_params if self.prior_params is not None else prior.PriorParams(variant=self.variant)


def for_delay(cfg, ctrl: ControllerConfig, delay: int) -> ControllerConfig:
    """The controller for a loop `delay` control steps late (`ControllerConfig.delay_reference`): the same,
    or, past the reference and with the sampling planner, its belt-speed and carriage-step caps scaled by
    (1 + delay_reference) / (1 + delay)."""
    ref = ctrl.delay_reference
    if ref is None or delay <= ref or ctrl.planner != "sampling":
        return ctrl
    from_opts = ctrl.sampling or SamplingOptions()
    g = cfg.gripper
    scale = (1 + ref) / (1 + delay)
    speed = (
        g.belt_speed_limit if from_opts.speed_cap is None else min(from_opts.speed_cap, g.belt_speed_limit)
    )
    step = (
        g.max_position_step
        if from_opts.position_cap is None
        else min(from_opts.position_cap, g.max_position_step)
    )
    opts = dataclasses.replace(from_opts, speed_cap=scale * speed, position_cap=scale * step)
    return dataclasses.replace(ctrl, sampling=opts)
