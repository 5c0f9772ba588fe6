"""One interface for every MPC planner, and one slot for the dynamics model they plan with.

The MPC is "same planner, different model" (DESIGN.md): the physics prior (`prior.PriorModel`) and the
black-box W (`baseline`) both fill the model slot, and every planner -- the paper's one-step Pareto random
shooting (`planner`), predictive sampling and its MPPI / CEM / gradient-refined relatives
(`sampling_planner`), the privileged simulator reference (`simulator_planner`) -- implements the same
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
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

NO_MARGIN = 1.0  # m, the stability margin a model reports when it cannot know it (larger than the box)


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


def update_drift(drift, predicted, observed, gain: float):
    """Integrating observer: drift + gain * (observed - predicted) in (x, y, yaw), where `predicted` is
    the corrected model's one-step prediction of the state just observed (both (5,))."""
    return drift + gain * (jnp.asarray(observed, jnp.float32)[2:] - jnp.asarray(predicted, jnp.float32)[2:])


@jax.jit
def predict_first(model, window, belt_speed, action) -> jax.Array:
    """(5,) the model's prediction one step ahead for `action` (4,)."""
    return model.rollout_sequence(window, belt_speed, jnp.asarray(action, jnp.float32)[None])[0]
