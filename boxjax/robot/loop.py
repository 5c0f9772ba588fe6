"""The control loop of a ROS node without ROS: the robot's messages in, its commands out, a boxjax
planner in between.

    loop = RobotLoop(PlannerStep(planner, model, key), AdapterConfig())
    every control step (50 ms), with the latest messages and the node's clock:
        velocity, carriage, status = loop.step(tracking, joints, now)
        publish velocity (always); publish carriage unless it is None

The loop keeps what boxjax's controller keeps (`control.episode.run_episode`): the window of the last
planning.MIN_WINDOW = 3 planar states, one per control step, the first one repeated at the start (the
box at rest); the target yaw (the first observed yaw + pi / 2 unless given); and the carriage targets,
each step's targets being the last ones plus the action's steps (as the simulator does; they start at the
first measured positions).

Given the tracking pose's noise (`pose_noise`: the vision pipeline's specification), the loop estimates the
pose as boxjax's controller does under a noisy sensor (`control.state_estimate`): a Kalman filter per
planar coordinate over the tracked poses, and the planner's window by `FilterConfig.window`'s rule (for a
noisy sensor, the line through the newest estimate along the filter's velocity: differences of noisy
poses would give the prior a velocity as wrong as the box's own; docs/results/faults.md). Without it the
tracked poses go into the window as received.

Given a model (`latency_model`, the planner's), the loop predicts the window over the vision pipeline's
latency as the simulated controller does (`planning.compensate`, a Smith predictor): from the newest
pose's stamp to now, through the actions it sent in between (as sent, after the adapter's clipping; a
stop's as rest), so the planner and the monitor act on the state the command will meet.

It stops (belts to 0 at the acceleration limit, carriages held) instead of planning when no observation
was ever valid (`no_observation`: no carriage command then, the carriages keep their last target), when
this step's messages are invalid (`invalid_observation`, with the adapter's ValueError in
status["error"]: a tipped box stops at once), and for the adapter's reasons (`adapter.STOP_REASONS`:
stale, future or non-finite stamps, a non-finite action). It resumes by itself when fresh valid messages
come; after a gap longer than max_observation_age the window restarts from the new state (the states
in a window must be one control step apart).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np

from boxjax import planning
from boxjax.config import DEFAULT, Config, TaskConfig
from boxjax.control.monitor import Monitor, MonitorConfig, present_one, tip_watch, to_host
from boxjax.control.monitor import check as monitor_check
from boxjax.control.state_estimate import FilterConfig, PoseFilter, make_filter, state_line, state_window
from boxjax.robot.adapter import (
    STOP_REASONS,
    AdapterConfig,
    carriage_targets,
    commands_from_action,
    observation_from_messages,
    stamp_problem,
    stop_commands,
)
from boxjax.robot.messages import CarriageCommand, JointState, TrackingFeedback, VelocityControl
from boxjax.sim.faults import Faults

LOOP_STOP_REASONS = (*STOP_REASONS, "no_observation", "invalid_observation")
MAX_PREDICTED_STEPS = 20  # the longest latency (control steps) the loop predicts over (as `Faults`' bound)
_compensate = jax.jit(planning.compensate)

PlanStep = Callable[[planning.Observation], Any]  # observation -> action (4,) (v1, v2, dp1, dp2)


def _now(value: float | Callable[[], float]) -> float:
    """A std given as a number or as a function of the moment (the loop's filter, step by step)."""
    return value() if callable(value) else value


class PlannerStep:
    """A boxjax `planning.Planner` and its model as a plan step `obs -> action (4,)`: it keeps the
    planner's own state (`init` on the first call, then `optimize`'s plan_state) and splits `key` once
    per call, as `control.episode.run_episode` does; and, as there, the runtime safety monitor
    (`boxjax.control.monitor`; on by default, `monitor=MonitorConfig(enabled=False)` removes it) checks
    each action and replaces it by the controlled stop when the turn is about to lose the box. It checks
    with the same model, or with `monitor_model` (required with `MonitorConfig.prior_params`: the
    monitor's own prior, e.g. `control.models.monitor_model(cfg, ctrl, belief, None)`). `sigma` (m, or a
    function giving it each step): the standard deviation of the pose estimate's y the monitor assumes
    (the robot's vision pipeline's; a `RobotLoop` given the pose noise links it to its filter's; the
    loop's staleness stops are the adapter's); `delay`: the control steps the loop predicts its
    observations over (`RobotLoop(latency_model=...)`), whose prediction error the monitor adds
    (`MonitorConfig.delay_std`). A `RobotLoop` with a `latency_model` also gives it, as `late`, the
    newest estimate and the actions in flight, from which the monitor predicts the present with its own
    model and, for `MonitorConfig.drag_bound`, without the carriages' drag (consumed by the next call).
    `stopped` and `monitor.record()` say what it did."""

    def __init__(
        self,
        planner: planning.Planner,
        model,
        key,
        *,
        cfg: Config = DEFAULT,
        monitor: MonitorConfig = MonitorConfig(),  # noqa: B008 (frozen)
        sigma: float | Callable[[], float] = 0.0,
        delay: int = 0,
        monitor_model=None,
        yaw_sigma: float | Callable[[], float] = 0.0,
    ):
        if monitor.enabled and monitor.prior_params is not None and monitor_model is None:
            raise ValueError(
                "MonitorConfig.prior_params (the monitor's own prior) needs its model: pass monitor_model, "
                "e.g. control.models.monitor_model(cfg, ctrl, belief, None)"
            )
        self.planner, self.model, self.key = planner, model, key
        self.monitor_model = monitor_model
        self.plan_state = None
        self.cfg, self.t = cfg, 0
        self.sigma: float | Callable[[], float] = sigma if callable(sigma) else float(sigma)
        # the estimate's yaw std (rad), for the "sigma" tipping watch (`Monitor.tip_spread`)
        self.yaw_sigma: float | Callable[[], float] = yaw_sigma if callable(yaw_sigma) else float(yaw_sigma)
        self.monitor = Monitor(cfg, monitor, delay) if monitor.enabled else None
        # the next call's (window (W, 5), belt speeds (2,), actions in flight (D, 4)) at the newest
        # estimate's time, set by the loop; None: the observation is the present as it is
        self.late = None

    @property
    def stopped(self) -> bool:
        return self.monitor is not None and self.monitor.stopped

    def __call__(self, obs: planning.Observation) -> np.ndarray:
        if self.plan_state is None:
            self.plan_state = self.planner.init(obs)
        self.key, key = jax.random.split(self.key)
        a, self.plan_state, _ = self.planner.optimize(key, self.model, obs, self.plan_state)
        a = np.asarray(a, np.float64)
        late, self.late = self.late, None
        if self.monitor is not None and np.all(np.isfinite(a)):
            model = self.model if self.monitor_model is None else self.monitor_model
            window, held = obs.window, None
            own, bound = self.monitor_model is not None, self.monitor.m.drag_bound
            if late is not None and (own or bound):  # predicted from the newest estimate by the monitor
                window, held = present_one(model, *late, np.asarray(obs.window, np.float32), own, bound)
            sigma = _now(self.sigma)
            tip = tip_watch(self.monitor.m)
            spread = None
            if tip == "sigma":
                belt = np.asarray(obs.belt_speed)
                spread = self.monitor.tip_spread(sigma, belt, yaw_sigma=_now(self.yaw_sigma))
            check = monitor_check(
                self.cfg,
                model,
                np.asarray(window, np.float32),
                obs.belt_speed,
                np.asarray(a, np.float32),
                self.monitor.m.horizon,
                self.monitor.m.backup,
                held,
                tip=tip,
                tip_spread=spread,
            )
            a = self.monitor.decide(self.t, a, to_host(check), sigma, 0, np.asarray(obs.belt_speed))
        self.t += 1
        return a


class RobotLoop:
    """Messages in, commands out (module docstring).

    Args:
      plan_step: observation (planning.Observation: window (3, 5), belt_speed (2,), target_yaw) ->
        action (4,); e.g. `PlannerStep(make_planner(cfg, for_delay(cfg, ctrl, delay)), model, key)`, where
        `delay` is the loop's latency in control steps (`control.for_delay` slows the sampling planner
        past `ControllerConfig.delay_reference`, as the simulated controller does). Exceptions it raises
        pass through (the robot's own command timeout then stops the belts).
      cfg: the adapter's conventions and limits.
      target_yaw: rad in the conveyor frame; None: the first observed yaw + `turn`.
      turn: rad, the turn to make (TaskConfig.target_yaw_delta, pi / 2).
      pose_noise: (mm, degrees) std of the tracked pose (the vision pipeline's specification), or None:
        the poses are taken as exact. pose_filter: the filter's settings (`FilterConfig`). With a
        `PlannerStep` whose sigma is 0, its monitor's sigma becomes the filter's (`y_std`), and its yaw
        sigma (0) the filter's yaw std (`yaw_std`).
      latency_model: a model with `rollout_sequence` (the planner's) to predict the window over the
        pipeline's latency, from the newest pose's stamp to `now` (whole control steps, at most
        `MAX_PREDICTED_STEPS`); None: the window is the newest poses as they are.
    """

    def __init__(
        self,
        plan_step: PlanStep,
        cfg: AdapterConfig = AdapterConfig(),  # noqa: B008 (frozen)
        *,
        target_yaw: float | None = None,
        turn: float = TaskConfig().target_yaw_delta,
        window: int = planning.MIN_WINDOW,
        pose_noise: tuple[float, float] | None = None,
        pose_filter: FilterConfig = FilterConfig(),  # noqa: B008 (frozen)
        latency_model=None,
    ):
        if window < planning.MIN_WINDOW:
            raise ValueError(f"window must be at least planning.MIN_WINDOW = {planning.MIN_WINDOW}")
        if pose_noise is not None and not (
            len(pose_noise) == 2 and all(math.isfinite(v) and v >= 0 for v in pose_noise) and any(pose_noise)
        ):
            raise ValueError(f"pose_noise must be (mm, degrees) >= 0, not both 0, got {pose_noise!r}")
        # the sensor as the filter is told it (a noise-only specification: no latency is compensated)
        self._sensor = (
            None if pose_noise is None else Faults(obs_noise_mm=pose_noise[0], obs_noise_deg=pose_noise[1])
        )
        self._filter_settings = dataclasses.replace(pose_filter, enabled=True, latency_steps=0)
        self._filter: PoseFilter | None = None
        self._state_line = self._sensor is not None and state_window(self._filter_settings, self._sensor)
        self.plan_step, self.cfg, self.turn, self.length = plan_step, cfg, float(turn), int(window)
        if self._sensor is not None and isinstance(plan_step, PlannerStep) and plan_step.sigma == 0.0:
            plan_step.sigma = self.y_std  # the monitor's margin: the filter's uncertainty, step by step
            if plan_step.yaw_sigma == 0.0:
                plan_step.yaw_sigma = self.yaw_std
        self.target_yaw = None if target_yaw is None else float(target_yaw)
        self._window: list[np.ndarray] = []
        self._belt_speed = np.zeros(2)
        self._stamp: float | None = None  # of the newest state in the window
        self._p_target: np.ndarray | None = None  # (P1, P2) m, the last carriage targets sent
        self.latency_model = latency_model
        self._sent: list[np.ndarray] = []  # the actions sent, newest last (at most MAX_PREDICTED_STEPS)

    @property
    def window(self) -> np.ndarray:
        """(W, 5) the planar states the planner sees (oldest first); (0, 5) before any observation: the
        tracked poses, or with `pose_noise` their estimates, as a line along the filter's velocity for a
        noisy sensor (`FilterConfig.window`)."""
        w = np.array(self._window, np.float64).reshape(-1, 5)
        if self._state_line and self._filter is not None and len(w):
            return state_line(w, self._filter).astype(np.float64)
        return w

    def y_std(self) -> float:
        """(m) the standard deviation of the estimated box y: the filter's (`PoseFilter.y_std`), the stated
        noise before its first frame, 0 for poses taken as exact."""
        if self._sensor is None:
            return 0.0
        return self._filter.y_std() if self._filter is not None else 1e-3 * self._sensor.obs_noise_mm

    def yaw_std(self) -> float:
        """(rad) the standard deviation of the estimated box yaw, as `y_std`."""
        if self._sensor is None:
            return 0.0
        return (
            self._filter.yaw_std() if self._filter is not None else math.radians(self._sensor.obs_noise_deg)
        )

    @property
    def p_target(self) -> np.ndarray | None:
        """(2,) m, the carriage targets (P1, P2) last sent, or None before the first observation."""
        return None if self._p_target is None else self._p_target.copy()

    def observe(self, tracking: TrackingFeedback | Mapping, joints: JointState | Mapping) -> str:
        """Take one pair of messages into the window. Returns what happened: "new", "first", "restarted"
        (after a gap), or "repeated" (not newer than the last state: ignored). Raises the adapter's
        ValueError for invalid messages."""
        prev_yaw = self._window[-1][4] if self._window else None
        s, v, stamp = observation_from_messages(tracking, joints, self.cfg, prev_yaw)
        if self._stamp is not None and stamp <= self._stamp:
            return "repeated"
        if self._stamp is None:
            what = "first"
            self._p_target = s[:2].copy()
            if self.target_yaw is None:
                self.target_yaw = float(s[4]) + self.turn
        elif stamp - self._stamp > self.cfg.max_observation_age:
            what = "restarted"
        else:
            what = "new"
        # estimate the pose: one filter step per new frame, a new filter after a gap
        if self._sensor is not None:
            if what != "new" or self._filter is None:
                self._filter = make_filter(self._filter_settings, self._sensor, self.cfg.gripper.control_dt)
            s = self._filter.step(s)
        if what == "new":
            self._window = [*self._window, s][-self.length :]
        else:
            self._window = [s] * self.length
        self._belt_speed, self._stamp = v, stamp
        return what

    def step(
        self, tracking: TrackingFeedback | Mapping, joints: JointState | Mapping, now: float
    ) -> tuple[VelocityControl, CarriageCommand | None, dict]:
        """One control step: observe the messages, plan, and return the commands to publish.

        Returns (VelocityControl, CarriageCommand or None (no_observation only), status): status has
        safe_stop, reason (LOOP_STOP_REASONS or None), observation ("first", "new", "restarted",
        "repeated", "invalid"), error (the ValueError's text for "invalid"), and for planned commands the
        adapter's age_s, clipped and action, and predicted_steps (the latency predicted over, `predicted`).
        """
        try:
            seen, error = self.observe(tracking, joints), None
        except ValueError as e:
            seen, error = "invalid", str(e)
        if self._stamp is None or seen == "invalid":
            reason = "invalid_observation" if seen == "invalid" else "no_observation"
            return (*self._stop(), {"safe_stop": True, "reason": reason, "observation": seen, "error": error})
        reason = stamp_problem(now, self._stamp, self.cfg)
        if reason is not None:
            return (*self._stop(), {"safe_stop": True, "reason": reason, "observation": seen, "error": None})
        window, belt, ahead = self.predicted(now)
        if isinstance(self.plan_step, PlannerStep):  # its monitor predicts from the newest estimate too
            self.plan_step.late = self.late(now)
        action = self.plan_step(planning.observation(window, belt, self.target_yaw))
        velocity, carriage, status = commands_from_action(action, self._p_target, now, self._stamp, self.cfg)
        self._p_target = carriage_targets(carriage, self.cfg)
        self._remember(status["action"])
        return velocity, carriage, {**status, "observation": seen, "error": None, "predicted_steps": ahead}

    def predicted(self, now: float) -> tuple[np.ndarray, np.ndarray, int]:
        """(window (W, 5), belt speeds (2,), steps): what the planner is given at `now`: the window and the
        measured belt speeds, predicted over the whole control steps from the newest pose's stamp to now
        with `latency_model` (`planning.compensate`) through the actions sent since; steps 0 without one."""
        window = planning.check_window(self.window)
        belt = np.asarray(self._belt_speed, np.float64)
        steps = self._steps(now)
        if self.latency_model is None or steps == 0:
            return window, belt, 0
        w, b = _compensate(
            self.latency_model,
            np.asarray(window, np.float32),
            np.asarray(belt, np.float32),
            self._flying(steps),
        )
        return np.asarray(w, np.float64), np.asarray(b, np.float64), steps

    def late(self, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(window (W, 5), belt speeds (2,), actions (D, 4)), float32: the window and belt speeds at the
        newest pose's stamp and the actions sent since, over which `predicted` moves them to `now`; None
        where nothing is predicted."""
        steps = self._steps(now)
        if self.latency_model is None or steps == 0:
            return None
        w = np.asarray(planning.check_window(self.window), np.float32)
        return w, np.asarray(self._belt_speed, np.float32), self._flying(steps)

    def _steps(self, now: float) -> int:
        """Whole control steps from the newest pose's stamp to `now` (0 to `MAX_PREDICTED_STEPS`)."""
        steps = round((now - self._stamp) / self.cfg.gripper.control_dt)
        return min(max(steps, 0), MAX_PREDICTED_STEPS)

    def _flying(self, steps: int) -> np.ndarray:
        """(steps, 4) float32: the last `steps` actions sent (rest before the first)."""
        return np.asarray(([np.zeros(4)] * steps + self._sent)[-steps:], np.float32)

    def _remember(self, action) -> None:
        self._sent = [*self._sent, np.asarray(action, np.float64)][-MAX_PREDICTED_STEPS:]

    def _stop(self) -> tuple[VelocityControl, CarriageCommand | None]:
        self._remember(np.zeros(4))  # rest: the belts ramp to 0, the carriages hold
        if self._p_target is None:
            acc = self.cfg.belt_acceleration
            return VelocityControl(self.cfg.belt_joints, (0.0, 0.0), (acc, acc)), None
        velocity, carriage = stop_commands(self._p_target, self.cfg)
        self._p_target = carriage_targets(carriage, self.cfg)
        return velocity, carriage


__all__ = ["LOOP_STOP_REASONS", "PlanStep", "PlannerStep", "RobotLoop"]
