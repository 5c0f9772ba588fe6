"""The fixed exploration phase (paper §2.2): 15 control vectors, each held 3 control steps (45 steps).

Every episode starts with the same open-loop sequence. It turns and shifts a uniform box a little, and is
built so that what the box does (and what the belts feel) depends as much as possible on where its mass
sits. The estimator H (`boxjax.estimator`) reads the resulting trajectory.

Physics that the design follows (docs/design.md#exploration, `boxjax.sim.model`):
  * Under Coulomb friction the box's motion does not depend on its total mass: mass cancels. A slipping
    belt i pulls on the box with mu * N_i, N_i the normal load it carries, so WHERE the mass sits shows in
    how the box turns and drifts when the belts move differently (the split N1 / N2 along y, the pressure
    centre along x within each contact patch).
  * The total MASS shows only through the drives' servo lag: a belt that slips under the box is slowed by
    mu * N_i / kv (kv = 2e4 N s/m: up to ~1.2 mm/s for 10 kg), and a carriage that drags or slips under
    the box lags its target by the lateral friction / kp (kp = 5e4 N/m: up to ~0.5 mm). Both are measured
    (the belt speeds, P1 and P2), so the phases below keep at least one belt slipping most of the time.
  * The height of the centre of mass shows only while the box accelerates: the inertial force at the
    centre of mass, mu * g at most, tilts the load between the belts (or front to back) by about
    M a h / d. Sideways carriage moves under the box (it slides at ~mu g) expose it.
  * At yaw 0 the centre of mass along x enters only through the turn (the pressure centre along each
    belt); once the box is turned by psi, the load split between the belts follows
    x sin(psi) + y cos(psi), so the one-belt drives and carriage moves are made at the turned yaw.
  * Belt setpoints move by at most belt_accel_limit * control_dt = 0.03 m/s per step, so a vector held 3
    steps reaches a setpoint up to 0.09 m/s away; the table never asks for more (no clipping with the
    default config). Carriage steps are at most 1 cm per step.

The sequence (v in m/s along belt travel +x; dp in m along y per step; "CCW" = yaw increasing, left belt
+x and right belt -x). It turns the box a little, probes it at the turned yaw, and turns it back. Measured
effect on the named boxes (`describe_effect`, default config): uniform / A / B / C / D turn by up to
+10.5 / +6.7 / +7.4 / +1.3 / +0.1 deg and end at +3.7 / +2.2 / +2.2 / +0.8 / +0.0 deg, 1.5 / 2.5 / 2.5 /
0.4 / 0.4 cm from where they started, worst balance error 0.5 / 0.9 / 0.9 / 1.0 / 1.1 cm. Over random boxes
(`boxjax.training.dataset`, 1000 boxes, 27 % hazardous) the worst balance error during the phase has median
1.3
cm; no non-hazardous box and 1 % of the hazardous ones cross the 4 cm limit (95 % of the non-hazardous
stay under 2.2 cm). Every carriage move is undone, so the belts end where they started (P1 = -0.10,
P2 = +0.10 m), and at rest.

 #    v1     v2     dp1     dp2    why
---  -----  -----  ------  ------  ------------------------------------------------------------------------
 1   +0.09  -0.09       0       0  spin up CCW from rest: the onset of slip and the turn's transient
 2   +0.12  -0.12       0       0  steady opposite slip: the turn's centre (so the y drift per radian) follows
                                   the pressure centre along x (COM x), the x drift the load split between the
                                   belts (COM y); both belts lag by mu N_i / kv (mass)
 3   +0.09  -0.09       0       0  a slower turn: how the slip pattern changes with the belt speed
 4       0      0       0       0  ramp both belts down: the box decelerates with them (transient). From here
                                   on the box is turned (uniform: ~10 deg), so the probes below load the belts
                                   through COM x as well as COM y (x sin(yaw) + y cos(yaw) across the belts)
 5   +0.09      0       0       0  left belt alone: the box turns about the right belt if that one carries
                                   more load, or rides with the left belt if not (sign and size of N1 - N2);
                                   belt 1 lags by mu N1 / kv
 6       0  +0.09       0       0  right belt alone (the left ramps down): the mirror test, N2 - N1 and mu N2
                                   / kv
 7       0      0  +0.007       0  left carriage in by 2.1 cm (the right belt ramps down): drags the box +y
                                   only if N1 > N2; carriage 1 lags by mu N1 / kp (mass)
 8       0      0  -0.007       0  left carriage back out: the same force reversed
 9       0      0       0  -0.007  right carriage in: drags the box -y only if N2 > N1; carriage 2 lags by mu
                                   N2 / kp
10       0      0       0  +0.007  right carriage back out
11       0      0  +0.004  +0.004  both carriages shift +y under the resting box: it slides at ~mu g on both
                                   belts, so the two carriage lags add up to mu M g / kp (mass) and split by
                                   the load transfer (the height of the COM: the inertial force mu g M at the
                                   COM tilts the load between the belts by about M a h / d)
12       0      0  -0.004  -0.004  back
13   -0.09  +0.09       0       0  turn back CW: the mirror of 1-2, so the drift per radian is seen with both
                                   signs and the box returns towards its start yaw and centre
14   -0.09  +0.09       0       0  steady CW slip
15       0      0       0       0  ramp down: the box ends near its start pose, at rest

Why this sequence: it was chosen by measurement among candidates (`scripts/exploration_candidates.py`,
results in `benchmarks/results_exploration_candidates.json`), each scored by what a net recovers from it
(the same 8000 training / 1000 test boxes; mass, centre of mass and I_zz regressed directly) and by how
many boxes it pushes past the 4 cm balance limit while exploring. Every candidate that turns, drags and
shifts the box (a longer turn, an oscillating turn, turns with sideways shifts, with or without squeezing
the box between both carriages) gives the centre of mass to 0.88-0.94 / 0.34-0.37 / 0.67-0.87 cm (median,
x / y / z); what sets them apart is safety. The previous sequence (turning while shifting the carriages,
probes at the final yaw, then squeezing the box between both carriages) pushed 1.6 % of the
non-hazardous and 28 % of the hazardous boxes past the limit during exploration (mostly during the
squeeze); this one 0 % and 1 %. H trained end to end on 16000 / 32000 boxes of each (1000 test boxes):
median IoU 0.619 / 0.634 (previous) vs 0.614 / 0.637 (this one), hazard precision at recall 0.98
0.89 / 0.93 vs 0.91 / 0.88, centre-of-mass error 1.49 / 1.36 vs 1.60 / 1.49 cm: the same IoU and hazard
precision within their run-to-run spread, ~0.1 cm more centre-of-mass error.

`exploration_actions(cfg)` gives the (45, 4) commanded actions; `applied_actions(cfg)` what the simulator
applies after the acceleration limit (the `actions` a rollout reports); `trajectory(...)` turns a rollout's
observations into the estimator's input; `run(env, state)` runs the phase on one environment.
What the sequence does to the named boxes (uniform, A-D) is measured in `tests/test_explore.py` and
reported by `describe_effect`.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist
from boxjax.config import DEFAULT, Config
from boxjax.sim import core, native

HOLD = 3  # control steps each vector is held (paper §2.2)

# (v1, v2, dp1, dp2): m/s, m/s, m, m. Reasons in the module docstring's table, same order.
VECTORS = np.array(
    [
        [+0.09, -0.09, 0.000, 0.000],
        [+0.12, -0.12, 0.000, 0.000],
        [+0.09, -0.09, 0.000, 0.000],
        [0.00, 0.00, 0.000, 0.000],
        [+0.09, 0.00, 0.000, 0.000],
        [0.00, +0.09, 0.000, 0.000],
        [0.00, 0.00, +0.007, 0.000],
        [0.00, 0.00, -0.007, 0.000],
        [0.00, 0.00, 0.000, -0.007],
        [0.00, 0.00, 0.000, +0.007],
        [0.00, 0.00, +0.004, +0.004],
        [0.00, 0.00, -0.004, -0.004],
        [-0.09, +0.09, 0.000, 0.000],
        [-0.09, +0.09, 0.000, 0.000],
        [0.00, 0.00, 0.000, 0.000],
    ],
    dtype=np.float64,
)
# The sequence designed for information (`TaskConfig.exploration = "designed"`; `boxjax.estimator.design`):
# the cross-entropy method from VECTORS over sequences of the same shape and rules, maximising the physics
# prior's expected information about (com, log I_zz / M) under two simulated constraints on 160 label-safe
# boxes of the wide training mixture: the 95th percentile of their worst balance error no larger than
# VECTORS' and no box judged past the exploration guard (so no more false aborts). It turns CCW, then probes
# with the carriages while the right belt alone keeps turning the box (the probes see the load split at a
# growing yaw), and turns back harder. `python scripts/exploration_design.py search --design-boxes 32
# --sim-boxes 160 --screen 24 --population 48 --elites 6 --iterations 14 --std 0.2` (2026-12-06); what it
# reveals beside VECTORS: docs/results/estimator-and-hazards.md#designed-exploration.
DESIGNED = np.array(
    [
        [+0.08989, -0.08994, -0.00035, +0.00104],
        [+0.11170, -0.09260, -0.00008, -0.00112],
        [+0.06389, -0.04321, -0.00085, +0.00223],
        [-0.02597, +0.04672, +0.00060, +0.00150],
        [+0.06390, +0.05263, -0.00109, -0.00095],
        [-0.02605, +0.12000, -0.00151, +0.00061],
        [-0.02856, +0.03014, +0.00699, +0.00037],
        [-0.00201, +0.05066, -0.00699, -0.00001],
        [-0.01313, +0.05728, +0.00179, -0.00700],
        [-0.00193, +0.06892, -0.00121, +0.00699],
        [+0.00125, +0.08923, +0.00374, -0.00003],
        [+0.00731, +0.09475, -0.00381, -0.00327],
        [-0.08260, +0.12000, -0.00157, +0.00097],
        [-0.06752, +0.09000, -0.00048, -0.00201],
        [+0.00000, +0.00000, +0.00482, +0.00069],
    ],
    dtype=np.float64,
)
# The fixed sequence with its first turn at half speed (`TaskConfig.exploration = "gentle"`): the belts spin
# up to +-0.045 / 0.06 / 0.045 m/s instead of +-0.09 / 0.12 / 0.09, the rest as VECTORS. An end-heavy box
# turns about its heavy end during the first turn and its centre swings sideways faster than a sensor 2
# steps late with 3 mm of noise can follow; at half speed the exploration loses 38 instead of 92 of 2,400
# hazardous boxes in the realistic world (the guard holding), none instead of 24 of 1,200 with no fault
# and a hold, and a regressor reads it about as well in the simulator (centre of mass along the box 0.98
# against 0.90 cm, the rest the same). Measured as a what-if with the oracle (docs/results/faults.md, "A
# slower first turn"); the shipped H and moments model were trained on VECTORS, so a learned estimator for
# it must be trained (`boxjax train-estimator --exploration gentle`).
GENTLE = VECTORS.copy()
GENTLE[:3, :2] *= 0.5
N_VECTORS = len(VECTORS)
N_STEPS = N_VECTORS * HOLD  # 45
N_TRAJ_COLUMNS = 11  # s (5), applied action (4), measured belt speeds at the end of the step (2)


def vectors(cfg: Config = DEFAULT) -> np.ndarray:
    """(15, 4) the exploration's vectors for `cfg.task.exploration`: VECTORS ("fixed"), DESIGNED or
    GENTLE."""
    return {"designed": DESIGNED, "gentle": GENTLE}.get(cfg.task.exploration, VECTORS)


def exploration_actions(cfg: Config = DEFAULT) -> np.ndarray:
    """(45, 4) float32 commanded actions (v1, v2, dp1, dp2) in m/s, m/s, m, m: each of the 15 vectors of
    `cfg.task.exploration` repeated 3 times. Values beyond the config's belt speed limit or position step
    are clipped to them (never the case with the default config)."""
    g = cfg.gripper
    lim = np.array([g.belt_speed_limit, g.belt_speed_limit, g.max_position_step, g.max_position_step])
    return np.clip(np.repeat(vectors(cfg), HOLD, axis=0), -lim, lim).astype(np.float32)


@partial(jax.jit, static_argnums=0)
def _applied(cfg: Config, actions):
    def body(carry, a):
        speed, p_target = carry
        ctrl, new_target, _, _ = core.command(cfg, a, speed, p_target)
        new_speed = jnp.clip(
            speed + ctrl[:2] * cfg.gripper.control_dt,
            -cfg.gripper.belt_speed_limit,
            cfg.gripper.belt_speed_limit,
        )
        applied = jnp.concatenate([new_speed, new_target - p_target])
        return (new_speed, new_target), applied

    p0 = jnp.asarray(cfg.gripper.belt_y0, actions.dtype)
    return jax.lax.scan(body, (jnp.zeros(2, actions.dtype), p0), actions)[1]


def applied_actions(cfg: Config = DEFAULT) -> np.ndarray:
    """(45, 4) float32 actions as the simulator applies them to a gripper starting at rest with the belts
    at `belt_y0`: belt speed columns are the ramped setpoints reached at the end of each step (at most
    belt_accel_limit * control_dt away from the previous one), position columns the increments after
    clipping to the belt ranges. Equal to the `actions` that `boxjax.sim.native.rollout` reports."""
    return np.asarray(_applied(cfg, jnp.asarray(exploration_actions(cfg), jnp.float32)), np.float32)


def trajectory(s, belt_speed, actions):
    """The estimator's input from ONE exploration rollout (pure; vmap for batches).

    Args:
      s: (T+1, 5) planar states (P1, P2, x, y, yaw) before each step and after the last (m, m, m, m, rad).
      belt_speed: (T+1, 2) measured belt surface speeds (m/s) at the same instants.
      actions: (T, 4) applied actions (see `applied_actions`).
    Returns:
      traj (T, 11) float32: row t = [s_t (5), a_t (4), belt speeds measured at the END of step t (2)];
      final (5,) float32: s_T.
    """
    s = jnp.asarray(s, jnp.float32)
    traj = jnp.concatenate(
        [s[:-1], jnp.asarray(actions, jnp.float32), jnp.asarray(belt_speed, jnp.float32)[1:]], axis=-1
    )
    return traj, s[-1]


def run(env, state: core.State, cfg: Config | None = None):
    """Run the exploration phase on ONE environment (native or MJX) from `state` (just after reset).

    Returns (state after the phase, traj (45, 11) numpy, final (5,) numpy). If the episode ends during the
    phase (e.g. a hazardous box goes out of balance), the environment freezes the state and the remaining
    rows repeat it; check `state.done`.
    """
    cfg = env.cfg if cfg is None else cfg
    step = env.step
    states, speeds = [np.asarray(state.s)], [np.asarray(state.belt_speed)]
    for a in exploration_actions(cfg):
        state = step(state, a)
        states.append(np.asarray(state.s))
        speeds.append(np.asarray(state.belt_speed))
    traj, final = trajectory(np.stack(states), np.stack(speeds), applied_actions(cfg))
    return state, np.asarray(traj), np.asarray(final)


def describe_effect(cfg: Config = DEFAULT, names=("uniform", "A", "B", "C", "D")) -> dict:
    """What the phase does to the named boxes (native rollout): per name, the final planar state change
    (dx, dy in cm, dyaw in degrees), the largest balance error over the phase (cm) and whether any
    action was clipped."""

    dists = [massdist.named(n, cfg.box) for n in names]
    out = native.rollout(cfg, dists, exploration_actions(cfg))
    bal = np.abs(out["s"][..., geometry.Y] - 0.5 * (out["s"][..., geometry.P1] + out["s"][..., geometry.P2]))
    d = out["s"][:, -1] - out["s"][:, 0]
    return {
        n: {
            "dx_cm": round(float(100 * d[i, geometry.X]), 2),
            "dy_cm": round(float(100 * d[i, geometry.Y]), 2),
            "dyaw_deg": round(float(np.degrees(d[i, geometry.YAW])), 2),
            "max_balance_error_cm": round(float(100 * bal[i].max()), 2),
            "clipped": bool(out["clipped"][i].any()),
        }
        for i, n in enumerate(names)
    }


# ----------------------------------------------------------------------------------------------------------
# The exploration guard: a box the fixed sequence itself is about to lose is refused, not lost.

GUARD_STEPS = 20  # control steps of the guard's stop after it trips (1 s at 20 Hz)
# What the guard does once tripped: "recentre" the carriages under the box (belts stopped, both carriages
# stepped towards the box's centre: `recentre_action`), or "hold" them (belts stopped, carriages still).
# Re-centring is feedback on the pose the controller sees, and holds a box well when that pose is exact;
# on a late, noisy estimate it chases where the box was and drags it off (docs/results/faults.md, "The
# exploration guard in a late, noisy world"), so the controller holds there (`ControllerConfig`'s
# `explore_guard_stop`).
STOPS = ("recentre", "hold")


def recentre_action(cfg: Config, s) -> np.ndarray:
    """(4,) belts stopped (speed setpoints 0) and both carriages stepped towards the box's geometric
    centre by its balance error (at most one position step), so the belts' midline follows the box."""
    s = np.asarray(s, np.float64)
    bal = s[3] - 0.5 * (s[0] + s[1])
    dp = float(np.clip(bal, -cfg.gripper.max_position_step, cfg.gripper.max_position_step))
    return np.array([0.0, 0.0, dp, dp])


def judged_balance(h, b, lead: int, noise: float = 0.0) -> np.ndarray:
    """m, the balance error the guard judges (numpy, elementwise over leading axes): the present error b plus
    `lead` times the smaller of the last two changes away from the midline of the last three signed offsets
    h (..., 3), newest last. A swing moves the box away at every step, while a pose's noise rarely does twice
    running (the two changes share a frame, so their noises are anti-correlated; with 1 mm of pose noise
    the mean change over two steps tripped the guard on 7 of 583 safe boxes, scripts/exploration_guard.py
    --noise-mm 1); what two noisy frames' difference may show of itself (2 sqrt 2 noise) is discounted."""
    h = np.asarray(h, np.float64)
    side = np.where(h[..., 2] >= 0, 1.0, -1.0)
    away = np.minimum(side * (h[..., 2] - h[..., 1]), side * (h[..., 1] - h[..., 0]))  # m per step
    return b + lead * np.maximum(away - 2.0 * np.sqrt(2.0) * noise, 0.0)


class Guarded:
    """The exploration of one box, step by step, with the guard (`guard`: a fraction of the task's balance
    limit; None: the paper's fixed sequence whatever happens): while the balance error stays within
    guard x limit the fixed sequence runs; once it exceeds that, `GUARD_STEPS` steps of its stop
    (`STOPS`: re-centring, `recentre_action`, or a hold) follow and the exploration ends `tripped` (the
    controller refuses the box: the exploration has shown that the belts cannot keep it balanced on their
    own). `next(s, balance_error)` gives the next action, or None when the exploration is over. Every path
    that explores (`controller.run_episode`, `batch.run_episodes`, the replay) steps through this one
    object, so they make the same decision."""

    def __init__(
        self,
        cfg: Config,
        guard: float | None,
        settle: int = 0,
        lead: int = 0,
        noise: float = 0.0,
        stop: str = "recentre",
    ):
        """`settle`: control steps of rest (belts to rest, carriages still) sent after the fixed sequence,
        while the frames of its last steps are still on their way (the controller's sensor and action
        latency: `World.exploration_delay`); the estimator then sees the whole sequence (`align`).
        `lead`: control steps the guard looks ahead: it trips on the balance error extrapolated `lead`
        steps along its trend (the smaller of its last two changes away from the midline), not only on
        the present one. A box whose end-heavy mass swings its centre sideways by ~1 cm per step during the
        first turn crosses the limit within a step of passing a fixed threshold, faster than the belts can
        stop (0 keeps the present-value rule).
        `noise`: m, the pose noise std the sensor is stated to have; a change between two frames counts
        towards the trend only beyond 2 x sqrt(2) x noise (with 3 mm the bare trend refused 3 of 100
        safe boxes of the realistic world that the present-value guard let through).
        `stop`: what the `GUARD_STEPS` after a trip send (`STOPS`): "recentre" (`recentre_action`) or
        "hold" (belts to rest, carriages still)."""
        if stop not in STOPS:
            raise ValueError(f"the guard's stop must be one of {STOPS}, got {stop!r}")
        self.stop = stop
        if lead < 0:
            raise ValueError(f"the guard's lead must be >= 0 control steps, got {lead}")
        if noise < 0:
            raise ValueError(f"the guard's pose noise must be >= 0 m, got {noise}")
        self.noise = float(noise)
        if guard is not None and not 0 < guard < 1:
            raise ValueError(
                f"the exploration guard must be a fraction of the balance limit in (0, 1), got {guard}"
            )
        if settle < 0:
            raise ValueError(f"settle must be >= 0 control steps, got {settle}")
        self.cfg = cfg
        self.settle = settle
        self.settled = 0  # rest steps sent after the fixed sequence
        self.threshold = None if guard is None else guard * cfg.task.balance_limit  # m
        self.actions = exploration_actions(cfg)
        self.k = 0  # fixed-sequence steps sent
        self.recentring = -1  # re-centring steps left once tripped (-1: not tripped)
        self.worst = 0.0  # m, the balance error that tripped the guard
        self.lead = int(lead)
        self.judged = 0.0  # m, the (extrapolated) balance error the guard tripped on
        self.history: list[float] = []  # signed balance errors seen (m)

    @property
    def tripped(self) -> bool:
        return self.recentring >= 0

    def _judge(self, s, balance_error) -> float:
        """m, the balance error the guard judges (the present one, or with lead > 0 its extrapolation);
        records the state's signed balance error in `history`, so call it once per step."""
        b = abs(float(balance_error))
        s = np.asarray(s, np.float64)
        self.history.append(float(geometry.balance_offset(s)))
        if self.lead == 0 or len(self.history) < 3:
            return b
        return float(judged_balance(self.history[-3:], b, self.lead, self.noise))

    def next(self, s, balance_error) -> np.ndarray | None:
        b = abs(float(balance_error))
        judged = self._judge(s, balance_error)
        if not self.tripped and self.threshold is not None and judged > self.threshold:
            self.recentring, self.worst, self.judged = GUARD_STEPS, b, judged
        if self.tripped:
            if self.recentring == 0:
                return None
            self.recentring -= 1
            return recentre_action(self.cfg, s) if self.stop == "recentre" else np.zeros(4)
        if self.k >= len(self.actions):
            if self.settled >= self.settle:
                return None
            self.settled += 1
            return np.zeros(4)
        self.k += 1
        return self.actions[self.k - 1]

    def why(self) -> str | None:
        """The refusal's explanation (None: not tripped)."""
        if not self.tripped:
            return None
        return guard_explanation(
            self.cfg, self.k, self.worst, self.judged, self.lead, self.threshold, self.stop
        )


def guard_explanation(
    cfg: Config, k: int, worst: float, judged: float, lead: int, threshold: float, stop: str = "recentre"
) -> str:
    """The exploration guard's refusal in words: it tripped after `k` fixed steps with the box `worst` (m)
    off the midline, judged `judged` (m) `lead` steps ahead, against `threshold` (m), and stopped by `stop`
    (`STOPS`)."""
    then = "the carriages re-centred under it" if stop == "recentre" else "the carriages held still"
    ahead = f" and moving away, {100 * judged:.1f} cm expected {lead} steps ahead" if judged > worst else ""
    return (
        f"refused during the exploration: after {k} of its {N_STEPS} fixed steps the "
        f"box's geometric centre was {100 * worst:.1f} cm off the belts' midline{ahead} (guard "
        f"{100 * threshold:.1f} cm, limit {100 * cfg.task.balance_limit:.1f} cm); the belts "
        f"stopped and {then}. The fixed exploration cannot hold this box, "
        "so neither its estimate nor a turn is attempted."
    )


def align(data: dict, delay: int, n_steps: int) -> dict:
    """The exploration as the estimator takes it (`trajectory`'s input: the states before and after each
    fixed step and the step's action, at the same instants), from the controller's record of it.

    With `delay` control steps between an action sent and the frame that shows its effect (the sensor's
    latency plus the drives' action latency), the frame received at step k + delay shows the state the
    k-th action started from; so the states (and belt speeds) are those received from step `delay` on,
    the actions the first `n_steps` sent. `data`: s (K+1, 5), belt_speed (K+1, 2), actions (K, 4) with
    K >= n_steps + delay (the fixed sequence, then `Guarded.settle` rest steps). delay 0: the first
    n_steps (the record as it is, with a perfect sensor).
    """
    s, b, a = (np.asarray(data[k]) for k in ("s", "belt_speed", "actions"))
    if delay < 0 or len(s) < n_steps + delay + 1 or len(a) < n_steps:
        raise ValueError(
            f"cannot align {len(a)} recorded steps to {n_steps} exploration steps with a delay of {delay}: "
            f"need {n_steps + delay} steps recorded"
        )
    return {
        "s": s[delay : delay + n_steps + 1],
        "belt_speed": b[delay : delay + n_steps + 1],
        "actions": a[:n_steps],
    }


__all__ = [
    "DESIGNED",
    "GENTLE",
    "GUARD_STEPS",
    "HOLD",
    "N_STEPS",
    "N_TRAJ_COLUMNS",
    "N_VECTORS",
    "STOPS",
    "VECTORS",
    "Guarded",
    "align",
    "applied_actions",
    "describe_effect",
    "exploration_actions",
    "guard_explanation",
    "judged_balance",
    "recentre_action",
    "run",
    "trajectory",
    "vectors",
]
