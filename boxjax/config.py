"""Physical and algorithmic defaults, as frozen dataclasses.

Every number that shapes the physics or the task lives here, once. Change one only with a reason recorded in
docs/design.md#physical-defaults. Units are SI (m, kg, s, rad) throughout.

Frames
------
Conveyor frame: x along belt travel, y across the belts, z up; origin midway between the two belts'
nominal centre-lines, on the belt surface. Box frame: origin at the box's geometric centre, x along the
box length (0.40 m), y along its width (0.30 m), z along its height. At reset the two frames are aligned
(yaw 0) and the box rests on the belts.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field


class ConfigError(ValueError):
    """A configuration value is invalid or beyond what the hardware can do."""


@dataclass(frozen=True)
class Hardware:
    """What the real gripper can do. A `GripperConfig` may ask for less, never more.

    Belt limits are from a public SOTO conveyor note (units assumed m/s and m/s^2, see
    docs/design.md#physical-defaults).
    """

    max_belt_speed: float = 0.247  # m/s
    max_belt_accel: float = 0.6  # m/s^2
    carriage_travel: tuple[float, float] = (-0.25, 0.25)  # m, y range of a belt centre-line
    max_carriage_speed: float = 0.25  # m/s


HARDWARE = Hardware()
MJX_BOX_CONTACTS = ("native", "mjx", "polygon")  # GripperConfig.mjx_box_contacts


@dataclass(frozen=True)
class BoxConfig:
    """The box and its voxel grid (paper §2.1, §4.2)."""

    size: tuple[float, float, float] = (0.40, 0.30, 0.15)  # length, width, height (m)
    # Length and width divisible by 4, so the hazard quarter-slabs U1..U4 fall on voxel faces.
    grid: tuple[int, int, int] = (8, 8, 4)
    mass_range: tuple[float, float] = (1.0, 10.0)  # kg, total mass ~ U(lo, hi)
    # Added to every voxel so no voxel is massless (paper Fig. 2 caption): friction never vanishes.
    voxel_eps: float = 1e-5  # kg

    def __post_init__(self):
        if any(s <= 0 for s in self.size):
            raise ConfigError(f"box size must be positive, got {self.size}")
        nx, ny, nz = self.grid
        if min(self.grid) < 1:
            raise ConfigError(f"voxel grid must have at least one voxel per axis, got {self.grid}")
        if nx % 4 or ny % 4:
            raise ConfigError(
                f"voxel grid {self.grid}: length and width counts must be divisible by 4 so that the "
                "hazard regions U1..U4 (quarter slabs) fall on voxel faces"
            )
        lo, hi = self.mass_range
        if not 0 < lo <= hi:
            raise ConfigError(f"mass_range must satisfy 0 < lo <= hi, got {self.mass_range}")
        if self.voxel_eps < 0:
            raise ConfigError(f"voxel_eps must be >= 0, got {self.voxel_eps}")

    @property
    def n_voxels(self) -> int:
        nx, ny, nz = self.grid
        return nx * ny * nz

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        return tuple(s / n for s, n in zip(self.size, self.grid, strict=True))  # type: ignore[return-value]

    @property
    def half_size(self) -> tuple[float, float, float]:
        return tuple(s / 2 for s in self.size)  # type: ignore[return-value]


@dataclass(frozen=True)
class GripperConfig:
    """The two-belt gripper as simulated (docs/design.md#simulation).

    Belt i (i = 1 left, y < 0; i = 2 right, y > 0) is a slab whose surface runs along x at a commanded
    speed, carried by a carriage that slides along y under a position servo.
    """

    belt_speed_limit: float = 0.247  # m/s, |v_i|
    belt_accel_limit: float = 0.6  # m/s^2, |dv_i/dt|
    belt_width: float = 0.10  # m, along y
    belt_length: float = 0.80  # m, slab length along x (re-centred every control step)
    belt_thickness: float = 0.02  # m
    belt_y0: tuple[float, float] = (-0.10, 0.10)  # m, initial centre-lines P1, P2
    p1_range: tuple[float, float] = (-0.20, -0.06)  # m, allowed P1
    p2_range: tuple[float, float] = (0.06, 0.20)  # m, allowed P2
    max_position_step: float = 0.01  # m, |dp_i| per control step
    friction: float = 0.5  # box-belt kinetic friction coefficient mu_k
    # Contact model (docs/design.md#simulation-model). MuJoCo's soft contacts make a slipping box
    # hop (the solver trades normal against tangential residual), which makes rotation under slip
    # chaotic. A longer friction reference time constant (elliptic cone only) stops the hopping but
    # also weakens sliding friction far below mu*g (measured: 1.2 instead of 4.9 m/s^2 at 0.2 s), so the
    # default keeps MuJoCo's reference: physically right sliding, with the hopping documented.
    contact_cone: str = "pyramidal"  # "pyramidal" or "elliptic"
    friction_timeconst: float = 0.0  # s, solreffriction time constant; 0 = MuJoCo's default (solref)
    # How the MJX backend finds the box-belt contacts (native MuJoCo always uses its own box-box collider):
    # "native", native MuJoCo's rules (one contact when an edge-cross axis wins the separating-axis test),
    # so that MJX simulates what native MuJoCo does (without it MJX turns boxes measurably more); "mjx",
    # MJX's collider (4 points per belt, a point repeated when fewer penetrate); "polygon", every vertex of
    # the touching faces' overlap (`boxjax.sim.mjx_contacts`; docs/results/simulation.md#colliders).
    mjx_box_contacts: str = "native"
    timestep: float = 0.002  # s, physics step
    control_dt: float = 0.05  # s, one control step (action held constant)
    gravity: float = 9.81  # m/s^2

    def __post_init__(self):
        hw = HARDWARE
        if not 0 < self.belt_speed_limit <= hw.max_belt_speed:
            raise ConfigError(
                f"belt_speed_limit={self.belt_speed_limit} m/s is beyond the hardware "
                f"(0 < v <= {hw.max_belt_speed} m/s)"
            )
        if not 0 < self.belt_accel_limit <= hw.max_belt_accel:
            raise ConfigError(
                f"belt_accel_limit={self.belt_accel_limit} m/s^2 is beyond the hardware "
                f"(0 < a <= {hw.max_belt_accel} m/s^2)"
            )
        for name, (lo, hi) in (("p1_range", self.p1_range), ("p2_range", self.p2_range)):
            if not hw.carriage_travel[0] <= lo < hi <= hw.carriage_travel[1]:
                raise ConfigError(
                    f"{name}={(lo, hi)} m is beyond the hardware carriage travel {hw.carriage_travel} m"
                )
        if self.p1_range[1] + self.belt_width > self.p2_range[0] + 1e-12:
            raise ConfigError(
                f"p1_range {self.p1_range} and p2_range {self.p2_range} let the belts (width "
                f"{self.belt_width} m) overlap"
            )
        for i, (p, (lo, hi)) in enumerate(zip(self.belt_y0, (self.p1_range, self.p2_range), strict=True)):
            if not lo <= p <= hi:
                raise ConfigError(f"belt_y0[{i}]={p} is outside its range {(lo, hi)}")
        if self.max_position_step <= 0 or self.max_position_step / self.control_dt > hw.max_carriage_speed:
            raise ConfigError(
                f"max_position_step={self.max_position_step} m per {self.control_dt} s exceeds the hardware "
                f"carriage speed {hw.max_carriage_speed} m/s"
            )
        if self.friction <= 0:
            raise ConfigError(f"friction must be positive, got {self.friction}")
        if self.contact_cone not in ("elliptic", "pyramidal"):
            raise ConfigError(f"contact_cone must be 'elliptic' or 'pyramidal', got {self.contact_cone!r}")
        if self.friction_timeconst < 0:
            raise ConfigError(f"friction_timeconst must be >= 0, got {self.friction_timeconst}")
        if self.mjx_box_contacts not in MJX_BOX_CONTACTS:
            raise ConfigError(
                f"mjx_box_contacts must be one of {MJX_BOX_CONTACTS}, got {self.mjx_box_contacts!r}"
            )
        if self.timestep <= 0 or self.control_dt < self.timestep:
            raise ConfigError(f"need 0 < timestep <= control_dt, got {self.timestep}, {self.control_dt}")
        ratio = self.control_dt / self.timestep
        if abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(
                f"control_dt={self.control_dt} must be an integer multiple of timestep={self.timestep}"
            )

    @property
    def n_substeps(self) -> int:
        """Physics steps per control step."""
        return round(self.control_dt / self.timestep)


EXPLORATIONS = ("fixed", "designed", "gentle")


@dataclass(frozen=True)
class TaskConfig:
    """The rotation task and its success / failure rules (paper §2.1, §4.2)."""

    target_yaw_delta: float = math.pi / 2  # rad, turn relative to the initial yaw
    yaw_tolerance: float = math.radians(2.0)  # rad, success band around the target
    # Balance error |y_geom - (P1 + P2) / 2| must never exceed this: 0.1 x box length (paper §4.2).
    balance_limit: float = 0.04  # m
    max_steps: int = 600  # control steps (30 s at 20 Hz)
    tip_limit: float = math.radians(20.0)  # rad, roll or pitch beyond this means the box tipped
    drop_limit: float = 0.03  # m, box centre this far below its resting height means it fell
    reward_eps: float = 1e-6  # epsilon of the rewards R1, R2 (paper eq. 1)
    # Optional noise on the initial pose (the paper starts every episode from the same pose: 0 by default).
    init_xy_noise: float = 0.0  # m, box centre x and y each ~ U(-n, n)
    init_yaw_noise: float = 0.0  # rad, yaw ~ U(-n, n)
    # The 45-step exploration every episode starts with (boxjax.estimator.explore): "fixed" (the paper's
    # shape, the shipped sequence), "designed" (chosen for information, boxjax.estimator.design) or "gentle"
    # (the fixed one with its first turn at half speed, for a late, noisy sensor: explore.GENTLE).
    exploration: str = "fixed"  # one of EXPLORATIONS

    def __post_init__(self):
        if self.balance_limit <= 0 or self.yaw_tolerance <= 0 or self.max_steps < 1:
            raise ConfigError("balance_limit and yaw_tolerance must be positive and max_steps >= 1")
        if self.exploration not in EXPLORATIONS:
            raise ConfigError(f"exploration must be one of {EXPLORATIONS}, got {self.exploration!r}")


@dataclass(frozen=True)
class Config:
    """Everything that defines an experiment."""

    box: BoxConfig = field(default_factory=BoxConfig)
    gripper: GripperConfig = field(default_factory=GripperConfig)
    task: TaskConfig = field(default_factory=TaskConfig)

    def replace(self, **changes) -> Config:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


DEFAULT = Config()
