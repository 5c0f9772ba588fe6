"""Random-shooting MPC with Pareto selection (paper §2.3 "Action selection", §4).

Per control step: sample `n_samples` actions without replacement from a discretised set of restricted
actions, predict the next state of each with ONE vmapped call to the physics prior, score it with
(R1, R2) = (pose reward, balance reward) (paper eq. 1), keep the Pareto front (maximisation), and pick one
action on it by a selection rule.

Action set (`action_set`, paper §4 "restricted actions"; 9 x 9 + 7 + 7 = 95 by default, the paper's 95):
  * velocity actions (v1, v2, 0, 0): a 9 x 9 grid of belt-speed commands;
  * position actions (0, 0, p1, 0) and (0, 0, 0, p2): 7 position steps each, in
    [-max_position_step, +max_position_step] (includes 0, so the set has duplicate "do nothing" rows, as
    a full grid would).
Velocity modes. The simulator takes speed SETPOINTS, the paper's actions are INCREMENTS (dv):
  * "increment" (default): the velocity columns are increments dv_i on a grid in
    [-belt_accel_limit * control_dt, +...] (= +-0.03 m/s, the most a belt can change in one step) and the
    setpoint sent is clip(belt_speed_i + dv_i). Position rows (dv = 0) therefore keep the belts at their
    current speed, exactly as the paper's position actions leave the velocities unchanged. Every grid
    point is reachable in one step, so the 81 velocity rows are 81 distinct outcomes.
  * "absolute": the velocity columns are setpoints on a grid in [-belt_speed_limit, +belt_speed_limit].
    Position rows (v1 = v2 = 0, dp != 0) are sent with the CURRENT belt speeds as setpoints (so a sideways
    correction does not stop the belts; with setpoints, a literal 0 would brake both belts). Note that
    with the 0.6 m/s^2 limit, setpoints more than 0.03 m/s away from the current speed all give the same
    full-rate ramp, so most of the 81 rows collapse onto a few outcomes.

Selection rules (`RULES`), all of which return a member of the Pareto front:
  * "random": uniformly at random on the front (the paper's choice);
  * "weighted": maximise w1 log R1 + w2 log R2 (a linear combination of the log rewards: the rewards
    themselves span 1 .. 1/eps = 1e6, so a linear combination of raw rewards is decided by whichever is
    near its epsilon; logs make the weights mean "relative improvement");
  * "lexicographic" (alias "safety-first"): among the front actions whose predicted balance error stays
    within `safe_balance` (default half the task's balance limit), the one with the best R1 (ties: best
    R2); if none, the one with the best R2 (ties: best R1).

Look-ahead (`horizon`, default 1 = the paper's one-step prediction): each action is held for `horizon`
steps (`prior.rollout`); R1 is taken at the last predicted state, R2 (and the balance error) at the
worst state along the way; `brake_steps` appends a predicted braking phase to that worst-case check.

Beyond the paper (both measured necessary in closed loop with the simulator, see the report):
  * stay on the belts (`x_margin`, default 3 cm): the paper's rewards ignore x, and the greedy pose
    reward happily translates the box along the belts until it drops off their ends (0.8 m belts).
    Candidates that bring the box's footprint, plus its braking distance v_x^2 / (2 belt_accel_limit),
    closer than x_margin to a belt end (and closer than it is now) are ranked below all others;
  * `speed_cap`: commanded belt speeds limited to +-speed_cap.

Keys are explicit; `make_planner` returns a jitted `plan(key, model, window, belt_speed, target_yaw)`;
the same key gives the same action.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, planning, task
from boxjax.config import Config, GripperConfig
from boxjax.planners.terms import overhang, y_excess

RULES = ("random", "weighted", "lexicographic", "safety-first", "safe-random")
VELOCITY_MODES = ("increment", "absolute")


def action_set(gripper: GripperConfig, n_v: int = 9, n_p: int = 7, velocity: str = "increment") -> np.ndarray:
    """(n_v^2 + 2 n_p, 4) float32 restricted actions (see module docstring); 95 by default.

    Rows 0 .. n_v^2 - 1: (v1, v2, 0, 0) with v1 the slow index (row-major over the grid), then
    (0, 0, p, 0) for each of the n_p position steps, then (0, 0, 0, p).
    velocity="increment": v columns are speed increments in [-a dt, +a dt] m/s (a = belt_accel_limit);
    "absolute": speed setpoints in [-belt_speed_limit, +belt_speed_limit] m/s.
    """
    if velocity not in VELOCITY_MODES:
        raise ValueError(f"unknown velocity mode {velocity!r}; choose one of {VELOCITY_MODES}")
    if n_v < 2 or n_p < 1:
        raise ValueError(f"need n_v >= 2 and n_p >= 1, got n_v={n_v}, n_p={n_p}")
    if velocity == "increment":
        vmax = gripper.belt_accel_limit * gripper.control_dt
    else:
        vmax = gripper.belt_speed_limit
    gv = np.linspace(-vmax, vmax, n_v)
    gp = np.linspace(-gripper.max_position_step, gripper.max_position_step, n_p) if n_p > 1 else np.zeros(1)
    v1, v2 = np.meshgrid(gv, gv, indexing="ij")
    vel = np.stack([v1.ravel(), v2.ravel(), np.zeros(n_v * n_v), np.zeros(n_v * n_v)], axis=1)
    z = np.zeros(n_p)
    pos1 = np.stack([z, z, gp, z], axis=1)
    pos2 = np.stack([z, z, z, gp], axis=1)
    return np.concatenate([vel, pos1, pos2]).astype(np.float32)


def to_env_actions(
    actions, belt_speed, gripper: GripperConfig, velocity: str = "increment", speed_cap: float | None = None
):
    """(N, 4) environment actions (speed setpoints, position increments) for rows of an action set.

    "increment": setpoint = clip(belt_speed + dv). "absolute": rows with v1 = v2 = 0 and a non-zero
    position step keep the current belt speeds as setpoints; other rows are sent as they are. Setpoints
    are clipped to +-speed_cap (default: the belt speed limit); a belt already faster than the cap is
    only ever slowed down towards it (increment mode).
    """
    actions = jnp.asarray(actions)
    lim = gripper.belt_speed_limit if speed_cap is None else min(speed_cap, gripper.belt_speed_limit)
    if velocity == "increment":
        v = jnp.clip(belt_speed[None] + actions[:, :2], -lim, lim)
    elif velocity == "absolute":
        hold = jnp.all(actions[:, :2] == 0, axis=1) & jnp.any(actions[:, 2:] != 0, axis=1)
        v = jnp.clip(jnp.where(hold[:, None], belt_speed[None], actions[:, :2]), -lim, lim)
    else:
        raise ValueError(f"unknown velocity mode {velocity!r}; choose one of {VELOCITY_MODES}")
    return jnp.concatenate([v, actions[:, 2:]], axis=1)


def pareto_front(scores, method: str = "auto") -> jax.Array:
    """(N,) bool: the non-dominated rows of scores (N, 2) under maximisation (pure jnp).

    Row j dominates row i when it is >= in every objective and > in at least one; equal rows do not
    dominate each other, so duplicates of a front point are all on the front. NaN scores are treated as
    -inf (never preferred).

    method: "pairwise" compares all pairs, O(N^2) (fastest for the paper's N = 50); "sorted" sorts by
    the first objective, O(N log N) (for thousands of candidates); "auto" picks pairwise for N <= 512.
    """
    s = jnp.where(jnp.isnan(scores), -jnp.inf, scores)
    n = s.shape[0]
    if method == "auto":
        method = "pairwise" if n <= 512 else "sorted"
    a, b = s[:, 0], s[:, 1]
    if method == "pairwise":
        # [i, j]: j >= i in both and j > i in one. Written per objective so no (N, N, 2) array is built.
        ge = (a[None, :] >= a[:, None]) & (b[None, :] >= b[:, None])
        gt = (a[None, :] > a[:, None]) | (b[None, :] > b[:, None])
        return ~jnp.any(ge & gt, axis=1)
    if method != "sorted":
        raise ValueError(f"unknown method {method!r}; choose 'auto', 'pairwise' or 'sorted'")
    # Sort by a descending, ties by b descending. Row i is dominated iff some row with a larger a has
    # b >= b_i, or some row with the same a has b > b_i (the first of its tie group has the largest b).
    order = jnp.lexsort((-b, -a))
    a_s, b_s = a[order], b[order]
    prefix_max = jax.lax.cummax(b_s)  # max of b over rows 0..k in sorted order
    start = jnp.searchsorted(-a_s, -a_s, side="left")  # first row of each row's tie group
    before = jnp.where(start > 0, prefix_max[jnp.maximum(start - 1, 0)], -jnp.inf)
    dominated_s = (before >= b_s) | (b_s[start] > b_s)
    return jnp.zeros(n, bool).at[order].set(~dominated_s)


def _lex_best(primary, secondary, mask):
    """Index maximising (primary, secondary) lexicographically among mask (mask must be non-empty)."""
    p = jnp.where(mask, primary, -jnp.inf)
    top = mask & (p >= jnp.max(p))
    return jnp.argmax(jnp.where(top, secondary, -jnp.inf))


def select(key, scores, front, balance_error, rule: str, weights=(0.5, 0.5), safe_balance: float = 0.02):
    """Index of the chosen action (a member of the front).

    Args:
      key: PRNG key (used by "random").
      scores: (N, 2) (R1, R2); front: (N,) bool from `pareto_front`; balance_error: (N,) m, predicted.
      rule: one of RULES. weights: (w1, w2) > 0 for "weighted". safe_balance: m, for "lexicographic".
    """
    r1, r2 = scores[:, 0], scores[:, 1]
    if rule == "random":
        p = front / jnp.sum(front)
        return jax.random.choice(key, front.shape[0], p=p)
    if rule == "weighted":
        w1, w2 = weights
        val = w1 * jnp.log(jnp.maximum(r1, 1e-30)) + w2 * jnp.log(jnp.maximum(r2, 1e-30))
        return jnp.argmax(jnp.where(front, val, -jnp.inf))
    if rule == "safe-random":
        safe = front & (balance_error <= safe_balance)
        p = safe / jnp.maximum(jnp.sum(safe), 1)
        return jnp.where(jnp.any(safe), jax.random.choice(key, front.shape[0], p=p), _lex_best(r2, r1, front))
    if rule in ("lexicographic", "safety-first"):
        safe = front & (balance_error <= safe_balance)
        return jnp.where(jnp.any(safe), _lex_best(r1, r2, safe), _lex_best(r2, r1, front))
    raise ValueError(f"unknown selection rule {rule!r}; choose one of {RULES}")


class PlanInfo(NamedTuple):
    """What `plan` considered (for logs and explanations). N = n_samples.

    choice: () index into the N candidates; set_index: (N,) rows of the action set that were sampled;
    candidates: (N, 4) environment actions; predicted: (N, 5) predicted state (last of the horizon);
    scores: (N, 2) (R1, R2); front: (N,) bool; balance_error: (N,) m (worst over the horizon);
    yaw_error: (N,) rad, at the last predicted state; feasible: (N,) bool, keeps the box on the belts.
    """

    choice: jax.Array
    set_index: jax.Array
    candidates: jax.Array
    predicted: jax.Array
    scores: jax.Array
    front: jax.Array
    balance_error: jax.Array
    yaw_error: jax.Array
    feasible: jax.Array


def plan(
    key,
    model: planning.Model,
    window,
    belt_speed,
    target_yaw,
    cfg: Config,
    *,
    actions=None,
    n_samples: int = 50,
    rule: str = "random",
    velocity: str = "increment",
    weights=(0.5, 0.5),
    safe_balance: float | None = None,
    horizon: int = 1,
    brake_steps: int = 0,
    x_margin: float | None = 0.03,
    y_margin: float | None = None,
    speed_cap: float | None = None,
):
    """One MPC step: (action (4,) for the environment, PlanInfo). Pure; jit it with `make_planner`.

    Args:
      key: PRNG key (sampling, and the "random" rule).
      model: the model slot (`planning.Model`: the physics prior `prior.PriorModel`, or a black box).
      window: (W, 5) last planar states (W >= planning.MIN_WINDOW), belt_speed: (2,) m/s, target_yaw: rad.
      cfg: the experiment config (gripper limits, task rewards).
      actions: (A, 4) action set (default `action_set(cfg.gripper, velocity=velocity)`), A >= n_samples.
      n_samples: actions scored per step (paper: 50), sampled without replacement.
      rule, weights, safe_balance (default cfg.task.balance_limit / 2): see `select`.
      velocity: how the set's velocity columns are read (see `to_env_actions`).
      horizon: steps each candidate is held for in the prediction (1 = paper); R1 is scored there.
      brake_steps: after the horizon, predict this many steps of braking (setpoints 0, belts in place)
        and take the balance error (R2) and the overhang as the worst along the whole rollout: a safety
        check that the box can still be stopped within the limits after this action (the one-step
        prediction cannot see the drift that the box's momentum causes after it).
      x_margin: m, keep the box this far inside the belt ends (see `overhang`); None: no constraint
        (the paper's objectives alone, which ignore x).
      speed_cap: m/s, the planner never commands belt speeds beyond +-speed_cap (None: the gripper's
        belt_speed_limit). A slower turn sweeps the box's centre more slowly, so the belts can follow it.
    """
    if actions is None:
        actions = action_set(cfg.gripper, velocity=velocity)
    actions = jnp.asarray(actions, jnp.float32)
    n_set = actions.shape[0]
    if not 1 <= n_samples <= n_set:
        raise ValueError(f"n_samples={n_samples} must be in 1..{n_set} (the size of the action set)")
    if rule not in RULES:
        raise ValueError(f"unknown selection rule {rule!r}; choose one of {RULES}")
    if horizon < 1 or brake_steps < 0:
        raise ValueError(f"need horizon >= 1 and brake_steps >= 0, got {horizon}, {brake_steps}")
    safe_balance = cfg.task.balance_limit / 2 if safe_balance is None else safe_balance
    key_sample, key_select = jax.random.split(key)
    window = jnp.asarray(window, jnp.float32)
    belt_speed = jnp.asarray(belt_speed, jnp.float32)
    idx = jax.random.permutation(key_sample, n_set)[:n_samples] if n_samples < n_set else jnp.arange(n_set)
    cand = to_env_actions(actions[idx], belt_speed, cfg.gripper, velocity, speed_cap)
    # Each candidate held for `horizon` steps, then `brake_steps` of braking (setpoints 0, belts in place).
    held = jnp.broadcast_to(cand[:, None], (cand.shape[0], horizon, 4))
    seqs = jnp.concatenate([held, jnp.zeros((cand.shape[0], brake_steps, 4), cand.dtype)], axis=1)
    traj = jax.vmap(lambda seq: model.rollout_sequence(window, belt_speed, seq))(seqs)  # (N, H + B, 5)
    states = traj[:, horizon - 1]
    bal = jnp.max(jax.vmap(jax.vmap(geometry.balance_error))(traj), axis=1)  # worst over the rollout
    r1 = jax.vmap(task.reward_pose, in_axes=(0, None, None))(states, target_yaw, cfg.task)
    r2 = 1.0 / (bal**2 + cfg.task.reward_eps)  # = task.reward_balance at the worst state
    scores = jnp.stack([r1, r2], axis=1)
    # Stay on the belts (not in the paper's rewards; the belts are 0.8 m long): a candidate is feasible
    # when the box stays x_margin inside the belt ends over the horizon, or at least overhangs no more
    # than it does now (both including the braking distance below). Infeasible candidates are ranked
    # below every feasible one (and among themselves by their overhang), so the front holds only
    # feasible candidates whenever there is one.
    over = jnp.max(jax.vmap(jax.vmap(lambda s: overhang(s, cfg)))(traj), axis=1)
    # ... plus the distance the box needs to stop if it keeps sliding outwards at its predicted speed:
    # the belts can change speed by at most belt_accel_limit, so a box moving with them at v_x needs
    # v_x^2 / (2 a) to stop (a short look-ahead cannot see that on its own; with brake_steps the braking
    # is predicted instead, and this term covers what is left of the speed at the end).
    last = jnp.concatenate([window[-1:, None].repeat(traj.shape[0], 0), traj], axis=1)[:, -2:]
    vx = (last[:, 1, geometry.X] - last[:, 0, geometry.X]) / cfg.gripper.control_dt
    outward = jnp.maximum(vx * jnp.sign(last[:, 1, geometry.X]), 0.0)
    over = over + outward**2 / (2 * cfg.gripper.belt_accel_limit)
    feasible = jnp.ones(over.shape, bool)
    violation = jnp.zeros(over.shape)
    if x_margin is not None:
        v_now = (window[-1, geometry.X] - window[-2, geometry.X]) / cfg.gripper.control_dt
        out_now = jnp.maximum(v_now * jnp.sign(window[-1, geometry.X]), 0.0)
        over_now = overhang(window[-1], cfg) + out_now**2 / (2 * cfg.gripper.belt_accel_limit)
        feasible = feasible & ((over <= -x_margin) | (over <= over_now + 1e-6))
        violation = violation + jnp.maximum(over + x_margin, 0.0)
    if y_margin is not None:
        ex = jnp.max(jax.vmap(jax.vmap(lambda s: y_excess(s, cfg, y_margin)))(traj), axis=1)
        ex_now = y_excess(window[-1], cfg, y_margin)
        feasible = feasible & ((ex <= 0) | (ex <= ex_now + 1e-6))
        violation = violation + jnp.maximum(ex, 0.0)
    ranked = jnp.where(feasible[:, None], scores, -2.0 - violation[:, None])  # rewards > 0 > -2 - violation
    front = pareto_front(ranked)
    choice = select(key_select, ranked, front, bal, rule, weights, safe_balance)
    info = PlanInfo(
        choice=choice,
        set_index=idx,
        candidates=cand,
        predicted=states,
        scores=scores,
        front=front,
        balance_error=bal,
        yaw_error=jax.vmap(task.yaw_error, in_axes=(0, None))(states, target_yaw),
        feasible=feasible,
    )
    return cand[choice], info


def make_planner(cfg: Config, **options):
    """A jitted `plan(key, model, window, belt_speed, target_yaw) -> (action (4,), PlanInfo)`.

    `options` are the keyword arguments of `plan` (n_samples, rule, velocity, actions, weights,
    safe_balance, horizon); they are fixed at construction. The model is a traced argument, so a new
    box (new masses) does not recompile; a different window length does.
    """
    if "actions" in options and options["actions"] is not None:
        options["actions"] = np.asarray(options["actions"], np.float32)
    return jax.jit(functools.partial(plan, cfg=cfg, **options))


def make(cfg: Config, **options) -> planning.Planner:
    """The paper's planner behind the planner interface (`planning.Planner`); memoryless (plan state ())."""
    step = make_planner(cfg, **options)

    def optimize(key, model, obs: planning.Observation, plan_state=()):
        a, info = step(key, model, obs.window, obs.belt_speed, obs.target_yaw)
        return a, plan_state, info

    return planning.Planner("paper", lambda obs: (), optimize)
