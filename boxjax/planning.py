"""One interface for every MPC planner, and one slot for the dynamics model they plan with.

The MPC is "same planner, different model" (docs/design.md#planner-interface): the physics prior
(`prior.PriorModel`) and the
black-box W (`baseline`) both fill the model slot, and every planner -- the paper's one-step Pareto random
shooting (`planner`), predictive sampling and its MPPI / CEM / gradient-refined relatives
(`planners.sampling`), the privileged simulator reference (`planners.simulator`) -- implements the same
three calls, as hydrax's `SamplingBasedController` shares one `optimize` across its algorithms:

    plan_state = planner.init(obs)                                   # before the first control step
    action, plan_state, info = planner.optimize(key, model, obs, plan_state)   # every control step

`obs` is an `Observation` (what the robot sees at time t); `plan_state` is the planner's own memory (a
pytree: the nominal sequence for predictive sampling, `()` for the memoryless paper planner); `info` is
what the planner considered (planner-specific NamedTuple, for logs and explanations). `optimize` of the
jnp planners is jitted at construction; the model is a traced argument, so a new box does not recompile.

The model slot. A model is a pytree with

    model.rollout_sequence(window (W, 5), belt_speed (2,), actions (H, 4)) -> (H, 5) predicted states
    model.stability_margin(s (5,)) -> () m, how far the centre of mass lies inside the support polygon

`rollout_sequence` feeds each predicted state back as the newest state of the window (so velocities come
from the same finite differences as for observed states). A model that knows nothing about the centre of
mass (a black box) returns a large constant margin (`NO_MARGIN`), so margin-based barriers are inert.

A model that knows the box's centre of mass also exposes `model.planar_com() -> (2,) m` (box frame,
x and y); `planar_com(model)` reads it and gives None for a model that knows none (W, PETS). The
sampling planner's turn-end term needs it (`planners.sampling.turn_end_excess`) and is left out for such
a model.

Particle models (several predicted trajectories per action sequence). A model may also expose

    model.n_particles -> int (static: a pytree meta field or derived from array shapes)
    model.rollout_particles(key, window (W, 5), belt_speed (2,), actions (H, 4)) -> (P, H, 5)
    model.particle_margins(states (P, H, 5)) -> (P, H) m, each particle's stability margin

and the sampling planner then scores a candidate sequence by the cost of every particle, aggregated by
`aggregate` (`SamplingOptions.particle_risk`: "mean" by default, as mbrl-lib's
`ModelEnv.evaluate_action_sequences`; "mean_std" = mean + k * std and "worst" = max, the risk strategies
of hydrax's `risk.py`). A model without `n_particles` (the prior, W) takes the plain path, unchanged
(bit-identical plans; a test). `n_particles(model)` is the switch; `rollout_particles(model, ...)`
works for either kind (a plain model gives one particle).

`Ensemble(members, particles_per_member)` is the one such model here: `members` is ONE pytree of E
models of the same type whose array leaves are stacked on a leading axis (`stack`), vmapped, never
looped over. Particle p = e * particles_per_member + j follows member e over the whole horizon
(trajectory sampling TS-inf of Chua et al. 2018, mbrl-lib's "fixed_model" propagation; the assignment is
balanced, every candidate sees every member equally often, instead of mbrl-lib's random permutation).
A member that predicts a distribution implements `rollout_sample(key, window, belt_speed, actions) ->
(H, 5)` (a sampled trajectory, e.g. `pets.GaussianMember`), and each particle gets its own key; a
deterministic member (a physics prior of H's ensemble) is rolled out by `rollout_sequence` and then one
particle per member is all there is. The plain slot of an Ensemble (`rollout_sequence`,
`stability_margin`) is the members' mean (mbrl-lib's "expectation"), so planners without particles, the
one-step error tables and the adapters still take it.

`Mixture(members)` holds models that cannot be stacked (other static settings, other types: priors
with different `prior.PriorParams`, `ControllerConfig.prior_params` given as a tuple), one
deterministic particle each, looped over inside the traced function.

Keys. Particles that need noise get it from the key the planner is given for the control step
(`planners.sampling.plan` folds in `PARTICLE_STREAM`): the same particle noise for every candidate of
that step (common random numbers, as hydrax shares its domain randomisations across rollouts), fresh
noise at the next step. No key lives in a model or in global state.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry

NO_MARGIN = 1.0  # m, the stability margin a model reports when it cannot know it (larger than the box)
RISKS = ("mean", "mean_std", "worst")  # how particle costs of one candidate are aggregated (`aggregate`)
PARTICLE_STREAM = 0x5045  # folded into a planning step's key for the particles' noise ("PE")


class Observation(NamedTuple):
    """What the planner sees at control time t (conveyor frame, SI units).

    window: (W, 5) float32 last planar states s_{t-W+1..t} at control_dt spacing (W >= prior.MIN_WINDOW).
    belt_speed: (2,) float32 m/s, measured belt surface speeds.
    target_yaw: () float32 rad, the yaw to reach (initial yaw + pi / 2).
    sim: the simulator's own state at t (privileged; only the simulator reference reads it, None otherwise).
    """

    window: jax.Array
    belt_speed: jax.Array
    target_yaw: jax.Array
    sim: Any = None


class Model(Protocol):
    """The model slot (see the module docstring)."""

    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array: ...

    def stability_margin(self, s) -> jax.Array: ...


def planar_com(model) -> jax.Array | None:
    """(2,) m: the model's centre of mass in the box frame (x, y); None for a model that knows none (a
    black box)."""
    f = getattr(model, "planar_com", None)
    c = None if f is None else f()
    return None if c is None else jnp.asarray(c, jnp.float32)


class ParticleModel(Model, Protocol):
    """A model of the slot with several particles per action sequence (see the module docstring)."""

    n_particles: int

    def rollout_particles(self, key, window, belt_speed, actions) -> jax.Array: ...

    def particle_margins(self, states) -> jax.Array: ...


class Planner(NamedTuple):
    """A planner: `init(obs) -> plan_state`, `optimize(key, model, obs, plan_state) -> (action (4,),
    plan_state, info)`. `privileged` planners read `obs.sim` (the simulator state) and need the truth."""

    name: str
    init: Callable[[Observation], Any]
    optimize: Callable[..., tuple[jax.Array, Any, Any]]
    privileged: bool = False


def observation(window, belt_speed, target_yaw, sim=None) -> Observation:
    """An Observation with the dtypes the jitted planners expect (float32; a weakly typed scalar would make
    them compile twice)."""
    return Observation(
        jnp.asarray(window, jnp.float32),
        jnp.asarray(belt_speed, jnp.float32),
        jnp.asarray(target_yaw, jnp.float32),
        sim,
    )


@functools.partial(jax.tree_util.register_dataclass, data_fields=["model", "drift"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class DriftCorrected:
    """A model whose predictions carry an estimated per-step drift (offset-free MPC's integrating
    output disturbance): step k of a rollout is moved by (k + 1) * drift in (x, y, yaw).

    drift: (3,) m, m, rad per control step, estimated online from what the box did against what the
    model predicted (`update_drift`). A model's systematic error under the current regime (a carriage
    dragging the box less than predicted, a slower spin) then stops steering the plan the wrong way.
    """

    model: Any
    drift: jax.Array

    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        states = self.model.rollout_sequence(window, belt_speed, actions)
        k = jnp.arange(1, states.shape[0] + 1, dtype=states.dtype)[:, None]
        return states.at[:, 2:].add(k * self.drift)

    def stability_margin(self, s) -> jax.Array:
        return self.model.stability_margin(s)

    @property
    def gripper(self):
        """The gripper the corrected model was built for (its belts' kinematics: `next_belt_speed`)."""
        return self.model.gripper

    def planar_com(self) -> jax.Array | None:
        return planar_com(self.model)

    # A particle model stays one under the correction (every particle moved by the same drift).
    @property
    def n_particles(self):
        return n_particles(self.model)

    def rollout_particles(self, key, window, belt_speed, actions) -> jax.Array:
        states = rollout_particles(self.model, key, window, belt_speed, actions)
        k = jnp.arange(1, states.shape[1] + 1, dtype=states.dtype)[None, :, None]
        return states.at[..., 2:].add(k * self.drift)

    def particle_margins(self, states) -> jax.Array:
        return particle_margins(self.model, states)


def update_drift(drift, predicted, observed, gain: float):
    """Integrating observer: drift + gain * (observed - predicted) in (x, y, yaw), where `predicted` is
    the corrected model's one-step prediction of the state just observed (both (5,))."""
    return drift + gain * (jnp.asarray(observed, jnp.float32)[2:] - jnp.asarray(predicted, jnp.float32)[2:])


@jax.jit
def predict_first(model, window, belt_speed, action) -> jax.Array:
    """(5,) the model's prediction one step ahead for `action` (4,)."""
    return model.rollout_sequence(window, belt_speed, jnp.asarray(action, jnp.float32)[None])[0]


# ----------------------------------------------------------------------------------------------------------
# Particles and ensembles (module docstring).


def n_particles(model) -> int | None:
    """The number of particles a model predicts per action sequence, or None for a single-trajectory
    model (the plain path of the planners). Static (a Python int), so it can choose code paths."""
    n = getattr(model, "n_particles", None)
    return None if n is None else int(n)


def rollout_particles(model, key, window, belt_speed, actions) -> jax.Array:
    """(P, H, 5) the particles' predicted states; a single-trajectory model gives (1, H, 5)."""
    if n_particles(model) is None:
        return model.rollout_sequence(window, belt_speed, actions)[None]
    return model.rollout_particles(key, window, belt_speed, actions)


def particle_margins(model, states) -> jax.Array:
    """(P, H) m: each particle's stability margin along its states (P, H, 5)."""
    if n_particles(model) is None:
        return jax.vmap(jax.vmap(model.stability_margin))(states)
    return model.particle_margins(states)


def aggregate(costs, risk: str = "mean", k: float = 1.0) -> jax.Array:
    """Aggregate particle costs (..., P) over the last axis: "mean", "mean_std" (mean + k * std) or
    "worst" (max). Non-finite particle costs make the result non-finite (a planner then drops it)."""
    if risk == "mean":
        return jnp.mean(costs, axis=-1)
    if risk == "mean_std":
        return jnp.mean(costs, axis=-1) + k * jnp.std(costs, axis=-1)
    if risk == "worst":
        return jnp.max(costs, axis=-1)
    raise ValueError(f"unknown particle risk {risk!r}; choose one of {RISKS}")


def stack(models) -> Any:
    """One pytree of `models` (a sequence of models of one type and static configuration) with every
    array leaf stacked on a new leading axis: the `members` of an Ensemble."""
    models = list(models)
    if not models:
        raise ValueError("stack needs at least one model")
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *models)


def member(members, i: int) -> Any:
    """Member i of stacked `members` (the inverse of `stack`)."""
    return jax.tree.map(lambda x: x[i], members)


def _leading(members) -> int:
    leaves = jax.tree.leaves(members)
    if not leaves:
        raise ValueError("an Ensemble needs members with array leaves")
    return int(leaves[0].shape[0])


@functools.partial(
    jax.tree_util.register_dataclass, data_fields=["members"], meta_fields=["particles_per_member"]
)
@dataclasses.dataclass(frozen=True)
class Ensemble:
    """E models of one type stacked on a leading axis (`stack`), a particle model of the slot.

    members: a model pytree whose array leaves have a leading axis E (each member a `planning.Model`;
      members with `rollout_sample` are stochastic). particles_per_member: static, particles that follow
      each member (TS-inf); 1 for deterministic members (more would be copies).
    """

    members: Any
    particles_per_member: int = 1

    def __post_init__(self):
        if int(self.particles_per_member) < 1:
            raise ValueError(f"particles_per_member must be >= 1, got {self.particles_per_member}")

    @property
    def n_members(self) -> int:
        return _leading(self.members)

    @property
    def gripper(self):
        """The gripper the members were built for (static, one for all: `next_belt_speed`)."""
        return self.members.gripper

    @property
    def n_particles(self) -> int:
        return self.n_members * int(self.particles_per_member)

    def rollout_particles(self, key, window, belt_speed, actions) -> jax.Array:
        """(E * particles_per_member, H, 5): particle e * k + j follows member e, with its own key."""
        e, k = self.n_members, int(self.particles_per_member)
        keys = jax.random.split(key, e * k).reshape(e, k, *jnp.shape(key))

        def one(m, key):
            if hasattr(m, "rollout_sample"):
                return m.rollout_sample(key, window, belt_speed, actions)
            return m.rollout_sequence(window, belt_speed, actions)

        states = jax.vmap(jax.vmap(one, in_axes=(None, 0)))(self.members, keys)  # (E, k, H, 5)
        return states.reshape(e * k, *states.shape[2:])

    def particle_margins(self, states) -> jax.Array:
        """(P, H) m: each particle's margin under its own member."""
        e, k = self.n_members, int(self.particles_per_member)
        st = states.reshape(e, k, *states.shape[1:])
        margins = jax.vmap(lambda m, s: jax.vmap(jax.vmap(m.stability_margin))(s))(self.members, st)
        return margins.reshape(e * k, -1)

    # The plain slot: the members' mean (mbrl-lib's "expectation" propagation).
    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        """(H, 5) the mean over members of each member's own (noise-free) rollout."""
        states = jax.vmap(lambda m: m.rollout_sequence(window, belt_speed, actions))(self.members)
        return jnp.mean(states, axis=0)

    def stability_margin(self, s) -> jax.Array:
        """() m, the members' mean margin at `s`."""
        return jnp.mean(jax.vmap(lambda m: m.stability_margin(s))(self.members))

    def planar_com(self) -> jax.Array | None:
        """(2,) m, the members' mean centre of mass (None: the members know none)."""
        if getattr(self.members, "planar_com", None) is None:
            return None
        return jnp.mean(jax.vmap(planar_com)(self.members), axis=0)


@functools.partial(jax.tree_util.register_dataclass, data_fields=["members"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Mixture:
    """Models of DIFFERENT static settings or types (a tuple: e.g. physics priors with other
    `prior.PriorParams`, or a prior beside a black box), a particle model of the slot with one
    deterministic particle per member. Where an `Ensemble` vmaps over stacked members of one type, a
    Mixture loops over its members inside the traced function (each keeps its own static settings).
    The plain slot is the members' mean, as an Ensemble's."""

    members: tuple

    def __post_init__(self):
        if not isinstance(self.members, tuple) or not self.members:
            raise ValueError("a Mixture needs a non-empty tuple of models")

    @property
    def n_particles(self) -> int:
        return len(self.members)

    @property
    def gripper(self):
        """The first member's gripper: the belts' kinematics (`next_belt_speed`), which members that
        differ in their settings or friction (`ControllerConfig.friction_set`) share."""
        return self.members[0].gripper

    def rollout_particles(self, key, window, belt_speed, actions) -> jax.Array:
        """(M, H, 5): member m's own rollout (`key` unused: the members are deterministic)."""
        return jnp.stack([m.rollout_sequence(window, belt_speed, actions) for m in self.members])

    def particle_margins(self, states) -> jax.Array:
        """(M, H) m: each particle's margin under its own member."""
        return jnp.stack([jax.vmap(m.stability_margin)(s) for m, s in zip(self.members, states, strict=True)])

    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        """(H, 5) the mean over members of each member's rollout."""
        return jnp.mean(self.rollout_particles(None, window, belt_speed, actions), axis=0)

    def stability_margin(self, s) -> jax.Array:
        """() m, the members' mean margin at `s`."""
        return jnp.mean(jnp.stack([m.stability_margin(s) for m in self.members]))

    def planar_com(self) -> jax.Array | None:
        """(2,) m, the mean centre of mass of the members that know one (None: none does)."""
        known = [c for c in (planar_com(m) for m in self.members) if c is not None]
        return jnp.mean(jnp.stack(known), axis=0) if known else None


MIN_WINDOW = 3  # states s_{t-2}, s_{t-1}, s_t: second-order velocities and the pre-action acceleration


def check_window(window, belt_speed=None, action=None, min_window: int = MIN_WINDOW) -> np.ndarray:
    """Validate predictor inputs on the host; returns the window as a float32 array.

    Raises:
      ValueError: window not of shape (W, 5), W < min_window (MIN_WINDOW = 3 states at control_dt
        spacing are needed), non-finite values (naming the rows and state components), or a belt_speed
        not (2,) / an action not (4,) / either non-finite.
    """
    w = np.asarray(window, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 5:
        raise ValueError(
            f"window must have shape (W, 5) = planar states {geometry.STATE_NAMES} over time, got {w.shape}"
        )
    if w.shape[0] < min_window:
        raise ValueError(
            f"window has {w.shape[0]} states; the predictor needs at least {min_window} "
            f"(s_(t-2), s_(t-1), s_t at control_dt spacing). At the start of an episode, repeat the "
            "initial state (the box is at rest)."
        )
    bad = ~np.isfinite(w)
    if np.any(bad):
        rows, cols = np.nonzero(bad)
        names = geometry.STATE_NAMES
        where = ", ".join(f"row {r} {names[c]}" for r, c in zip(rows[:5], cols[:5], strict=True))
        raise ValueError(f"window contains NaN or inf ({int(bad.sum())} values: {where})")
    for name, x, n in (("belt_speed", belt_speed, 2), ("action", action, 4)):
        if x is None:
            continue
        a = np.asarray(x, dtype=np.float64)
        if a.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf: {a.tolist()}")
    return w.astype(np.float32)


def initial_window(s0, length: int = MIN_WINDOW) -> jax.Array:
    """(length, 5) window for the first step of an episode: the initial state repeated (box at rest)."""
    return jnp.tile(jnp.asarray(s0, jnp.float32)[None], (length, 1))


def next_belt_speed(model, belt_speed, action) -> jax.Array:
    """(2,) m/s belt speeds after one step: the setpoint, or as close as belt_accel_limit allows."""
    gr = model.gripper
    sp = jnp.clip(action[:2], -gr.belt_speed_limit, gr.belt_speed_limit)
    dv = gr.belt_accel_limit * gr.control_dt
    return belt_speed + jnp.clip(sp - belt_speed, -dv, dv)


def compensate(model, window, belt_speed, actions):
    """The window (W, 5) and belt speeds (2,) moved forward over `actions` (D, 4), the actions applied since
    the window's newest state: a Smith predictor for the loop's delays (a late observation, an action
    applied late), with the model in the planner's slot. Returns (window (W, 5), belt_speed (2,)) ending
    at the predicted present; D = 0 returns them unchanged."""
    if actions.shape[0] == 0:
        return window, belt_speed
    predicted = model.rollout_sequence(window, belt_speed, actions)  # (D, 5)
    belt = jax.lax.scan(lambda b, a: (next_belt_speed(model, b, a), None), belt_speed, actions)[0]
    return jnp.concatenate([window, predicted.astype(window.dtype)])[-window.shape[0] :], belt


def compensate_held(model, window, belt_speed, actions, compensated, withheld=1.0):
    """The window `compensate` gives (`compensated`, from the same window, belt speeds and `actions`) with
    the box's pose moved back by the fraction `withheld` of the drag the model predicts from the carriage
    steps in flight: at 1 the box as if they had not dragged it at all (the box rolled out over `actions`
    with their carriage steps withheld), the carriages always where `compensated` has them. With
    `compensate`'s window it bounds the prediction's least certain part over the loop's delay: how far a
    carriage moved under the box drags it (the monitor's `drag_bound`). D = 0 returns `compensated`."""
    if actions.shape[0] == 0:
        return compensated
    compensated = jnp.asarray(compensated)
    undragged, _ = compensate(model, window, belt_speed, jnp.asarray(actions).at[:, 2:].set(0.0))
    held = compensated + withheld * (undragged.astype(compensated.dtype) - compensated)
    return held.at[:, :2].set(compensated[:, :2])
