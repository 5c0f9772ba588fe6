"""Many closed-loop episodes at once, the JAX way: one jitted, vmapped planner call per control step.

`run_episodes(cfg, truths, keys)` runs the episode `controller.run_episode` runs for every box (explore,
estimate, refuse or turn), with the same pieces (`controller.decide`, `planning_model`, the planner by
name) and the same per-box key chain, but

* the worlds are stepped together (`sim.native.NativeBatch`: each box's own MuJoCo data, one vmapped
  command and observation for all);
* the exploration, a fixed open-loop sequence, runs for all boxes at once;
* the MPC runs `slots` boxes per planner call (`jax.vmap` of the planner's `optimize` over boxes, models
  and plan states, jitted once per shape). A box that ends frees its slot for the next box waiting
  (continuous batching: the batch keeps one shape, so it compiles once, and no box waits for the slowest
  of its group). A box waiting for a slot is paused, not simulated: its world does not move meanwhile.
  The boxes expected to take longest get their slots first (`expected_length`: longest-processing-time
  scheduling, so that few long episodes are left running in a mostly idle batch at the end); which
  slot a box gets, and when, does not change its episode (its own key; a test).
* with several local devices the boxes of a call are split over them (`jax.sharding`); on a CPU,
  `use_host_devices` asks for one host device per core before JAX starts.

What it is not: bit-identical to the one-box path. XLA vectorises a vmapped computation differently from
one box's (and differently for other batch widths), so now and then a planner's action differs from the
one-box action at float32 round-off, which the Adam refinement can amplify
(docs/results/batched-episodes.md); slip makes the closed loop chaotic, so a single
episode may then end differently, while the statistics over boxes agree within their spread
(benchmarks/episodes.py runs both on the same boxes; docs/results/batched-episodes.md). The physics is the
same
bit for bit for the same actions (a test), so every episode's actions are kept
(`EpisodeResult.trace.actions`) and `replay_episode` re-simulates any one exactly.

Supported: the jnp planners ("sampling", "paper") with the physics prior and the oracle or a learned
estimator, or with a model in the slot (the black box W, PETS) and its online adaptation: each box's
model is its own slot of the batched model, re-fitted on its own episode every `ctrl.adapt_every` MPC
steps (the one-box adapter, called per box on the host; cheap beside the planning,
docs/results/batched-episodes.md). The
privileged simulator planner and the drift observer run through `controller.run_episode`, one box at a
time (`supports` says which).
"""

from __future__ import annotations

import functools
import os
import time
from collections import deque
from functools import lru_cache
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from boxjax import geometry, massdist, planning
from boxjax.config import Config
from boxjax.control import episode as controller
from boxjax.control import monitor
from boxjax.control.config import ControllerConfig, for_delay
from boxjax.control.episode import EpisodeResult
from boxjax.control.models import monitor_model, planning_model, refuse_own_prior_without_belief
from boxjax.control.monitor import Monitor
from boxjax.control.world import World
from boxjax.estimator.belief import decide
from boxjax.planners.registry import make_planner
from boxjax.sim.episode import EpisodeTrace
from boxjax.sim.faults import NONE as NO_FAULTS
from boxjax.sim.faults import Faults
from boxjax.sim.mjx_backend import MjxBatch, stack
from boxjax.sim.native import NativeBatch

# Boxes per planner call and device: wider calls cost little less per box (benchmarks/episodes.py) and
# leave more slots idle while the last boxes finish.
SLOTS_PER_DEVICE = 8
# The order in which boxes waiting for the MPC get a slot (`run_episodes(order=...)`).
ORDERS = ("longest_first", "given")


def expected_length(cfg: Config, belief) -> float:
    """How long a box's turn is expected to take, as a number to sort by: how far the belief's centre
    of mass lies from the box centre in the plane, in units of the box's half length and half width.
    Box centres far off-centre turn slowest (on 100 random safe boxes the rank correlation of this number
    with the episode's steps was 0.86; docs/results/batched-episodes.md). No belief (a model in the slot):
    0."""
    if belief is None:
        return 0.0
    com = np.asarray(massdist.mass_properties(belief, cfg.box).com, np.float64)
    hx, hy, _ = cfg.box.half_size
    return float(np.hypot(com[0] / hx, com[1] / hy))


def supports(ctrl: ControllerConfig) -> str | None:
    """None when `run_episodes` can run `ctrl`, else why not (then use `controller.run_episode`)."""
    if ctrl.planner not in ("sampling", "paper"):
        return f"the {ctrl.planner!r} planner is not vmappable (it plans on the host)"
    if ctrl.observer_gain > 0:
        return "the drift observer (observer_gain > 0) runs one box at a time"
    return None


@lru_cache(maxsize=1)
def _batched_compensate():
    """`planning.compensate` vmapped over boxes and jitted."""
    return jax.jit(jax.vmap(planning.compensate))


@lru_cache(maxsize=1)
def _batched_predict_first():
    """`planning.predict_first` vmapped over boxes and jitted (the filters' predictions of the next frame)."""
    return jax.jit(jax.vmap(planning.predict_first))


@lru_cache(maxsize=8)
def batched_planner(cfg: Config, ctrl: ControllerConfig):
    """(init, optimize) of the planner `ctrl` names, vmapped over boxes and jitted (cached per config)."""
    mpc = make_planner(cfg, ctrl)
    return jax.jit(jax.vmap(mpc.init)), jax.jit(jax.vmap(mpc.optimize))


def use_host_devices(n: int | None = None) -> int:
    """Ask JAX for `n` host (CPU) devices (default: one per core) so that batched episodes shard their
    boxes over the cores (`box_sharding`). Must run before JAX starts its backend; afterwards (or on an
    accelerator, where the devices are what they are) it changes nothing. Returns the local devices."""
    n = n or os.cpu_count() or 1
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:  # the backend is already up: keep its devices
        pass
    return len(jax.local_devices())


def box_sharding():
    """(put, n): `put(tree)` places a batch's arrays split along their leading (box) axis over the n
    local devices (`jax.sharding`; identity for one device), so the vmapped planner runs one shard per
    device. On a CPU, `jax.config.update("jax_num_cpu_devices", k)` before JAX starts gives k host
    devices, one per core (`boxjax evaluate` does it): XLA runs these small computations on one core
    each, so a single device leaves the other cores idle."""
    devices = jax.local_devices()
    if len(devices) == 1:
        return (lambda tree: tree), 1
    sharding = NamedSharding(Mesh(np.asarray(devices), ("boxes",)), PartitionSpec("boxes"))
    return (lambda tree: jax.device_put(tree, sharding)), len(devices)


def as_key(key):
    """A typed PRNG key from a typed key or raw uint32 key data (`jax.random.PRNGKey`)."""
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key
    return jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))


@functools.partial(jax.jit, donate_argnums=0)
def set_slot(batch, k, tree):
    """`batch` with slot k replaced by `tree`, in place: the batch's buffers are donated, so replacing
    one box's W (2.45e6 parameters) does not copy the other boxes' models."""
    return jax.tree.map(lambda b, x: b.at[k].set(x), batch, tree)


class _Record:
    """One box's episode as it happens (host lists; turned into an EpisodeTrace at the end): the true
    world's states and applied actions, and the controller's view through its `World` (the states it
    estimated, the actions it sent)."""

    def __init__(self, sim: NativeBatch, b: int, world: World):
        self.world = world
        world.prepare(sim.models[b])
        self.s, self.belt_speed, self.balance = (
            [sim.s[b].copy()],
            [sim.belt_speed[b].copy()],
            [float(sim.balance_error[b])],
        )
        self.seen = [world.observe(sim.s[b], sim.belt_speed[b])]
        self.sent: list[np.ndarray] = []
        self.guard_steps: list[int] = []
        self.monitor: Monitor | None = None
        self.actions: list[np.ndarray] = []
        self.clipped: list[bool] = []
        self.plan_ms: list[float] = []
        self.mpc_steps = 0  # planner calls so far
        self.adapt_s, self.adaptations = 0.0, 0  # online adaptation: wall time, calls

    def send(self, sim: NativeBatch, b: int, action) -> np.ndarray:
        """The action the gripper applies when the controller sends `action` at this step (and the mass
        slides, if this is its step)."""
        self.sent.append(np.asarray(action, np.float64))
        self.world.before_step(len(self.actions), sim.models[b], sim.ids.box_body)
        return self.world.send(np.asarray(action, np.float64))

    def add(self, sim: NativeBatch, b: int, applied) -> None:
        self.actions.append(np.asarray(applied, np.float64))
        self.s.append(sim.s[b].copy())
        self.belt_speed.append(sim.belt_speed[b].copy())
        self.balance.append(float(sim.balance_error[b]))
        self.clipped.append(bool(sim.clipped[b]))
        self.seen.append(self.world.observe(sim.s[b], sim.belt_speed[b]))

    def exploration(self) -> dict:
        """The episode so far as the controller knows it, as the estimators and adapters take it: the
        states and belt speeds it saw, s (T+1, 5) and belt_speed (T+1, 2), and the actions it sent (T, 4)."""
        return controller._controller_data(self.seen, self.sent)

    def trace(self, cfg: Config, wall_s: float) -> EpisodeTrace:
        return EpisodeTrace.from_lists(
            cfg.gripper.control_dt, self.s, self.belt_speed, self.actions, self.balance, self.clipped, wall_s
        )


def _result(cfg, truth, sim: NativeBatch, b: int, rec: _Record, decided, n_explore, lost, wall, estimator):
    """World b's EpisodeResult, its summary as `controller.run_episode` makes it."""
    est, belief, why = decided
    final = sim.state(b).summary()
    summary = controller.episode_summary(
        cfg, truth, final, est, belief, why, n_explore=int(n_explore), lost_exploring=bool(lost),
        wall_s=wall, plan_ms=rec.plan_ms, adapt_s=rec.adapt_s, adaptations=rec.adaptations,
        estimator=estimator, monitor=rec.monitor, guard_steps=rec.guard_steps,
        balance_errors=np.asarray(rec.balance), states=np.stack(rec.s), mass_shift=rec.world.shift,
    )  # fmt: skip
    timed = controller.timed_calls(rec.plan_ms)
    return EpisodeResult(summary, rec.trace(cfg, wall), belief, truth, np.asarray(timed))


def run_episodes(
    cfg: Config,
    truths,
    keys,
    *,
    estimator: Any = "oracle",
    ctrl: ControllerConfig = ControllerConfig(),  # noqa: B008 (frozen dataclass: immutable)
    force_map=None,
    max_steps: int | None = None,
    slots: int | None = None,
    progress: Any = None,
    model: Any = None,
    adapter: Any = None,
    order: str = "longest_first",
    faults: Faults = NO_FAULTS,
    backend: str = "native",
) -> list[EpisodeResult]:
    """`controller.run_episode(cfg, truths[j], keys[j], estimator=..., ctrl=...)` for every box j, batched
    (see the module docstring). Returns one EpisodeResult per box, in order; `wall_s` of each is the
    batch's wall time up to the box's end, `plan_ms` the batched planner calls it took part in.

    Args:
      truths: B mass distributions. keys: B episode keys (jax PRNG keys, typed or raw).
      estimator: "oracle" or a callable as for `run_episode` (called once per box after the exploration).
      slots: boxes per planner call (default SLOTS_PER_DEVICE per local device; rounded up to a
        multiple of the devices, the boxes split over them, `use_host_devices`; at most B are used).
      progress: optional callable(box index, EpisodeResult) called as each episode ends.
      model: a model for the planners' slot used for every box (as `run_episode`'s: the estimator and
        the hazard check are skipped); None: the physics prior on each box's belief.
      adapter: online adaptation as for `run_episode`: `adapter(model, episode data so far)` replaces a
        box's model every `ctrl.adapt_every` of its MPC steps.
      order: which waiting box gets the next free slot: "longest_first" (by `expected_length` of its
        belief, ties in the given order) or "given" (the order of `truths`).
      faults: how each box's simulated world differs from the controller's (`run_episode`'s), drawn from
        the box's own key; with `ctrl.monitor` enabled the runtime safety monitor checks every action.
      backend: "native" (`NativeBatch`) or "mjx": this host loop on MJX worlds (`MjxBatch`, no faults),
        to compare with the on-device loop (`control.device_loop`) on the same physics.
    Raises:
      ValueError: an unsupported controller (`supports`), no boxes, mismatched keys, slots < 1, an
        adapter with ctrl.adapt_every < 1, or an unknown order.
      RuntimeError: a planner produced a non-finite action (naming the box).
    """
    why_not = supports(ctrl)
    if why_not is not None:
        raise ValueError(f"batched episodes cannot run this controller: {why_not}; use run_episode")
    truths = list(truths)
    B = len(truths)
    if B < 1 or len(keys) != B:
        raise ValueError(f"need at least one box and one key per box, got {B} boxes and {len(keys)} keys")
    if slots is not None and slots < 1:
        raise ValueError(f"slots must be >= 1, got {slots}")
    refuse_own_prior_without_belief(ctrl, model)
    if adapter is not None and ctrl.adapt_every < 1:
        raise ValueError("an adapter needs ctrl.adapt_every >= 1 (steps between adaptations)")
    if order not in ORDERS:
        raise ValueError(f"unknown order {order!r}; choose one of {ORDERS}")
    if backend not in ("native", "mjx"):
        raise ValueError(f"unknown backend {backend!r}; choose 'native' or 'mjx'")
    if backend == "mjx" and faults.any:
        raise ValueError("faults are simulated on the native backend only, not 'mjx'")
    max_steps = cfg.task.max_steps if max_steps is None else max_steps
    t_start = time.perf_counter()
    split = [jax.random.split(as_key(k)) for k in keys]
    key_reset = [k[0] for k in split]
    key_plan = [k[1] for k in split]
    sim = (NativeBatch if backend == "native" else MjxBatch)(cfg, truths, key_reset)
    rec = [
        _Record(sim, b, World(cfg, faults, ctrl.pose_filter, as_key(keys[b]), truths[b])) for b in range(B)
    ]
    delay = rec[0].world.delay
    results: list[EpisodeResult | None] = [None] * B
    decided: list[tuple] = [({}, None, None)] * B

    def finish(b: int, n_explore: int, lost: bool) -> None:
        wall = time.perf_counter() - t_start
        results[b] = _result(cfg, truths[b], sim, b, rec[b], decided[b], n_explore, lost, wall, estimator)
        if progress is not None:
            progress(b, results[b])

    # 1. exploration: the fixed sequence for every box at once; a box that ends stops there
    # (each box through its own `explore.Guarded`, as `run_episode` does)
    n_explore = np.zeros(B, np.int32)
    guard_m = ctrl.explore_guard if model is None else None
    guards = (
        [controller.guarded_exploration(cfg, ctrl, r.world, guard_m) for r in rec] if ctrl.explore else []
    )
    exploring = np.full(B, bool(guards))
    while exploring.any():
        acts, live = np.zeros((B, 4)), np.zeros(B, bool)
        for b in np.flatnonzero(exploring):
            if sim.done[b] or sim.t[b] >= max_steps:
                a = None
            else:  # what the controller sees (with a perfect sensor the env's own state and balance error)
                s_seen = rec[b].seen[-1][0]
                bal = geometry.balance_error(s_seen) if rec[b].world.active else sim.balance_error[b]
                a = guards[b].next(s_seen, bal)
            if a is None:
                exploring[b] = False
            else:
                if guards[b].tripped:
                    rec[b].guard_steps.append(len(rec[b].actions))
                acts[b], live[b] = rec[b].send(sim, b, a), True
        if not live.any():
            break
        sim.step(acts, live)
        for b in np.flatnonzero(live):
            rec[b].add(sim, b, acts[b])
        n_explore += live
    lost = sim.done.copy()

    # 2.-3. belief and decision per box; 4. the models of the boxes to turn
    queue: deque[int] = deque()
    models: dict[int, Any] = {}
    own_monitor = ctrl.monitor.enabled and ctrl.monitor.prior_params is not None
    mon_models: dict[int, Any] = {}  # the monitor's own priors (`MonitorConfig.prior_params`)
    for b in range(B):
        if lost[b]:
            finish(b, int(n_explore[b]), True)
            continue
        if guards and guards[b].tripped:
            decided[b] = ({}, None, guards[b].why())
        elif model is None:
            n_fixed = len(guards[b].actions) if guards else 0
            decided[b] = decide(
                cfg, truths[b], rec[b].world.for_estimator(rec[b].exploration(), n_fixed), estimator
            )
        est, belief, why = decided[b]
        if why is not None or sim.t[b] >= max_steps:
            finish(b, int(n_explore[b]), False)
            continue
        models[b] = model if model is not None else planning_model(cfg, ctrl, belief, force_map, est)
        if own_monitor:
            mon_models[b] = monitor_model(cfg, ctrl, belief, None, force_map, est)
        queue.append(b)
    if order == "longest_first":  # a stable sort: ties (no belief) keep the given order
        queue = deque(sorted(queue, key=lambda b: -expected_length(cfg, decided[b][1])))

    # 5. the MPC, `slots` boxes per planner call
    if queue:
        init_b, optimize_b = batched_planner(cfg, for_delay(cfg, ctrl, delay))  # slower when late
        put, n_dev = box_sharding()
        slots = SLOTS_PER_DEVICE * n_dev if slots is None else slots
        width = -(-min(slots, len(queue)) // n_dev) * n_dev  # a multiple of the devices: equal shards
        windows = {b: controller.first_window(np.stack([s for s, _ in rec[b].seen])) for b in queue}
        compensate_b = _batched_compensate()
        predict_b = _batched_predict_first()

        def measured(boxes_: list[int]) -> tuple[np.ndarray, np.ndarray]:
            """These boxes' planner windows (`World.planner_window`) and belt speeds at their newest
            frames' measurement times, stacked."""
            w = [
                planning.check_window(rec[b].world.planner_window(windows[b][-planning.MIN_WINDOW :]))
                for b in boxes_
            ]
            return np.stack(w), np.stack([rec[b].seen[-1][1] for b in boxes_]).astype(np.float32)

        def observations(boxes_: list[int], model_b=None) -> planning.Observation:
            """The planner's observations of these boxes, stacked (one host -> device copy per field),
            predicted over the loop's delays with each box's model (`planning.compensate`)."""
            w, belt = measured(boxes_)
            if delay and model_b is not None:
                flying = np.stack([controller.in_flight(rec[b].sent, delay) for b in boxes_])
                w, belt = compensate_b(model_b, put(w), put(belt), put(flying))
            return put(planning.observation(w, belt, sim.target_yaw[boxes_]))

        first = queue[0]
        slot_box: list[int | None] = [None] * width
        model_b = put(stack([models[first]] * width))
        mon_b = put(stack([mon_models[first]] * width)) if own_monitor else None
        plan_b = init_b(observations([first] * width, model_b))
        keys_b = put(jnp.stack([key_plan[first]] * width))

        def admit(k: int) -> None:
            nonlocal model_b, plan_b, keys_b, mon_b
            b = queue.popleft()
            slot_box[k] = b
            model_b = put(set_slot(model_b, k, models[b]))
            if own_monitor:
                mon_b = put(set_slot(mon_b, k, mon_models[b]))
            one = put(stack([models[b]] * n_dev)) if delay else None  # for the compensation only
            first_plan = jax.tree.map(lambda x: x[0], init_b(observations([b] * n_dev, one)))
            plan_b = put(set_slot(plan_b, k, first_plan))
            keys_b = put(keys_b.at[k].set(key_plan[b]))
            if ctrl.monitor.enabled:
                rec[b].monitor = Monitor(cfg, ctrl.monitor, delay)

        for k in range(width):
            if queue:
                admit(k)
        while any(b is not None for b in slot_box):
            live = [b for b in slot_box if b is not None]
            for k, b in enumerate(slot_box):  # online adaptation, each box on its own episode so far
                r = None if b is None else rec[b]
                if adapter is None or r is None or r.mpc_steps == 0 or r.mpc_steps % ctrl.adapt_every:
                    continue
                t0 = time.perf_counter()
                models[b] = adapter(models[b], r.exploration())
                model_b = put(set_slot(model_b, k, models[b]))
                r.adapt_s += time.perf_counter() - t0
                r.adaptations += 1
            obs_b = observations([b if b is not None else live[0] for b in slot_box], model_b)
            pair = jax.vmap(jax.random.split)(keys_b)
            keys_b, key_step = pair[:, 0], pair[:, 1]
            t0 = time.perf_counter()
            actions, plan_b, _ = optimize_b(key_step, model_b, obs_b, plan_b)
            actions = np.asarray(actions, np.float64)
            ms = 1e3 * (time.perf_counter() - t0)
            if ctrl.monitor.enabled:  # the runtime safety monitor, all slots in one call
                m_b = mon_b if own_monitor else model_b
                seen_b, held = obs_b.window, None
                if delay and (own_monitor or ctrl.monitor.drag_bound):
                    use = [b if b is not None else live[0] for b in slot_box]
                    w, belt = measured(use)
                    flying = put(np.stack([controller.in_flight(rec[b].sent, delay) for b in use]))
                    present_b = monitor.present_batch(own_monitor, ctrl.monitor.drag_bound)
                    seen_b, held = present_b(m_b, put(w), put(belt), flying, obs_b.window)
                tip, spread = monitor.tip_watch(ctrl.monitor), None
                belts = np.asarray(obs_b.belt_speed)
                newest = np.asarray(seen_b[:, -1])  # predicted for when the actions apply
                if tip == "sigma":  # how far off each checked pose may be, as decide will count it
                    spread = np.zeros((len(slot_box), 4), np.float32)
                    for k, b in enumerate(slot_box):
                        if b is not None and rec[b].monitor is not None:
                            w = rec[b].world
                            spread[k] = rec[b].monitor.tip_spread(
                                w.y_std(), belts[k], windows[b][-1], newest[k], w.yaw_std()
                            )
                    spread = put(spread)
                checks = monitor.check_batch(
                    cfg, m_b, seen_b, obs_b.belt_speed, put(jnp.asarray(actions, jnp.float32)),
                    ctrl.monitor.horizon, ctrl.monitor.backup, held, tip=tip, tip_spread=spread,
                )  # fmt: skip
                checks = monitor.to_host(checks)
            full = np.zeros((B, 4))
            active = np.zeros(B, bool)
            for k, b in enumerate(slot_box):
                if b is None:
                    continue
                if not np.all(np.isfinite(actions[k])):  # never send a NaN action to the belts
                    raise RuntimeError(
                        f"planner produced a non-finite action {actions[k].tolist()} for box {b}; stopping"
                    )
                a, r = actions[k], rec[b]
                if r.monitor is not None:
                    a = r.monitor.decide(
                        len(r.actions), a, monitor.to_host(checks, k), r.world.y_std(), r.world.stale,
                        belts[k], measured=windows[b][-1], predicted=newest[k],
                    )  # fmt: skip
                full[b], active[b] = r.send(sim, b, a), True
                r.plan_ms.append(ms)
                r.mpc_steps += 1
            if rec[live[0]].world.model_motion:  # the filters' predictions of the next frame, one call
                use = [b if b is not None else live[0] for b in slot_box]
                w, belt = measured(use)
                nxt = np.stack([rec[b].world.applied_next(rec[b].sent) for b in use])
                expected = np.asarray(predict_b(model_b, put(w), put(belt), put(nxt)))
                for k, b in enumerate(slot_box):
                    if b is not None:
                        rec[b].world.expect(expected[k])
            sim.step(full, active)
            for k, b in enumerate(slot_box):
                if b is None:
                    continue
                rec[b].add(sim, b, full[b])
                windows[b].append(rec[b].seen[-1][0].copy())
                ended = rec[b].monitor is not None and rec[b].monitor.ended
                if sim.done[b] or sim.t[b] >= max_steps or ended:
                    finish(b, int(n_explore[b]), False)
                    slot_box[k] = None
                    models.pop(b)
                    mon_models.pop(b, None)
                    if queue:
                        admit(k)
    return results  # type: ignore[return-value]


def replay_episode(
    cfg: Config,
    truth: massdist.MassDistribution,
    key,
    actions,
    *,
    estimator: Any = "oracle",
    ctrl: ControllerConfig = ControllerConfig(),  # noqa: B008
    faults: Faults = NO_FAULTS,
) -> EpisodeResult:
    """An episode again from the actions (T, 4) the gripper applied, with its episode key and faults: the
    physics re-simulated (the same states bit for bit: `NativeBatch` steps each world as `NativeEnv`
    does, the plant's faults and the mass shift drawn again from the key), the controller's view through
    the same sensor draws, the estimator and the hazard decision re-run on the exploration, the summary
    as the episode's own (without the monitor's record: its decisions are in the actions).

    Raises:
      ValueError: the episode ends before its actions do, or its exploration is not the one the
        controller's (guarded) exploration sends (another box, key, config or faults).
    """
    t0 = time.perf_counter()
    key_reset, _ = jax.random.split(as_key(key))
    sim = NativeBatch(cfg, [truth], [key_reset])
    world = World(cfg, faults, ctrl.pose_filter, as_key(key), truth)
    rec = _Record(sim, 0, world)
    actions = np.asarray(actions, np.float64).reshape(-1, 4)
    late = faults.action_latency  # the action sent at step t is applied at t + late
    sent = np.concatenate([actions[late:], np.zeros((min(late, len(actions)), 4))])
    guard = controller.guarded_exploration(cfg, ctrl, world, ctrl.explore_guard)
    exploring, n_explore, lost = guard is not None, 0, False
    decided: tuple = ({}, None, None)

    def exploration_over(recorded=None) -> bool:
        # the guard is asked with the states the controller saw, so it ends the exploration where it did
        if not exploring:
            return False
        s_seen = rec.seen[-1][0]
        bal = geometry.balance_error(s_seen) if world.active else sim.balance_error[0]
        expected = None if sim.done[0] else guard.next(s_seen, bal)
        if expected is not None and recorded is not None and not np.allclose(expected, recorded):
            raise ValueError(
                f"recorded action {len(rec.actions)} {np.round(recorded, 4).tolist()} is not the "
                f"exploration's {np.round(expected, 4).tolist()} (another box, key, config or faults?)"
            )
        return expected is None

    def decided_now() -> tuple:
        if guard.tripped:
            return ({}, None, guard.why())
        return decide(cfg, truth, world.for_estimator(rec.exploration(), len(guard.actions)), estimator)

    for t, a in enumerate(actions):
        if sim.done[0]:
            raise ValueError(f"the episode ended at step {t}, before its {len(actions)} recorded actions did")
        if exploration_over(sent[t] if t + late < len(actions) else None):
            exploring = False
            decided = decided_now()
        rec.send(sim, 0, sent[t])  # through the world, as sent: it applies `a` (the actuator's delay)
        sim.step(a[None], np.ones(1, bool))
        rec.add(sim, 0, a)
        n_explore += int(exploring)
    if exploration_over():  # the actions ended with the exploration: lost, or refused
        lost = bool(sim.done[0])
        if not lost:
            decided = decided_now()
    return _result(cfg, truth, sim, 0, rec, decided, n_explore, lost, time.perf_counter() - t0, estimator)
