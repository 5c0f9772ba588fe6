"""An exploration designed for what it must reveal: the expected information of an action sequence about the
box's planar moments under the physics prior, and a search for the sequence that maximises it.

What the exploration must reveal, of all that the mass distribution is, is what reaches the motion
(docs/results/estimator-and-hazards.md#moments): the centre of mass (x, y, z) and I_zz. Their information in
an exploration is measured here the way optimal experiment design measures it (Bayesian D-optimality):

  * the box's moments theta = (com_x, com_y, com_z, log(I_zz / M)) (the last: the squared radius of
    gyration about the vertical through the centre of mass) enter the prior (`boxjax.prior`) through
    `PriorModel.com`, `.izz` and the contact offsets; the mass cancels under Coulomb friction and is not
    in theta (the exploration shows it through the drives' lags, which the prior does not model);
  * along the prior's own rollout of the sequence from rest, every step's one-step prediction of the box
    pose (x, y, yaw) from the window before it has a Jacobian J_t = d pose_{t+1} / d theta (forward mode);
  * the pose is seen with the prior's one-step error (`NOISE`: its median rms on recorded turns), so the
    Fisher information is F = sum_t J_t^T Sigma^-1 J_t;
  * with the population's covariance C0 of theta as the prior belief, the expected information gain is
    0.5 log det(I + C0^(1/2) F C0^(1/2)) nats per box, and the posterior std of each quantity
    sqrt(diag((C0^-1 + F)^-1)).

`search` (the cross-entropy method, as the planners' sampling) maximises the mean gain over a set of boxes
among sequences of the same shape as the paper's (15 vectors held 3 steps), under the shipped sequence's
rules: belt setpoints at most 0.09 m/s from the previous vector's (no clipping by the 0.6 m/s^2 ramp),
|v| <= 0.12 m/s, carriage steps <= 7 mm, every carriage move undone and the belts at rest at the end; and no
less safe than the shipped sequence, judged in the simulator (`simulated_offsets`: the worst balance errors
of label-safe boxes and the exploration guard's judgement of them, `guard_judged`) or, less reliably, by the
prior's open-loop prediction. The search ranks sequences by the PRIOR's account of their information; what
a sequence reveals in the simulator is measured by `scripts/exploration_design.py` (a regressor trained on
simulated explorations of each), which decides (docs/results/estimator-and-hazards.md#designed-exploration).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning
from boxjax.config import DEFAULT, Config
from boxjax.estimator import explore
from boxjax.prior import force_map as calibrate
from boxjax.prior import predictor
from boxjax.sim import native

THETA = ("com_x", "com_y", "com_z", "log_gyration2")
# The prior's one-step error on recorded turns (x, y in m; yaw in rad): the median rms of its one-step
# predictions, 1.6-1.9 mm and 0.42-0.44 degrees (benchmarks/results_turn_evidence.json, k = 1).
NOISE = np.array([1.8e-3, 1.8e-3, np.radians(0.43)])
V_MAX = 0.12  # m/s, the largest belt setpoint the search may ask (the shipped sequence's)
DV_MAX = 0.09  # m/s between consecutive vectors: a vector held 3 steps reaches its setpoint (0.6 m/s^2)
DP_MAX = 0.007  # m per step, the largest carriage step the search may ask (the shipped sequence's)


def theta_of(masses, cfg: Config = DEFAULT) -> jax.Array:
    """(4,) theta = (com_x, com_y, com_z, log(I_zz / M)) of voxel masses (nx, ny, nz) kg."""
    p = massdist.mass_properties_from_masses(jnp.asarray(masses, jnp.float32), cfg.box)
    return jnp.concatenate([p.com, jnp.log(p.inertia[2, 2] / p.mass)[None]])


def with_theta(model: predictor.PriorModel, theta) -> predictor.PriorModel:
    """The prior `model` with its centre of mass and I_zz replaced by theta's (differentiable)."""
    com = jnp.asarray(theta[:3], jnp.float32)
    izz = model.mass * jnp.exp(theta[3])
    return dataclasses.replace(model, com=com, izz=izz, offsets=calibrate.bottom_offsets_box(com, model.box))


def initial_state(cfg: Config = DEFAULT) -> jax.Array:
    """(5,) the state every exploration starts from: the belts at `belt_y0`, the box centred, at rest."""
    p1, p2 = cfg.gripper.belt_y0
    return jnp.array([p1, p2, 0.0, 0.5 * (p1 + p2), 0.0], jnp.float32)


class Information(NamedTuple):
    """One box's information about theta from one sequence (per box when vmapped)."""

    fisher: jax.Array  # (4, 4)
    worst_balance: jax.Array  # () m, the largest |balance offset| along the prior's rollout
    states: jax.Array  # (T, 5) the prior's rollout


def information(model: predictor.PriorModel, actions, cfg: Config = DEFAULT, noise=NOISE) -> Information:
    """The Fisher information about theta of the commanded `actions` (T, 4) for the box of `model` (pure;
    vmap over boxes and sequences). See the module docstring."""
    actions = jnp.asarray(actions, jnp.float32)
    s0 = initial_state(cfg)
    window0 = planning.initial_window(s0)
    belt0 = jnp.zeros(2, jnp.float32)
    states = model.rollout_sequence(window0, belt0, actions)  # (T, 5)
    past = jnp.concatenate([window0, states[:-1]])  # (T + 2, 5): the windows ending at s_0 .. s_{T-1}
    windows = past[jnp.arange(actions.shape[0])[:, None] + jnp.arange(planning.MIN_WINDOW)]  # (T, 3, 5)
    belts = jax.lax.scan(lambda b, a: (planning.next_belt_speed(model, b, a), b), belt0, actions)[1]
    theta = jnp.concatenate([model.com, jnp.log(model.izz / model.mass)[None]])

    def jac(w, b, a):
        return jax.jacfwd(lambda th: predictor.predict(with_theta(model, th), w, b, a)[2:])(theta)

    j = jax.vmap(jac)(windows, belts, actions) / jnp.asarray(noise, jnp.float32)[None, :, None]  # (T, 3, 4)
    fisher = jnp.einsum("tki,tkj->ij", j, j)
    worst = jnp.max(jnp.abs(jax.vmap(geometry.balance_offset)(states)))
    return Information(fisher, worst, states)


def gain(fisher, c0) -> tuple[jax.Array, jax.Array]:
    """(expected information gain in nats, posterior std (4,)) of a box with Fisher information `fisher`
    (4, 4) under the prior belief covariance `c0` (4, 4) of theta."""
    lo = jnp.linalg.cholesky(c0)
    m = jnp.eye(4) + lo.T @ fisher @ lo
    eig = 0.5 * jnp.linalg.slogdet(m)[1]
    post = lo @ jnp.linalg.inv(m) @ lo.T  # (C0^-1 + F)^-1 = L (I + L^T F L)^-1 L^T
    return eig, jnp.sqrt(jnp.clip(jnp.diag(post), 0.0))


def sequence(free, cfg: Config = DEFAULT) -> jax.Array:
    """(15, 4) exploration vectors from the search's free variables (14, 4) in R: belt setpoints stepped by
    at most DV_MAX from the previous vector (starting at rest) and bounded by V_MAX, carriage steps bounded
    by DP_MAX; the 15th vector stops the belts (the 14th is within DV_MAX of rest) and undoes what the
    carriages moved, within 3 maximal steps (the rest is left, and `undone_error` reports it)."""
    free = jnp.asarray(free, jnp.float32)

    def belt(prev, raw):
        v = jnp.clip(prev + DV_MAX * jnp.tanh(raw), -V_MAX, V_MAX)
        return v, v

    n = free.shape[0]
    # The last free vector must leave the belts within DV_MAX of rest: squeeze its bound.
    _, v = jax.lax.scan(belt, jnp.zeros(2, jnp.float32), free[:, :2])
    v = v.at[n - 1].set(jnp.clip(v[n - 1], -DV_MAX, DV_MAX))
    dp = DP_MAX * jnp.tanh(free[:, 2:])
    step = cfg.gripper.max_position_step
    last = jnp.clip(-jnp.sum(dp, 0), -step, step)  # held HOLD steps, as every vector
    vectors = jnp.concatenate([jnp.concatenate([v, dp], 1), jnp.concatenate([jnp.zeros(2), last])[None]])
    return vectors


def undone_error(vectors) -> jax.Array:
    """(2,) m, how far each carriage ends from where it started (every move undone: 0)."""
    return explore.HOLD * jnp.sum(jnp.asarray(vectors)[:, 2:], 0)


def free_of(vectors) -> np.ndarray:
    """(14, 4) free variables whose `sequence` is `vectors` (15, 4) (the inverse where it exists)."""
    v = np.asarray(vectors, np.float64)
    dv = np.diff(np.concatenate([np.zeros((1, 2)), v[:-1, :2]]), axis=0)
    return np.concatenate(
        [
            np.arctanh(np.clip(dv / DV_MAX, -0.999, 0.999)),
            np.arctanh(np.clip(v[:-1, 2:] / DP_MAX, -0.999, 0.999)),
        ],
        1,
    )


def actions_of(vectors) -> jax.Array:
    """(45, 4) commanded actions: each vector held `explore.HOLD` steps (the sequence's shape)."""
    return jnp.repeat(jnp.asarray(vectors, jnp.float32), explore.HOLD, axis=0)


@functools.partial(jax.jit, static_argnums=(0,))
def evaluate(cfg: Config, models, vectors, c0):
    """For a batch of boxes (`models`, a PriorModel stacked on a leading axis) and sequences `vectors`
    (S, 15, 4): (mean information gain (S,), posterior std (S, B, 4), worst balance (S, B))."""

    def one(vec):
        info = jax.vmap(lambda m: information(m, actions_of(vec), cfg))(models)
        eig, std = jax.vmap(lambda f: gain(f, c0))(info.fisher)
        return jnp.mean(eig), std, info.worst_balance

    return jax.lax.map(one, vectors)


def simulated_offsets(cfg: Config, dists, vectors) -> np.ndarray:
    """(S, B, T + 1) m, the signed balance offset of each of the boxes `dists` (B, a batched
    MassDistribution) at every step while the simulator (native MuJoCo) runs each of the sequences `vectors`
    (S, 15, 4) open loop."""
    vectors = np.asarray(vectors, np.float64)
    n_seq, n_box = len(vectors), len(np.asarray(dists.total_mass))
    actions = np.repeat(np.asarray(jax.vmap(actions_of)(vectors)), n_box, axis=0)
    tiled = massdist.MassDistribution(
        np.tile(np.asarray(dists.occupancy), (n_seq, 1, 1, 1)), np.tile(np.asarray(dists.total_mass), n_seq)
    )
    s = native.rollout(cfg, tiled, actions)["s"]
    return geometry.balance_offset(np.moveaxis(s, -1, 0)).reshape(n_seq, n_box, -1)


def guard_judged(offsets, lead: int) -> np.ndarray:
    """(..., T + 1) m, what the exploration guard (a sensor without noise) judges at each step of the signed
    balance offsets (..., T + 1): `explore.judged_balance` once three offsets are seen, the present error
    before."""
    h = np.asarray(offsets, np.float64)
    windows = np.stack([h[..., :-2], h[..., 1:-1], h[..., 2:]], axis=-1)
    judged = explore.judged_balance(windows, np.abs(h[..., 2:]), lead)
    return np.concatenate([np.abs(h[..., :2]), judged], axis=-1)


class Search(NamedTuple):
    vectors: np.ndarray  # (15, 4) the best sequence found
    gain: float  # its mean information gain (nats per box)
    balance_p95: float  # m, its 95th percentile of the worst balance error (simulated where checked)
    guard_trips: int  # of the simulated boxes, how many it would make the guard refuse (-1: not simulated)
    history: list  # per iteration: best gain, feasible candidates


def search(
    key,
    models,
    c0,
    cfg: Config = DEFAULT,
    start=None,
    sim_boxes=None,
    screen: int | None = None,
    guard: float = 0.875,
    lead: int = 3,
    population: int = 64,
    elites: int = 8,
    iterations: int = 8,
    std: float = 0.6,
    progress=None,
) -> Search:
    """The cross-entropy method over `sequence`'s free variables, starting at `start` (15, 4) (default the
    shipped `explore.VECTORS`); the best feasible sequence ever seen is kept. Feasible: every carriage move
    undone, and no less safe than the start. With `sim_boxes` (a batched MassDistribution of label-safe
    boxes) simulated: the 95th percentile of their worst balance errors no larger than the start's, and no
    more of them judged past the exploration guard (`guard` x the balance limit, `lead` steps ahead: the
    controller's defaults) than with the start, so that the sequence costs no more false aborts. Without:
    the prior's predicted 95th percentile over `models` no larger than the start's (the prior's open-loop
    account of a sequence's drift is optimistic: a sequence it judged safe pushed 5.6 % of safe boxes past
    4 cm in the simulator; scripts/exploration_design.py). `screen`: simulate only this many of each
    iteration's most informative candidates (the others are not elites)."""
    start = explore.VECTORS if start is None else np.asarray(start)
    mean = jnp.asarray(free_of(start), jnp.float32)
    g0, _, w0 = evaluate(cfg, models, jnp.asarray(start, jnp.float32)[None], c0)
    threshold = guard * cfg.task.balance_limit

    def safety(vecs, predicted):  # ((S, B) worst balance, (S,) guard trips)
        if sim_boxes is None:
            return predicted, np.full(len(predicted), -1)
        off = simulated_offsets(cfg, sim_boxes, vecs)
        trips = np.sum(np.max(guard_judged(off, lead), axis=-1) > threshold, axis=-1)
        return np.max(np.abs(off), axis=-1), trips

    w_start, t_start = safety(np.asarray(start)[None], np.asarray(w0))
    p95_max, trips_max = float(np.percentile(w_start[0], 95)), int(t_start[0])
    best = Search(np.asarray(start), float(g0[0]), p95_max, trips_max, [])
    sd = jnp.full_like(mean, std)
    for it in range(iterations):
        key, sub = jax.random.split(key)
        free = mean[None] + sd[None] * jax.random.normal(sub, (population, *mean.shape))
        free = free.at[0].set(mean)
        vecs = jax.vmap(lambda f: sequence(f, cfg))(free)
        g, _, predicted = evaluate(cfg, models, vecs, c0)
        g = np.asarray(g)
        undone = np.max(np.abs(np.asarray(jax.vmap(undone_error)(vecs))), axis=1)
        # Only the `screen` most informative candidates are checked (the rest cannot be elites).
        checked = np.argsort(-np.where(undone < 1e-4, g, -np.inf))[: screen or population]
        worst = np.full((population, w_start.shape[1]), 1e9)  # unchecked: infeasible
        trips = np.full(population, trips_max + 1)
        worst[checked], trips[checked] = safety(np.asarray(vecs)[checked], np.asarray(predicted)[checked])
        p95 = np.percentile(worst, 95, axis=1)
        feasible = (p95 <= p95_max) & (undone < 1e-4) & (trips <= trips_max)
        score = np.where(feasible, g, -np.inf)
        order = np.argsort(-score)[:elites]
        if np.isfinite(score[order[0]]) and score[order[0]] > best.gain:
            i = order[0]
            best = Search(np.asarray(vecs[i]), float(score[i]), float(p95[i]), int(trips[i]), best.history)
        ok = order[np.isfinite(score[order])]
        if len(ok):
            mean = jnp.mean(free[ok], 0)
            sd = jnp.maximum(jnp.std(free[ok], 0), 0.05)
        best.history.append({"iteration": it, "best_gain": best.gain, "feasible": int(feasible.sum())})
        if progress:
            progress(it, best)
    return best


__all__ = [
    "NOISE",
    "THETA",
    "Information",
    "Search",
    "actions_of",
    "evaluate",
    "free_of",
    "gain",
    "information",
    "initial_state",
    "search",
    "sequence",
    "guard_judged",
    "simulated_offsets",
    "theta_of",
    "undone_error",
    "with_theta",
]
