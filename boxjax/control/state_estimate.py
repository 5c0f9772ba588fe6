"""The controller's estimate of the box pose from noisy, delayed, sometimes missing observations.

A robot's vision pipeline gives the box pose late (`latency_steps` control steps), with noise, and now and
then not at all (a held frame). The planner's prior takes velocities and the pre-action acceleration from
finite differences of its last three states, so raw noisy poses would turn 3 mm of noise into ~6 cm/s of
velocity noise. `PoseFilter` is the standard answer: a Kalman filter per planar coordinate (x, y, yaw),
run at the time of the measurements, updated when a fresh frame arrives and only predicted when a frame
is held. How it predicts from one frame to the next (`FilterConfig.motion`):

* "constant_velocity" (default, and always during the exploration, whose model is not known yet): a
  constant-velocity filter with white-acceleration process noise (`accel_std`, `yaw_accel_std`);
* "model" (once the controller has a model: after the exploration): the model in the planner's
  slot predicts the pose at the next frame from the estimate's window and the action the gripper applied
  in between (`World.expect`), as a robot's estimator uses its dynamics model (MuJoCo MPC's Kalman filter
  steps the MuJoCo model). The belts' and carriages' commanded motion is known, so between frames only the
  model's one-step error is uncertain (`model_std_mm`, `model_std_deg`), not a white acceleration that
  must allow for every belt command. Measured, it does not pay with the physics prior: its one-step error
  in closed loop (1.4 mm) is not far enough below a 3 mm sensor's, and under a friction mismatch the
  model's bias enters the estimate (docs/results/faults.md#the-filters-motion-model).

Its output, with model compensation, is the state at the newest frame's measurement time, which the
controller predicts forward over the known latency with its model (`planning.compensate`). The carriage
positions P1, P2 come from the drives' encoders and are passed through as received.

`FilterConfig` holds its settings; `measurement_noise(cfg, faults)` gives the noise it assumes when told
the sensor's specification. With a perfect sensor the filter is not used at all (`enabled`): the
controller then sees exactly the state it saw before faults existed.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

from boxjax import geometry
from boxjax.config import ConfigError

_AXES = (geometry.X, geometry.Y, geometry.YAW)
COMPENSATIONS = ("model", "constant_velocity")
MOTIONS = ("model", "constant_velocity")
WINDOWS = ("frames", "state")


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Settings of the pose filter (defaults: told the sensor's specification by the faults)."""

    # Whether the controller filters the pose: None (default) when the sensor is not perfect
    # (noise, latency or drops), True always, False never (the raw observations).
    enabled: bool | None = None
    # Process noise: white acceleration std. The belts accelerate at <= 0.6 m/s^2, which bounds how fast
    # the box's velocity can change while it is carried; the yaw acceleration of a 40 x 30 cm box driven
    # at opposite 0.6 m/s^2 is of order 2 x 0.6 / 0.3 = 4 rad/s^2.
    accel_std: float = 0.6  # m/s^2 (x, y)
    yaw_accel_std: float = 4.0  # rad/s^2
    # Measurement noise std (None: the sensor's specification, `Faults.obs_noise_mm` / `obs_noise_deg`,
    # floored at 0.1 mm and 0.05 degrees).
    noise_mm: float | None = None
    noise_deg: float | None = None
    # The sensor's latency the controller compensates (None: the sensor's specification,
    # `Faults.obs_latency`), and the drives' action latency (None: `Faults.action_latency`).
    latency_steps: int | None = None
    action_latency_steps: int | None = None
    # How: "model" (default) the filter estimates the state at the measurement's time and the controller
    # predicts it forward through the actions applied since with the model in its planner's slot (a
    # Smith predictor: the carriage moves it commanded are known, a constant velocity misses them, by
    # 3.6 mm rms of balance error at one step of latency and 12 mm at four); "constant_velocity" the
    # filter extrapolates its own velocity estimate over the sensor's latency (no model; the exploration
    # always uses it).
    compensation: str = "model"
    # How the filter predicts between frames (module docstring): "constant_velocity" (default) or "model"
    # (constant velocity until the controller has a model; needs model compensation). Measured no better:
    # docs/results/faults.md#the-filters-motion-model.
    motion: str = "constant_velocity"
    # The model's one-step prediction error (std per axis, per control step), the filter's process noise
    # with motion="model": the physics prior on the true box in closed loop errs by 1.41 mm median / 3.05
    # mm p90 in position and 0.19 / 0.68 degrees in yaw one step ahead
    # (benchmarks/results_closed_loop_error.json).
    model_std_mm: float = 1.5
    model_std_deg: float = 0.4
    # The carriages' drag: a carriage moved under the box drags it sideways by a fraction of the travel
    # that nothing in a constant-velocity motion knows (0.19 mean, 0.23 rms, 5-95 % 0.01-0.39 from rest in
    # MuJoCo, benchmarks/results_carriage_drag.json; more under moving belts). Each carriage's travel
    # between frames (its encoder) adds (carriage_drag_std x travel)^2 to the variance of the box's y, so
    # that after a carriage move the filter weighs the frames that show where the box went instead of
    # holding an estimate it averaged at rest. Off (0): the filter without it is already consistent after
    # carriage moves (rms z 0.94 at 10 mm of noise, 0.99 in the realistic row), and at 0.3 it turned 695
    # instead of 708 of 800 boxes over the noisy rows (docs/results/faults.md, "A resume on an estimate
    # that had not caught up").
    carriage_drag_std: float = 0.0
    # The window of states the planner and the monitor predict from (`World.planner_window`): "frames"
    # the filter's estimates at the last frames (their finite differences are the velocities and the
    # acceleration the prior starts from), "state" the straight line through the newest estimate along
    # the filter's velocity (no acceleration: differences of noisy estimates amplify the noise, the
    # filter's velocity does not), or None (default): "state" for a sensor with pose noise, else "frames".
    # Measured (docs/results/faults.md#the-planners-window): 3 mm of noise, 79 -> 90 of 100 turned with
    # the monitor, 83 -> 96 without; 2 steps of latency alone (exact frames), 84 -> 78 with the monitor.
    window: str | None = None

    def __post_init__(self):
        for name in ("accel_std", "yaw_accel_std"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"filter: {name}={v!r} must be a positive number")
        for name in ("model_std_mm", "model_std_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"filter: {name}={v!r} must be a positive number")
        if not (math.isfinite(self.carriage_drag_std) and self.carriage_drag_std >= 0):
            raise ConfigError(f"filter: carriage_drag_std={self.carriage_drag_std!r} must be a number >= 0")
        if self.window is not None and self.window not in WINDOWS:
            raise ConfigError(f"filter: window={self.window!r}; choose one of {WINDOWS}")
        if self.motion not in MOTIONS:
            raise ConfigError(f"filter: motion={self.motion!r}; choose one of {MOTIONS}")
        if self.motion == "model" and self.compensation != "model":
            raise ConfigError(
                "filter: motion='model' runs the filter at the frames' measurement times, which needs "
                "compensation='model'; choose motion='constant_velocity' with constant-velocity compensation"
            )
        for name in ("noise_mm", "noise_deg"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ConfigError(f"filter: {name}={v!r} must be a positive number or None")
        for name in ("latency_steps", "action_latency_steps"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, int) and 0 <= v <= 20):
                raise ConfigError(f"filter: {name}={v!r} must be a whole number in [0, 20] or None")
        if self.compensation not in COMPENSATIONS:
            raise ConfigError(f"filter: compensation={self.compensation!r}; choose one of {COMPENSATIONS}")


class PoseFilter:
    """Kalman filters on (x, y, yaw) of one box (numpy, host-side, per control step).

    step(s_obs (5,), fresh, still, predicted) -> (5,) the estimated present planar state. `fresh` says
    whether s_obs is a new measurement (False: the sensor held its last frame; the filter only predicts);
    `still` that the gripper is known to be at rest (its belts measured still, nothing commanded since the
    measurement): the box's velocity is then zero (a zero-velocity update, as inertial navigation makes
    at standstill), so a stopped box's estimate averages frames instead of chasing their noise.
    `predicted`: (5,) the model's prediction of the state at this frame's measurement time (the module
    docstring's "model" motion), or None: constant velocity.
    """

    def __init__(self, dt: float, noise: tuple[float, float], settings: FilterConfig, latency: int):
        self.dt = dt
        self.latency = latency
        q_xy, q_yaw = settings.accel_std**2, settings.yaw_accel_std**2
        g = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        self.Q = np.stack([q_xy * g, q_xy * g, q_yaw * g])  # (3 axes, 2, 2)
        self.R = np.array([noise[0] ** 2, noise[0] ** 2, noise[1] ** 2])
        mm, rad = 1e-3 * settings.model_std_mm, math.radians(settings.model_std_deg)
        self.q_model = np.array([mm**2, mm**2, rad**2])  # the model's one-step error, per axis
        self.F = np.array([[1.0, dt], [0.0, 1.0]])
        self.drag_var = settings.carriage_drag_std**2
        self.x: np.ndarray | None = None  # (3 axes, 2): position, velocity at measurement time
        self.P: np.ndarray | None = None  # (3, 2, 2)
        self.p_carriages = np.zeros(2)

    def step(self, s_obs, fresh: bool = True, still: bool = False, predicted=None) -> np.ndarray:
        z = np.asarray(s_obs, np.float64)[list(_AXES)]
        carriages = np.asarray(s_obs, np.float64)[[geometry.P1, geometry.P2]]
        travel, self.p_carriages = carriages - self.p_carriages, carriages
        if self.x is None:  # the first frame: at rest where it is seen
            self.x = np.stack([z, np.zeros(3)], axis=1)
            self.P = np.stack([np.diag([r, 0.01]) for r in self.R])
            return self.output()
        if predicted is not None and not still:  # the model's motion: only its one-step error is uncertain
            before = self.x[:, 0].copy()
            self.x[:, 0] = np.asarray(predicted, np.float64)[list(_AXES)]
            self.x[:, 1] = (self.x[:, 0] - before) / self.dt
            self.P[:, 0, 0] += self.q_model
            self.P[:, 0, 1] = self.P[:, 1, 0] = 0.0  # the velocity is the model's, not the filter's state
        else:
            self.x = self.x @ self.F.T
            # at rest nothing moves the box: no process noise, so frames of a box at rest are averaged
            self.P = self.F @ self.P @ self.F.T + (0.0 if still else self.Q)
            # the carriages moved since the last frame (a held frame carries no new travel, the next fresh
            # one all of it): the box's y went along by a fraction of each travel that a constant
            # velocity does not know (the model's motion predicts it)
            self.P[1, 0, 0] += self.drag_var * float(np.sum(np.square(travel)))
        if fresh:
            innov = z - self.x[:, 0]
            innov[2] = (innov[2] + np.pi) % (2 * np.pi) - np.pi  # yaw: the nearest turn
            S = self.P[:, 0, 0] + self.R
            K = self.P[:, :, 0] / S[:, None]  # (3, 2)
            self.x = self.x + K * innov[:, None]
            self.P = self.P - K[:, :, None] * self.P[:, None, 0, :]
        if still:  # a zero-velocity update: the gripper is at rest, so is the box (it rests on the belts)
            self.x[:, 1] = 0.0
            self.P[:, 1, :] = 0.0
            self.P[:, :, 1] = 0.0
        return self.output()

    def std(self, axis: int) -> float:
        """The standard deviation of the present box coordinate `axis` (0: x m, 1: y m, 2: yaw rad;
        `output`): the filter's covariance at the measurement time, carried over the latency (constant
        velocity plus the process noise)."""
        if self.P is None:
            return float(np.sqrt(self.R[axis]))
        tau = self.latency * self.dt
        p = self.P[axis]
        q = self.Q[axis, 1, 1] / self.dt  # white-acceleration intensity (per s^3)
        var = p[0, 0] + 2 * tau * p[0, 1] + tau**2 * p[1, 1] + q * tau**3 / 3
        return float(np.sqrt(max(var, 0.0)))

    def y_std(self) -> float:
        """(m) the standard deviation of the present box y (`std`)."""
        return self.std(1)

    def yaw_std(self) -> float:
        """(rad) the standard deviation of the present box yaw (`std`)."""
        return self.std(2)

    def velocity(self) -> np.ndarray:
        """(3,) the estimated velocity of (x, y, yaw) (m/s, rad/s)."""
        return self.x[:, 1].copy()

    def measured(self) -> np.ndarray:
        """(5,) the state at the newest frame's measurement time (the carriages as measured)."""
        s = np.zeros(5)
        s[[geometry.P1, geometry.P2]] = self.p_carriages
        s[list(_AXES)] = self.x[:, 0]
        return s

    def output(self) -> np.ndarray:
        """(5,) the present state: the carriages as measured, the pose predicted over the latency."""
        ahead = self.x[:, 0] + self.latency * self.dt * self.x[:, 1]
        s = np.zeros(5)
        s[[geometry.P1, geometry.P2]] = self.p_carriages
        s[list(_AXES)] = ahead
        return s


def measurement_noise(settings: FilterConfig, faults) -> tuple[float, float]:
    """(m, rad) the measurement noise std the filter assumes."""
    mm = settings.noise_mm if settings.noise_mm is not None else max(faults.obs_noise_mm, 0.1)
    deg = settings.noise_deg if settings.noise_deg is not None else max(faults.obs_noise_deg, 0.05)
    return 1e-3 * mm, math.radians(deg)


def filtered(settings: FilterConfig, faults) -> bool:
    """Whether the controller filters the pose of this sensor."""
    return faults.observation if settings.enabled is None else settings.enabled


def sensor_latency(settings: FilterConfig, faults) -> int:
    return faults.obs_latency if settings.latency_steps is None else settings.latency_steps


def state_line(window, flt: PoseFilter) -> np.ndarray:
    """(W, 5) float32 `window` (the controller's estimates, newest last) with its pose columns replaced by
    the straight line through the newest estimate along the filter's velocity (the carriages as they are):
    the planner's window with `FilterConfig.window == "state"`."""
    w = np.array(window, np.float32)
    ages = np.arange(len(w) - 1, -1, -1, dtype=np.float64) * flt.dt
    axes = list(_AXES)
    w[:, axes] = w[-1, axes][None].astype(np.float64) - ages[:, None] * flt.velocity()[None]
    return w


def state_window(settings: FilterConfig, faults) -> bool:
    """Whether the planner's window is the filter's state line (`FilterConfig.window`)."""
    if not filtered(settings, faults):
        return False
    if settings.window is None:
        return faults.obs_noise_mm > 0 or faults.obs_noise_deg > 0
    return settings.window == "state"


def model_motion(settings: FilterConfig, faults) -> bool:
    """Whether the controller's filter of this sensor predicts between frames with its model."""
    return filtered(settings, faults) and settings.motion == "model"


def make_filter(settings: FilterConfig, faults, dt: float) -> PoseFilter | None:
    """The controller's pose filter for this sensor, or None when it observes the raw state. With
    model compensation its output is the state at the measurement's time (no extrapolation)."""
    if not filtered(settings, faults):
        return None
    ahead = sensor_latency(settings, faults) if settings.compensation == "constant_velocity" else 0
    return PoseFilter(dt, measurement_noise(settings, faults), settings, ahead)


def model_delay(settings: FilterConfig, faults) -> int:
    """Control steps the controller predicts its estimate forward with its model (`planning.compensate`)
    so that it plans from the state at which its next action applies: the sensor's latency (model
    compensation of a filtered sensor) plus the drives' action latency."""
    model_compensated = filtered(settings, faults) and settings.compensation == "model"
    d = sensor_latency(settings, faults) if model_compensated else 0
    a = faults.action_latency if settings.action_latency_steps is None else settings.action_latency_steps
    return d + a


class RestWatch:
    """Whether the gripper is known at rest: nothing but rest (all zeros) among the last `n` actions sent
    and the belts measured at most `speed` (m/s). The pose filter's zero-velocity update and the safety
    monitor's resume both ask it, each with its own window (`World`, `monitor.Monitor`)."""

    def __init__(self, n: int, speed: float):
        self._sent: deque = deque(maxlen=n)
        self.speed = speed

    def sent(self, action) -> None:
        self._sent.append(np.asarray(action, np.float64))

    def still(self, belt_speed) -> bool:
        rested = len(self._sent) == self._sent.maxlen and not np.any(np.asarray(self._sent))
        return rested and bool(np.all(np.abs(np.asarray(belt_speed)) <= self.speed))
