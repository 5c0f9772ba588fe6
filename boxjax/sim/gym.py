"""A Gymnasium environment for the box-turning task, over the native MuJoCo simulator.

    import gymnasium as gym
    env = gym.make("boxjax.sim.gym:boxjax/BoxTurn-v0")      # imports this module, which registers the id
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

One episode is one box on the belts (`sim.NativeEnv`): the agent sends `(v1, v2, dp1, dp2)` each 0.05 s
control step and must turn the box by pi/2 while its geometric centre stays within the balance limit
(4 cm) of the belts' midline. Everything is in SI units, in the conveyor frame (x along the belts, y
across, z up; docs/design.md#task-rules).

Observation (8,) float32: P1, P2 (m, belt centre-lines), x, y (m, box centre), yaw (rad, continuous), the
two measured belt surface speeds (m/s) and the yaw still to turn, target - yaw (rad); bounds: the
carriage travel, the belts' reach plus the box diagonal, twice the hardware belt speed, +-8 pi rad (values
are clipped to them). The mass distribution is hidden, as it is from the controller.

Action (4,) float32: belt speed setpoints v1, v2 (m/s, |v| <= belt_speed_limit) and carriage steps dp1,
dp2 (m, |dp| <= max_position_step); the simulator clips a carriage target to its range.

Reward per step: the yaw turned towards the target in this step, in units of the whole turn (so an
episode that turns the box sums to about 1), minus 0.01 x (balance error / balance limit)^2; at the end
+1 for a success and -1 for a failure (unbalanced, off the belts, tipped). `terminated` at success or
failure, `truncated` at the step cap (TaskConfig.max_steps).

info: balance_error_m, max_balance_error_m, yaw_error_rad, outcome ("running", "success" or the failure
reason, `task.REASONS`), clipped (the action was beyond a limit), step, hazardous (of the box, for
analysis only).

Faults (`faults=boxjax.sim.faults.Faults(...)`, default none): the agent then observes the pose as a
robot's camera gives it (noise, latency, dropped frames: `info["obs_age"]`, `info["obs_fresh"]`), its
actions apply late (`action_latency`), the belts' friction and servo gains differ from the config's, and
the box's mass may shift; reward and outcome follow the true world. Drawn from the reset's seed, so an
episode replays.

Boxes: `box="safe"` (default) draws a random label-safe mixture box per episode from the reset seed
(`massdist.sample`, hazardous draws rejected); "any" keeps hazardous ones; a name ("A".."D", "uniform"), a
box file path (`boxfile`) or a `MassDistribution` fixes the box. `reset(options={"box": ...})` overrides it
for one episode.
"""

from __future__ import annotations

import math

import gymnasium
import jax
import numpy as np
from gymnasium import spaces

from boxjax import boxfile, massdist, task
from boxjax.config import DEFAULT, HARDWARE, Config
from boxjax.sim import faults as F
from boxjax.sim.episode import EpisodeTrace
from boxjax.sim.native import NativeEnv
from boxjax.viz.animate import frame_rgb

ENV_ID = "boxjax/BoxTurn-v0"
OBS_NAMES = ("P1", "P2", "x", "y", "yaw", "belt1_speed", "belt2_speed", "yaw_to_go")
SUCCESS_BONUS = 1.0
BALANCE_PENALTY = 0.01


def _box_source(box, cfg: Config):
    """A MassDistribution, or the strings "safe" / "any" (drawn per episode)."""
    if isinstance(box, massdist.MassDistribution):
        return massdist.validate(jax.tree.map(np.asarray, box), cfg.box)
    if box in ("safe", "any"):
        return box
    if box in massdist.NAMES:
        return jax.tree.map(np.asarray, massdist.named(box, cfg.box))

    return boxfile.load(box, cfg.box)


class BoxTurnEnv(gymnasium.Env):
    """The two-belt gripper turning one box (module docstring: spaces, reward, info)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self, cfg: Config = DEFAULT, box="safe", render_mode: str | None = None, faults: F.Faults = F.NONE
    ):

        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.cfg = cfg
        self.render_mode = render_mode
        if not isinstance(faults, F.Faults):
            faults = F.Faults.from_dict(dict(faults))
        self.faults = faults
        self._sensor = self._actuator = self._shift = None
        self._seen = None  # (s, belt_speed, age, fresh) the agent observes
        self._box = _box_source(box, cfg)
        self._sim = NativeEnv(cfg)
        g, hw = cfg.gripper, HARDWARE
        act_hi = np.array([g.belt_speed_limit] * 2 + [g.max_position_step] * 2, np.float32)
        self.action_space = spaces.Box(-act_hi, act_hi, dtype=np.float32)
        reach = g.belt_length / 2 + math.hypot(*cfg.box.size[:2])  # the box is off the belts beyond it
        speed = 2 * hw.max_belt_speed  # measured belt speeds stay near their setpoints
        turns = 8 * math.pi  # yaw bound (clipped beyond): four whole turns, far past any real episode
        low = [hw.carriage_travel[0]] * 2 + [-reach, -reach, -turns, -speed, -speed, -turns]
        low = np.array(low, np.float32)
        self.observation_space = spaces.Box(low, -low, dtype=np.float32)
        self._state = None
        self._trace: list = []
        self._dist = None

    def _draw_box(self) -> massdist.MassDistribution:
        if isinstance(self._box, massdist.MassDistribution):
            return self._box
        while True:  # label-safe boxes by rejection (about 4 % of draws are hazardous)
            key = jax.random.PRNGKey(int(self.np_random.integers(2**31 - 1)))
            d = jax.tree.map(np.asarray, massdist.sample(key, self.cfg.box))
            if self._box == "any" or not bool(massdist.is_hazardous(d, self.cfg.box)):
                return d

    def _look(self) -> None:
        st = self._state
        if self._sensor is None:
            self._seen = (np.asarray(st.s, np.float64), np.asarray(st.belt_speed, np.float64), 0, True)
        else:
            self._seen = self._sensor.observe(st.s, st.belt_speed)

    def _obs(self) -> np.ndarray:
        s, belt, _, _ = self._seen
        obs = np.concatenate([s, belt, [float(self._state.target_yaw) - s[4]]])
        return np.clip(obs, self.observation_space.low, self.observation_space.high).astype(np.float32)

    def _info(self) -> dict:
        st = self._state
        return {
            "balance_error_m": float(st.balance_error),
            "max_balance_error_m": float(st.max_balance_error),
            "yaw_error_rad": float(np.asarray(st.s)[4] - float(st.target_yaw)),
            "outcome": task.REASONS[int(st.reason)],
            "clipped": bool(st.clipped),
            "step": int(st.t),
            "hazardous": bool(massdist.is_hazardous(self._dist, self.cfg.box)),
            "obs_age": int(self._seen[2]),  # control steps since the observed frame was taken
            "obs_fresh": bool(self._seen[3]),  # False: a dropped frame, the last one held
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        self._dist = _box_source(options["box"], self.cfg) if "box" in options else self._draw_box()
        if isinstance(self._dist, str):
            self._dist = self._draw_box()
        key = jax.random.PRNGKey(int(self.np_random.integers(2**31 - 1)))  # initial-pose noise, if any
        self._state = self._sim.reset(key, self._dist)
        if self.faults.any:  # this episode's faults, drawn from its key
            gen = F.rng(key)
            self._shift = F.mass_shift(self._dist, self.cfg, self.faults, gen)
            self._sensor = F.Sensor(self.faults, gen) if self.faults.observation else None
            self._actuator = F.Actuator(self.faults) if self.faults.action_latency else None
            if self.faults.plant:
                F.world_model(self._state.model, self.faults)
        self._look()
        self._trace = [self._state]
        return self._obs(), self._info()

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if bool(self._state.done):
            raise RuntimeError("the episode has ended: call reset()")
        a = np.asarray(action, np.float64).reshape(-1)
        if a.shape != (4,):
            raise ValueError(f"action must have shape (4,) = (v1, v2, dp1, dp2), got {np.shape(action)}")
        before = abs(float(self._state.s[4]) - float(self._state.target_yaw))
        if self._shift is not None and not self._shift.done and int(self._state.t) >= self._shift.step:
            self._shift.apply(self._state.model, self._sim.ids.box_body)
        if self._actuator is not None:
            a = self._actuator.send(a)
        self._state = self._sim.step(self._state, a)
        self._look()
        self._trace.append(self._state)
        st = self._state
        after = abs(float(st.s[4]) - float(st.target_yaw))
        turn = abs(self.cfg.task.target_yaw_delta)
        balance = float(st.balance_error) / self.cfg.task.balance_limit
        reward = (before - after) / turn - BALANCE_PENALTY * balance**2
        reason = int(st.reason)
        truncated = reason == task.STEP_CAP
        terminated = reason not in (task.RUNNING, task.STEP_CAP)
        if reason == task.SUCCESS:
            reward += SUCCESS_BONUS
        elif terminated:
            reward -= SUCCESS_BONUS
        return self._obs(), float(reward), terminated, truncated, self._info()

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None

        trace = EpisodeTrace.from_states(self._trace, [], self.cfg.gripper.control_dt, 0.0)
        return frame_rgb(trace, self.cfg, self._dist)

    def close(self):
        self._state = None


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="boxjax.sim.gym:BoxTurnEnv")
