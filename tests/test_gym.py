"""The Gymnasium environment: gymnasium's own checker, a random-policy episode through gymnasium.make."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from boxjax.config import DEFAULT
from boxjax.sim.gym import ENV_ID, OBS_NAMES, BoxTurnEnv


def test_gymnasium_env_checker_passes():
    env = BoxTurnEnv(DEFAULT, box="A")
    check_env(env, skip_render_check=True)
    env = BoxTurnEnv(DEFAULT)  # random label-safe boxes, drawn from the reset seed
    check_env(env.unwrapped, skip_render_check=True)


def test_random_policy_episode_through_gymnasium_make():
    cfg = DEFAULT.replace(task=DEFAULT.task.__class__(max_steps=60))
    env = gymnasium.make("boxjax.sim.gym:" + ENV_ID, cfg=cfg)
    env.action_space.seed(1)
    obs, info = env.reset(seed=3)
    assert obs.shape == (len(OBS_NAMES),) and env.observation_space.contains(obs)
    assert info["outcome"] == "running" and info["step"] == 0 and not info["hazardous"]
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        total += reward
        steps += 1
        assert env.observation_space.contains(obs) and np.isfinite(reward)
        assert info["max_balance_error_m"] >= info["balance_error_m"] >= 0
        if terminated or truncated:
            break
    assert steps <= 60 and info["step"] == steps
    assert info["outcome"] == ("step_cap" if truncated else info["outcome"]) and info["outcome"] != "running"
    assert truncated == (info["outcome"] == "step_cap")
    env.close()


def test_same_seed_same_episode_and_box_options():
    env = BoxTurnEnv(DEFAULT)
    a = np.array([0.15, -0.15, 0.0, 0.0], np.float32)
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=11)
        runs.append([obs] + [env.step(a)[0] for _ in range(5)])
    assert np.array_equal(np.stack(runs[0]), np.stack(runs[1]))
    obs, info = env.reset(seed=0, options={"box": "D"})
    assert info["hazardous"] and obs[4] == 0.0
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))


def test_render_rgb_array_is_the_top_view():
    env = BoxTurnEnv(DEFAULT, box="uniform", render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.array([0.1, -0.1, 0.0, 0.0], np.float32))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def test_faults_reach_the_agent_as_a_robot_would_see_them_and_replay():
    from boxjax.sim.faults import Faults

    faults = Faults(obs_noise_mm=3.0, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.2, action_latency=1)
    env = BoxTurnEnv(DEFAULT, box="A", faults=faults)
    clean = BoxTurnEnv(DEFAULT, box="A")
    a = np.array([0.15, -0.15, 0.0, 0.0], np.float32)
    runs = []
    for _ in range(2):
        obs, info = env.reset(seed=3)
        rows = [obs]
        for _ in range(12):
            obs, _, _, _, info = env.step(a)
            rows.append(obs)
        runs.append(np.stack(rows))
    np.testing.assert_array_equal(runs[0], runs[1])  # drawn from the reset seed: it replays
    obs0, _ = clean.reset(seed=3)
    assert not np.allclose(runs[0][0][2:5], obs0[2:5], atol=1e-4)  # the pose is noisy
    assert info["obs_age"] >= 2  # late by the latency (or more after a drop)
    # the late action: the first step applies the initial rest, so the belts have not started
    env.reset(seed=3)
    _, _, _, _, info = env.step(a)
    assert abs(env._state.belt_speed[0]) < 1e-3
    from gymnasium.utils.env_checker import check_env

    check_env(BoxTurnEnv(DEFAULT, box="A", faults=faults), skip_render_check=True)
