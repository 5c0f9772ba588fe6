"""boxjax's actions and observations <-> the real gripper's messages (`boxjax.robot.messages`).

    s, belt_speed, stamp = observation_from_messages(tracking, joints, cfg)          # robot -> boxjax
    velocity, carriage, status = commands_from_action(action, p, now, stamp, cfg)    # boxjax -> robot

Conventions (every one is a field of `AdapterConfig`; the defaults are ASSUMPTIONS TO VERIFY ON THE ROBOT)
----------------------------------------------------------------------------------------------------------
boxjax's conveyor frame: x along belt travel, y across the belts, z up (right-handed), origin midway
between the belts' nominal centre-lines on the belt surface. Looking along +x, +y is on the LEFT (the
ROS convention, REP 103: x forward, y left, z up). The planar state is s = (P1, P2, x, y, yaw) with
P1 < 0 < P2 the belts' centre-lines, (x, y) the box's geometric centre and yaw its rotation about z.

* Belts. Belt 1 (P1 < 0, the right belt looking along +x) is the joint `conveyor_belt_right`, belt 2
  (P2 > 0) is `conveyor_belt_left`. A positive velocity moves the belt surface along +x, on the robot as
  in boxjax (`belt_sign` = (+1, +1)); the robot's target_velocities are belt surface speeds in m/s, and
  its JointState velocity of a belt joint is a surface speed in m/s too (`belt_state_scale` = 1).
  NOTE: boxjax's own docs (docs/design.md#frames, GripperConfig) call belt 1 the "left" belt, naming the
  sides as seen by someone facing the gripper (looking along -x). The robot's joint names are taken here
  from the robot's own point of view (REP 103). If the robot disagrees, `AdapterConfig.sides_swapped()`
  exchanges the sides of both the belt and the carriage joints.
* Carriages. The robot reports and takes each carriage as a POSITIVE distance from the gripper's centre
  line: gripper_y_right = -P1, gripper_y_left = +P2, in m. In general robot value = carriage_sign[i] *
  P_i + carriage_offset[i] (defaults (-1, +1) and (0, 0): the distance of the belt's centre-line from the
  conveyor frame's origin; an offset of -belt_width / 2 would make it the distance of the belt's inner
  edge).
* Box pose. The tracking feedback's `items_in_manipulator[0].pose` is the box in `gripper_surface_tip_link`
  (`tracking_frame`), its orientation a ROS quaternion (x, y, z, w: w LAST). The tip link's pose in the
  conveyor frame is the planar transform `tip_in_conveyor` = (x, y, yaw), default (0, 0, 0): the tip
  link sits at the conveyor frame's origin on the belt surface with its axes aligned (z up). The item's
  position is taken as the box's geometric centre (`item_centre_offset` = (0, 0): the centre's x, y in
  the item's own frame, for a tracker that reports a corner or a marker instead).
* Time. Stamps are float seconds on one clock (the node's `now` and the messages' header stamps). An
  observation is the older of the tracking and joint stamps.

Safety
------
Nothing that leaves `commands_from_action` is NaN, inf or beyond the limits: belt velocities are clipped
to min(GripperConfig.belt_speed_limit, ROBOT_MAX_VELOCITY), every acceleration is the gripper's
belt_accel_limit (in (0, 0.6] m/s^2: 0.0 would mean UNLIMITED on the robot, so it is never sent, a stop
included), the carriage step to +-max_position_step and the target to p1_range / p2_range (as
`boxjax.sim.core.command` clips). A non-finite action becomes a stop (`non_finite_action`), and so does
an observation older than `max_observation_age` (0.1 s = two control steps) at command time
(`stale_observation`), a non-finite stamp (`invalid_stamp`) or one more than `max_clock_skew` in the
future (`future_observation`). A stop is belt velocity 0 at the acceleration limit with the carriages
held where they are (`status["safe_stop"]`, `status["reason"]`).

Incoming data is checked by `observation_from_messages`, which raises ValueError naming the field:
non-finite values, a missing joint, a quaternion far from unit length, a box tilted past `max_tilt`
(tipped, or a quaternion read in the wrong order), a box farther than `max_pose_distance` from the
origin, a carriage on the wrong side or beyond the hardware travel, a belt faster than the robot can run.
`commands_from_action` raises ValueError only for arguments of the wrong shape and for non-finite
carriage positions `state_p` (the adapter's own observation, already checked): there is no position
to hold then.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from boxjax.config import HARDWARE, GripperConfig
from boxjax.robot.messages import (
    ROBOT_MAX_ACCELERATION,
    ROBOT_MAX_VELOCITY,
    CarriageCommand,
    Header,
    ItemInManipulator,
    JointState,
    Point,
    Pose,
    Quaternion,
    TrackingFeedback,
    VelocityControl,
)

# Why a command is a stop (`status["reason"]`).
STOP_REASONS = ("stale_observation", "future_observation", "invalid_stamp", "non_finite_action")


@dataclass(frozen=True)
class AdapterConfig:
    """How boxjax's conveyor frame and action map onto the robot's joints and frames (module docstring).

    The defaults are assumptions to verify on the robot: which belt each joint drives and which way it
    runs, the carriages' sign and zero, and where `gripper_surface_tip_link` lies in the conveyor frame.
    Indices 0 / 1 of the pairs are belt 1 (P1 < 0) / belt 2 (P2 > 0).
    """

    # Limits: the belt speed, acceleration, carriage ranges, position step and control step of boxjax.
    gripper: GripperConfig = field(default_factory=GripperConfig)
    # Belts: the VelocityControl / JointState joint of belt 1 and belt 2; robot velocity = sign * v_i.
    belt_joints: tuple[str, str] = ("conveyor_belt_right", "conveyor_belt_left")
    belt_sign: tuple[float, float] = (1.0, 1.0)
    belt_state_scale: float = 1.0  # m/s of belt surface per unit of a belt joint's JointState velocity
    # Carriages: the joint of P1 and of P2; robot position = sign * P_i + offset (m).
    carriage_joints: tuple[str, str] = ("gripper_y_right", "gripper_y_left")
    carriage_sign: tuple[float, float] = (-1.0, 1.0)
    carriage_offset: tuple[float, float] = (0.0, 0.0)  # m
    # Frames: the tracking's frame, the planar pose (x m, y m, yaw rad) of that frame in the conveyor
    # frame, and the box's geometric centre (x, y, m) in the tracked item's frame.
    tracking_frame: str = "gripper_surface_tip_link"
    tip_in_conveyor: tuple[float, float, float] = (0.0, 0.0, 0.0)
    item_centre_offset: tuple[float, float] = (0.0, 0.0)
    # Time: the oldest observation a command may act on (s; 0.1 = two control steps), and how far in
    # the future a stamp may lie before the clocks are taken to disagree.
    max_observation_age: float = 0.1
    max_clock_skew: float = 0.05
    # Plausibility of incoming data (beyond these, observation_from_messages raises).
    max_tilt: float = math.radians(20.0)  # rad, the task's tip limit (TaskConfig.tip_limit)
    max_pose_distance: float = 1.0  # m, |x| and |y| of the box in the conveyor frame
    position_tolerance: float = 0.005  # m, a carriage may read this far beyond the hardware travel
    speed_tolerance: float = 0.02  # m/s, a belt may read this far above ROBOT_MAX_VELOCITY

    def __post_init__(self):
        if not isinstance(self.gripper, GripperConfig):
            raise ValueError(f"gripper must be a boxjax GripperConfig, got {type(self.gripper).__name__}")
        for name in ("belt_joints", "carriage_joints"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and len(v) == 2 and all(isinstance(n, str) and n for n in v)):
                raise ValueError(f"{name} must be two non-empty joint names (belt 1, belt 2), got {v!r}")
        joints = self.belt_joints + self.carriage_joints
        if len(set(joints)) != 4:
            raise ValueError(f"belt_joints and carriage_joints must be four different names, got {joints}")
        for name in ("belt_sign", "carriage_sign"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and len(v) == 2 and all(s in (1.0, -1.0) for s in v)):
                raise ValueError(f"{name} must be two signs, each +1.0 or -1.0, got {v!r}")
        for name, n in (("carriage_offset", 2), ("tip_in_conveyor", 3), ("item_centre_offset", 2)):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and len(v) == n and all(_finite_number(x) for x in v)):
                raise ValueError(f"{name} must be {n} finite numbers, got {v!r}")
        for name in ("belt_state_scale", "max_observation_age", "max_tilt", "max_pose_distance"):
            v = getattr(self, name)
            if not (_finite_number(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        for name in ("max_clock_skew", "position_tolerance", "speed_tolerance"):
            v = getattr(self, name)
            if not (_finite_number(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        if not isinstance(self.tracking_frame, str):
            raise ValueError(f"tracking_frame must be a string, got {self.tracking_frame!r}")
        if not 0 < self.belt_acceleration <= ROBOT_MAX_ACCELERATION:
            raise ValueError(f"the gripper's belt_accel_limit must be in (0, {ROBOT_MAX_ACCELERATION}]")

    @property
    def belt_speed_limit(self) -> float:
        """m/s, the largest |belt velocity| sent: the gripper's limit, never above the robot's."""
        return min(self.gripper.belt_speed_limit, ROBOT_MAX_VELOCITY)

    @property
    def belt_acceleration(self) -> float:
        """m/s^2, the acceleration every belt command carries (boxjax reaches setpoints at this limit)."""
        return min(self.gripper.belt_accel_limit, ROBOT_MAX_ACCELERATION)

    @property
    def p_low(self) -> np.ndarray:
        """(2,) m, the lower ends of p1_range and p2_range."""
        return np.array([self.gripper.p1_range[0], self.gripper.p2_range[0]])

    @property
    def p_high(self) -> np.ndarray:
        """(2,) m, the upper ends of p1_range and p2_range."""
        return np.array([self.gripper.p1_range[1], self.gripper.p2_range[1]])

    def sides_swapped(self) -> AdapterConfig:
        """This config with the robot's left and right joints exchanged (belts and carriages): for a robot
        whose `*_left` joints drive belt 1 (P1 < 0)."""
        return dataclasses.replace(
            self, belt_joints=self.belt_joints[::-1], carriage_joints=self.carriage_joints[::-1]
        )

    # Conversions of the carriages (robot value <-> P_i), both (2,) in the order (P1, P2).
    def carriage_to_robot(self, p) -> np.ndarray:
        return np.asarray(self.carriage_sign) * np.asarray(p, np.float64) + np.asarray(self.carriage_offset)

    def carriage_from_robot(self, q) -> np.ndarray:
        return np.asarray(self.carriage_sign) * (np.asarray(q, np.float64) - np.asarray(self.carriage_offset))


def _finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _wrap(a: float) -> float:
    """Radians to [-pi, pi), as geometry.wrap_angle."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def _rot(theta: float, x: float, y: float) -> tuple[float, float]:
    c, s = math.cos(theta), math.sin(theta)
    return c * x - s * y, s * x + c * y


def _finite(value: float, name: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{name} is {value}; it must be finite")
    return value


def _as(msg, cls, name: str):
    if isinstance(msg, cls):
        return msg
    if isinstance(msg, Mapping):
        return cls.from_dict(msg)
    raise ValueError(f"{name} must be a {cls.__name__} or its dict, got {type(msg).__name__}")


# ----------------------------------------------------------------------------------------------------------
# Robot -> boxjax.


def observation_from_messages(
    tracking: TrackingFeedback | Mapping,
    joints: JointState | Mapping,
    cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
    prev_yaw: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """boxjax's planar state and belt speeds from the tracking feedback and the joint states.

    Args:
      tracking: TrackingFeedback (or its dict); item 0 is the box, its pose in cfg.tracking_frame (a
        header frame_id of "" is taken to be that frame; another frame is refused).
      joints: JointState (or its dict) with the carriage joints' positions and the belt joints'
        velocities, matched by name in any order; other joints are ignored.
      prev_yaw: rad, the previous observation's yaw: the yaw returned is the angle closest to it (boxjax's
        yaw is continuous, never wrapped, as `sim.core.planar_state`). None: wrapped to [-pi, pi).
    Returns:
      s (5,) float64 (P1, P2, x, y, yaw) in m, m, m, m, rad in the conveyor frame; belt_speed (2,) float64
      m/s of belt 1 and belt 2 along +x; stamp (float s), the older of the two messages' stamps.
    Raises:
      ValueError naming the field: wrong message type or frame, no item, a non-finite value, a missing
      joint or unreported position / velocity, a quaternion not of unit length (norm outside [0.9, 1.1]),
      a box tilted beyond cfg.max_tilt, a box beyond cfg.max_pose_distance, a carriage on the wrong side
      of the centre line or beyond the hardware travel (+ position_tolerance), a belt speed beyond
      ROBOT_MAX_VELOCITY + speed_tolerance.
    """
    tracking = _as(tracking, TrackingFeedback, "tracking")
    joints = _as(joints, JointState, "joints")
    frame = tracking.header.frame_id
    if frame not in ("", cfg.tracking_frame):
        raise ValueError(
            f"tracking.header.frame_id is {frame!r}; the adapter expects poses in {cfg.tracking_frame!r}"
        )
    stamp_t = _finite(tracking.header.stamp, "tracking.header.stamp")
    stamp_j = _finite(joints.header.stamp, "joints.header.stamp")
    if not tracking.items_in_manipulator:
        raise ValueError("tracking.items_in_manipulator is empty: no box in the gripper")

    # The box's planar pose.
    pose = tracking.items_in_manipulator[0].pose
    where = "tracking.items_in_manipulator[0].pose"
    px, py, _ = (_finite(getattr(pose.position, k), f"{where}.position.{k}") for k in "xyz")
    qx, qy, qz, qw = (_finite(getattr(pose.orientation, k), f"{where}.orientation.{k}") for k in "xyzw")
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not 0.9 <= norm <= 1.1:
        raise ValueError(
            f"{where}.orientation has norm {norm:.4g}; a rotation quaternion (x, y, z, w) has norm 1"
        )
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    tilt = math.acos(max(-1.0, min(1.0, 1 - 2 * (qx * qx + qy * qy))))
    if tilt > cfg.max_tilt:
        raise ValueError(
            f"{where}.orientation tilts the box by {math.degrees(tilt):.1f} degrees (limit "
            f"{math.degrees(cfg.max_tilt):.1f}): the box tipped, or the quaternion is not in ROS order "
            "(x, y, z, w)"
        )
    yaw_tip = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    cx, cy = _rot(yaw_tip, *cfg.item_centre_offset)
    tx, ty, tyaw = cfg.tip_in_conveyor
    x, y = _rot(tyaw, px + cx, py + cy)
    x, y = x + tx, y + ty
    yaw = _wrap(yaw_tip + tyaw)
    if prev_yaw is not None:
        prev_yaw = _finite(float(prev_yaw), "prev_yaw")
        yaw = prev_yaw + _wrap(yaw - prev_yaw)
    for name, v in (("x", x), ("y", y)):
        if abs(v) > cfg.max_pose_distance:
            raise ValueError(
                f"{where}.position puts the box at {name} = {v:.3f} m in the conveyor frame, beyond "
                f"max_pose_distance = {cfg.max_pose_distance} m"
            )

    # Carriages (P1 < 0 < P2) and belts.
    q = [_finite(joints.value(j, "position"), f"joints.position of {j!r}") for j in cfg.carriage_joints]
    p = cfg.carriage_from_robot(q)
    lo, hi = HARDWARE.carriage_travel
    tol = cfg.position_tolerance
    for i, (j, side_ok, within) in enumerate(
        (
            (cfg.carriage_joints[0], p[0] < 0, p[0] >= lo - tol),
            (cfg.carriage_joints[1], p[1] > 0, p[1] <= hi + tol),
        )
    ):
        if not (side_ok and within):
            raise ValueError(
                f"joints.position of {j!r} = {q[i]} gives P{i + 1} = {p[i]:.4g} m; P1 must lie in "
                f"[{lo}, 0) and P2 in (0, {hi}] m (check carriage_sign / carriage_offset and the units)"
            )
    v = []
    for i, j in enumerate(cfg.belt_joints):
        raw = _finite(joints.value(j, "velocity"), f"joints.velocity of {j!r}")
        vi = cfg.belt_sign[i] * cfg.belt_state_scale * raw
        if abs(vi) > ROBOT_MAX_VELOCITY + cfg.speed_tolerance:
            raise ValueError(
                f"joints.velocity of {j!r} = {raw} reads as a belt speed of {vi:.4g} m/s, beyond the robot's "
                f"{ROBOT_MAX_VELOCITY} m/s (check belt_state_scale and the units)"
            )
        v.append(vi)
    s = np.array([p[0], p[1], x, y, yaw], np.float64)
    return s, np.array(v, np.float64), min(stamp_t, stamp_j)


def messages_from_observation(
    s,
    belt_speed,
    stamp: float,
    cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
    *,
    z: float = 0.075,
) -> tuple[TrackingFeedback, JointState]:
    """The messages the robot would send for the planar state `s` (5,) and belt speeds (2,) at `stamp`
    (the inverse of `observation_from_messages`; a simulated robot). z: m, the box centre's height in the
    tracking frame (half the default box height). Joint order: carriages, then belts."""
    s = np.asarray(s, np.float64)
    belt_speed = np.asarray(belt_speed, np.float64)
    if s.shape != (5,) or belt_speed.shape != (2,):
        raise ValueError(f"s must be (5,) and belt_speed (2,), got {s.shape} and {belt_speed.shape}")
    tx, ty, tyaw = cfg.tip_in_conveyor
    yaw_tip = float(s[4]) - tyaw
    cx, cy = _rot(-tyaw, float(s[2]) - tx, float(s[3]) - ty)
    ox, oy = _rot(yaw_tip, *cfg.item_centre_offset)
    pose = Pose(Point(cx - ox, cy - oy, z), Quaternion.from_yaw(yaw_tip))
    tracking = TrackingFeedback(Header(stamp, cfg.tracking_frame), (ItemInManipulator(pose),))
    q = cfg.carriage_to_robot(s[:2])
    raw = [belt_speed[i] / (cfg.belt_sign[i] * cfg.belt_state_scale) for i in range(2)]
    joints = JointState(
        Header(stamp, ""),
        cfg.carriage_joints + cfg.belt_joints,
        position=(q[0], q[1], 0.0, 0.0),
        velocity=(0.0, 0.0, raw[0], raw[1]),
        effort=(0.0, 0.0, 0.0, 0.0),
    )
    return tracking, joints


# ----------------------------------------------------------------------------------------------------------
# boxjax -> robot.


def _vector(x, n: int, name: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{name} must be {n} numbers, got {x!r}") from e
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got shape {a.shape}")
    return a


def stamp_problem(now: float, stamp: float, cfg: AdapterConfig = AdapterConfig()) -> str | None:  # noqa: B008
    """Why an observation stamped `stamp` may not be acted on at `now` (a STOP_REASONS entry), or None."""
    try:
        now, stamp = float(now), float(stamp)
    except (TypeError, ValueError, OverflowError):
        return "invalid_stamp"
    if not (math.isfinite(now) and math.isfinite(stamp)):
        return "invalid_stamp"
    age = now - stamp
    if not math.isfinite(age) or age > cfg.max_observation_age:
        return "stale_observation"
    if age < -cfg.max_clock_skew:
        return "future_observation"
    return None


def _commands(
    v: np.ndarray, target: np.ndarray, cfg: AdapterConfig
) -> tuple[VelocityControl, CarriageCommand]:
    """Robot messages for belt velocities v (2,) along +x and carriage targets (P1, P2), both already
    within the limits."""
    acc = cfg.belt_acceleration
    velocity = VelocityControl(
        cfg.belt_joints, tuple(float(cfg.belt_sign[i] * v[i]) for i in range(2)), (acc, acc)
    )
    carriage = CarriageCommand(cfg.carriage_joints, tuple(float(q) for q in cfg.carriage_to_robot(target)))
    return velocity, carriage


def stop_commands(
    state_p,
    cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
) -> tuple[VelocityControl, CarriageCommand]:
    """A stop: both belts to velocity 0.0 at the acceleration limit (never 0.0: unlimited on the robot),
    the carriages held at `state_p` (P1, P2) (m, clipped into p1_range / p2_range).

    Raises ValueError when state_p is not 2 finite numbers."""
    p = _vector(state_p, 2, "state_p")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"state_p must be finite carriage positions (P1, P2), got {p.tolist()}")
    return _commands(np.zeros(2), np.clip(p, cfg.p_low, cfg.p_high), cfg)


def commands_from_action(
    action,
    state_p,
    now: float,
    last_obs_stamp: float,
    cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
) -> tuple[VelocityControl, CarriageCommand, dict]:
    """The robot's commands for boxjax's action a = (v1, v2, dp1, dp2).

    Args:
      action: (4,) belt speed setpoints v1, v2 (m/s along +x) and carriage steps dp1, dp2 (m along y).
      state_p: (2,) m, the carriages' positions (P1, P2) the steps start from: the last targets sent (as
        boxjax's simulator does) or the measured positions.
      now: s, the time the command is sent; last_obs_stamp: s, the stamp of the observation the action
        was planned on.
    Returns:
      VelocityControl: belt i's velocity belt_sign[i] * clip(v_i, +-belt_speed_limit) at the
        acceleration limit; CarriageCommand: the targets clip(P_i + clip(dp_i, +-max_position_step),
        p_i range) in the robot's convention (carriage_sign * P + carriage_offset); and a status dict:
        safe_stop (bool), reason (a STOP_REASONS entry or None), age_s (now - last_obs_stamp), clipped
        (the action was beyond a limit), action (the action as sent, [v1, v2, dp1, dp2], dp = target - P).
      A stale, future or non-finite stamp, or a non-finite action, gives a stop (`stop_commands`).
    Raises:
      ValueError: action not of shape (4,), or state_p not 2 finite numbers.
    """
    a = _vector(action, 4, "action")
    p = _vector(state_p, 2, "state_p")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"state_p must be finite carriage positions (P1, P2), got {p.tolist()}")
    reason = stamp_problem(now, last_obs_stamp, cfg)
    if reason is None and not np.all(np.isfinite(a)):
        reason = "non_finite_action"
    try:
        age = float(now) - float(last_obs_stamp)
    except (TypeError, ValueError, OverflowError):
        age = math.nan
    held = np.clip(p, cfg.p_low, cfg.p_high)
    if reason is not None:
        velocity, carriage = _commands(np.zeros(2), held, cfg)
        sent = [0.0, 0.0, *(held - p).tolist()]
        status = {"safe_stop": True, "reason": reason, "age_s": age, "clipped": False, "action": sent}
        return velocity, carriage, status
    limit, step = cfg.belt_speed_limit, cfg.gripper.max_position_step
    v = np.clip(a[:2], -limit, limit)
    dp = np.clip(a[2:], -step, step)
    target = np.clip(p + dp, cfg.p_low, cfg.p_high)
    clipped = bool(np.any(v != a[:2]) or np.any(dp != a[2:]) or np.any(target != p + dp))
    velocity, carriage = _commands(v, target, cfg)
    sent = [*v.tolist(), *(target - p).tolist()]
    status = {"safe_stop": False, "reason": None, "age_s": age, "clipped": clipped, "action": sent}
    return velocity, carriage, status


def carriage_targets(carriage: CarriageCommand | Mapping, cfg: AdapterConfig = AdapterConfig()) -> np.ndarray:  # noqa: B008
    """(2,) m, the targets (P1, P2) in boxjax's convention of a CarriageCommand (joints matched by name)."""
    carriage = _as(carriage, CarriageCommand, "carriage")
    return cfg.carriage_from_robot([carriage.position(j) for j in cfg.carriage_joints])


def action_from_commands(
    velocity: VelocityControl | Mapping,
    carriage: CarriageCommand | Mapping,
    state_p,
    cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
) -> np.ndarray:
    """The boxjax action (4,) (v1, v2, dp1, dp2) that the robot's commands carry, read back (joints
    matched by name): v_i = velocity of belt i's joint / belt_sign[i], dp_i = target P_i - state_p[i].
    The inverse of `commands_from_action` for an action within the limits."""
    velocity = _as(velocity, VelocityControl, "velocity")
    p = _vector(state_p, 2, "state_p")
    v = [velocity.velocity(j) * cfg.belt_sign[i] for i, j in enumerate(cfg.belt_joints)]
    dp = carriage_targets(carriage, cfg) - p
    return np.array([v[0], v[1], dp[0], dp[1]], np.float64)


__all__ = [
    "STOP_REASONS",
    "AdapterConfig",
    "action_from_commands",
    "carriage_targets",
    "commands_from_action",
    "messages_from_observation",
    "observation_from_messages",
    "stamp_problem",
    "stop_commands",
]
