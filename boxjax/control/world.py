"""One episode's world around the controller: the faulty sensor and actuators, the plant mismatch and
the mass shift (`boxjax.sim.faults`), and the controller's pose filter (`state_estimate`).

`World` is built per box and episode from the episode's key, and used the same way by `run_episode` and
the batched `run_episodes`:

    world = World(cfg, faults, ctrl.pose_filter, key, truth)
    world.prepare(model)                 # the simulator's model of this box: friction, servo gains
    s_hat, b_hat = world.observe(s, b)   # after every step (and the reset): what the controller believes
    applied = world.send(action)         # what the gripper applies this step (action latency)
    world.before_step(t, model, body)    # the mass slides at its step

With no faults every call is the identity and no random number is drawn: the episode is the one it was.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from boxjax import massdist
from boxjax.config import Config
from boxjax.control.state_estimate import FilterConfig, make_filter, model_delay
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
        if not self.active:
            self.sensor = self.actuator = self.filter = self.shift = None
            return
        gen = F.rng(key)
        self.shift = F.mass_shift(truth, cfg, faults, gen)
        self.sensor = F.Sensor(faults, gen) if faults.observation else None
        self.actuator = F.Actuator(faults) if faults.action_latency else None
        self.filter = make_filter(pose_filter, faults, cfg.gripper.control_dt)
        self._sent: deque = deque(maxlen=self.delay + 2)  # the actions sent lately (for `_still`)

    def prepare(self, model) -> None:
        """Apply the plant mismatch to this box's native model (in place)."""
        if self.active and self.faults.plant:
            F.world_model(model, self.faults)

    def observe(self, s, belt_speed) -> tuple[np.ndarray, np.ndarray]:
        """The planar state (5,) and belt speeds (2,) the controller works with, from the true ones."""
        if self.sensor is None and self.filter is None:
            return np.asarray(s), np.asarray(belt_speed)
        fresh = True
        if self.sensor is not None:
            s, belt_speed, _, fresh = self.sensor.observe(s, belt_speed)
        self.stale = 0 if fresh else self.stale + 1
        if self.filter is not None:
            s = self.filter.step(s, fresh, self._still(belt_speed))
        return np.asarray(s, np.float32), np.asarray(belt_speed, np.float32)

    def y_std(self) -> float:
        """(m) the standard deviation of the controller's estimate of the box's y: the filter's, the
        sensor's noise when the raw observations are used, 0 with a perfect sensor."""
        if self.filter is not None:
            return self.filter.y_std()
        if self.sensor is not None:
            return 1e-3 * self.faults.obs_noise_mm
        return 0.0

    def _still(self, belt_speed) -> bool:
        """Whether the gripper is known to be at rest: its belts measured still, and nothing but rest sent
        over the delay since the measurement (so the box on them is at rest too)."""
        resting = len(self._sent) == self._sent.maxlen and not np.any(self._sent)
        return bool(resting and np.all(np.abs(np.asarray(belt_speed)) <= STILL_SPEED))

    def send(self, action) -> np.ndarray:
        """The action (4,) the gripper applies this step, for `action` sent now."""
        if self.active:
            self._sent.append(np.asarray(action, np.float64))
        return action if self.actuator is None else self.actuator.send(action)

    def before_step(self, t: int, model, box_body: int) -> bool:
        """Before control step t (0-based): slide the mass if this is its step. True when it slid."""
        if self.shift is not None and not self.shift.done and t >= self.shift.step:
            self.shift.apply(model, box_body)
            return True
        return False
