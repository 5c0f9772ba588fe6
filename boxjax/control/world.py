"""One episode's world around the controller: the faulty sensor and actuators, the plant mismatch and
the mass shift (`boxjax.sim.faults`), and the controller's pose filter (`state_estimate`).

`World` is built per box and episode from the episode's key, and used the same way by `run_episode` and
the batched `run_episodes`:

    world = World(cfg, faults, ctrl.pose_filter, key, truth)
    world.prepare(model)                 # the simulator's model of this box: friction, servo gains
    s_hat, b_hat = world.observe(s, b)   # after every step (and the reset): what the controller believes
    if world.model_motion:               # the model's prediction of the next frame, for the filter
        world.expect(model.rollout_sequence(window, b_hat, world.applied_next(sent)[None])[0])
    applied = world.send(action)         # what the gripper applies this step (action latency)
    world.before_step(t, model, body)    # the mass slides at its step

With no faults every call is the identity and no random number is drawn: the episode is the one it was.
"""

from __future__ import annotations

import math

import numpy as np

from boxjax import massdist
from boxjax.config import Config
from boxjax.control.state_estimate import (
    FilterConfig,
    RestWatch,
    make_filter,
    model_delay,
    model_motion,
    sensor_latency,
    state_line,
    state_window,
)
from boxjax.estimator import explore
from boxjax.sim import faults as F

STILL_SPEED = 0.005  # m/s: measured belt speeds under this, with rest commanded, are a gripper at rest


class World:
    def __init__(
        self,
        cfg: Config,
        faults: F.Faults,
        pose_filter: FilterConfig,
        key,
        truth: massdist.MassDistribution,
    ):
        self.faults = faults
        self.active = faults.any
        self.stale = 0  # steps since the last fresh frame
        # control steps between the newest estimate and the application of the next action, which the
        # controller bridges with its model (`planning.compensate`)
        self.delay = model_delay(pose_filter, faults)
        # control steps from an action sent to the frame that shows its effect, as the controller knows
        # them (its sensor's latency and the drives'): how long the exploration waits for its last frames
        # (`explore.Guarded(settle=...)`) and how its record is aligned for the estimator (`for_estimator`)
        acting = pose_filter.action_latency_steps
        self.exploration_delay = (
            sensor_latency(pose_filter, faults) * faults.observation
            + (faults.action_latency if acting is None else acting)
            if self.active
            else 0
        )
        # per observation: the pose at its frame's measurement time (the filter's, or the raw frame's), the
        # belt speeds and whether the frame was fresh: what the estimator is given (`for_estimator`)
        self.frames: list[tuple[np.ndarray, np.ndarray, bool]] = []
        # the filter predicts between frames with the controller's model (`FilterConfig.motion`)
        self.model_motion = self.active and model_motion(pose_filter, faults)
        self._expected = None  # the model's prediction of the next frame (`expect`)
        self.state_window = self.active and state_window(pose_filter, faults)
        # the sensor's specification as the controller states it (pose noise std in mm, the filter's if
        # set, and the share of dropped frames): the learned estimator chooses its H by it
        stated_mm = faults.obs_noise_mm if pose_filter.noise_mm is None else pose_filter.noise_mm
        self.sensor_spec = {"obs_noise_mm": float(stated_mm), "drop_rate": float(faults.drop_rate)}
        self.stated_noise_m = float(stated_mm) / 1000  # the exploration guard's allowance (`explore.Guarded`)
        if not self.active:
            self.sensor = self.actuator = self.filter = self.shift = None
            return
        gen = F.rng(key)
        self.shift = F.mass_shift(truth, cfg, faults, gen)
        self.sensor = F.Sensor(faults, gen) if faults.observation else None
        self.actuator = F.Actuator(faults) if faults.action_latency else None
        self.filter = make_filter(pose_filter, faults, cfg.gripper.control_dt)
        self.rest = RestWatch(self.delay + 2, STILL_SPEED)  # for the filter's zero-velocity update

    def prepare(self, model) -> None:
        """Apply the plant mismatch to this box's native model (in place)."""
        if self.active and self.faults.plant:
            F.world_model(model, self.faults)

    def observe(self, s, belt_speed) -> tuple[np.ndarray, np.ndarray]:
        """The planar state (5,) and belt speeds (2,) the controller works with, from the true ones."""
        if self.sensor is None and self.filter is None:
            if self.exploration_delay:  # action latency alone: the true state, as it is when it arrives
                self.frames.append((np.asarray(s, np.float32), np.asarray(belt_speed, np.float32), True))
            return np.asarray(s), np.asarray(belt_speed)
        fresh = True
        if self.sensor is not None:
            s, belt_speed, _, fresh = self.sensor.observe(s, belt_speed)
        self.stale = 0 if fresh else self.stale + 1
        measured = s
        if self.filter is not None:
            s = self.filter.step(s, fresh, self.rest.still(belt_speed), self._expected)
            self._expected = None
            measured = self.filter.measured()
        self.frames.append((np.asarray(measured, np.float32), np.asarray(belt_speed, np.float32), fresh))
        return np.asarray(s, np.float32), np.asarray(belt_speed, np.float32)

    def planner_window(self, window) -> np.ndarray:
        """(W, 5) float32 the window the planner and the monitor predict from, given the window of the
        controller's estimates (the newest last): as it is, or with `FilterConfig.window == "state"` its
        pose columns replaced by the straight line through the newest estimate along the filter's
        velocity (the carriages as measured)."""
        if self.filter is None or not self.state_window:
            return np.array(window, np.float32)
        return state_line(window, self.filter)

    def applied_next(self, sent) -> np.ndarray:
        """(4,) the action that moves the box from the newest frame's measurement time to the next frame's:
        the one the gripper applies at that time, sent `delay` steps before it (`sent`: the actions sent so
        far, the one just decided included; zeros before the first)."""
        k = self.delay + 1
        return np.asarray(sent[-k], np.float32) if len(sent) >= k else np.zeros(4, np.float32)

    def expect(self, predicted) -> None:
        """The model's prediction (5,) of the state at the next frame's measurement time, from the
        estimate's window and `applied_next`: the filter's prediction for that frame (`model_motion`)."""
        self._expected = np.asarray(predicted, np.float64)

    def for_estimator(self, data: dict, n_steps: int) -> dict:
        """The exploration as the estimator takes it, from the controller's record `data` (states and belt
        speeds seen, actions sent, `episode._controller_data`) of the fixed sequence's `n_steps` and the
        rest sent after it, with "sensor" the sensor's specification as the controller states it
        (`sensor_spec`: the learned estimator chooses its H by it): the poses at their measurement
        times, a dropped frame (held: its pose, the carriages and belt speeds stale) replaced by the
        straight line between the fresh frames around it (the record is complete by now, so the estimator
        need not see a stale frame), aligned with the actions that led to them (`explore.align`; a step
        cap that cut the rest short: aligned by the frames that arrived). With a perfect sensor and no
        action latency: `data` itself."""
        if not self.frames:
            return data
        frames = {
            "s": held_frames_interpolated([s for s, _, _ in self.frames], [f for *_, f in self.frames]),
            "belt_speed": held_frames_interpolated(
                [b for _, b, _ in self.frames], [f for *_, f in self.frames]
            ),
            "actions": data["actions"],
        }
        # a step cap that cut the rest short leaves fewer frames: align by what arrived
        delay = min(self.exploration_delay, len(frames["s"]) - 1 - n_steps)
        return {**explore.align(frames, max(delay, 0), n_steps), "sensor": self.sensor_spec}

    def y_std(self) -> float:
        """(m) the standard deviation of the controller's estimate of the box's y: the filter's, the
        sensor's noise when the raw observations are used, 0 with a perfect sensor."""
        if self.filter is not None:
            return self.filter.y_std()
        if self.sensor is not None:
            return 1e-3 * self.faults.obs_noise_mm
        return 0.0

    def yaw_std(self) -> float:
        """(rad) the standard deviation of the controller's estimate of the box's yaw, as `y_std`."""
        if self.filter is not None:
            return self.filter.yaw_std()
        if self.sensor is not None:
            return math.radians(self.faults.obs_noise_deg)
        return 0.0

    def send(self, action) -> np.ndarray:
        """The action (4,) the gripper applies this step, for `action` sent now."""
        if self.active:
            self.rest.sent(action)
        return action if self.actuator is None else self.actuator.send(action)

    def before_step(self, t: int, model, box_body: int) -> bool:
        """Before control step t (0-based): slide the mass if this is its step. True when it slid."""
        if self.shift is not None and not self.shift.done and t >= self.shift.step:
            self.shift.apply(model, box_body)
            return True
        return False


def held_frames_interpolated(values, fresh) -> np.ndarray:
    """(K, n) the frames `values` (K of (n,)) with each held one (`fresh` False) replaced by the linear
    interpolation, per component, between the fresh frames before and after it (held at the ends: the
    nearest fresh frame). Yaw is interpolated as it is (frames 0.05 s apart do not wrap)."""
    v = np.asarray(values, np.float64)
    ok = np.asarray(fresh, bool)
    if ok.all() or not ok.any():
        return v.astype(np.float32)
    k, idx = np.arange(len(v)), np.flatnonzero(ok)
    out = np.stack([np.interp(k, idx, v[idx, j]) for j in range(v.shape[1])], axis=1)
    return out.astype(np.float32)
