"""Domain randomisation of the estimator's training data: each exploration as a faulty sensor shows it.

H is trained on exploration trajectories (`boxjax.training.dataset`). Recorded from the simulator's own
state they are exact, and an H trained on them reads force-gauge features at the 0.1 mm level (the
carriage lag, `estimator.training`), so a real sensor's 3 mm of pose noise or a dropped frame moves its
estimate anywhere: on 100 safe + 100 hazardous boxes, 3 mm / 1.5 degrees of noise made the shipped H refuse
98 of the safe boxes, 5 % dropped frames 28 even with the dropped frames bridged
(scripts/estimator_randomisation.py, docs/results/faults.md).

`sensor_view(data, cfg, settings, seed)` replaces every box's trajectory by what the controller's
estimator would be given through a sensor drawn for that box (`SensorRandomisation`: with probability
`p_perfect` a perfect one, otherwise a pose noise and a drop rate drawn uniformly from their ranges):
the SAME path as at run time, `control.world.World` (the sensor, the pose filter told the sensor's
specification) and `World.for_estimator` (the poses at their measurement times, dropped frames bridged).
The sensor's latency is not randomised: `for_estimator` aligns the frames with the actions, so a
latency changes nothing H sees. The plant (friction, servo gains) is not randomised here: that needs new
simulations, and friction mismatch does not hurt H's hazard decision (docs/results/faults.md).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from boxjax.config import Config
from boxjax.control.state_estimate import FilterConfig
from boxjax.control.world import World
from boxjax.estimator import explore
from boxjax.sim.faults import Faults


@dataclasses.dataclass(frozen=True)
class SensorRandomisation:
    """The distribution of sensors the training explorations are seen through."""

    p_perfect: float = 0.25  # share of boxes seen exactly (H stays sharp with a good sensor)
    noise_mm: tuple[float, float] = (0.0, 5.0)  # pose position noise std, uniform in this range
    deg_per_mm: float = 0.5  # yaw noise std per mm of position noise (the fault table's 1 / 0.5, 3 / 1.5 ...)
    drop_rate: tuple[float, float] = (0.0, 0.2)  # share of frames dropped, uniform in this range

    def __post_init__(self):
        if not 0 <= self.p_perfect <= 1:
            raise ValueError(f"p_perfect must be in [0, 1], got {self.p_perfect}")
        for name in ("noise_mm", "drop_rate"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must be a range 0 <= low <= high, got {(lo, hi)}")
        if self.drop_rate[1] >= 1 or self.deg_per_mm < 0:
            raise ValueError("drop_rate must stay below 1 and deg_per_mm >= 0")

    def draw(self, gen: np.random.Generator) -> Faults:
        perfect = gen.random() < self.p_perfect
        mm = float(gen.uniform(*self.noise_mm))
        drop = float(gen.uniform(*self.drop_rate))
        if perfect:
            return Faults()
        return Faults(obs_noise_mm=mm, obs_noise_deg=self.deg_per_mm * mm, drop_rate=drop)


def seen_exploration(cfg: Config, traj, final, faults: Faults, key) -> tuple[np.ndarray, np.ndarray]:
    """One box's exploration (traj (T, 11), final (5,), as recorded from the simulator) as the estimator
    is given it through `faults`' sensor, the episode's `key` drawing the sensor's noise: (traj, final)."""
    traj, final = np.asarray(traj, np.float64), np.asarray(final, np.float64)
    if not faults.observation:
        return traj.astype(np.float32), final.astype(np.float32)
    n = len(traj)
    states = np.concatenate([traj[:, :5], final[None]])
    belts = np.concatenate([np.zeros((1, 2)), traj[:, 9:11]])  # at rest at the reset
    actions = traj[:, 5:9]
    world = World(cfg, faults, FilterConfig(), key, truth=None)
    seen = [world.observe(states[0], belts[0])]
    for t in range(n):
        world.send(actions[t])
        seen.append(world.observe(states[t + 1], belts[t + 1]))
    record = {
        "s": np.stack([s for s, _ in seen]),
        "belt_speed": np.stack([b for _, b in seen]),
        "actions": actions,
    }
    view = world.for_estimator(record, n)
    out, last = explore.trajectory(view["s"], view["belt_speed"], actions)
    return np.asarray(out, np.float32), np.asarray(last, np.float32)


def sensor_view(data: dict, cfg: Config, settings: SensorRandomisation, seed: int) -> dict:
    """The dataset `data` (`boxjax.training.dataset` arrays) with every box's traj and final replaced by
    `seen_exploration` through a sensor drawn from `settings` (box b's draws from seed and b: the same
    seed gives the same view). Adds obs_noise_mm (B,) and drop_rate (B,), the sensors drawn."""
    gen = np.random.default_rng(seed)
    base = jax.random.PRNGKey(seed)
    traj, final = np.array(data["traj"]), np.array(data["final"])
    noise, drops = np.zeros(len(traj), np.float32), np.zeros(len(traj), np.float32)
    for b in range(len(traj)):
        faults = settings.draw(gen)
        noise[b], drops[b] = faults.obs_noise_mm, faults.drop_rate
        traj[b], final[b] = seen_exploration(cfg, traj[b], final[b], faults, jax.random.fold_in(base, b))
    return {**data, "traj": traj, "final": final, "obs_noise_mm": noise, "drop_rate": drops}
