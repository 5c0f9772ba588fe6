"""The world as a robot meets it: faults and mismatch between the simulated gripper and the controller.

`Faults` says how the simulated world differs from the perfect one every other result assumes. Three
kinds, each applied where it happens on a robot:

* The sensor (`Sensor`): the box pose the controller receives is the true pose of `obs_latency` control
  steps ago, with gaussian noise on x, y (`obs_noise_mm`) and yaw (`obs_noise_deg`); a frame is lost with
  probability `drop_rate`, and then the last delivered observation is held (and known to be old). The
  carriage positions P1, P2 and the belt speeds come from the drives' encoders: delayed like the pose,
  not noisy.
* The actuators (`Actuator`): an action is applied `action_latency` control steps after it was sent
  (until the first one arrives the belts and carriages are commanded to stay at rest).
* The plant (`world_model`, `MassShift`): the simulator's box-belt friction (`friction`, on both belts
  or one, `friction_belt`) and its servo gains (`carriage_gain`, `belt_gain`, fractions of the nominal
  kp and kv) differ from what the controller's model assumes (`Config.gripper`, unchanged); and at a random
  control step a mass of `mass_shift_kg` inside the box slides `mass_shift_m` (the paper's first
  assumption, a rigid mass distribution, broken).

Every random draw comes from the episode's key (`fault_key`, a stream of its own, so that the episode's
other draws, and every result without faults, stay as they were): a run replays exactly, and two fault
levels on the same key see the same underlying draws scaled (settings compared on the same path).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import jax
import mujoco
import numpy as np

from boxjax import geometry, massdist
from boxjax.config import Config, ConfigError

FAULT_STREAM = 0x0FA1  # folded into an episode key for its fault draws ("FAuLt")
FRICTION_BELTS = ("both", "1", "2")
MAX_LATENCY = 20  # control steps (1 s): beyond this the controller is blind, not late


@dataclasses.dataclass(frozen=True)
class Faults:
    """How the simulated world differs from the controller's perfect one (defaults: not at all)."""

    obs_noise_mm: float = 0.0  # std of gaussian noise on the observed box position x, y (mm)
    obs_noise_deg: float = 0.0  # std of gaussian noise on the observed box yaw (degrees)
    obs_latency: int = 0  # control steps between the world and the observation the controller receives
    drop_rate: float = 0.0  # probability that a frame is lost (the last delivered one is held)
    action_latency: int = 0  # control steps between an action sent and applied
    # the simulator's box-belt friction (None: the config's); the controller's model keeps its own
    friction: float | None = None
    friction_belt: str = "both"  # which belt has `friction`: "both", "1" or "2"
    carriage_gain: float = 1.0  # simulator's carriage servo stiffness and damping, fraction of nominal
    belt_gain: float = 1.0  # simulator's belt-speed servo gain, fraction of nominal
    mass_shift_kg: float = 0.0  # mass that slides inside the box during the episode (kg; 0: none)
    mass_shift_m: float = 0.10  # how far it slides (m), in a random direction in the box's plane
    mass_shift_steps: tuple[int, int] = (60, 200)  # control steps between which the slide happens

    def __post_init__(self):
        def bad(name, why):
            raise ConfigError(f"faults: {name}={getattr(self, name)!r} {why}")

        for name in ("obs_noise_mm", "obs_noise_deg", "mass_shift_kg", "mass_shift_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                bad(name, "must be a finite number >= 0")
        for name in ("obs_latency", "action_latency"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 0 <= v <= MAX_LATENCY):
                bad(name, f"must be a whole number of control steps in [0, {MAX_LATENCY}]")
        if not (isinstance(self.drop_rate, (int, float)) and 0 <= self.drop_rate < 1):
            bad("drop_rate", "must be a probability in [0, 1)")
        if self.friction is not None and not (math.isfinite(self.friction) and self.friction > 0):
            bad("friction", "must be a positive friction coefficient (or None: the config's)")
        if self.friction_belt not in FRICTION_BELTS:
            bad("friction_belt", f"must be one of {FRICTION_BELTS}")
        if self.friction_belt != "both" and self.friction is None:
            bad("friction_belt", "needs a friction to give that belt")
        for name in ("carriage_gain", "belt_gain"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.05 <= v <= 20):
                bad(name, "must be a fraction of the nominal gain in [0.05, 20]")
        lo, hi = self.mass_shift_steps
        if not (0 <= lo <= hi):
            bad("mass_shift_steps", "must be (first, last) control steps with 0 <= first <= last")

    @property
    def any(self) -> bool:
        """Whether the world differs from the perfect one at all."""
        return self != Faults()

    @property
    def observation(self) -> bool:
        return bool(self.obs_noise_mm or self.obs_noise_deg or self.obs_latency or self.drop_rate)

    @property
    def plant(self) -> bool:
        return self.friction is not None or self.carriage_gain != 1 or self.belt_gain != 1

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["mass_shift_steps"] = list(self.mass_shift_steps)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Faults:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"faults: unknown field(s) {unknown}; known: {sorted(known)}")
        d = dict(d)
        if "mass_shift_steps" in d:
            d["mass_shift_steps"] = tuple(d["mass_shift_steps"])
        return cls(**d)


NONE = Faults()


def fault_key(key) -> jax.Array:
    """The episode key's stream for fault draws (a raw or typed jax PRNG key)."""
    return jax.random.fold_in(key, FAULT_STREAM)


def rng(key) -> np.random.Generator:
    """A numpy generator seeded from the episode's fault stream (host-side draws, cheap per step)."""
    k = fault_key(key)
    data = jax.random.key_data(k) if jax.dtypes.issubdtype(k.dtype, jax.dtypes.prng_key) else k
    return np.random.default_rng(np.asarray(data, np.uint32).tolist())


# --------------------------------------------------------------------------------------------------------
# The plant: the simulator's model differs from the controller's.


def world_model(m: mujoco.MjModel, faults: Faults) -> mujoco.MjModel:
    """Apply the plant mismatch to a native model of one box, in place (friction of the box-belt pairs,
    servo gains). Returns `m`. The controller's config is untouched: it keeps planning with its own."""
    if faults.friction is not None:
        belts = (1, 2) if faults.friction_belt == "both" else (int(faults.friction_belt),)
        for i in belts:  # the box-belt contact pair(s) of belt i (sim.model.mjcf)
            g = m.geom(f"belt{i}").id
            pairs = np.flatnonzero((m.pair_geom1 == g) | (m.pair_geom2 == g))
            m.pair_friction[pairs, :2] = faults.friction
    if faults.belt_gain != 1:
        for a in (0, 1):  # belt velocity servos: force = kv * (act - qvel)
            m.actuator_gainprm[a, 0] *= faults.belt_gain
            m.actuator_biasprm[a, 2] *= faults.belt_gain
    if faults.carriage_gain != 1:
        for a in (2, 3):  # carriage position servos: kp * (ctrl - q) - kv * qdot
            m.actuator_gainprm[a, 0] *= faults.carriage_gain
            m.actuator_biasprm[a, 1:3] *= faults.carriage_gain
    return m


@dataclasses.dataclass
class MassShift:
    """A mass that slides inside the box at control step `step`: the box's new inertial fields."""

    step: int
    mass: float
    com: np.ndarray  # (3,) m, box frame, after the slide
    inertia: np.ndarray  # (3, 3) about the new centre of mass
    direction: float  # rad, in the box's plane
    masses: np.ndarray  # (nx, ny, nz) kg, the voxel masses after the slide
    done: bool = False

    def apply(self, m: mujoco.MjModel, box_body: int) -> None:
        """Write the shifted inertial into the native model `m` (its derived constants recomputed)."""
        diag, quat = massdist.principal_axes(self.inertia)
        m.body_ipos[box_body] = self.com
        m.body_iquat[box_body] = quat
        m.body_inertia[box_body] = diag
        mujoco.mj_setConst(m, mujoco.MjData(m))
        self.done = True


def mass_shift(
    dist: massdist.MassDistribution, cfg: Config, faults: Faults, gen: np.random.Generator
) -> MassShift | None:
    """Draw the slide of `faults.mass_shift_kg` inside the box `dist` (None when there is none).

    Of every voxel's mass, the same fraction f = min(1, shift_kg / total mass) slides `mass_shift_m`
    along a random direction in the box's plane; mass that would leave the box piles up against its
    wall (the voxel index is clipped). The total mass is unchanged; the centre of mass and the inertia are
    those of the new voxel masses (`massdist.mass_properties_from_masses`).
    """
    step = int(gen.integers(faults.mass_shift_steps[0], faults.mass_shift_steps[1] + 1))
    direction = float(gen.uniform(-np.pi, np.pi))
    if faults.mass_shift_kg <= 0:
        return None
    box = cfg.box
    masses = np.asarray(massdist.voxel_masses(dist, box), np.float64)
    total = float(masses.sum())
    f = min(1.0, faults.mass_shift_kg / total)
    size = np.asarray(box.voxel_size[:2], np.float64)
    shift = faults.mass_shift_m * np.array([np.cos(direction), np.sin(direction)])
    di, dj = np.rint(shift / size).astype(int)
    moved = np.zeros_like(masses)
    nx, ny = box.grid[:2]
    ii = np.clip(np.arange(nx) + di, 0, nx - 1)
    jj = np.clip(np.arange(ny) + dj, 0, ny - 1)
    np.add.at(moved, (ii[:, None], jj[None, :]), masses)  # every voxel column moved by (di, dj), clipped
    new = (1 - f) * masses + f * moved
    props = massdist.mass_properties_from_masses(new, box)
    return MassShift(
        step=step,
        mass=float(props.mass),
        com=np.asarray(props.com, np.float64),
        inertia=np.asarray(props.inertia, np.float64),
        direction=direction,
        masses=new,
    )


# --------------------------------------------------------------------------------------------------------
# The channels: what the controller receives and when its commands act.


class Sensor:
    """The observation channel of one world: latency, dropped frames and pose noise, in that order.

    `observe(s, belt_speed)` is called once per control step with the TRUE planar state (5,) and belt
    speeds (2,) just reached, and returns what the controller receives then: (s, belt_speed, age, fresh)
    where age is how many control steps old the returned observation is (0 with no latency and no drop)
    and fresh whether it is a new frame (False: the last frame held, a drop).
    """

    def __init__(self, faults: Faults, gen: np.random.Generator):
        self.f = faults
        self.gen = gen
        self._history: deque = deque(maxlen=faults.obs_latency + 1)
        self._held: tuple | None = None
        self._held_age = 0

    def observe(self, s, belt_speed) -> tuple[np.ndarray, np.ndarray, int, bool]:
        f = self.f
        s = np.asarray(s, np.float64).copy()
        b = np.asarray(belt_speed, np.float64).copy()
        # the draws are made every step whatever the settings, so that noise levels share the same path
        z = self.gen.standard_normal(3)
        lost = self.gen.random() < f.drop_rate
        self._history.append((s, b))
        s_d, b_d = self._history[0]  # the state obs_latency steps ago (or the oldest seen)
        age = len(self._history) - 1
        if lost and self._held is not None:
            self._held_age += 1
            hs, hb = self._held
            return hs.copy(), hb.copy(), self._held_age, False
        noisy = s_d.copy()
        noisy[geometry.X] += 1e-3 * f.obs_noise_mm * z[0]
        noisy[geometry.Y] += 1e-3 * f.obs_noise_mm * z[1]
        noisy[geometry.YAW] += np.radians(f.obs_noise_deg) * z[2]
        self._held, self._held_age = (noisy, b_d), age
        return noisy.copy(), b_d.copy(), age, True


class Actuator:
    """The command channel of one world: an action applied `action_latency` control steps after it was
    sent. Until the first action arrives the belts are held at rest and the carriages still."""

    def __init__(self, faults: Faults):
        self.queue: deque = deque([np.zeros(4)] * faults.action_latency)

    def send(self, action) -> np.ndarray:
        """Send `action` (4,); returns the action the gripper applies this step."""
        self.queue.append(np.asarray(action, np.float64))
        return self.queue.popleft()
