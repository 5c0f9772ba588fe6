"""Predictive sampling over action sequences with the physics prior (beyond the paper's one-step planner).

Why. The paper's planner (`planner.py`) scores each candidate action by the state ONE control step ahead.
Measured in closed loop with the simulator (docs/results/planner.md), that is too short-sighted for boxes
whose
centre of mass is far off-centre (box C): a 0.05 s prediction cannot see that a turn started now carries
the box's geometric centre sideways for the next half second, faster than the belts can follow, and the
random pick on the Pareto front alternates between turning and re-centring without a plan for either.

What. Predictive sampling (Howell et al. 2022, the default planner of MuJoCo MPC): keep a nominal plan of
`horizon` actions; each control step, roll out the nominal and `n_samples - 1` gaussian perturbations of
it with the physics prior (`prior.predict`, one vmap over sequences, one scan over time), score every
rollout, keep the best as the new nominal, send its first action, and shift it by one step. Nothing is
learned; the prior alone is the model.

Actions are the simulator's full 4-d actions (both belt-speed setpoints and both position steps at once):
the paper restricts its candidates to one non-zero component so that its calibrated action->force map
applies; the "slip" prior needs no such restriction.

Score (lower is better), summed over the predicted states s_1..s_H (paper's objectives, made a cost):
  * pose:     w_yaw * (sqrt(e^2 + d^2) - d), e the yaw error, d the task's 2 degree tolerance ("l1",
              default), or w_yaw * e^2 ("quadratic": R1 of eq. 1 without the epsilon, the cost before
              2026-12-01). A quadratic's pull vanishes near the target, where the balance and effort
              terms then win: episodes stalled a few degrees short with the carriages at their stops;
  * balance:  w_balance * (balance_error / limit)^2    (R2 of eq. 1) plus a steep barrier
              w_barrier * relu(balance_error / limit - safe_fraction)^2 beyond safe_fraction of the limit;
  * workspace: the same barrier on the box's overhang beyond the belt ends (x), on its distance
              outside the band where the carriages can still centre the belts on it (y), and on each
              belt's support: less than `support_margin` of a belt's width under the box
              (`support_deficit`);
  * tipping:  the same barrier on how much closer than `tip_margin` the centre of mass comes to the edge
              of the support polygon (`prior.stability_margin`). With the belts spread to their stops a
              turned box rests on two corner patches; box C, whose centre of mass lies off that diagonal,
              tipped into the gap in 5 of 20 episodes without this term (oracle, seeds 0-19, the support
              barrier alone), in none with it;
  * effort:   w_effort * (dp / max_position_step)^2 (sideways moves drag the box; use them when needed);
  * turn end: on the last predicted state only, w_reach * relu(turn_end_excess / limit)^2: how far beyond
              the carriages' reach the geometric centre will be once the box has turned to the target
              about its centre of mass (`turn_end_excess`; needs a model that knows the centre of mass).
              A terminal cost that sees the carriage stops beyond the horizon: a box with its centre of
              mass far along its length must be dragged sideways while it turns, or it stalls with both
              carriages at their stops.
The best rollout's (R1, R2) at its worst state are reported in PlanInfo so the Pareto view of the paper
stays available.

Beyond predictive sampling (all `SamplingOptions`, measured in docs/results/planner.md): perturbations at
spline
knots (`n_knots`, MuJoCo MPC's parameterisation), several sampling rounds per step with MPPI's weighted
mean or CEM's elite mean and std (`update`, `iterations`), Adam refinement of the chosen sequence by
gradient through the differentiable prior (`gradient_steps`, optax), and a deadband on carriage steps
(`position_deadband`). `make(cfg, options)` puts the planner behind the one planner interface
(`planning.Planner`).

Particle models (`planning` module docstring: a PETS ensemble, an ensemble of priors): every candidate
sequence is rolled out as P particles and its cost is the particles' costs aggregated by
`particle_risk` (mean by default; mean + particle_risk_k * std, or the worst particle), the same for the
sampled candidates, the gradient refinement and the scoring of what is sent. The particles' noise comes
from this step's key (`planning.PARTICLE_STREAM` folded in): common to all candidates of the step. A
single-trajectory model (the prior, W) takes the plain path, which is what it was before particles
existed (bit-identical plans; a test).

Keys are explicit; `make_sampling_planner(cfg, **options)` returns a jitted
`plan(key, model, window, belt_speed, target_yaw, nominal) -> (action (4,), SamplingInfo)`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import geometry, planning
from boxjax.config import Config
from boxjax.planners import terms

UPDATES = ("best", "mppi", "cem")
POSE_COSTS = ("quadratic", "l1")


@dataclasses.dataclass(frozen=True)
class SamplingOptions:
    """Settings of the predictive-sampling planner (static: changing one recompiles)."""

    n_samples: int = 64  # rollouts per control step, the nominal included
    horizon: int = 10  # control steps per rollout (0.5 s at 20 Hz)
    speed_sigma: float = 0.04  # m/s, std of the perturbation of each belt-speed setpoint
    position_sigma: float = 0.004  # m, std of the perturbation of each position step
    speed_cap: float | None = 0.12  # m/s, |setpoint| limit (None: the belt speed limit); see below
    position_cap: float | None = None  # m, |carriage step| limit per control step (None: the hardware's)
    w_yaw: float = 1.0
    w_balance: float = 0.5
    w_barrier: float = 1000.0
    # Of the balance limit, where the barrier starts. 0.5 left box C (oracle) 18/20 (2 unbalanced: the
    # carriages near their stops could not re-centre a drift that began above 2 cm); 0.4: 40/40.
    safe_fraction: float = 0.4
    x_margin: float = 0.03  # m, keep the footprint this far inside the belt ends
    y_margin: float = 0.01  # m, keep the geometric centre this far inside the carriages' reach
    support_margin: float = 0.06  # m, each belt keeps at least this much of its width under the box
    tip_margin: float = 0.03  # m, the centre of mass stays this far inside the support polygon
    w_effort: float = 0.01
    # Turn-end reach: w_reach * relu(turn_end_excess / balance_limit)^2 on the last predicted state, where
    # the geometric centre will be once the box has turned to the target about its centre of mass
    # (`turn_end_excess`). 0: off. 100 was chosen over 30 and 300 on development seeds
    # (docs/results/random-boxes.md); models without a centre of mass (W, PETS) get no term.
    w_reach: float = 100.0
    # Carriage rate: w_position_rate * ((dp_k - dp_{k-1}) / max_position_step)^2 over the sequence, dp_{-1}
    # the carriages' last observed step (window). 0: off. See `position_rate_cost`.
    w_position_rate: float = 0.0
    # Perturbations drawn at this many knots spread evenly over the horizon and interpolated linearly in
    # between (MuJoCo MPC's spline parameterisation); None: an independent draw at every step.
    n_knots: int | None = None
    # How the sampling mean moves between rounds: "best" (predictive sampling: the lowest-cost sequence),
    # "mppi" (cost-weighted mean, `temperature`), "cem" (mean and std of the `n_elite` best).
    update: str = "best"
    iterations: int = 1  # sampling rounds per control step (each n_samples sequences)
    temperature: float = 0.1  # MPPI, relative to the mean cost spread above the best
    n_elite: int = 8  # CEM
    min_sigma_fraction: float = 0.2  # CEM, the std never shrinks below this fraction of the sigmas
    # Adam steps through the prior on the chosen sequence (0: none). 5 turned 273 of 300 random safe boxes
    # (oracle, seeds 0-2) against 259 without, for 1.8x the planning time (docs/results/random-boxes.md).
    gradient_steps: int = 5
    gradient_lr: float = 0.1  # in units of the perturbation std per step
    # m: position steps smaller than this are sent (and predicted) as 0. Every carriage step is an
    # impulsive event the prior predicts worst (docs/results/planner.md: one-step error 0.75 mm for position
    # actions,
    # 0.25 mm for speed actions); without a deadband the gaussian noise moves a carriage every step.
    position_deadband: float = 0.0
    # The pose term: "quadratic" w_yaw * e^2 (the paper's R1 = 1 / (e^2 + eps) made a cost), or "l1"
    # w_yaw * (sqrt(e^2 + d^2) - d) with d the task's yaw tolerance: a quadratic cost's pull vanishes
    # near the target (at 5 degrees its slope is 1/5 of the L1's), where the other terms then decide.
    pose_cost: str = "l1"
    # Particle models only (planning.n_particles(model) is not None): how a candidate's particle costs
    # are aggregated (planning.RISKS: "mean", "mean_std" = mean + particle_risk_k * std, "worst").
    particle_risk: str = "mean"
    particle_risk_k: float = 1.0

    def __post_init__(self):
        if self.n_samples < 2 or self.horizon < 1:
            raise ValueError(f"need n_samples >= 2 and horizon >= 1, got {self.n_samples}, {self.horizon}")
        if self.pose_cost not in POSE_COSTS:
            raise ValueError(f"unknown pose_cost {self.pose_cost!r}; choose one of {POSE_COSTS}")
        if self.particle_risk not in planning.RISKS:
            raise ValueError(f"unknown particle_risk {self.particle_risk!r}; choose one of {planning.RISKS}")
        if self.update not in UPDATES:
            raise ValueError(f"unknown update {self.update!r}; choose one of {UPDATES}")
        if self.iterations < 1 or self.gradient_steps < 0:
            raise ValueError(
                f"need iterations >= 1 and gradient_steps >= 0, got {self.iterations}, {self.gradient_steps}"
            )
        if self.update == "cem" and not 1 <= self.n_elite < self.n_samples:
            raise ValueError(f"CEM needs 1 <= n_elite < n_samples, got {self.n_elite}, {self.n_samples}")
        if self.temperature <= 0 or not 0 < self.min_sigma_fraction <= 1:
            raise ValueError("need temperature > 0 and min_sigma_fraction in (0, 1]")
        if self.n_knots is not None and not 2 <= self.n_knots <= self.horizon:
            raise ValueError(f"n_knots must be in 2..horizon ({self.horizon}) or None, got {self.n_knots}")
        if self.w_reach < 0:
            raise ValueError(f"w_reach must be >= 0, got {self.w_reach}")
        if min(self.speed_sigma, self.position_sigma) < 0 or not 0 < self.safe_fraction <= 1:
            raise ValueError("sigmas must be >= 0 and safe_fraction in (0, 1]")
        for name in ("speed_cap", "position_cap"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"{name} must be > 0 or None, got {v}")


class SamplingInfo(NamedTuple):
    """What one planning step considered. N = n_samples, H = horizon.

    nominal: (H, 4) the chosen sequence (its first row is the action sent), shifted by `shift_nominal`
      for the next step. states: (H, 5) its predicted states (a particle model: the particles' mean).
      cost: (N,) rollout costs (particle models: aggregated over particles; row 0 is the old
      nominal). best: () index of the chosen rollout. balance_error: () m, worst predicted over the
      chosen rollout. yaw_error: () rad at its last state.
    """

    nominal: jax.Array
    states: jax.Array
    cost: jax.Array
    best: jax.Array
    balance_error: jax.Array
    yaw_error: jax.Array


def initial_nominal(cfg: Config, options: SamplingOptions, belt_speed=None) -> jax.Array:
    """(H, 4) the first nominal: hold the current belt speeds (zero if not given), no sideways moves."""
    v = jnp.zeros(2) if belt_speed is None else jnp.asarray(belt_speed, jnp.float32)
    return jnp.tile(jnp.concatenate([v, jnp.zeros(2)])[None], (options.horizon, 1)).astype(jnp.float32)


def knot_matrix(horizon: int, n_knots: int | None) -> np.ndarray:
    """(horizon, n_knots) linear interpolation from knot values to steps (identity when n_knots is None):
    knots at steps 0, (H - 1) / (K - 1), ..., H - 1."""
    if n_knots is None:
        return np.eye(horizon, dtype=np.float32)
    t = np.linspace(0.0, n_knots - 1.0, horizon)
    return np.clip(1.0 - np.abs(t[:, None] - np.arange(n_knots)[None]), 0.0, 1.0).astype(np.float32)


def perturbations(key, o: SamplingOptions) -> jax.Array:
    """(n_samples - 1, horizon, 4) unit-variance-at-the-knots gaussian perturbations (see `n_knots`)."""
    k = o.horizon if o.n_knots is None else o.n_knots
    z = jax.random.normal(key, (o.n_samples - 1, k, 4))
    return jnp.einsum("hk,nkc->nhc", jnp.asarray(knot_matrix(o.horizon, o.n_knots)), z)


def shift_nominal(nominal) -> jax.Array:
    """Drop the executed first action and repeat the last one (receding horizon)."""
    return jnp.concatenate([nominal[1:], nominal[-1:]], axis=0)


def clip_actions(
    actions,
    cfg: Config,
    speed_cap: float | None = None,
    position_deadband: float = 0.0,
    position_cap: float | None = None,
):
    """Clip (..., 4) actions to the hardware (and the planner's speed and carriage-step caps); position
    steps smaller than `position_deadband` (m) become 0."""
    g = cfg.gripper
    vmax = g.belt_speed_limit if speed_cap is None else min(speed_cap, g.belt_speed_limit)
    pmax = g.max_position_step if position_cap is None else min(position_cap, g.max_position_step)
    hi = jnp.array([vmax, vmax, pmax, pmax], jnp.float32)
    a = jnp.clip(actions, -hi, hi)
    if position_deadband > 0:
        dp = a[..., 2:]
        a = a.at[..., 2:].set(jnp.where(jnp.abs(dp) < position_deadband, 0.0, dp))
    return a


def support_deficit(s, cfg: Config, margin: float) -> jax.Array:
    """() m: how much less than `margin` of belt width lies under the box on the worse-supported belt
    (negative: both belts carry the box over more than `margin`). The box's footprint spans
    y +- (|sin| l / 2 + |cos| w / 2); belt i covers P_i +- belt_width / 2. When the carriages spread the
    belts until one only touches the box's edge, the box tips into the gap (the planar prior cannot see
    that; measured in the simulator)."""
    hx, hy, _ = cfg.box.half_size
    half_w = cfg.gripper.belt_width / 2
    ext = jnp.abs(jnp.sin(s[geometry.YAW])) * hx + jnp.abs(jnp.cos(s[geometry.YAW])) * hy
    lo, hi = s[geometry.Y] - ext, s[geometry.Y] + ext
    over1 = jnp.minimum(s[geometry.P1] + half_w, hi) - jnp.maximum(s[geometry.P1] - half_w, lo)
    over2 = jnp.minimum(s[geometry.P2] + half_w, hi) - jnp.maximum(s[geometry.P2] - half_w, lo)
    return margin - jnp.minimum(over1, over2)


def turn_end_excess(s, com_xy, target_yaw, cfg: Config, y_margin: float) -> jax.Array:
    """() m: how far outside the carriages' reach (`terms.y_excess`) the box's geometric centre will lie
    when the box, now in state s (5,), has turned to `target_yaw` about its centre of mass (box frame
    (x, y) `com_xy`, m).

    Why: the belts push only along x, so a turn leaves the centre of mass's y where it is, and only a
    carriage's sideways drag moves it. The geometric centre then ends at y_end = y_com - (sin(target) c_x +
    cos(target) c_y): a box with its centre of mass 12 cm along its length ends 12 cm to the side of it.
    If y_end is out of the belts' reach the turn cannot be finished balanced; the box has to be dragged
    sideways first, which takes longer than a planning horizon, so the horizon's states alone cannot see
    it (docs/results/random-boxes.md: the step-cap failures)."""
    cx, cy = com_xy[0], com_xy[1]
    yaw = s[geometry.YAW]
    y_com = s[geometry.Y] + jnp.sin(yaw) * cx + jnp.cos(yaw) * cy
    y_end = y_com - (jnp.sin(target_yaw) * cx + jnp.cos(target_yaw) * cy)
    return terms.y_excess(s.at[geometry.Y].set(y_end), cfg, y_margin)


def rollout_cost(model, states, actions, target_yaw, cfg: Config, o: SamplingOptions) -> jax.Array:
    """() cost of one predicted rollout (see module docstring); `model` (the model slot,
    `planning.Model`) gives the stability margin for the tipping barrier and the centre of mass for the
    turn-end term."""
    margins = jax.vmap(model.stability_margin)(states)
    return cost_given_margins(states, margins, actions, target_yaw, cfg, o, planning.planar_com(model))


def cost_given_margins(
    states, margins, actions, target_yaw, cfg: Config, o: SamplingOptions, com_xy=None
) -> jax.Array:
    """() cost of one predicted rollout (H, 5) whose stability margins (H,) m are given; `com_xy` (2,) m,
    the box-frame centre of mass for the turn-end term (None: a model that knows none; no such term)."""
    lim = cfg.task.balance_limit
    yaw_err = states[:, geometry.YAW] - target_yaw
    bal = jax.vmap(geometry.balance_error)(states) / lim
    over_x = jax.vmap(lambda s: terms.overhang(s, cfg))(states) + o.x_margin
    over_y = jax.vmap(lambda s: terms.y_excess(s, cfg, o.y_margin))(states)
    relu2 = lambda u: jnp.square(jnp.maximum(u, 0.0))  # noqa: E731
    support = jax.vmap(lambda s: support_deficit(s, cfg, o.support_margin))(states)
    tip = o.tip_margin - margins
    barrier = relu2(bal - o.safe_fraction) + relu2(over_x / lim) + relu2(over_y / lim) + relu2(support / lim)
    barrier = barrier + relu2(tip / lim)
    effort = jnp.sum(jnp.square(actions[:, 2:] / cfg.gripper.max_position_step), axis=-1)
    if o.pose_cost == "l1":
        d = cfg.task.yaw_tolerance
        pose = jnp.sqrt(yaw_err**2 + d * d) - d
    else:
        pose = yaw_err**2
    per_step = o.w_yaw * pose + o.w_balance * bal**2 + o.w_barrier * barrier + o.w_effort * effort
    total = jnp.sum(per_step)
    if o.w_reach > 0 and com_xy is not None:
        end = turn_end_excess(states[-1], com_xy, target_yaw, cfg, o.y_margin)
        total = total + o.w_reach * relu2(end / lim)
    return total


def position_rate_cost(seq, window, cfg: Config, o: SamplingOptions) -> jax.Array:
    """() w_position_rate * sum_k ((dp_k - dp_{k-1}) / max_position_step)^2 for a sequence (H, 4), with
    dp_{-1} = P_t - P_{t-1} the carriages' last step as observed (window (W, 5)).

    Why: predictive sampling's best-of-N keeps each sample's gaussian noise, and a cost on states cannot
    tell a carriage alternating +-10 mm from one standing still (their net moves are alike), so the
    carriages chatter at the step limit. Each carriage step is an impulsive event that the prior predicts
    worst (docs/results/planner.md: its one-step error is 3x larger for position actions), and a real servo
    wears under
    it. A penalty on the rate, not the size, leaves a sustained move free."""
    if o.w_position_rate <= 0:
        return jnp.zeros((), seq.dtype)
    prev = window[-1, geometry.P1 : geometry.P2 + 1] - window[-2, geometry.P1 : geometry.P2 + 1]
    dp = jnp.concatenate([prev[None], seq[:, 2:]], axis=0)
    rate = jnp.diff(dp, axis=0) / cfg.gripper.max_position_step
    return o.w_position_rate * jnp.sum(jnp.square(rate))


def evaluate_sequences(
    model, window, belt_speed, target_yaw, seqs, cfg: Config, o: SamplingOptions, key=None
):
    """(states (N, H, 5), cost (N,)) of the sequences (N, H, 4) under the model; non-finite costs -> inf.
    A particle model (`planning.n_particles`) needs `key` (its particles' noise, common to all N
    sequences); its states are the particles' mean and its cost the particles' aggregate
    (`o.particle_risk`)."""
    if planning.n_particles(model) is None:
        states = jax.vmap(lambda seq: model.rollout_sequence(window, belt_speed, seq))(seqs)
        cost = jax.vmap(rollout_cost, in_axes=(None, 0, 0, None, None, None))(
            model, states, seqs, target_yaw, cfg, o
        )
    else:
        if key is None:
            raise ValueError("a particle model needs a key (its particles' noise) to evaluate sequences")
        states, cost = jax.vmap(
            lambda seq: particle_cost(model, key, window, belt_speed, target_yaw, seq, cfg, o)
        )(seqs)
    if o.w_position_rate > 0:
        cost = cost + jax.vmap(lambda seq: position_rate_cost(seq, window, cfg, o))(seqs)
    return states, jnp.where(jnp.isfinite(cost), cost, jnp.inf)


def particle_cost(model, key, window, belt_speed, target_yaw, seq, cfg: Config, o: SamplingOptions):
    """(mean states (H, 5), aggregated cost ()) of ONE sequence (H, 4) under a particle model."""
    parts = planning.rollout_particles(model, key, window, belt_speed, seq)  # (P, H, 5)
    margins = planning.particle_margins(model, parts)  # (P, H)
    costs = jax.vmap(cost_given_margins, in_axes=(0, 0, None, None, None, None, None))(
        parts, margins, seq, target_yaw, cfg, o, planning.planar_com(model)
    )
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    return jnp.mean(parts, axis=0), planning.aggregate(costs, o.particle_risk, o.particle_risk_k)


def _update(seqs, cost, sigma, o: SamplingOptions):
    """The next sampling mean (H, 4) and std (H, 4) from scored sequences, by `o.update`."""
    if o.update == "mppi":
        # Weights exp(-(c - c_min) / (temperature x spread)): the temperature is relative to the spread
        # of the finite costs, so the rule does not depend on the cost's units (its barriers span 1e3).
        finite = jnp.isfinite(cost)
        c = jnp.where(finite, cost, 0.0)
        lo = jnp.min(jnp.where(finite, cost, jnp.inf))
        spread = jnp.sum(c - lo * finite) / jnp.maximum(jnp.sum(finite), 1) + 1e-9
        w = jnp.where(finite, jnp.exp(-(c - lo) / (o.temperature * spread)), 0.0)
        w = w / jnp.sum(w)
        return jnp.einsum("n,nhc->hc", w, seqs), sigma
    # "cem": mean and std of the elite set; the std shrinks to no less than min_sigma_fraction of the prior
    elite = seqs[jnp.argsort(cost)[: o.n_elite]]
    std = jnp.clip(jnp.std(elite, axis=0), o.min_sigma_fraction * sigma, sigma)
    return jnp.mean(elite, axis=0), std


def refine_gradient(model, window, belt_speed, target_yaw, seq, cfg: Config, o: SamplingOptions, key=None):
    """`o.gradient_steps` Adam steps (optax) on the rollout cost w.r.t. the sequence (H, 4), through the
    differentiable prior, projected onto the action limits after each step. Returns (sequence, cost) of
    the best iterate (the start included), so refining never makes the plan worse under the model.
    A particle model descends its aggregated particle cost with the particles' noise of `key` fixed."""
    if planning.n_particles(model) is None:

        def cost_of(x):
            st = model.rollout_sequence(window, belt_speed, x)
            return rollout_cost(model, st, x, target_yaw, cfg, o)

    else:

        def cost_of(x):
            return particle_cost(model, key, window, belt_speed, target_yaw, x, cfg, o)[1]

    if o.w_position_rate > 0:
        state_cost = cost_of

        def cost_of(x):
            return state_cost(x) + position_rate_cost(x, window, cfg, o)

    scale = jnp.array([o.speed_sigma, o.speed_sigma, o.position_sigma, o.position_sigma], jnp.float32)
    opt = optax.adam(o.gradient_lr)  # in units of the perturbation std: the actions' scales differ by 10x
    value_grad = jax.value_and_grad(lambda z: cost_of(z * scale))

    def step(carry, _):
        z, state, best_z, best_c = carry
        c, g = value_grad(z)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        better = jnp.isfinite(c) & (c < best_c)
        best_z, best_c = jnp.where(better, z, best_z), jnp.where(better, c, best_c)
        upd, state = opt.update(g, state, z)
        z = clip_actions(optax.apply_updates(z, upd) * scale, cfg, o.speed_cap, 0.0, o.position_cap) / scale
        return (z, state, best_z, best_c), None

    z0 = seq / scale
    (z, _, best_z, best_c), _ = jax.lax.scan(
        step, (z0, opt.init(z0), z0, jnp.inf), None, length=o.gradient_steps
    )
    c_last = cost_of(z * scale)
    last_better = jnp.isfinite(c_last) & (c_last < best_c)
    best_z, best_c = jnp.where(last_better, z, best_z), jnp.where(last_better, c_last, best_c)
    return best_z * scale, best_c


def plan(
    key, model: planning.Model, window, belt_speed, target_yaw, nominal, cfg: Config, o: SamplingOptions
):
    """One planning step: (action (4,), SamplingInfo). Pure; jit with `make_sampling_planner`.

    `o.iterations` rounds of: sample around the mean (the nominal first), score, update the mean
    (`o.update`: keep the best, MPPI's weighted mean, or CEM's elite mean and std). The plan is the
    lowest-cost sequence evaluated in any round (an updated mean is evaluated too), then optionally
    refined by gradient (`o.gradient_steps`). A particle model's noise comes from `key` (folded with
    `planning.PARTICLE_STREAM`), the same for every candidate of this step."""
    nominal = jnp.asarray(nominal, jnp.float32)
    key_p = None if planning.n_particles(model) is None else jax.random.fold_in(key, planning.PARTICLE_STREAM)
    if nominal.shape != (o.horizon, 4):
        raise ValueError(f"nominal must have shape ({o.horizon}, 4), got {nominal.shape}")
    sigma0 = jnp.array([o.speed_sigma, o.speed_sigma, o.position_sigma, o.position_sigma], jnp.float32)
    mean, sigma = nominal, jnp.broadcast_to(sigma0, nominal.shape)
    best_seq, best_cost, best_states, costs = nominal, jnp.inf, None, []
    keys = jax.random.split(key, o.iterations) if o.iterations > 1 else [key]
    for it in range(o.iterations):
        noise = perturbations(keys[it], o) * sigma
        seqs = clip_actions(
            jnp.concatenate([mean[None], mean[None] + noise]),
            cfg,
            o.speed_cap,
            o.position_deadband,
            o.position_cap,
        )
        states, cost = evaluate_sequences(model, window, belt_speed, target_yaw, seqs, cfg, o, key_p)
        costs.append(cost)
        i = jnp.argmin(cost)
        better = cost[i] < best_cost
        best_seq = jnp.where(better, seqs[i], best_seq)
        best_states = states[i] if best_states is None else jnp.where(better, states[i], best_states)
        best_cost = jnp.where(better, cost[i], best_cost)
        mean, sigma = (seqs[i], sigma) if o.update == "best" else _update(seqs, cost, sigma, o)
    if o.update != "best":  # score the final mean too
        mean = clip_actions(mean, cfg, o.speed_cap, o.position_deadband, o.position_cap)
        st_m, c_m = evaluate_sequences(model, window, belt_speed, target_yaw, mean[None], cfg, o, key_p)
        better = c_m[0] < best_cost
        best_seq, best_states = jnp.where(better, mean, best_seq), jnp.where(better, st_m[0], best_states)
        best_cost = jnp.where(better, c_m[0], best_cost)
    if o.gradient_steps > 0:
        seq_g, _ = refine_gradient(model, window, belt_speed, target_yaw, best_seq, cfg, o, key_p)
        # The deadband is not differentiable: apply it to the refined sequence and score what is sent.
        seq_g = clip_actions(seq_g, cfg, o.speed_cap, o.position_deadband, o.position_cap)
        st_g, c_g = evaluate_sequences(model, window, belt_speed, target_yaw, seq_g[None], cfg, o, key_p)
        better = c_g[0] < best_cost
        best_seq, best_states = jnp.where(better, seq_g, best_seq), jnp.where(better, st_g[0], best_states)
        best_cost = jnp.where(better, c_g[0], best_cost)
    cost = jnp.concatenate(costs)
    info = SamplingInfo(
        nominal=best_seq,
        states=best_states,
        cost=cost,
        best=jnp.argmin(cost),
        balance_error=jnp.max(jax.vmap(geometry.balance_error)(best_states)),
        yaw_error=best_states[-1, geometry.YAW] - target_yaw,
    )
    return best_seq[0], info


def make_sampling_planner(cfg: Config, options: SamplingOptions | None = None, **overrides):
    """A jitted `plan(key, model, window, belt_speed, target_yaw, nominal) -> (action, SamplingInfo)`."""
    o = options or SamplingOptions()
    if overrides:
        o = dataclasses.replace(o, **overrides)
    return jax.jit(functools.partial(plan, cfg=cfg, o=o))


def make(cfg: Config, options: SamplingOptions | None = None) -> planning.Planner:
    """Predictive sampling behind the planner interface (`planning.Planner`): the plan state is the
    nominal sequence (H, 4), shifted by one step after each action."""
    o = options or SamplingOptions()

    def optimize(key, model, obs: planning.Observation, nominal):
        a, info = plan(key, model, obs.window, obs.belt_speed, obs.target_yaw, nominal, cfg, o)
        return a, shift_nominal(info.nominal), info

    return planning.Planner(
        "sampling", lambda obs: initial_nominal(cfg, o, obs.belt_speed), jax.jit(optimize)
    )
