"""The whole closed loop on the device: the worlds stepped with MJX, the guarded exploration, the planner,
the runtime safety monitor and the episode bookkeeping in jitted programs, vmapped over boxes and scanned
over control steps, with no host round trip per control step.

`run_episodes(cfg, truths, keys)` runs the episode `batch.run_episodes` runs for every box (explore,
estimate, refuse or turn; the same per-box key chain, planner, monitor settings and outcomes) in three
phases per box:

1. the exploration, for `slots` boxes at a time: one program scans the fixed sequence behind its guard
   (`estimator.guard_pure`, the host guard's decisions as a pure function) for all of them;
2. the belief and the hazard decision on the host (`estimator.belief.decide`: the oracle, or H on the
   exploration it read), once per box, and the physics prior built on it (`models.planning_model`);
3. the turn: `slots` boxes in slots, a program scans `block` control steps of all of them (planner,
   monitor (`control.monitor_pure`), MJX step, done masks); between blocks the host collects what they did
   and gives the slots whose box ended to the next boxes (continuous batching at block granularity: a
   finished box costs at most `block` - 1 idle steps of its slot).

So the host meets the device once per block of control steps, not once per step; the slots are split over
the local devices (`jax.sharding`, as `batch`).

What it runs: the jnp planners with the physics prior on the oracle's or a learned estimator's belief,
with or without the monitor (not in shadow mode), in the world MJX simulates: the true pose every step, no
latency, the controller's friction the simulator's (faults are the native backend's: `batch`). MJX's
contact solver is not native MuJoCo's, and slip makes episodes chaotic, so episodes differ from the native
backend's; their statistics are compared in docs/results/batched-episodes.md. Nor can an episode be
replayed: an MJX world's step depends at float32 round-off on the program it runs in (vmapped, how wide,
sharded), and slip turns that into millimetres within a few steps (benchmarks/mjx_sensitivity.py measures it).
"""

from __future__ import annotations

import dataclasses
import time
from functools import lru_cache
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import planning
from boxjax.config import Config
from boxjax.control import batch, monitor, monitor_pure
from boxjax.control import episode as controller
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import EpisodeResult
from boxjax.control.models import monitor_model, planning_model
from boxjax.estimator import explore, guard_pure
from boxjax.estimator.belief import decide
from boxjax.planners.registry import make_planner
from boxjax.sim import core, mjx_backend
from boxjax.sim.episode import EpisodeTrace
from boxjax.sim.faults import Faults

BLOCK = 20  # control steps per program call (the host collects and re-fills slots between blocks)
# Boxes per device and program call. On a CPU, 64 (MJX: 4.4 k world steps/s at 64, 0.9 k at 1;
# docs/results/simulation.md), and never more than mjx_backend.CPU_CHUNK (jaxlib's batched Cholesky hangs
# from ~768 worlds). On an accelerator, 1024: a guess, not a measurement (no GPU was at hand).
SLOTS_PER_DEVICE = {"cpu": 64}
SLOTS_PER_ACCELERATOR = 1024


def default_slots(n_devices: int) -> int:
    """Boxes per program call by default on this machine's devices."""
    return SLOTS_PER_DEVICE.get(jax.default_backend(), SLOTS_PER_ACCELERATOR) * n_devices


def supports(ctrl: ControllerConfig, faults: Faults | None = None) -> str | None:
    """None when the on-device loop can run `ctrl` (in a world with `faults`), else why not."""
    why = batch.supports(ctrl)
    if why is not None:
        return why
    if ctrl.monitor.enabled and ctrl.monitor.shadow:
        return "the monitor's shadow mode runs on the host (native backend)"
    if faults is not None and faults.any:
        return "faults (sensor noise, latency, drops, friction, servo, mass shift) run on the native backend"
    return None


def _where(mask, new, old):
    """`new` where `mask` (a scalar per box) else `old`, leaf by leaf."""
    return jax.tree.map(lambda a, b: jnp.where(mask, a, b) if hasattr(a, "shape") else a, new, old)


class Slot(NamedTuple):
    """One slot's box during its turn (a pytree; stacked over slots)."""

    state: core.State
    window: jax.Array  # (MIN_WINDOW, 5) the planner's window of states
    plan: Any  # the planner's state
    key: jax.Array
    mon: monitor_pure.MonitorState
    model: Any  # the physics prior on the box's belief
    mon_model: Any  # the monitor's own prior on it (`MonitorConfig.prior_params`), or None: `model`
    active: jax.Array  # () bool: the slot's box is turning
    nonfinite: jax.Array  # () bool: the planner produced a non-finite action (the box ended there)


@lru_cache(maxsize=4)
def _programs(cfg: Config, ctrl: ControllerConfig, block: int):
    """(explore, turn, init_plan): the jitted programs of the phases for this controller (the step cap
    and whether the box explores are arguments of the programs, not compiled in: call it with
    `explore=True`: the controllers with and without the exploration share them)."""
    env = mjx_backend.env_for(cfg)
    mpc = make_planner(cfg, ctrl)
    guard = ctrl.explore_guard
    stop = controller.guard_stop(ctrl, Faults())  # the world here has no faults
    n_explore = explore.N_STEPS + explore.GUARD_STEPS + 1
    settings = ctrl.monitor

    def explore_one(params, key_reset, max_steps, exploring):
        state = env.pure_init(params, key_reset)

        def body(carry, _):
            state, g, exploring = carry
            asked = exploring & ~state.done & (state.t < max_steps)
            g_next, a, over = guard_pure.step(
                cfg, g, state.s, state.balance_error, guard, lead=ctrl.explore_guard_lead, stop=stop
            )
            g = _where(asked, g_next, g)
            live = asked & ~over
            state = _where(live, env.pure_step(state, a), state)
            rec = {
                "s": state.s,
                "belt_speed": state.belt_speed,
                "balance": state.balance_error,
                "clipped": state.clipped,
                "action": a,
                "live": live,
                "guard": live & g.tripped,
            }
            return (state, g, live), rec

        carry = (state, guard_pure.init(), exploring)
        first = {"s": state.s, "belt_speed": state.belt_speed, "balance": state.balance_error}
        (state, g, _), rec = jax.lax.scan(body, carry, None, length=n_explore)
        return state, g, rec, first

    def turn_one(slot: Slot, max_steps):
        def body(slot: Slot, _):
            obs = planning.observation(slot.window, slot.state.belt_speed, slot.state.target_yaw)
            pair = jax.random.split(slot.key)
            a, plan, _ = mpc.optimize(pair[1], slot.model, obs, slot.plan)
            finite = jnp.all(jnp.isfinite(a))
            a = jnp.where(finite, a, 0.0).astype(jnp.float32)
            mon, sent = slot.mon, a
            ev = monitor_pure.Events(*(jnp.zeros((), bool),) * len(monitor_pure.Events._fields))
            if settings.enabled:
                m_model = slot.model if slot.mon_model is None else slot.mon_model
                # a perfect sensor and no delay on the device: only the rollout's carriage drag is uncertain
                spread = jnp.asarray([0.0, 0.0, 0.0, monitor.tip_drag(settings)], jnp.float32)
                check = monitor.predicted_errors(
                    cfg,
                    m_model,
                    obs.window,
                    obs.belt_speed,
                    a,
                    settings.horizon,
                    settings.backup,
                    tip=monitor.tip_watch(settings),
                    tip_spread=spread,
                )
                mon, sent, ev = monitor_pure.decide(cfg, settings, slot.mon, a, check, 0.0, obs.belt_speed)
            state = env.pure_step(slot.state, sent)
            window = jnp.concatenate([slot.window[1:], state.s[None]])
            ended = state.done | (state.t >= max_steps) | mon.ended | ~finite
            new = slot._replace(
                state=state, window=window, plan=plan, key=pair[0], mon=mon, active=~ended,
                nonfinite=slot.nonfinite | ~finite,
            )  # fmt: skip
            rec = {
                "s": state.s,
                "belt_speed": state.belt_speed,
                "balance": state.balance_error,
                "clipped": state.clipped,
                "action": sent,
                "live": slot.active,
                **{k: v & slot.active for k, v in ev._asdict().items()},
            }
            return _where(slot.active, new, slot), rec

        return jax.lax.scan(body, slot, None, length=block)

    explore_b = jax.jit(jax.vmap(explore_one, in_axes=(0, 0, None, None)))
    turn_b = jax.jit(jax.vmap(turn_one, in_axes=(0, None)), donate_argnums=0)
    return explore_b, turn_b, jax.jit(mpc.init)


class _MonitorRecord:
    """The monitor's part of an episode, from the on-device events (what `episode_summary` reads of a
    host `Monitor`)."""

    def __init__(self, stops, resumes, recoveries, stopping, stopped: bool, tips=()):
        tips = set(int(t) for t in tips)  # the steps of the tipping stops among `stops`
        self.stops = [(int(t), monitor.TIP if int(t) in tips else monitor.BALANCE) for t in stops]
        self.resumes, self.recoveries = list(resumes), list(recoveries)
        self.stopping_steps = set(int(t) for t in stopping)
        self.stopped = stopped
        self.reason = (self.stops[-1][1] if self.stops else monitor.BALANCE) if stopped else None

    def record(self) -> dict:
        return monitor.record(self.stops, len(self.resumes), len(self.recoveries))


class _Box:
    """One box's episode as the host collects it from the programs' records."""

    def __init__(self, s0, belt0, balance0):
        self.s, self.belt_speed, self.balance = [s0], [belt0], [float(balance0)]
        self.actions: list = []
        self.clipped: list = []
        self.guard_steps: list[int] = []
        self.events: dict[str, list[int]] = {name: [] for name in monitor_pure.Events._fields}
        self.final: dict | None = None

    def add(self, rec: dict, i) -> None:
        """Append step `i` of a program's record (numpy, indexed by `i`) if the box was live there."""
        if not rec["live"][i]:
            return
        t = len(self.actions)
        for name in self.events:
            if name in rec and rec[name][i]:
                self.events[name].append(t)
        if "guard" in rec and rec["guard"][i]:
            self.guard_steps.append(t)
        self.actions.append(np.asarray(rec["action"][i], np.float64))
        self.s.append(np.asarray(rec["s"][i], np.float64))
        self.belt_speed.append(np.asarray(rec["belt_speed"][i], np.float64))
        self.balance.append(float(rec["balance"][i]))
        self.clipped.append(bool(rec["clipped"][i]))

    def trace(self, cfg: Config, wall_s: float) -> EpisodeTrace:
        return EpisodeTrace.from_lists(
            cfg.gripper.control_dt, self.s, self.belt_speed, self.actions, self.balance, self.clipped, wall_s
        )


def _summary_state(state: core.State) -> core.State:
    """The fields `State.summary` reads, on the host (no physics, no model)."""
    return state._replace(physics=None, model=None)


def _host(tree):
    return jax.tree.map(np.asarray, tree)


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
    block: int = BLOCK,
    progress: Any = None,
) -> list[EpisodeResult]:
    """`batch.run_episodes(cfg, truths, keys, estimator=..., ctrl=...)` on the device (module docstring).
    Returns one EpisodeResult per box, in order; `wall_s` of each is the run's wall time up to the block
    in which the box ended; `plan_ms` is empty (the planner runs inside the block's program: time the
    blocks with benchmarks/episodes.py).

    Args:
      slots: boxes per program call (default `default_slots`, rounded up to a multiple of the devices;
        at most the boxes given).
      block: control steps per call of the turn's program.
      progress: optional callable(box index, EpisodeResult) called as each episode ends.
    Raises:
      ValueError: a controller the loop cannot run (`supports`), no boxes, mismatched keys, slots or
        block < 1, more than mjx_backend.CPU_CHUNK slots per CPU device.
      RuntimeError: a planner produced a non-finite action (naming the box; the box was stopped there).
    """
    why_not = supports(ctrl)
    if why_not is not None:
        raise ValueError(f"the on-device loop cannot run this controller: {why_not}")
    truths = list(truths)
    B = len(truths)
    if B < 1 or len(keys) != B:
        raise ValueError(f"need at least one box and one key per box, got {B} boxes and {len(keys)} keys")
    if slots is not None and slots < 1:
        raise ValueError(f"slots must be >= 1, got {slots}")
    if block < 1:
        raise ValueError(f"block must be >= 1 control step, got {block}")
    max_steps = cfg.task.max_steps if max_steps is None else max_steps
    t_start = time.perf_counter()
    explore_b, turn_b, init_plan = _programs(cfg, dataclasses.replace(ctrl, explore=True), block)
    cap = jnp.asarray(max_steps, jnp.int32)
    env = mjx_backend.env_for(cfg)
    put, n_dev = batch.box_sharding()
    width = default_slots(n_dev) if slots is None else slots
    width = -(-min(width, B) // n_dev) * n_dev  # a multiple of the devices: equal shards
    if jax.default_backend() == "cpu" and width // n_dev > mjx_backend.CPU_CHUNK:
        raise ValueError(
            f"{width // n_dev} worlds per CPU device: MJX on a CPU hangs in jaxlib's batched Cholesky from "
            f"~768 worlds; use at most {mjx_backend.CPU_CHUNK * n_dev} slots here"
        )
    split = [jax.random.split(batch.as_key(k)) for k in keys]
    results: list[EpisodeResult | None] = [None] * B
    boxes: list[_Box] = []
    decided: list[tuple] = [({}, None, None)] * B
    n_explore = np.zeros(B, np.int32)

    def finish(b: int, lost: bool, mon: _MonitorRecord | None = None) -> None:
        wall = time.perf_counter() - t_start
        r = boxes[b]
        est, belief, why = decided[b]
        trace = r.trace(cfg, wall)
        summary = controller.episode_summary(
            cfg, truths[b], r.final, est, belief, why, n_explore=int(n_explore[b]), lost_exploring=lost,
            wall_s=wall, plan_ms=[], estimator=estimator, monitor=mon, guard_steps=r.guard_steps,
            balance_errors=np.asarray(r.balance), states=trace.s,
        )  # fmt: skip
        results[b] = EpisodeResult(summary, trace, belief, truths[b], np.zeros(0))
        if progress is not None:
            progress(b, results[b])

    # 1. the exploration, `width` boxes per call (the last call padded with the first box)
    explored = []
    for lo in range(0, B, width):
        idx = list(range(lo, min(lo + width, B))) + [lo] * max(0, lo + width - B)
        params = mjx_backend.stack([env.box_params(truths[b]) for b in idx])
        key_reset = jnp.stack([split[b][0] for b in idx])
        states, g, rec, first = explore_b(put(params), put(key_reset), cap, jnp.asarray(ctrl.explore))
        rec, g_host, final, first = _host(rec), _host(g), _host(_summary_state(states)), _host(first)
        for k, b in enumerate(idx[: min(width, B - lo)]):
            boxes.append(_Box(first["s"][k], first["belt_speed"][k], first["balance"][k]))
            for i in range(rec["live"].shape[1]):
                boxes[b].add({n: v[k] for n, v in rec.items()}, i)
            n_explore[b] = len(boxes[b].actions)
            boxes[b].final = jax.tree.map(lambda x, k=k: x[k], final).summary()
            tripped = bool(g_host.recentring[k] >= 0)
            if tripped:
                decided[b] = ({}, None, explore.guard_explanation(
                    cfg, int(g_host.k[k]), float(g_host.worst[k]), float(g_host.judged[k]),
                    ctrl.explore_guard_lead, ctrl.explore_guard * cfg.task.balance_limit,
                    controller.guard_stop(ctrl, Faults()),
                ))  # fmt: skip
        explored.append((idx[: min(width, B - lo)], states))

    # 2. the belief and the decision, on the host; the boxes to turn, longest expected first
    queue, models, mon_models = [], {}, {}
    for b in range(B):
        if boxes[b].final["done"]:  # lost while exploring (even as the guard tripped): a failure
            decided[b] = ({}, None, None)
            finish(b, True)
            continue
        if decided[b][2] is None:
            exploration = {
                "s": np.stack(boxes[b].s),
                "belt_speed": np.stack(boxes[b].belt_speed),
                "actions": np.asarray(boxes[b].actions, np.float64).reshape(-1, 4),
            }
            decided[b] = decide(cfg, truths[b], exploration, estimator)
        est, belief, why = decided[b]
        if why is not None or boxes[b].final["steps"] >= max_steps:
            finish(b, False)
            continue
        models[b] = planning_model(cfg, ctrl, belief, force_map, est)
        if ctrl.monitor.enabled:
            mon_models[b] = monitor_model(cfg, ctrl, belief, None, force_map, est)
        queue.append(b)
    queue.sort(key=lambda b: -batch.expected_length(cfg, decided[b][1]))  # stable: ties keep the order
    where = {b: (chunk, k) for chunk, (idx, _) in enumerate(explored) for k, b in enumerate(idx)}

    # 3. the turn, `width` slots, `block` control steps per call
    def slot_of(b: int) -> Slot:
        chunk, k = where[b]
        state = jax.tree.map(lambda x: x[k], explored[chunk][1])
        window = jnp.asarray(controller.first_window(np.stack(boxes[b].s)), jnp.float32)
        obs = planning.observation(window, state.belt_speed, state.target_yaw)
        mon = monitor_pure.init(ctrl.monitor)
        f = jnp.zeros((), bool)
        return Slot(state, window, init_plan(obs), split[b][1], mon, models[b], mon_models.get(b), ~f, f)

    if queue:
        waiting = list(queue)
        slot_box: list[int | None] = [waiting.pop(0) if waiting else None for _ in range(width)]
        first = slot_of(slot_box[0])
        batch_slots = mjx_backend.stack([slot_of(b) if b is not None else first for b in slot_box])
        empty = [k for k, b in enumerate(slot_box) if b is None]
        if empty:
            active = np.ones(width, bool)
            active[empty] = False
            batch_slots = batch_slots._replace(active=jnp.asarray(active))
        batch_slots = put(batch_slots)
        while any(b is not None for b in slot_box):
            batch_slots, rec = turn_b(batch_slots, cap)
            batch_slots = put(batch_slots)  # XLA returns MJX's empty arrays replicated: keep one layout
            rec = _host(rec)
            active = np.asarray(batch_slots.active)
            ended = [k for k, b in enumerate(slot_box) if b is not None and not active[k]]
            for k, b in enumerate(slot_box):
                if b is not None:
                    for i in range(block):
                        boxes[b].add({n: v[k] for n, v in rec.items()}, i)
            if ended:
                final = _host(_summary_state(batch_slots.state))
                mon_host = _host(batch_slots.mon)
                bad = np.asarray(batch_slots.nonfinite)
            for k in ended:
                b = slot_box[k]
                if bad[k]:
                    raise RuntimeError(
                        f"the planner produced a non-finite action for box {b}; it was stopped"
                    )
                boxes[b].final = jax.tree.map(lambda x, k=k: x[k], final).summary()
                ev = boxes[b].events
                mon = None
                if ctrl.monitor.enabled:
                    stopped = bool(mon_host.stopped[k])
                    mon = _MonitorRecord(
                        ev["stop"], ev["resume"], ev["recovery"], ev["stopping"], stopped, ev["tip"]
                    )
                finish(b, False, mon)
                models.pop(b)
                mon_models.pop(b, None)
                slot_box[k] = waiting.pop(0) if waiting else None
                if slot_box[k] is not None:  # (an ended slot is already inactive)
                    batch_slots = put(batch.set_slot(batch_slots, k, slot_of(slot_box[k])))
    return results  # type: ignore[return-value]
