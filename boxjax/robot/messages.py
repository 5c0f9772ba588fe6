"""The real conveyor gripper's messages as plain Python data (no ROS needed).

Each class is a frozen dataclass that mirrors one ROS message field by field, with `from_dict` (what a
ROS node gets from `rosidl_runtime_py.message_to_ordereddict`, rosbridge or a recorded bag turned into
dicts) and `to_dict` (the inverse, which `set_message_fields` / rosbridge accept). Sequences are stored as
tuples of floats / strings, so a message is immutable and hashable.

    Header            std_msgs/Header: stamp (float seconds), frame_id
    Point, Quaternion geometry_msgs/Point (x, y, z), geometry_msgs/Quaternion (x, y, z, w: ROS order!)
    Pose              geometry_msgs/Pose: position (Point), orientation (Quaternion)
    ItemInManipulator one tracked item: its pose (in the feedback's header frame)
    TrackingFeedback  header + items_in_manipulator (the box tracking feedback)
    JointState        sensor_msgs/JointState: header, name, position, velocity, effort
    VelocityControl   canopen_interface/VelocityControl: joint_names, target_velocities (m/s),
                      target_accelerations (m/s^2) -- the belt command
    CarriageCommand   one position target per carriage joint: joint_names, positions (m)

Stamps. A stamp is a plain float in seconds. `from_dict` also accepts a ROS 2 stamp {"sec", "nanosec"}
or a ROS 1 stamp {"secs", "nsecs"} and turns it into seconds; `to_dict` writes the float.

What is checked here. The structure: types, equal lengths, no duplicate joint names. The values of
received messages (Pose, JointState, TrackingFeedback) are kept as they came, NaN included (a JointState
may carry NaN for a joint nobody reads); the adapter (`boxjax.robot.adapter`) checks every value it
reads and names the field when one is bad. The OUTGOING belt command is checked in full on construction:
a `VelocityControl` with a non-finite velocity, |velocity| > ROBOT_MAX_VELOCITY, or an acceleration not
in (0, ROBOT_MAX_ACCELERATION] cannot exist. On the robot an acceleration of 0.0 means UNLIMITED, never
"no change": a stop is velocity 0.0 at the acceleration limit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

ROBOT_MAX_VELOCITY = 0.247126  # m/s, |target_velocities| the belt drives accept
ROBOT_MAX_ACCELERATION = 0.6  # m/s^2, the largest target_accelerations; 0.0 means UNLIMITED on the robot


# ----------------------------------------------------------------------------------------------------------
# Field conversion helpers (they raise ValueError naming the field).


def _float(value: Any, name: str) -> float:
    if isinstance(value, (bool, str, bytes)):
        raise ValueError(f"{name} must be a number, got {type(value).__name__} {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{name} must be a number, got {type(value).__name__} {value!r}") from e


def _floats(values: Any, name: str) -> tuple[float, ...]:
    if (
        isinstance(values, (str, bytes, Mapping))
        or not isinstance(values, Sequence)
        and not hasattr(values, "tolist")
    ):
        raise ValueError(f"{name} must be a sequence of numbers, got {type(values).__name__}")
    if hasattr(values, "tolist"):  # numpy arrays
        values = values.tolist()
        if not isinstance(values, list):
            raise ValueError(f"{name} must be a 1-d sequence of numbers, got a scalar")
    return tuple(_float(v, f"{name}[{i}]") for i, v in enumerate(values))


def _names(values: Any, name: str) -> tuple[str, ...]:
    if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence):
        raise ValueError(f"{name} must be a sequence of strings, got {type(values).__name__}")
    out = []
    for i, v in enumerate(values):
        if not isinstance(v, str) or not v:
            raise ValueError(f"{name}[{i}] must be a non-empty string, got {v!r}")
        out.append(v)
    dup = sorted({n for n in out if out.count(n) > 1})
    if dup:
        raise ValueError(f"{name} names a joint more than once: {dup}")
    return tuple(out)


def _mapping(d: Any, name: str, keys: Sequence[str], optional: Sequence[str] = ()) -> Mapping:
    if not isinstance(d, Mapping):
        raise ValueError(f"{name} must be a mapping, got {type(d).__name__}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise ValueError(f"{name} lacks the field(s) {missing}")
    unknown = sorted(set(d) - set(keys) - set(optional))
    if unknown:
        raise ValueError(f"{name} has unknown field(s) {unknown}")
    return d


def stamp_from(value: Any, name: str = "stamp") -> float:
    """Seconds (float) from a float stamp, a ROS 2 {"sec", "nanosec"} or a ROS 1 {"secs", "nsecs"}."""
    if isinstance(value, Mapping):
        for sec, nsec in (("sec", "nanosec"), ("secs", "nsecs")):
            if sec in value:
                _mapping(value, name, (sec, nsec))
                return _float(value[sec], f"{name}.{sec}") + 1e-9 * _float(value[nsec], f"{name}.{nsec}")
        raise ValueError(f"{name} must be seconds or a mapping with sec/nanosec (or secs/nsecs), got {value}")
    return _float(value, name)


def _check_lengths(names: tuple[str, ...], arrays: dict[str, tuple], cls: str, allow_empty: bool) -> None:
    for key, arr in arrays.items():
        if len(arr) != len(names) and not (allow_empty and len(arr) == 0):
            extra = " (or be empty: not reported)" if allow_empty else ""
            raise ValueError(
                f"{cls}.{key} has {len(arr)} values for {len(names)} joint names; it must have one per "
                f"name{extra}"
            )


# ----------------------------------------------------------------------------------------------------------
# Messages.


@dataclass(frozen=True)
class Header:
    """std_msgs/Header. stamp: seconds (float); frame_id: the frame the message's poses are in."""

    stamp: float = 0.0
    frame_id: str = ""

    def __post_init__(self):
        object.__setattr__(self, "stamp", _float(self.stamp, "header.stamp"))
        if not isinstance(self.frame_id, str):
            raise ValueError(f"header.frame_id must be a string, got {self.frame_id!r}")

    @classmethod
    def from_dict(cls, d: Mapping) -> Header:
        d = _mapping(d, "header", ("stamp",), ("frame_id",))
        return cls(stamp_from(d["stamp"], "header.stamp"), d.get("frame_id", ""))

    def to_dict(self) -> dict:
        return {"stamp": self.stamp, "frame_id": self.frame_id}


@dataclass(frozen=True)
class Point:
    """geometry_msgs/Point (m)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _float(getattr(self, f.name), f"position.{f.name}"))

    @classmethod
    def from_dict(cls, d: Any) -> Point:
        """From {"x", "y", "z"} or a sequence (x, y, z)."""
        if isinstance(d, Mapping):
            d = _mapping(d, "position", ("x", "y", "z"))
            return cls(d["x"], d["y"], d["z"])
        v = _floats(d, "position")
        if len(v) != 3:
            raise ValueError(f"position must have 3 values (x, y, z), got {len(v)}")
        return cls(*v)

    def to_dict(self) -> dict:
        return {"x": self.x, "y": self.y, "z": self.z}


@dataclass(frozen=True)
class Quaternion:
    """geometry_msgs/Quaternion in ROS order (x, y, z, w): w is the LAST component (MuJoCo and
    boxjax.geometry put w first). The identity is (0, 0, 0, 1)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _float(getattr(self, f.name), f"orientation.{f.name}"))

    @classmethod
    def from_dict(cls, d: Any) -> Quaternion:
        """From {"x", "y", "z", "w"} or a sequence in ROS order (x, y, z, w)."""
        if isinstance(d, Mapping):
            d = _mapping(d, "orientation", ("x", "y", "z", "w"))
            return cls(d["x"], d["y"], d["z"], d["w"])
        v = _floats(d, "orientation")
        if len(v) != 4:
            raise ValueError(f"orientation must have 4 values in ROS order (x, y, z, w), got {len(v)}")
        return cls(*v)

    @classmethod
    def from_yaw(cls, yaw: float) -> Quaternion:
        """The rotation by `yaw` (rad) about z: (0, 0, sin(yaw / 2), cos(yaw / 2))."""
        return cls(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))

    def to_dict(self) -> dict:
        return {"x": self.x, "y": self.y, "z": self.z, "w": self.w}

    def xyzw(self) -> tuple[float, float, float, float]:
        return (self.x, self.y, self.z, self.w)


@dataclass(frozen=True)
class Pose:
    """geometry_msgs/Pose: position (m) and orientation of a frame in the message's header frame."""

    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)

    def __post_init__(self):
        if not isinstance(self.position, Point) or not isinstance(self.orientation, Quaternion):
            raise ValueError("Pose needs a Point position and a Quaternion orientation (use Pose.from_dict)")

    @classmethod
    def from_dict(cls, d: Mapping) -> Pose:
        d = _mapping(d, "pose", ("position", "orientation"))
        return cls(Point.from_dict(d["position"]), Quaternion.from_dict(d["orientation"]))

    def to_dict(self) -> dict:
        return {"position": self.position.to_dict(), "orientation": self.orientation.to_dict()}


@dataclass(frozen=True)
class ItemInManipulator:
    """One item the tracking sees in the gripper: its pose (of the item's centre, see AdapterConfig) in
    the TrackingFeedback's header frame, and an optional id."""

    pose: Pose = field(default_factory=Pose)
    id: str = ""

    def __post_init__(self):
        if not isinstance(self.pose, Pose):
            raise ValueError("ItemInManipulator.pose must be a Pose (use ItemInManipulator.from_dict)")
        if not isinstance(self.id, str):
            raise ValueError(f"ItemInManipulator.id must be a string, got {self.id!r}")

    @classmethod
    def from_dict(cls, d: Mapping) -> ItemInManipulator:
        d = _mapping(d, "items_in_manipulator[i]", ("pose",), ("id",))
        return cls(Pose.from_dict(d["pose"]), d.get("id", ""))

    def to_dict(self) -> dict:
        return {"pose": self.pose.to_dict(), "id": self.id}


@dataclass(frozen=True)
class TrackingFeedback:
    """The box tracking feedback: header (stamp: when the poses were measured; frame_id: their frame,
    `gripper_surface_tip_link` on the robot) and the items in the manipulator (the box is item 0)."""

    header: Header = field(default_factory=Header)
    items_in_manipulator: tuple[ItemInManipulator, ...] = ()

    def __post_init__(self):
        if not isinstance(self.header, Header):
            raise ValueError("TrackingFeedback.header must be a Header (use TrackingFeedback.from_dict)")
        items = self.items_in_manipulator
        if isinstance(items, (str, bytes, Mapping)) or not isinstance(items, Sequence):
            raise ValueError("TrackingFeedback.items_in_manipulator must be a sequence of items")
        if not all(isinstance(i, ItemInManipulator) for i in items):
            raise ValueError("TrackingFeedback.items_in_manipulator must hold ItemInManipulator values")
        object.__setattr__(self, "items_in_manipulator", tuple(items))

    @classmethod
    def from_dict(cls, d: Mapping) -> TrackingFeedback:
        d = _mapping(d, "tracking feedback", ("header", "items_in_manipulator"))
        items = d["items_in_manipulator"]
        if isinstance(items, (str, bytes, Mapping)) or not isinstance(items, Sequence):
            raise ValueError("items_in_manipulator must be a sequence")
        return cls(Header.from_dict(d["header"]), tuple(ItemInManipulator.from_dict(i) for i in items))

    def to_dict(self) -> dict:
        return {
            "header": self.header.to_dict(),
            "items_in_manipulator": [i.to_dict() for i in self.items_in_manipulator],
        }


@dataclass(frozen=True)
class JointState:
    """sensor_msgs/JointState. Joints are matched BY NAME, in any order. position (m for the carriages),
    velocity (belt surface speed, see AdapterConfig.belt_state_scale) and effort each have one value per
    name, or are empty (ROS: not reported)."""

    header: Header = field(default_factory=Header)
    name: tuple[str, ...] = ()
    position: tuple[float, ...] = ()
    velocity: tuple[float, ...] = ()
    effort: tuple[float, ...] = ()

    def __post_init__(self):
        if not isinstance(self.header, Header):
            raise ValueError("JointState.header must be a Header (use JointState.from_dict)")
        object.__setattr__(self, "name", _names(self.name, "JointState.name"))
        arrays = {}
        for key in ("position", "velocity", "effort"):
            arrays[key] = _floats(getattr(self, key), f"JointState.{key}")
            object.__setattr__(self, key, arrays[key])
        _check_lengths(self.name, arrays, "JointState", allow_empty=True)

    def index(self, joint: str) -> int:
        """Where `joint` is in `name`. Raises ValueError when the message lacks it."""
        try:
            return self.name.index(joint)
        except ValueError:
            raise ValueError(
                f"JointState.name lacks the joint {joint!r} (it has {list(self.name)})"
            ) from None

    def value(self, joint: str, key: str) -> float:
        """`key` ("position", "velocity" or "effort") of `joint`. Raises ValueError when the message lacks
        the joint or does not report `key`."""
        i = self.index(joint)
        arr = getattr(self, key)
        if not arr:
            raise ValueError(f"JointState.{key} is empty (not reported), but {joint!r} is needed")
        return arr[i]

    @classmethod
    def from_dict(cls, d: Mapping) -> JointState:
        d = _mapping(d, "joint state", ("header", "name"), ("position", "velocity", "effort"))
        return cls(
            Header.from_dict(d["header"]),
            d["name"],
            d.get("position", ()),
            d.get("velocity", ()),
            d.get("effort", ()),
        )

    def to_dict(self) -> dict:
        return {
            "header": self.header.to_dict(),
            "name": list(self.name),
            "position": list(self.position),
            "velocity": list(self.velocity),
            "effort": list(self.effort),
        }


@dataclass(frozen=True)
class VelocityControl:
    """canopen_interface/VelocityControl, the belt command: per joint a target velocity (m/s, belt surface
    speed) reached at the target acceleration (m/s^2).

    Checked on construction (an invalid one cannot exist): one velocity and one acceleration per joint
    name, every velocity finite with |v| <= ROBOT_MAX_VELOCITY, every acceleration in
    (0, ROBOT_MAX_ACCELERATION]. An acceleration of 0.0 would mean UNLIMITED on the robot.
    """

    joint_names: tuple[str, ...]
    target_velocities: tuple[float, ...]
    target_accelerations: tuple[float, ...]

    def __post_init__(self):
        names = _names(self.joint_names, "VelocityControl.joint_names")
        v = _floats(self.target_velocities, "VelocityControl.target_velocities")
        a = _floats(self.target_accelerations, "VelocityControl.target_accelerations")
        _check_lengths(names, {"target_velocities": v, "target_accelerations": a}, "VelocityControl", False)
        for n, x in zip(names, v, strict=True):
            if not math.isfinite(x) or abs(x) > ROBOT_MAX_VELOCITY:
                raise ValueError(
                    f"VelocityControl.target_velocities for {n!r} is {x}; it must be finite with "
                    f"|v| <= {ROBOT_MAX_VELOCITY} m/s"
                )
        for n, x in zip(names, a, strict=True):
            if not (0.0 < x <= ROBOT_MAX_ACCELERATION):  # False for NaN too
                raise ValueError(
                    f"VelocityControl.target_accelerations for {n!r} is {x}; it must be in "
                    f"(0, {ROBOT_MAX_ACCELERATION}] m/s^2 (0.0 means UNLIMITED on the robot)"
                )
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "target_velocities", tuple(x + 0.0 for x in v))  # no -0.0 on the wire
        object.__setattr__(self, "target_accelerations", a)

    @classmethod
    def from_dict(cls, d: Mapping) -> VelocityControl:
        d = _mapping(d, "VelocityControl", ("joint_names", "target_velocities", "target_accelerations"))
        return cls(d["joint_names"], d["target_velocities"], d["target_accelerations"])

    def to_dict(self) -> dict:
        return {
            "joint_names": list(self.joint_names),
            "target_velocities": list(self.target_velocities),
            "target_accelerations": list(self.target_accelerations),
        }

    def velocity(self, joint: str) -> float:
        """The target velocity of `joint` (matched by name). Raises ValueError when it is not commanded."""
        if joint not in self.joint_names:
            raise ValueError(f"VelocityControl.joint_names lacks {joint!r} (it has {list(self.joint_names)})")
        return self.target_velocities[self.joint_names.index(joint)]


@dataclass(frozen=True)
class CarriageCommand:
    """One position target per carriage joint (m, in the robot's convention: see AdapterConfig). Checked
    on construction: one finite position per distinct joint name (the ranges are the adapter's)."""

    joint_names: tuple[str, ...]
    positions: tuple[float, ...]

    def __post_init__(self):
        names = _names(self.joint_names, "CarriageCommand.joint_names")
        p = _floats(self.positions, "CarriageCommand.positions")
        _check_lengths(names, {"positions": p}, "CarriageCommand", False)
        for n, x in zip(names, p, strict=True):
            if not math.isfinite(x):
                raise ValueError(f"CarriageCommand.positions for {n!r} is {x}; it must be finite")
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "positions", tuple(x + 0.0 for x in p))

    @classmethod
    def from_dict(cls, d: Mapping) -> CarriageCommand:
        d = _mapping(d, "CarriageCommand", ("joint_names", "positions"))
        return cls(d["joint_names"], d["positions"])

    def to_dict(self) -> dict:
        return {"joint_names": list(self.joint_names), "positions": list(self.positions)}

    def position(self, joint: str) -> float:
        """The target of `joint` (matched by name). Raises ValueError when it is not commanded."""
        if joint not in self.joint_names:
            raise ValueError(f"CarriageCommand.joint_names lacks {joint!r} (it has {list(self.joint_names)})")
        return self.positions[self.joint_names.index(joint)]
