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
from functools import lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning, prior, task
from boxjax.config import Config
from boxjax.control import monitor
from boxjax.control.config import ControllerConfig, for_delay
from boxjax.control.models import monitor_model, planning_model, refuse_own_prior_without_belief
from boxjax.control.monitor import Monitor
from boxjax.control.monitor import crossing as monitor_crossing
from boxjax.control.world import World
from boxjax.estimator import com_error_cm, explore, moments
from boxjax.estimator.belief import decide
from boxjax.planners import simulator
from boxjax.planners.registry import make_planner
from boxjax.sim import make_env
from boxjax.sim.episode import EpisodeTrace
from boxjax.sim.faults import NONE as NO_FAULTS
from boxjax.sim.faults import Faults


class EpisodeResult(NamedTuple):
    """What a controlled episode did. `summary` is plain data (the CLI's JSON)."""

    summary: dict
    trace: EpisodeTrace
    belief: massdist.MassDistribution | None  # None when the box was lost while exploring
    truth: massdist.MassDistribution
    plan_ms: np.ndarray  # (n_plans,) wall milliseconds per planning call (after the first)


@lru_cache(maxsize=8)
def env_for(cfg: Config, backend: str):
    """One env per (config, backend), so its jitted pieces compile once, not once per episode."""
    return make_env(cfg, backend)


def _controller_data(seen, sent) -> dict:
    """The episode so far as the controller knows it: the states and belt speeds it saw, s (T+1, 5) and
    belt_speed (T+1, 2), and the actions it sent, (T, 4)."""
    return {
        "s": np.stack([np.asarray(s) for s, _ in seen]),
        "belt_speed": np.stack([np.asarray(b) for _, b in seen]),
        "actions": np.asarray(sent, np.float64).reshape(-1, 4),
    }


_compensate = jax.jit(planning.compensate)


def in_flight(sent: list, n: int) -> np.ndarray:
    """(n, 4) float32: the last n actions sent (zeros before the first: the drives start at rest)."""
    last = [np.zeros(4)] * max(0, n - len(sent)) + list(sent[-n:] if n else [])
    return np.asarray(last, np.float32).reshape(n, 4)


def first_window(s) -> list:
    """The planner's first state window: the last planning.MIN_WINDOW states of `s` (T+1, 5), the oldest
    repeated when the episode is shorter (no exploration)."""
    window = list(np.asarray(s)[-planning.MIN_WINDOW :])
    while len(window) < planning.MIN_WINDOW:
        window.insert(0, window[0])
    return window


def guarded_exploration(cfg: Config, ctrl: ControllerConfig, world: World, fraction: float | None):
    """The exploration of one box behind its guard (`explore.Guarded`: trips at `fraction` of the balance
    limit, None: never; looks `ctrl.explore_guard_lead` steps ahead, discounting the sensor's stated noise,
    stops as `guard_stop` says and rests for the world's delay at the end), or None when the controller
    does not explore. Every path that explores (`run_episode`, the batched episodes, their replay) builds
    it here."""
    if not ctrl.explore:
        return None
    return explore.Guarded(
        cfg,
        fraction,
        settle=world.exploration_delay,
        lead=ctrl.explore_guard_lead,
        noise=world.stated_noise_m,
        stop=guard_stop(ctrl, world.faults),
    )


def guard_stop(ctrl: ControllerConfig, faults: Faults) -> str:
    """What the exploration guard does once tripped (`explore.STOPS`): `ctrl.explore_guard_stop`, its
    "auto" resolved by the sensor: a hold when the pose the guard judges is noisy or late (pose noise or
    latency), re-centring when it is exact (a dropped frame now and then, or a plant mismatch alone, leave
    it exact). Re-centring is feedback on that pose: through 2 steps of latency a full step towards the
    seen centre is unstable (e_k+1 = e_k - e_k-2 grows by 1.15 a step), and on a noisy pose it chases the
    noise; measured on hazardous boxes (docs/results/faults.md, "The guard's stop, chosen by the sensor")."""
    if ctrl.explore_guard_stop != "auto":
        return ctrl.explore_guard_stop
    noisy_or_late = faults.obs_noise_mm or faults.obs_noise_deg or faults.obs_latency
    return "hold" if noisy_or_late else "recentre"


# m: an exact stability margin under which a box counts as a near tip in an evaluation's summary. At rest in
# MuJoCo no box 2 mm or more inside by the exact margin tipped (0 of 1,083 placements; 29 of 121 between 0
# and 2 mm did: benchmarks/results_tip_calibration.json).
NEAR_TIP_M = 0.002


@partial(jax.jit, static_argnames=("box", "gripper"))
def _exact_margins(masses, states, box, gripper):
    model = prior.make_prior(masses, None, box, gripper, prior.PriorParams(margin="exact"))
    return jax.vmap(model.stability_margin)(states)


def true_stability_margins(cfg: Config, truth: massdist.MassDistribution, states, shift=None) -> np.ndarray:
    """(T+1,) m: the exact stability margin (`prior.stability_margin` with margin="exact") of the TRUE box
    at each of its TRUE planar states `states` (T+1, 5): how far its centre of mass lay inside the support
    of both belts, the static tipping criterion MuJoCo follows to 2 mm (tests/test_statics.py). What a
    comparison of settings can read where tips themselves are too rare to count. `shift`: the episode's
    mass shift (`sim.faults.MassShift`), once applied the states after its step are those of the slid
    masses. Padded to a multiple of 128 states (one compile for most episodes)."""
    s = np.asarray(states, np.float32).reshape(-1, 5)
    n = len(s)
    padded = jnp.asarray(np.concatenate([s, np.repeat(s[-1:], -n % 128, axis=0)]))

    def margins(masses):
        masses = jnp.asarray(masses, jnp.float32)
        return np.array(_exact_margins(masses, padded, cfg.box, cfg.gripper))[:n]

    out = margins(massdist.voxel_masses(truth, cfg.box))
    if shift is not None and shift.done:  # applied before the action of step `shift.step`
        out[shift.step + 1 :] = margins(shift.masses)[shift.step + 1 :]
    return out


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
    monitor: Monitor | None = None,
    guard_steps=(),
    balance_errors=None,
    states=None,
    mass_shift=None,
) -> dict:
    """An episode's summary (plain data; the CLI's JSON) from the final state's `State.summary()`.

    With the runtime safety monitor (`monitor`): an episode the monitor ended stopped, or that reached
    the step cap while stopped, with the box still balanced and on the belts, is `safe_stop` (its
    reason in `safe_stop_reason`), neither a success nor a failure. `crossing` says whether the TRUE
    balance error (`balance_errors`, (T+1,)) ever passed the limit, `unnoticed_crossing` whether that
    happened with no stop issued (the monitor's, or the exploration guard's at `guard_steps`).
    `min_stability_margin_m` is the smallest exact stability margin of the true box along its TRUE states
    `states` (T+1, 5) (`true_stability_margins`, after `mass_shift` if one slid; None without states),
    `turn_min_stability_margin_m` the same over the states after the exploration's `n_explore` steps
    (None when the box was refused or never turned)."""
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
        summary["iou"] = float(massdist.iou(belief.occupancy, truth.occupancy))
        summary["mass_error_kg"] = float(belief.total_mass - truth.total_mass)
        summary["com_error_cm"] = float(com_error_cm(belief, truth, cfg.box))
        if est.get("hazard_prob") is not None:
            summary["hazard_prob"] = float(est["hazard_prob"])
        if est.get("estimator_weights") is not None:  # which H read the exploration (`learned_estimator`)
            summary["estimator_weights"] = est["estimator_weights"]
        if est.get("moments") is not None:  # and the moments, with each one's error in stated stds
            truth_q = np.asarray(moments.true_moments(truth, cfg.box), np.float64)
            summary["moments"] = est["moments"]
            summary["moments_z"] = {
                q: (float(truth_q[i]) - v["mean"]) / v["std"]
                for i, (q, v) in enumerate(est["moments"].items())
            }
    safe_stop = None
    if monitor is not None and monitor.stopped and not final["success"] and not aborted:
        failed = final["done"]  # the true world ended the episode: a failure the stop did not prevent
        safe_stop = None if failed else monitor.reason
    if not aborted and not final["done"] and safe_stop is None:
        summary["failed_reason"] = task.REASONS[task.STEP_CAP]
    summary["safe_stop"] = safe_stop is not None
    summary["safe_stop_reason"] = safe_stop
    if monitor is not None:
        summary.update(monitor.record())
    crossed, unnoticed = (False, False)
    if balance_errors is not None:
        stopping = () if monitor is None else monitor.stopping_steps
        crossed, unnoticed = monitor_crossing(balance_errors, cfg.task.balance_limit, stopping, guard_steps)
    summary["crossing"] = crossed
    summary["unnoticed_crossing"] = unnoticed
    margins = None if states is None else true_stability_margins(cfg, truth, states, mass_shift)
    summary["min_stability_margin_m"] = None if margins is None else float(np.min(margins))
    # The same over the turn alone (the states its actions reached; None when the box was refused): the
    # exploration is the same whatever the planner, so comparisons of settings read this one.
    turned = margins is not None and not aborted and len(margins) > n_explore + 1
    summary["turn_min_stability_margin_m"] = float(np.min(margins[n_explore + 1 :])) if turned else None
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
    faults: Faults = NO_FAULTS,
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
      faults: how the simulated world differs from the controller's (`boxjax.sim.faults.Faults`: pose
        noise, latencies, dropped frames, friction and servo mismatch, a mass shift), drawn from `key`.
        The controller then sees the pose through its filter (`ctrl.pose_filter`), never the simulator's
        state; the episode's outcome is the true world's. Native backend only.
    """
    refuse_own_prior_without_belief(ctrl, model)
    if adapter is not None and ctrl.adapt_every < 1:
        raise ValueError("an adapter needs ctrl.adapt_every >= 1 (steps between adaptations)")
    if faults.any and backend != "native":
        raise ValueError(f"faults are simulated on the native backend only, not {backend!r}")
    key_reset, key_plan = jax.random.split(key)
    max_steps = cfg.task.max_steps if max_steps is None else max_steps
    t_start = time.perf_counter()
    env = env_for(cfg, backend)
    step = env.step
    state = env.reset(key_reset, truth)
    world = World(cfg, faults, ctrl.pose_filter, key, truth)
    world.prepare(state.model)
    rows, actions = [state], []  # the true world: states and the actions the gripper applied
    seen, sent = [world.observe(state.s, state.belt_speed)], []  # the controller's view: (s, belt_speed)

    def act(state, a):
        a = np.asarray(a, dtype=np.float64)
        world.before_step(len(actions), state.model, env.ids.box_body)
        applied = world.send(a)
        state = step(state, applied)
        rows.append(state)
        actions.append(np.asarray(applied, dtype=np.float64))
        sent.append(a)
        seen.append(world.observe(state.s, state.belt_speed))
        return state

    # 1. exploration (paper §2.2): a fixed open-loop sequence, guarded (`explore.Guarded`)
    n_explore = 0
    guard = guarded_exploration(cfg, ctrl, world, ctrl.explore_guard if model is None else None)
    guard_steps: list[int] = []  # control steps of the guard's re-centring (a stop, for `crossing`)
    while guard is not None and not bool(state.done):
        s_seen = seen[-1][0]  # with a perfect sensor the true state, and its balance error as the env has it
        a = guard.next(s_seen, geometry.balance_error(s_seen) if world.active else state.balance_error)
        if a is None:
            break
        if guard.tripped:
            guard_steps.append(len(actions))
        state = act(state, a)
    n_explore = len(actions)
    exploration = _controller_data(seen, sent)

    # 2. the belief. A box lost while exploring (it left the belts, tipped or crossed the balance limit
    # within the fixed sequence) is a failure of the episode: there is nothing left to estimate or turn.
    # One the guard caught is refused.
    lost_exploring = bool(state.done)
    est, belief, why = {}, None, None
    if not lost_exploring and guard is not None and guard.tripped:
        why = guard.why()
    elif not lost_exploring and model is None:
        seen_by_estimator = world.for_estimator(exploration, len(guard.actions) if guard else 0)
        est, belief, why = decide(cfg, truth, seen_by_estimator, estimator)  # 3. refuse when hazardous
    plan_ms: list[float] = []
    adapt_s, adaptations = 0.0, 0
    if why is None and not lost_exploring:
        # 4. physics-prior MPC
        if model is None:
            model = planning_model(cfg, ctrl, belief, force_map, est)
        # the monitor's own prior, if it has one (else it predicts with the planner's model as it is now)
        mon_model = monitor_model(cfg, ctrl, belief, None, force_map, est) if ctrl.monitor.enabled else None
        mpc = make_planner(cfg, for_delay(cfg, ctrl, world.delay))  # slower when the loop is late
        window = first_window(exploration["s"])
        # The simulator reference simulates the believed box when asked to, else the env's own.
        sim_box = simulator.belief_model(cfg, ctrl.simulator, belief) if mpc.privileged else None

        def measured():
            """The planner's window and the belt speeds at the newest frame's measurement time."""
            w = planning.check_window(world.planner_window(window[-planning.MIN_WINDOW :]))
            return w, np.asarray(seen[-1][1], np.float32)

        def observe(state):
            w, b = measured()
            if world.delay:  # predicted over the loop's delays to when the next action applies
                w, b = _compensate(model, w, b, in_flight(sent, world.delay))
            sim = None
            if mpc.privileged:
                sim = state if sim_box is None else state._replace(model=sim_box)
            return planning.observation(w, b, state.target_yaw, sim)

        plan_state = mpc.init(observe(state))
        if ctrl.observer_gain > 0:
            model = planning.DriftCorrected(model, jnp.zeros(3, jnp.float32))
        mon = Monitor(cfg, ctrl.monitor, world.delay) if ctrl.monitor.enabled else None
        mpc_steps = 0
        while not bool(state.done) and len(actions) < max_steps and not (mon is not None and mon.ended):
            if adapter is not None and mpc_steps > 0 and mpc_steps % ctrl.adapt_every == 0:
                t0 = time.perf_counter()
                model = adapter(model, _controller_data(seen, sent))
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
            if mon is not None:  # the runtime safety monitor: send the action, or stop
                own = mon_model is not None  # the monitor's own model predicts over the delay too
                m_model = mon_model if own else model
                seen_w, held = obs.window, None
                if world.delay and (own or ctrl.monitor.drag_bound):
                    w, b = measured()
                    flying = in_flight(sent, world.delay)
                    seen_w, held = monitor.present_one(
                        m_model, w, b, flying, obs.window, own, ctrl.monitor.drag_bound
                    )
                tip = monitor.tip_watch(ctrl.monitor)
                spread = None
                if tip == "sigma":  # how far off the checked pose may be, as decide will count it
                    spread = mon.tip_spread(
                        world.y_std(),
                        np.asarray(obs.belt_speed),
                        measured=window[-1],
                        predicted=np.asarray(seen_w[-1]),
                        yaw_sigma=world.yaw_std(),
                    )
                check = monitor.check(
                    cfg,
                    m_model,
                    seen_w,
                    obs.belt_speed,
                    jnp.asarray(a, jnp.float32),
                    ctrl.monitor.horizon,
                    ctrl.monitor.backup,
                    held,
                    tip=tip,
                    tip_spread=spread,
                )
                a = mon.decide(
                    len(actions),
                    a,
                    monitor.to_host(check),
                    world.y_std(),
                    world.stale,
                    np.asarray(obs.belt_speed),
                    measured=window[-1],
                    predicted=np.asarray(seen_w[-1]),
                )
            if ctrl.observer_gain > 0:
                predicted = planning.predict_first(model, obs.window, obs.belt_speed, a)
            if world.model_motion:  # the filter's prediction of the next frame, with this model
                w_meas, b_meas = measured()
                world.expect(planning.predict_first(model, w_meas, b_meas, world.applied_next([*sent, a])))
            state = act(state, a)
            window.append(np.asarray(seen[-1][0]))
            if ctrl.observer_gain > 0 and not bool(state.done):
                drift = planning.update_drift(model.drift, predicted, seen[-1][0], ctrl.observer_gain)
                model = dataclasses.replace(model, drift=drift)
    else:
        mon = None
    wall = time.perf_counter() - t_start

    trace = EpisodeTrace.from_states(rows, actions, cfg.gripper.control_dt, wall)
    summary = episode_summary(
        cfg, truth, state.summary(), est, belief, why, n_explore=n_explore, lost_exploring=lost_exploring,
        wall_s=wall, plan_ms=plan_ms, adapt_s=adapt_s, adaptations=adaptations, estimator=estimator,
        monitor=mon, guard_steps=guard_steps, balance_errors=trace.balance_error, states=trace.s,
        mass_shift=world.shift,
    )  # fmt: skip
    timed = timed_calls(plan_ms)
    return EpisodeResult(summary, trace, belief, truth, np.asarray(timed))
