"""The runtime safety monitor: between the planner and the gripper, it stops a turn that is about to lose
the box's balance.

Where it sits: the planner proposes an action; before it is sent the monitor asks the model in the
planner's slot (the physics prior, W or PETS: whatever plans) what happens if the action is sent and the
gripper then stops (a simplex architecture's backup controller, or a predictive safety filter's backup
trajectory). If the predicted balance error over that horizon, plus a margin (`k_sigma` standard
deviations of the state estimate's uncertainty about the box's y and `k_delay` of the prediction's over
the loop's delay, in quadrature), reaches the stop threshold, the action is replaced
by the stop: a category-2 controlled stop in the industrial sense, power kept, the belts commanded to
rest (the drives decelerate at their acceleration limit) and the carriages either held or moved together
under the box's centre (`backup_set`; `MonitorConfig.backup` "best": whichever the model predicts
safer). The stop is issued while the stop itself still keeps the box balanced, which is what "about to"
means here, and once issued it is followed as planned (a predictive safety filter's committed backup
trajectory), then rest.

A stop is a state, not an end:

* While stopped the planner keeps planning; once the gripper is known at rest (standstill watched: the
  belts at rest, |belt speed| <= `standstill_speed`, and nothing but rest sent over the loop's delay, so
  the estimate is observed, not predicted through the stop's own carriage moves) and the planner's next
  step and stop are predicted within `resume_below` (hysteresis: below `stop_at`), the turn resumes.
  An episode that resumes and finishes is a success.
* A box that came to rest between the two thresholds cannot resume (its present error alone is above
  `resume_below`); it is recovered instead (`MonitorConfig.recover`): at rest, the planner's action is
  sent when the model predicts that it, followed by a stop that holds the carriages, brings the box
  `recover_gain` closer to the middle without passing `stop_at` on the way; then that stop, then rest
  again, until the box rests inside `resume_below` and the turn resumes, or until a recovery leaves the
  box further out than it found it (`recover_until_worse`: the model has the direction wrong there). The
  stop still counts toward `stop_timeout`, and a crossing a recovery leads to counts as unnoticed.
* The `max_stops`-th balance stop is final, as is a stop that cannot resume within `stop_timeout`
  control steps: the gripper comes to rest, the episode ends `safe_stop` with its reason, kept apart
  from failures (`REASONS`).
* An observation older than `stale_steps` control steps (the sensor dropped frames) stops the belts too,
  reason `stale_observation`, as robot stacks do with a command timeout; it resumes when fresh frames
  come back (within `stop_timeout` steps) and does not count toward `max_stops`.
* With `tip_stop` (0.8 cm by default; 0 turns it off) the check also predicts how far the box's centre
  of mass stays inside the support of both belts along the action and its stop (`Check.go_tip`); under
  `tip_stop` the action is stopped too, reason `tip`, counted as a balance stop, and it resumes only with
  an action that keeps the margin.

The monitor checks from the state at which the action will apply: the controller's estimate, predicted
over the loop's delays (sensor and action latency) by `planning.compensate`. That prediction's least
certain part is the drag of the carriage moves in flight on the box; with `drag_bound` the check is also
made from the same present without (part of) that drag (`planning.compensate_held`), the worse counting.

The check is one jitted, vmappable computation (`predicted_errors`: four rollouts of `horizon` steps); the
state machine around it is host-side Python (`Monitor`, one per episode), the same in `run_episode` and
the batched `run_episodes`. Its measured cost per control step is in benchmarks/planner.py.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from functools import lru_cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, planning
from boxjax.config import Config, ConfigError
from boxjax.control.state_estimate import RestWatch
from boxjax.prior.predictor import PriorParams

# Why a stop was issued; an episode that ends stopped is `safe_stop` with one of these.
BALANCE, STALE, TIP = "balance", "stale_observation", "tip"
TIP_UNCERTAINTY = ("y", "pose", "sigma")  # `MonitorConfig.tip_uncertainty`
REASONS = (BALANCE, STALE, TIP)
RUN, STOP = "run", "stop"
# The controlled stops the monitor can issue (`backup_actions`): belts to rest, carriages held where they
# are or moved toward the box's centre; "best" lets the model pick the one predicted safer.
BACKUPS = ("hold", "recentre")
BACKUP_CHOICES = ("best", *BACKUPS)


@dataclasses.dataclass(frozen=True)
class MonitorConfig:
    """Settings of the runtime safety monitor (balance distances as fractions of the balance limit)."""

    enabled: bool = True
    # Watch only: check every action and record the stops it would issue (`Monitor.log`,
    # `monitor_would_stop` in the summary), but send the planner's actions unchanged (how a monitor is
    # first run beside a robot, and how its thresholds are measured: docs/results/faults.md).
    shadow: bool = False
    stop_at: float = 0.8  # predicted balance error (+ k_sigma std) that issues a stop (3.2 of 4 cm)
    resume_below: float = 0.65  # predicted balance error (+ k_sigma std) under which a stop may resume
    horizon: int = 10  # control steps predicted: the action, then the stop (0.247 m/s to rest: 8 steps)
    # Standard deviations of the estimate's y uncertainty (k_sigma) and of the prediction's error over the
    # delay (k_delay, of `delay_std` or a miss; None: k_sigma), added in quadrature to the predicted error.
    # The estimate's counts once: the predicted error, the largest of `horizon` predictions from the noisy
    # estimate, already carries its noise upward. Chosen in shadow mode on development boxes with 0
    # unnoticed crossings in every row: k_sigma 2 -> 1 cut the needless stops per turned episode 3.73 ->
    # 2.29 (realistic) and 11.1 -> 4.0 (10 mm of noise); closed loop 79 -> 81 and 70 -> 74 of 100 turned
    # (docs/results/faults.md).
    k_sigma: float = 1.0
    k_delay: float | None = 2.0
    # The estimate's standard deviations a resume and a recovery count (None: k_sigma). Both are sent
    # from rest, where waiting costs time, not the box: a 10 mm sensor's estimate was 1 cm (2.7 std)
    # short one step after a recovery dragged its box, and the resume it allowed crossed the limit. At 2
    # it turned 697 instead of 708 of 800 boxes over the noisy rows, 6 lost against 9, with half as many
    # recoveries again (docs/results/faults.md, "A resume on an estimate that had not caught up").
    resume_k_sigma: float | None = None
    # The error of the model's prediction over the loop's delays (`planning.compensate`), m per square
    # root of a control step: 1.65 / 2.48 / 3.68 mm rms of balance error at 1 / 2 / 4 steps with the prior
    # on the true box (scripts/monitor_study.py, docs/results/faults.md).
    delay_std: float = 0.0018
    # The prediction over the delay, checked against what then arrived: every step the balance offset
    # predicted `delay` steps ago for now is compared with the newest estimate (the miss). A miss beyond
    # `miss_sigmas` of its expected std (the delay's and the estimate's) says the model is failing here
    # (the box slips, the friction is not the model's): the prediction's std is then the largest miss of
    # the last `miss_window` steps instead of `delay_std`'s. 0 turns it off. With no delay there is
    # nothing to check.
    miss_sigmas: float = 0.0
    miss_window: int = 5
    # The carriages' drag over the delay: a carriage moved under the box drags it by a fraction of the
    # move the prior predicts with an error of 0.21 rms (scripts/carriage_drag.py), the same for every move
    # of that carriage under that box. So the carriage travel in flight (the last `delay` actions, summed
    # per carriage) adds drag_std x travel to the prediction's std over the delay. 0: off.
    drag_std: float = 0.0
    # The carriages' drag over the delay, bounded instead: the check is made from two predictions of the
    # present, the model's and one in which the carriage moves in flight drag the box `drag_bound` less
    # than the model predicts (1: not at all; `planning.compensate_held`), and every predicted error is
    # the worse of the two. It widens nothing when the carriages move the middle toward the box; it
    # catches a turn that moves them away from the box, unseen, counting on a drag the world does not
    # give. 0: off.
    drag_bound: float = 0.0
    # The monitor's own model: a physics prior with these settings (`prior.PriorParams`) on the planner's
    # belief, for the check and its prediction over the delay; None: the model in the planner's slot.
    # The planner's settings were chosen with the default prior's biases; a safety check wants the most
    # accurate prediction instead (docs/results/faults.md, "The monitor's own model").
    prior_params: PriorParams | None = None
    # Recovery: a balance stop at rest above `resume_below` sends the planner's action (then the stop
    # `Check.go_stop`: belts to rest, carriages held) when the model predicts it brings the box at least
    # `recover_gain` (m) closer to the middle and never above `stop_at` (with the estimate's margin), so
    # that a box that came to rest between the two thresholds is brought back inside instead of waiting
    # out `stop_timeout`.
    recover: bool = True
    recover_gain: float = 0.001
    # A recovery is an experiment on the model. Once the gripper is known at rest again, a box that rests
    # further from the middle than the recovery found it (by more than k_sigma of the estimate's std) says
    # the model has the direction wrong here: with `recover_until_worse` no further recovery is sent in
    # the episode (the stop waits out `stop_timeout`). Without it, recoveries go on while the model
    # predicts a gain: a light box recovered from 3.25 cm came to rest at 3.29 cm instead of 3.10, and the
    # next recovery, predicted to take it 1 mm closer, crossed the limit (docs/results/faults.md,
    # "Recoveries that leave the box further out").
    recover_until_worse: bool = True
    max_stops: int = 60  # the max_stops-th balance stop is final
    stop_timeout: int = 100  # control steps (5 s) a stop may last without resuming before it is final
    stale_steps: int = 2  # an observation older than this many control steps stops the belts (0.1 s)
    standstill_speed: float = 0.01  # m/s, |belt speed| under which the belts count as at rest
    # Tipping: a stop (reason "tip") when the smallest stability margin predicted for the action and its
    # stop (`Check.go_tip`: how far the centre of mass stays inside the support polygon of both belts'
    # contacts, `prior.stability_margin`), less k_sigma of the estimate's std, falls under `tip_stop` (m);
    # a stop resumes or recovers only once the action's margin is back above it. Boxes whose mass sits in
    # a corner tipped as a carriage moved out from under them, the margin falling from ~2 cm to below
    # zero in 1-3 steps; one tipped at rest at 9 mm. At 1.5 cm, over 1,500 paired episodes (no fault and
    # the noisy rows): lost 12 -> 6 (tipped 8 -> 3), turned 1,344 -> 1,339 (docs/results/faults.md,
    # "Tipping"); on by default since the fault table was rerun with it (the same document). 0.8 cm since
    # the prior's margin is "refined" (exact to 2 mm where the sampled one over-estimated by up to 18):
    # over 2,200 paired episodes against 1.5 cm on the sampled margin, turned 1,987 vs 1,981, lost 3 vs 6
    # (tipped 1 vs 3), the true boxes 1.3 mm further from tipping (docs/results/faults.md).
    # 0: off (the check then computes no margin).
    tip_stop: float = 0.008
    # What the tipping watch subtracts from the predicted margin for the pose it cannot see exactly: "y"
    # the balance check's own margin (k_sigma of the estimate's y std and k_delay of the prediction's over
    # the delay), as if the margin moved 1:1 with the pose; "pose" that margin times the margin's slope in
    # x and y (`Check.go_tip_slope`) and k_delay of `tip_yaw_std` per square-root step of delay times its
    # slope in yaw, added in quadrature. Near a corner patch of the support the margin moves several times
    # faster than the pose: a box 4 steps late (seed 0, box 28) was predicted 30 mm inside as its true
    # margin fell 21 -> 9 -> -2 mm; 5 mm of xy error moved it 12 mm, 1 degree 7 mm (docs/results/faults.md).
    # "sigma" (default): the margin itself at poses that far off (`Check.go_tip` the smallest over
    # `SIGMA_POINTS` scaled by `Monitor.tip_spread`: the balance check's margin in x and y, k_sigma of the
    # estimate's yaw std and k_delay of `tip_yaw_std`'s over the delay in yaw, y widened by the carriages'
    # drag, `tip_drag_std`), nothing subtracted: a slope is zero on the margin's plateau next to a cliff,
    # a point on the far side of it is not. Box 28, 120 episodes (4 steps late, 10 mm noise, realistic):
    # lost 17 ("y") -> 0; 300 episodes of 100 random boxes: turned 261 -> 259, none lost either way
    # (docs/results/faults.md, "The sigma watch").
    tip_uncertainty: str = "sigma"
    # rad per square-root control step: the std of the latency compensation's yaw error over the delay
    # ("pose" only), 0.31-0.36 degrees per square-root step over 1, 2 and 4 steps of delay along 40 turns
    # of the 4-step latency row (x 0.6-0.9 mm, y 1.4-1.6 mm, as `delay_std`; docs/results/faults.md)
    tip_yaw_std: float = 0.0061
    # ("sigma" only) the std of the carriages' drag per m of carriage travel, times k_delay added in
    # quadrature to the y spread: the travel in flight (as `drag_std`) and, state by state, the checked
    # rollout's own. A carriage moved under a box near a corner patch drags it less than the prior
    # predicts (0.21 rms of the move, scripts/carriage_drag.py; the prior's bias, docs/results/faults.md),
    # and there 1.3 mm less drag took the margin 10 mm lower (seed 0, box 28, 4 steps late: predicted 9 mm,
    # true -1, tipped). 0: the pose's spread alone.
    tip_drag_std: float = 0.21
    # The stop's carriages (`BACKUPS`): "best" (default) the model's choice, made when the stop is issued,
    # between holding them and moving them toward the box's centre; "hold" or "recentre" always. Moving a
    # carriage drags the box on its belt with it: with one carriage at its stop, re-centring moved a
    # development box 7.4 cm for 12 cm of carriage travel and its balance error grew from 2.0 to 3.1 cm
    # while stopped (docs/results/faults.md).
    backup: str = "best"

    def __post_init__(self):
        def bad(name, why):
            raise ConfigError(f"monitor: {name}={getattr(self, name)!r} {why}")

        if not isinstance(self.enabled, bool):
            bad("enabled", "must be true or false")
        if not 0 < self.stop_at <= 1:
            bad("stop_at", "must be a fraction of the balance limit in (0, 1]")
        if not 0 < self.resume_below < self.stop_at:
            bad("resume_below", "must be a fraction of the balance limit in (0, stop_at)")
        if not (isinstance(self.horizon, int) and 1 <= self.horizon <= 40):
            bad("horizon", "must be a whole number of control steps in [1, 40]")
        for name in ("recover", "recover_until_worse"):
            if not isinstance(getattr(self, name), bool):
                bad(name, "must be true or false")
        for name in (
            "k_sigma",
            "delay_std",
            "miss_sigmas",
            "recover_gain",
            "drag_std",
            "tip_stop",
            "tip_yaw_std",
            "tip_drag_std",
        ):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                bad(name, "must be a number >= 0")
        if not (isinstance(self.drag_bound, int | float) and 0 <= self.drag_bound <= 1):
            bad("drag_bound", "must be a fraction of the model's drag in [0, 1]")
        for name in ("k_delay", "resume_k_sigma"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0):
                bad(name, "must be a number >= 0 or None")
        for name in ("max_stops", "stop_timeout", "stale_steps", "miss_window"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                bad(name, "must be a whole number >= 1")
        if not self.standstill_speed > 0:
            bad("standstill_speed", "must be a positive speed (m/s)")
        if self.prior_params is not None and not isinstance(self.prior_params, PriorParams):
            bad("prior_params", "must be a prior.PriorParams or None")
        if self.backup not in BACKUP_CHOICES:
            bad("backup", f"must be one of {BACKUP_CHOICES}")
        if self.tip_uncertainty not in TIP_UNCERTAINTY:
            bad("tip_uncertainty", f"must be one of {TIP_UNCERTAINTY}")


OFF = MonitorConfig(enabled=False)


# ----------------------------------------------------------------------------------------------------------
# The check (pure jnp, one box; vmap for batches).


def backup_actions(cfg: Config, s, n: int, recentre: bool = True) -> jax.Array:
    """(n, 4) a controlled stop from the planar state s (5,): belt speeds 0 (the drives decelerate at
    their limit) and, with `recentre`, both carriages moved together toward the box's centre, at most
    `max_position_step` per step and within their ranges, so that the midpoint between the belts comes
    under the box (without: the carriages hold)."""
    g = cfg.gripper
    offset = s[geometry.Y] - 0.5 * (s[geometry.P1] + s[geometry.P2])
    reach = g.max_position_step * jnp.arange(1, n + 1)
    moved = jnp.clip(offset, -reach, reach) * recentre  # (n,) cumulative move of the midpoint

    def carriage(p, lo, hi):
        c = jnp.clip(p + moved, lo, hi) - p
        return jnp.diff(c, prepend=0.0)

    d1 = carriage(s[geometry.P1], *g.p1_range)
    d2 = carriage(s[geometry.P2], *g.p2_range)
    return jnp.stack([jnp.zeros(n), jnp.zeros(n), d1, d2], axis=1).astype(jnp.float32)


def backup_set(cfg: Config, s, n: int, backup: str = "best") -> jax.Array:
    """(V, n, 4) the stops the monitor chooses between (`MonitorConfig.backup`): both of `BACKUPS` for
    "best", else the one named."""
    names = BACKUPS if backup == "best" else (backup,)
    return jnp.stack([backup_actions(cfg, s, n, recentre=name == "recentre") for name in names])


class Check(NamedTuple):
    """What the monitor's model predicts for the planner's action (`predicted_errors`), one box; distances
    in m (balance errors). A batch (`check_batch`) has a leading box axis on every field."""

    go: jax.Array  # () the largest balance error, now and over the horizon, of the action then a stop
    stop: jax.Array  # () the same for a stop at once
    now: jax.Array  # () the window's newest balance error (the state at which the action applies)
    # The recovery's prediction (`Monitor`): the action followed by the first stop of `backup_set`, the
    # hold unless only re-centring is allowed. A recovery follows its action with that stop, not with the
    # one predicted safest: re-centring after it moves a carriage alone under a box at rest, whose drag the
    # prior predicts worst (a box at a friction of 0.65 was recovered twice into a 4 cm crossing that way).
    go_ahead: jax.Array  # () its largest balance error over the predicted steps alone (without now)
    go_end: jax.Array  # () its balance error at the horizon's end, once the stop has played out
    stop_plan: jax.Array  # (horizon, 4) the stop predicted safest at once (a stop issued now sends it)
    go_stop: jax.Array  # (horizon, 4) that stop (its first horizon - 1 steps follow a recovery)
    # () the smallest stability margin (m), now and over the horizon, of the action then its stop (the
    # `go` one); +inf when not asked for (`tip`)
    go_tip: jax.Array = np.float32(np.inf)
    # (3,) how fast that margin falls as the box's pose is off: |d margin / d (x, y, yaw)| (m/m, m/m,
    # m/rad) at the state where it is smallest; zeros when not asked for
    go_tip_slope: jax.Array = np.zeros(3, np.float32)


def _sigma_points() -> np.ndarray:
    """(27, 3) the centre and its 26 neighbours on a 3 x 3 x 3 grid, each scaled onto the unit sphere: the
    pose offsets (in units of the spread per axis, x, y, yaw) at which the "sigma" tipping watch evaluates
    the margin. The faces, the edges' and the corners' directions: near a corner patch of the support the
    margin's cliff lies along x and y together."""
    g = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return (g / np.maximum(n, 1.0)).astype(np.float32)


SIGMA_POINTS = _sigma_points()


def predicted_errors(
    cfg: Config,
    model,
    window,
    belt_speed,
    action,
    horizon: int,
    backup: str = "best",
    held=None,
    tip=False,
    tip_spread=None,
) -> Check:
    """The largest balance error, now (the window's newest state) and over `horizon` predicted steps, of
    (a) `action` followed by a stop and (b) a stop at once, each with the stop of `backup_set` predicted
    safest, those stops, and the recovery's prediction (a `Check`). `held`: a second window for the same
    present (`planning.compensate_held`: the carriage moves over the delay not dragging the box); every
    error is then the worse of the two windows' (`MonitorConfig.drag_bound`). `tip`: also the smallest
    stability margin of the action's rollout (`Check.go_tip`, the worse window's; the model's
    `stability_margin`); "slope": and how fast it falls with the pose there (`Check.go_tip_slope`);
    "sigma": the smallest at the poses `SIGMA_POINTS` x the spread off every state's (`tip_spread`, (4,):
    how far off in x (m), y (m) and yaw (rad) the box may be, and per m of carriage travel along the rollout
    how much further in y, its drag being uncertain; `Monitor.tip_spread`; `tip_watch` says which the
    settings need)."""
    backups = backup_set(cfg, window[-1], horizon, backup)  # (V, horizon, 4)
    first = jnp.broadcast_to(action.astype(jnp.float32), backups[:, :1].shape)
    go = jnp.concatenate([first, backups[:, :-1]], 1)
    starts = window[None] if held is None else jnp.stack([window, held.astype(window.dtype)])
    rollout = jax.vmap(model.rollout_sequence, in_axes=(None, None, 0))
    states = jax.vmap(lambda w: rollout(w, belt_speed, jnp.concatenate([go, backups])))(starts)
    errors = jax.vmap(jax.vmap(jax.vmap(geometry.balance_error)))(states)  # (windows, 2V, horizon)
    errors = jnp.where(jnp.isfinite(errors), errors, jnp.inf)  # a model that diverges is not believed safe
    errors = jnp.max(errors, axis=0).reshape(2, -1, horizon)  # (go | stop, V, horizon)
    worst = jnp.max(errors, axis=2)  # (go | stop, V)
    go_b, stop_b = jnp.argmin(worst[0]), jnp.argmin(worst[1])
    now = jnp.max(jax.vmap(geometry.balance_error)(starts[:, -1]))
    go_tip, go_tip_slope = jnp.float32(jnp.inf), jnp.zeros(3, jnp.float32)
    if tip:
        go_states = states[:, go_b]  # (windows, horizon, 5): the action, then its stop
        watched = jnp.concatenate([starts[:, -1:], go_states.astype(starts.dtype)], 1).reshape(-1, 5)
        if tip == "sigma":  # the margin at poses off by the spread, along each axis and diagonal
            if tip_spread is None:
                raise ValueError('the tipping watch "sigma" needs the pose\'s spread (tip_spread)')
            spread = jnp.asarray(tip_spread, watched.dtype)
            # the drag of the carriage moves along the rollout (the action, then its stop) widens y:
            # travel per state, the squared per-carriage sums of the moves up to it (0 at the present)
            travel = jnp.sum(jnp.square(jnp.cumsum(go[go_b, :, 2:], axis=0)), axis=-1)
            travel = jnp.tile(jnp.concatenate([jnp.zeros(1), travel]), starts.shape[0]).astype(watched.dtype)
            per_state = jnp.stack(
                [
                    jnp.broadcast_to(spread[0], travel.shape),
                    jnp.sqrt(spread[1] ** 2 + spread[3] ** 2 * travel),
                    jnp.broadcast_to(spread[2], travel.shape),
                ],
                -1,
            )  # (watched, 3)
            off = jnp.zeros((*per_state.shape[:1], len(SIGMA_POINTS), 5), watched.dtype)
            off = off.at[..., jnp.array([geometry.X, geometry.Y, geometry.YAW])].set(
                jnp.asarray(SIGMA_POINTS)[None] * per_state[:, None]
            )
            watched = (watched[:, None] + off).reshape(-1, 5)
        margins = jax.vmap(model.stability_margin)(watched)  # now and along the rollouts
        at = jnp.argmin(jnp.where(jnp.isnan(margins), -jnp.inf, margins))
        go_tip = margins[at]
        go_tip = jnp.where(jnp.isfinite(go_tip), go_tip, -jnp.inf)  # a diverged model: not believed safe
        if tip == "slope":  # what tip_uncertainty "pose" reads (`tip_watch`)
            slope = jnp.abs(jax.grad(model.stability_margin)(watched[at]))[
                jnp.array([geometry.X, geometry.Y, geometry.YAW])
            ]
            go_tip_slope = jnp.where(jnp.isfinite(slope), slope, 0.0).astype(jnp.float32)
    return Check(
        go=jnp.maximum(worst[0, go_b], now),
        stop=jnp.maximum(worst[1, stop_b], now),
        now=now,
        go_ahead=worst[0, 0],
        go_end=errors[0, 0, -1],
        stop_plan=backups[stop_b],
        go_stop=backups[0],
        go_tip=go_tip,
        go_tip_slope=go_tip_slope,
    )


def present(model, window, belt_speed, actions, compensated, own: bool, drag_bound: float):
    """What the monitor checks from, for a loop `actions` (D, 4) late: (window, held). `window`: the
    planner's present (`compensated`), or with `own` (the monitor's own prior in `model`) that model's
    prediction from the newest estimate's `window` and `belt_speed` over the actions in flight
    (`planning.compensate`); `held`: with `drag_bound` the same present with that fraction of the drag of
    the carriage moves in flight withheld (`planning.compensate_held`), else None."""
    if own:
        compensated = planning.compensate(model, window, belt_speed, actions)[0]
    if not drag_bound:
        return compensated, None
    return compensated, planning.compensate_held(model, window, belt_speed, actions, compensated, drag_bound)


present_one = jax.jit(present, static_argnames=("own", "drag_bound"))


@lru_cache(maxsize=4)
def present_batch(own: bool, drag_bound: float):
    """`present` vmapped over boxes (their models stacked) and jitted, for these settings."""
    return jax.jit(jax.vmap(partial(present, own=own, drag_bound=drag_bound)))


check = jax.jit(predicted_errors, static_argnames=("cfg", "horizon", "backup", "tip"))  # one box


@partial(jax.jit, static_argnames=("cfg", "horizon", "backup", "tip"))
def check_batch(
    cfg: Config,
    models,
    windows,
    belt_speeds,
    actions,
    horizon: int,
    backup: str = "best",
    held=None,
    tip=False,
    tip_spread=None,
):
    """`check` vmapped over boxes (their models stacked on a leading axis, as the batched planner's;
    `tip_spread` (B, 4) one per box)."""
    one = partial(predicted_errors, cfg, horizon=horizon, backup=backup, tip=tip)
    if tip_spread is None:
        tip_spread = jnp.zeros((actions.shape[0], 4), jnp.float32)
    if held is None:
        return jax.vmap(lambda m, w, b, a, s: one(m, w, b, a, tip_spread=s))(
            models, windows, belt_speeds, actions, tip_spread
        )
    both = jax.vmap(lambda m, w, b, a, h, s: one(m, w, b, a, held=h, tip_spread=s))
    return both(models, windows, belt_speeds, actions, held, tip_spread)


def to_host(c: Check, k: int | None = None) -> Check:
    """The check as numpy (box k of a batch's)."""
    return Check(*(np.asarray(x if k is None else x[k]) for x in c))


# ----------------------------------------------------------------------------------------------------------
# The state machine (host side, one per episode).


class Monitor:
    """One episode's monitor. Per MPC step: the check (`check` or `check_batch`) on the planner's action,
    then `decide(...)` -> the action to send. `ended` when a stop became final and the gripper is at
    rest; `record()` the episode's monitor summary."""

    def __init__(self, cfg: Config, settings: MonitorConfig, delay: int = 0):
        """`delay`: the control steps the controller predicts its estimate over (`World.delay`)."""
        self.cfg, self.m = cfg, settings
        self.delay = delay
        self.delay_var = delay * settings.delay_std**2
        self._predicted: deque = deque(maxlen=max(delay, 1))  # offsets predicted for the steps to come
        self._misses: deque = deque(maxlen=settings.miss_window)  # |miss| of the last steps (m)
        self.limit = cfg.task.balance_limit
        self.mode, self.reason = RUN, None
        self.stops: list[tuple[int, str]] = []  # (control step, reason) of every stop issued
        self.resumes: list[int] = []
        # control steps at which a stop sent a recovery (`MonitorConfig.recover`)
        self.recoveries: list[int] = []
        self._recovering = False  # from a recovery until the gripper is known at rest again
        self._recovered_from: float | None = None  # the last recovery's balance error until judged
        self.recovery_failed = False  # a recovery left the box further out (`recover_until_worse`)
        self.balance_stops = 0
        self.stopped_for = 0
        self.final = False
        self.ended = False
        self.stopping_steps: set[int] = set()  # control steps at which a stop action was sent
        # per check: (t, go error, stop error, the estimate's sigma before the delay's is added, the largest
        # miss of the prediction over the delay in the last `miss_window` steps, the carriage travel in
        # flight: the squared per-carriage sums of the last `delay` actions' moves, m^2)
        self.log: list[tuple[int, float, float, float, float, float]] = []
        self._in_flight: deque = deque(maxlen=delay)  # carriage moves (2,) of the actions in flight
        self.would_stop: list[int] = []  # shadow mode: the steps at which it would have stopped
        self._plan: deque = deque()  # the stop's actions still to send (then rest)
        # known at rest: nothing but rest sent over the delay and the step before it, belts at rest (so the
        # estimate comes from a frame taken after a step of rest and is predicted over rest only: a stop
        # resumes from a state observed at rest, not one predicted through its own carriage moves)
        self.rest = RestWatch(delay + 1, settings.standstill_speed)

    def decide(
        self,
        t: int,
        action,
        check: Check,
        sigma: float,
        stale: int,
        belt_speed,
        measured=None,
        predicted=None,
    ) -> np.ndarray:
        """The action to send at control step t.

        Args:
          action: the planner's (4,). check: `predicted_errors` for it, on the host (`to_host`): a stop
          issued now sends its `stop_plan`, then rest.
          sigma: the std of the estimate's y at its measurement (m; the prediction's over the delay is
          added, `delay_std`, unless the gripper is known at rest); stale: control steps since the
          last fresh frame; belt_speed: (2,) the estimated belt speeds.
          measured, predicted: (5,) the newest estimate (at its measurement time) and the state predicted
          from it for when this action applies (the checked window's newest): the prediction's misses
          (`MonitorConfig.miss_sigmas`); None: not checked.
        """
        m, limit = self.m, self.limit
        miss = self._track(measured, predicted)
        travel = self._travel()
        self.log.append((t, float(check.go), float(check.stop), float(sigma), miss, travel))
        still = self.rest.still(belt_speed)
        self._recovering = self._recovering and not still
        if still and self._recovered_from is not None:  # the last recovery played out: judged
            self.recovery_failed |= recovery_worse(self._recovered_from, check.now, m.k_sigma * sigma)
            self._recovered_from = None
        margin, resume_margin = self._margins(sigma, still, miss, travel)
        go_error = float(check.go) + margin
        tipping = (
            m.tip_stop > 0
            and float(check.go_tip) - tip_margin(m, check, margin, self.delay, still) < m.tip_stop
        )
        if m.shadow:
            if stale > m.stale_steps or go_error >= m.stop_at * limit or tipping:
                self.would_stop.append(t)
            return self._send(action)
        if self.mode == RUN:
            why = STALE if stale > m.stale_steps else (BALANCE if go_error >= m.stop_at * limit else None)
            why = TIP if why is None and tipping else why
            if why is not None:
                self._stop(t, why, check.stop_plan)
        else:
            self.stopped_for += 1
            if not self.final:
                if self.reason == STALE:  # fresh frames again, and the action is safe
                    can_go = stale <= m.stale_steps and go_error < m.stop_at * limit and not tipping
                else:  # known at rest, and the turn's next step and stop predicted well inside the limit
                    inside = float(check.go) + resume_margin < m.resume_below * limit
                    can_go = still and inside and not tipping
                if can_go:
                    self.mode, self.reason = RUN, None
                    self.resumes.append(t)
                elif (
                    self.reason != STALE
                    and still
                    and m.recover
                    and not tipping
                    and self._recovers(check, resume_margin)
                ):
                    self.recoveries.append(t)
                    self._recovering = True
                    self._recovered_from = float(check.now) if m.recover_until_worse else None
                    self._plan = deque(np.asarray(check.go_stop, np.float64)[:-1])
                    return self._send(action)  # the planner's own action: not a stop's
                elif self.stopped_for >= m.stop_timeout:
                    self.final = True
            if self.final and still and self.stopped_for >= 2:
                self.ended = True
        if self.mode == RUN:
            return self._send(action)
        if not self._recovering:  # a crossing that a recovery led to was not foreseen by a stop
            self.stopping_steps.add(t)
        return self._send(self._plan.popleft() if self._plan else np.zeros(4))

    def _travel(self) -> float:
        """The carriage travel in flight: the squared per-carriage sums of the actions in flight (m^2)."""
        return float(np.sum(np.square(np.sum(self._in_flight, axis=0)))) if self._in_flight else 0.0

    def _margins(self, sigma: float, still: bool, miss: float, travel: float) -> tuple[float, float]:
        """(the balance check's margin, a resume's and a recovery's): k_sigma (resume_k_sigma) of the
        estimate's y std `sigma` and k_delay of the prediction's error over the delay (none when the
        gripper is known at rest: `still`; with the drag of the carriage `travel` in flight; the
        prediction's recent `miss` where the model is failing), in quadrature."""
        m = self.m
        delay_var = 0.0 if still else self.delay_var + m.drag_std**2 * travel
        if (
            not still
            and m.miss_sigmas > 0
            and miss > m.miss_sigmas * math.sqrt(self.delay_var + 2 * sigma**2)
        ):
            delay_var = max(delay_var, miss**2)  # the model is failing here: its miss is its error
        k_delay = m.k_sigma if m.k_delay is None else m.k_delay
        k_resume = m.k_sigma if m.resume_k_sigma is None else m.resume_k_sigma
        margin = math.sqrt((m.k_sigma * sigma) ** 2 + k_delay**2 * delay_var)
        return margin, math.sqrt((k_resume * sigma) ** 2 + k_delay**2 * delay_var)

    def tip_spread(
        self, sigma: float, belt_speed, measured=None, predicted=None, yaw_sigma: float = 0.0
    ) -> np.ndarray:
        """(4,) how far off (x m, y m, yaw rad) the checked pose may be, and how much further in y per m of
        carriage travel along the checked rollout, for the "sigma" tipping watch
        (`MonitorConfig.tip_uncertainty`; `check`'s `tip_spread`), from what the step's `decide` will be
        given (the same arguments; `yaw_sigma`: the estimate's yaw std, rad) before it is called: in x the
        balance check's margin, in y that and k_delay `tip_drag_std` of the carriage travel in flight, in
        yaw k_sigma of `yaw_sigma` and k_delay of `tip_yaw_std` per square-root step of delay (none when
        the gripper is known at rest), each in quadrature; then k_delay `tip_drag_std`. Changes nothing."""
        m = self.m
        misses = list(self._misses)
        if (
            self.delay
            and measured is not None
            and predicted is not None
            and len(self._predicted) == self.delay
        ):
            misses = [*misses, abs(_offset(measured) - self._predicted[0])][-m.miss_window :]
        still = self.rest.still(belt_speed)
        travel = self._travel()
        margin = self._margins(sigma, still, max(misses, default=0.0), travel)[0]
        k_delay = m.k_sigma if m.k_delay is None else m.k_delay
        drag = tip_drag(m)
        y = math.sqrt(margin**2 + drag**2 * travel)
        yaw = math.hypot(
            m.k_sigma * yaw_sigma, k_delay * m.tip_yaw_std * math.sqrt(self.delay) * (1.0 - still)
        )
        return np.array([margin, y, yaw, drag], np.float32)

    def _recovers(self, check: Check, margin: float) -> bool:
        """At rest between the thresholds: does the action bring the box `recover_gain` closer to the
        middle, once its stop has played out, without passing `stop_at` on the way?"""
        m = self.m
        return (
            not self.recovery_failed
            and float(check.go_ahead) + margin < m.stop_at * self.limit
            and float(check.go_end) <= float(check.now) - m.recover_gain
        )

    def _track(self, measured, predicted) -> float:
        """Record this step's prediction and the miss of the one made `delay` steps ago for now (the newest
        estimate is of that time); the largest |miss| of the last `miss_window` steps (m), 0 if none."""
        if self.delay and measured is not None and predicted is not None:
            if len(self._predicted) == self.delay:
                self._misses.append(abs(_offset(measured) - self._predicted[0]))
            self._predicted.append(_offset(predicted))
        return max(self._misses, default=0.0)

    def _send(self, a) -> np.ndarray:
        a = np.asarray(a, np.float64)
        self.rest.sent(a)
        self._in_flight.append(a[2:])
        return a

    def _stop(self, t: int, why: str, plan) -> None:
        self.mode, self.reason, self.stopped_for = STOP, why, 0
        self._plan = deque(np.asarray(plan, np.float64).reshape(-1, 4))
        self.stops.append((t, why))
        if why != STALE:  # a balance or a tipping stop: both count toward max_stops
            self.balance_stops += 1
            self.final = self.balance_stops >= self.m.max_stops

    @property
    def stopped(self) -> bool:
        return self.mode == STOP

    def record(self) -> dict:
        """The monitor's part of an episode summary (plain data)."""
        return record(
            self.stops, len(self.resumes), len(self.recoveries), self.would_stop if self.m.shadow else None
        )


def record(stops, resumes: int, recoveries: int, would_stop=None) -> dict:
    """The monitor's part of an episode summary from its stops ((control step, reason) each), the counts
    of its resumes and recoveries and, in shadow mode, the steps it would have stopped at."""
    return {
        "monitor_stops": len(stops),
        "monitor_stop_steps": [t for t, _ in stops],
        "monitor_stop_reasons": [r for _, r in stops],
        "monitor_resumes": resumes,
        "monitor_recoveries": recoveries,
        **({"monitor_would_stop": would_stop} if would_stop is not None else {}),
    }


def tip_watch(m: MonitorConfig):
    """The check's `tip` for these settings: False (no tipping watch), True (the margin), "slope" (the
    margin and its slope, for tip_uncertainty "pose") or "sigma" (the margin at the spread's poses)."""
    if m.tip_stop <= 0:
        return False
    return {"y": True, "pose": "slope", "sigma": "sigma"}[m.tip_uncertainty]


def tip_drag(m: MonitorConfig) -> float:
    """The "sigma" watch's y spread per m of carriage travel: k_delay `tip_drag_std`."""
    return (m.k_sigma if m.k_delay is None else m.k_delay) * m.tip_drag_std


def tip_margin(m: MonitorConfig, check: Check, margin, delay: int, still):
    """What the tipping watch subtracts from `check.go_tip` (`MonitorConfig.tip_uncertainty`): `margin`,
    the balance check's for the estimate's y, alone ("y"), or ("pose") that margin in x and y and k_delay
    `tip_yaw_std` per square-root step of `delay` in yaw (none when the gripper is known at rest: `still`),
    each times the margin's slope (`Check.go_tip_slope`), in quadrature. numpy or jnp alike."""
    if m.tip_uncertainty == "y":
        return margin
    if m.tip_uncertainty == "sigma":  # counted in the check's points (`Monitor.tip_spread`)
        return 0.0 * margin
    k_delay = m.k_sigma if m.k_delay is None else m.k_delay
    yaw = k_delay * m.tip_yaw_std * math.sqrt(delay) * (1.0 - still)
    sx, sy, syaw = check.go_tip_slope[0], check.go_tip_slope[1], check.go_tip_slope[2]
    return ((sx * margin) ** 2 + (sy * margin) ** 2 + (syaw * yaw) ** 2) ** 0.5


def recovery_worse(before, after, tolerance):
    """Whether a recovery left the box further from the middle: the balance error at rest `after` it
    above the one it was sent at (`before`) by more than `tolerance` (m). Works on floats and jnp."""
    return after - before > tolerance


def _offset(s) -> float:
    return float(geometry.balance_offset(np.asarray(s, np.float64)))


def crossing(balance_errors, limit: float, stopping_steps, guard_steps=()) -> tuple[bool, bool]:
    """(crossed, unnoticed) for an episode's TRUE balance errors (T+1,) after each action (index 0 is the
    reset): crossed when one passed `limit`; unnoticed when, at the first crossing, the action that led to
    it was not a stop (a monitor stop or the exploration guard's re-centring, `stopping_steps` and
    `guard_steps`: control-step indices of those actions)."""
    over = np.flatnonzero(np.asarray(balance_errors) > limit)
    if over.size == 0:
        return False, False
    t = int(over[0])
    if t == 0:  # over the limit at the reset: nothing could have stopped it
        return True, True
    noticed = (t - 1) in set(stopping_steps) or (t - 1) in set(guard_steps)
    return True, not noticed
