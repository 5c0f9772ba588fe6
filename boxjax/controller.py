"""One controlled episode: explore -> estimate -> refuse if hazardous -> plan and act until done.

The estimator is a slot: "oracle" (the true mass distribution, issue 3) or a trained H (issue 4). Either
way the controller believes in ONE mass distribution after the exploration phase, checks it against the
paper's hazard rule (§4.2) and either refuses, saying why in physical terms, or turns the box with the
physics-prior random-shooting MPC (`planner`).
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from functools import lru_cache
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist, planner, planning, prior, task
from boxjax.config import Config
from boxjax.sim import make_env
from boxjax.sim.episode import EpisodeTrace

PLANNERS = ("paper", "sampling", "simulator")  # simulator: privileged reference, oracle only
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
    # passes it during the fixed exploration is re-centred and refused instead of being lost. None: the
    # paper's fixed sequence whatever happens. Models given to `run_episode` (W, PETS: no refusal) always
    # explore without it. 0.875 (3.5 of 4 cm) was chosen over 0.75 on development boxes (README, "Hazard
    # decisions").
    explore_guard: float | None = 0.875
    planner: str = "sampling"  # "sampling": predictive sampling (default); "paper": one-step Pareto shooting
    sampling: Any = None  # sampling_planner.SamplingOptions (None: its defaults)
    simulator: Any = None  # simulator_planner.SimulatorOptions (None: its defaults)
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
    # A learned residual on the physics prior (`boxjax.residual`): the path of its checkpoint, or None
    # (the prior alone). The "slip" prior with belief="mean" and one prior setting only.
    residual: str | None = None

    def __post_init__(self):
        if self.explore_guard is not None and not 0 < self.explore_guard < 1:
            raise ValueError(
                "explore_guard must be a fraction of the balance limit in (0, 1) or None, got "
                f"{self.explore_guard}"
            )
        if self.planner not in PLANNERS:
            raise ValueError(f"unknown planner {self.planner!r}; choose one of {PLANNERS}")
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


class EpisodeResult(NamedTuple):
    """What a controlled episode did. `summary` is plain data (the CLI's JSON)."""

    summary: dict
    trace: EpisodeTrace
    belief: massdist.MassDistribution | None  # None when the box was lost while exploring
    truth: massdist.MassDistribution
    plan_ms: np.ndarray  # (n_plans,) wall milliseconds per planning call (after the first)


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


def learned_estimator(cfg: Config, weights: str | None = None, hazard_rule: str = "physics"):
    """The learned H as a controller estimator: exploration dict -> {"distribution", "hazardous", ...}.

    weights: an estimator checkpoint (default: the one shipped with boxjax). Raises CheckpointError for a
    missing, corrupt or incompatible file.
    hazard_rule: "physics" (default: refuse when H's ensemble puts the centre of mass and the mass inside
    an outer quarter, or when H's hazard head says so; `boxjax.hazard`), "head" (the hazard head alone, the
    previous rule) or "physics_only". With a physics rule the dict also holds "hazard_explanation" (the
    estimated centre of mass, its uncertainty and the region, in words), "hazard_margin" and
    "hazard_region"; "hazard_prob" stays the head's probability.
    """
    from boxjax import estimator as E
    from boxjax import explore, hazard
    from boxjax.estimator_pipeline import default_estimator

    if hazard_rule not in hazard.HAZARD_RULES:
        choices = ", ".join(hazard.HAZARD_RULES)
        raise ValueError(f"unknown hazard rule {hazard_rule!r}; choose one of {choices}")

    model = default_estimator(cfg) if weights is None else E.load(weights, expected_box_config=cfg.box)
    applied = explore.applied_actions(cfg)

    def estimate(exploration: dict) -> dict:
        if exploration["actions"].shape[0] != applied.shape[0]:
            raise ValueError(
                f"the learned estimator needs the full {applied.shape[0]}-step exploration, got "
                f"{exploration['actions'].shape[0]} steps (did the box leave the belts while exploring?)"
            )
        traj, final = explore.trajectory(exploration["s"], exploration["belt_speed"], applied)
        out = E.estimate(model, np.asarray(traj), np.asarray(final))
        if hazard_rule != "head":
            a = hazard.assess(model, np.asarray(traj), np.asarray(final), hazard_rule)
            keys = ("hazardous", "hazard_margin", "hazard_region", "hazard_explanation")
            out.update({k: a[k] for k in keys}, hazard_rule=hazard_rule)
        return out

    return estimate


@lru_cache(maxsize=8)
def _env(cfg: Config, backend: str):
    """One env per (config, backend), so its jitted pieces compile once, not once per episode."""
    return make_env(cfg, backend)


def _episode_data(rows, actions) -> dict:
    """The episode so far as arrays: s (T+1, 5), belt_speed (T+1, 2), actions (T, 4)."""
    return {
        "s": np.stack([np.asarray(r.s) for r in rows]),
        "belt_speed": np.stack([np.asarray(r.belt_speed) for r in rows]),
        "actions": np.asarray(actions, np.float64).reshape(-1, 4),
    }


@lru_cache(maxsize=8)
def make_planner(cfg: Config, ctrl: ControllerConfig) -> planning.Planner:
    """The planner `ctrl.planner` names, behind the one planner interface (`planning.Planner`); cached
    per (config, options) so its jitted pieces compile once, not once per episode."""
    if ctrl.planner == "simulator":
        from boxjax import simulator_planner

        return simulator_planner.make(cfg, ctrl.simulator or simulator_planner.SimulatorOptions())
    if ctrl.planner == "sampling":
        from boxjax import sampling_planner as sp

        return sp.make(cfg, ctrl.sampling or sp.SamplingOptions())
    return planner.make(
        cfg,
        n_samples=ctrl.n_samples,
        rule=ctrl.rule,
        velocity=ctrl.velocity,
        horizon=ctrl.horizon,
        brake_steps=ctrl.brake_steps,
        speed_cap=ctrl.speed_cap,
        safe_balance=ctrl.safe_balance,
        y_margin=ctrl.y_margin,
    )


def decide(cfg: Config, truth: massdist.MassDistribution, exploration: dict, estimator: Any):
    """The belief after the exploration and the decision on it: (est dict, belief, why). `why` is None
    when the box is to be turned, else the refusal in words (paper §4.2, plus the physics rule's reading
    when the estimator gives one)."""
    est = oracle_estimator(truth, cfg) if estimator == "oracle" else estimator(exploration)
    belief = massdist.validate(est["distribution"], cfg.box)
    why = hazard_explanation(belief, cfg, bool(est["hazardous"]), est.get("hazard_prob"))
    if why is not None and est.get("hazard_explanation"):  # the physics rule's reading (boxjax.hazard)
        why = f"{why} Physics rule: {est['hazard_explanation']}"
    return est, belief, why


def planning_model(
    cfg: Config, ctrl: ControllerConfig, belief: massdist.MassDistribution, force_map=None, est=None
):
    """The model the planners plan with: the physics prior (`ctrl.variant`) on the belief, or with
    `ctrl.belief == "ensemble"` a `planning.Ensemble` of one prior per member of the estimate
    (`est["members"]`, the learned H's ensemble), or with a tuple of `ctrl.prior_params` a
    `planning.Mixture` of one prior per setting on the belief."""
    if ctrl.variant == "paper" and force_map is None:
        from boxjax.calibrate import default_force_map

        force_map = default_force_map(cfg)

    settings = ctrl.prior_settings()

    def on(dist, params):
        return prior.make_prior(massdist.voxel_masses(dist, cfg.box), force_map, cfg.box, cfg.gripper, params)

    if isinstance(settings, tuple):  # the per-box quantities do not depend on the settings: built once
        base = on(belief, settings[0])
        return planning.Mixture(tuple(dataclasses.replace(base, params=p) for p in settings))
    if ctrl.belief == "mean":
        if ctrl.residual is not None:
            from boxjax import residual

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


def first_window(s) -> list:
    """The planner's first state window: the last prior.MIN_WINDOW states of `s` (T+1, 5), the oldest
    repeated when the episode is shorter (no exploration)."""
    window = list(np.asarray(s)[-prior.MIN_WINDOW :])
    while len(window) < prior.MIN_WINDOW:
        window.insert(0, window[0])
    return window


def timed_calls(plan_ms: list) -> list:
    """The planning times worth a median: all but the first call, which compiles (unless it is alone)."""
    return plan_ms[1:] if len(plan_ms) > 1 else plan_ms


def episode_summary(
    cfg: Config,
    truth: massdist.MassDistribution,
    final: dict,
    est: dict,
    belief,
    why: str | None,
    *,
    n_explore: int,
    lost_exploring: bool,
    wall_s: float,
    plan_ms: list,
    adapt_s: float = 0.0,
    adaptations: int = 0,
    estimator: Any = "oracle",
) -> dict:
    """An episode's summary (plain data; the CLI's JSON) from the final state's `State.summary()`."""
    aborted = why is not None
    timed = timed_calls(plan_ms)
    summary = {
        "success": bool(final["success"]) and not aborted,
        "aborted": aborted,
        "abort_reason": why,
        "failed_reason": None if aborted else final["failed_reason"],
        "steps": final["steps"],
        "exploration_steps": n_explore,
        "max_balance_error_m": final["max_balance_error_m"],
        "final_yaw_error_rad": final["final_yaw_error_rad"],
        "wall_s": wall_s,
        "plan_ms_median": statistics.median(timed) if timed else None,
        "truth_hazardous": bool(massdist.is_hazardous(truth, cfg.box)),
        "lost_exploring": lost_exploring,
        "adapt_s": adapt_s,
        "adaptations": adaptations,
    }
    if estimator != "oracle" and belief is not None:
        from boxjax.estimator import com_error_cm

        summary["iou"] = float(massdist.iou(belief.occupancy, truth.occupancy))
        summary["mass_error_kg"] = float(belief.total_mass - truth.total_mass)
        summary["com_error_cm"] = float(com_error_cm(belief, truth, cfg.box))
        if est.get("hazard_prob") is not None:
            summary["hazard_prob"] = float(est["hazard_prob"])
    if not aborted and not final["done"]:
        summary["failed_reason"] = task.REASONS[task.STEP_CAP]
    return summary


def run_episode(
    cfg: Config,
    truth: massdist.MassDistribution,
    key,
    *,
    estimator: Any = "oracle",
    ctrl: ControllerConfig = ControllerConfig(),
    backend: str = "native",
    force_map=None,
    max_steps: int | None = None,
    model: Any = None,
    adapter: Any = None,
) -> EpisodeResult:
    """Explore, estimate, then refuse or rotate the box `truth` (which the controller never sees, except
    through the oracle estimator).

    Args:
      estimator: "oracle", or a callable(exploration dict with s (T+1, 5), belt_speed (T+1, 2),
        actions (T, 4)) -> dict with "distribution" (MassDistribution) and "hazardous" (bool), such as
        `learned_estimator(cfg)`.
      force_map: calibrate.ForceMap for the "paper" prior variant (default: the shipped calibration,
        `calibrate.default_force_map`).
      max_steps: control-step cap (default cfg.task.max_steps), exploration included.
      model: a model for the planners' slot (`planning.Model`, e.g. the black box W), used as it is; the
        estimator and the hazard check are then skipped (a black box has no physical estimate to refuse
        on). None (default): the physics prior built on the estimator's belief.
      adapter: callable(model, data) -> model, online adaptation (paper §4.1): called every
        `ctrl.adapt_every` MPC steps with this episode's data so far (dict s (T+1, 5), belt_speed
        (T+1, 2), actions (T, 4)); its wall time is reported apart (`adapt_s`, `adaptations`).
    """
    if adapter is not None and ctrl.adapt_every < 1:
        raise ValueError("an adapter needs ctrl.adapt_every >= 1 (steps between adaptations)")
    from boxjax import explore

    key_reset, key_plan = jax.random.split(key)
    max_steps = cfg.task.max_steps if max_steps is None else max_steps
    t_start = time.perf_counter()
    env = _env(cfg, backend)
    step = env.step_checked if hasattr(env, "step_checked") else env.step
    state = env.reset(key_reset, truth)
    rows, actions = [state], []

    def act(state, a):
        state = step(state, a)
        rows.append(state)
        actions.append(np.asarray(a, dtype=np.float64))
        return state

    # 1. exploration (paper §2.2): a fixed open-loop sequence, guarded (`explore.Guarded`)
    n_explore = 0
    guard = explore.Guarded(cfg, ctrl.explore_guard if model is None else None) if ctrl.explore else None
    while guard is not None and not bool(state.done):
        a = guard.next(state.s, state.balance_error)
        if a is None:
            break
        state = act(state, a)
    n_explore = len(actions)
    exploration = _episode_data(rows, actions)

    # 2. the belief. A box lost while exploring (it left the belts, tipped or crossed the balance limit
    # within the fixed sequence) is a failure of the episode: there is nothing left to estimate or turn.
    # One the guard caught is refused.
    lost_exploring = bool(state.done)
    est, belief, why = {}, None, None
    if not lost_exploring and guard is not None and guard.tripped:
        why = guard.why()
    elif not lost_exploring and model is None:
        est, belief, why = decide(cfg, truth, exploration, estimator)  # 3. refuse when hazardous
    plan_ms: list[float] = []
    adapt_s, adaptations = 0.0, 0
    if why is None and not lost_exploring:
        # 4. physics-prior MPC
        if model is None:
            model = planning_model(cfg, ctrl, belief, force_map, est)
        mpc = make_planner(cfg, ctrl)
        window = first_window(exploration["s"])

        def observe(state):
            w = prior.check_window(np.asarray(window[-prior.MIN_WINDOW :]))
            sim = state if mpc.privileged else None
            return planning.observation(w, np.asarray(state.belt_speed, np.float32), state.target_yaw, sim)

        plan_state = mpc.init(observe(state))
        if ctrl.observer_gain > 0:
            model = planning.DriftCorrected(model, jnp.zeros(3, jnp.float32))
        mpc_steps = 0
        while not bool(state.done) and len(actions) < max_steps:
            if adapter is not None and mpc_steps > 0 and mpc_steps % ctrl.adapt_every == 0:
                t0 = time.perf_counter()
                model = adapter(model, _episode_data(rows, actions))
                adapt_s += time.perf_counter() - t0
                adaptations += 1
            mpc_steps += 1
            key_plan, key_step = jax.random.split(key_plan)
            obs = observe(state)
            t0 = time.perf_counter()
            a, plan_state, _ = mpc.optimize(key_step, model, obs, plan_state)
            a = np.asarray(a, dtype=np.float64)
            plan_ms.append(1e3 * (time.perf_counter() - t0))
            if not np.all(np.isfinite(a)):  # never send a NaN action to the belts
                raise RuntimeError(f"planner produced a non-finite action {a.tolist()}; stopping")
            if ctrl.observer_gain > 0:
                predicted = planning.predict_first(model, obs.window, obs.belt_speed, a)
            state = act(state, a)
            window.append(np.asarray(state.s))
            if ctrl.observer_gain > 0 and not bool(state.done):
                drift = planning.update_drift(model.drift, predicted, state.s, ctrl.observer_gain)
                model = dataclasses.replace(model, drift=drift)
    wall = time.perf_counter() - t_start

    trace = EpisodeTrace.from_states(rows, actions, cfg.gripper.control_dt, wall)
    summary = episode_summary(
        cfg, truth, state.summary(), est, belief, why, n_explore=n_explore, lost_exploring=lost_exploring,
        wall_s=wall, plan_ms=plan_ms, adapt_s=adapt_s, adaptations=adaptations, estimator=estimator,
    )  # fmt: skip
    timed = timed_calls(plan_ms)
    return EpisodeResult(summary, trace, belief, truth, np.asarray(timed))
