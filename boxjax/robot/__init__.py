"""The real conveyor gripper's messages, without ROS (issue 29, item 4).

An adapter between boxjax's actions and observations and the robot's messages, as plain Python data, so
that a ROS node is a thin shell around it (convert each ROS message to a dict, call, convert back):

    from boxjax.robot import AdapterConfig, TrackingFeedback, JointState, RobotLoop, PlannerStep

    cfg = AdapterConfig()                                            # conventions: verify on the robot
    s, belt_speed, stamp = observation_from_messages(tracking, joints, cfg)       # (5,), (2,), s
    velocity, carriage, status = commands_from_action(action, p_target, now, stamp, cfg)
    ros_velocity_msg_fields = velocity.to_dict()                     # canopen_interface/VelocityControl

`messages` holds the message dataclasses (VelocityControl, CarriageCommand, JointState, Pose,
TrackingFeedback, ...), `adapter` the conversions and the conventions (`AdapterConfig`, whose module
docstring lists every sign, unit and frame and which of them are assumptions), `loop` a control loop
(`RobotLoop`) that turns a stream of messages into commands with a boxjax planner (`PlannerStep`).

Never sent: NaN, inf, a belt velocity beyond +-0.247 m/s, an acceleration above 0.6 m/s^2 or equal to
0.0 (UNLIMITED on the robot). Observations older than 0.1 s at command time give a stop.
"""

from boxjax.robot.adapter import (
    STOP_REASONS,
    AdapterConfig,
    action_from_commands,
    carriage_targets,
    commands_from_action,
    messages_from_observation,
    observation_from_messages,
    stamp_problem,
    stop_commands,
)
from boxjax.robot.loop import LOOP_STOP_REASONS, PlannerStep, PlanStep, RobotLoop
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

__all__ = [
    "LOOP_STOP_REASONS",
    "ROBOT_MAX_ACCELERATION",
    "ROBOT_MAX_VELOCITY",
    "STOP_REASONS",
    "AdapterConfig",
    "CarriageCommand",
    "Header",
    "ItemInManipulator",
    "JointState",
    "PlanStep",
    "PlannerStep",
    "Point",
    "Pose",
    "Quaternion",
    "RobotLoop",
    "TrackingFeedback",
    "VelocityControl",
    "action_from_commands",
    "carriage_targets",
    "commands_from_action",
    "messages_from_observation",
    "observation_from_messages",
    "stamp_problem",
    "stop_commands",
]
