"""W's training episodes on the device (`training.baseline_device`, `train-baseline --backend mjx`): the
perturbed kinds' on-device rules draw from the same distributions as the host's (`training.baseline`), state
by state, and (slow) an MJX collection gives every kind's episodes in the host's form."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT as cfg
from boxjax.estimator import explore
from boxjax.training import baseline as host
from boxjax.training import baseline_device as device
from boxjax.training import baseline_rules as rules

N = 20000
G = cfg.gripper

# (s = (P1, P2, x, y, yaw), belt speeds, target, steps left): a held target; a renewal at the centre; a
# renewal far out on +x (a translation heads back); a held target driving further out (renewed); a balance
# error past the correction threshold
STATES = {
    "held": ([-0.1, 0.1, 0.02, 0.0, 0.3], [0.05, -0.04], [0.15, -0.15], 5),
    "renew_centre": ([-0.1, 0.1, 0.0, 0.0, 0.0], [0.0, 0.0], [0.0, 0.0], 0),
    "renew_far": ([-0.1, 0.1, 0.08, 0.0, 0.0], [0.1, 0.1], [0.1, 0.1], 0),
    "turn_back": ([-0.1, 0.1, 0.13, 0.0, 0.0], [0.1, 0.1], [0.1, 0.1], 12),
    "unbalanced": ([-0.1, 0.1, 0.0, 0.02, 0.0], [0.0, 0.0], [0.05, -0.05], 8),
}


def _host_draws(s, b, target, left):
    rng = np.random.default_rng(0)
    out = [
        host.random_drive(cfg, rng, np.asarray(target), left, np.asarray(s), np.asarray(b)) for _ in range(N)
    ]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out]), np.array([o[2] for o in out])


@jax.jit
def _device_draws(s, b, target, left):
    keys = jax.random.split(jax.random.PRNGKey(1), N)
    drive = device.Drive(jnp.asarray(target, jnp.float32), jnp.asarray(left, jnp.int32))
    a, d = jax.vmap(lambda k: device.random_action(cfg, k, drive, s, b))(keys)
    return a, d.target, d.left


def _same_distribution(x, y, name):
    """Each component of the N draws x and y passes a two-sample Kolmogorov-Smirnov test at the 0.1 %
    level (the largest gap between the empirical distribution functions below 1.95 sqrt(2 / N)); values
    within 1e-6 count as equal (the device computes in float32, the host in float64: an atom of the
    distribution, such as a speed at the acceleration limit, lands an ulp apart)."""
    for c in range(x.shape[1]):
        grid = np.sort(np.concatenate([x[:, c], y[:, c]])) + 1e-6
        fx = np.searchsorted(np.sort(x[:, c]), grid, side="right") / N
        fy = np.searchsorted(np.sort(y[:, c]), grid, side="right") / N
        gap = np.max(np.abs(fx - fy))
        assert gap < 1.95 * np.sqrt(2 / N), (name, c, gap)


def _device(fn, *args):
    return np.asarray(jax.vmap(fn)(jax.random.split(jax.random.PRNGKey(1), N), *args), np.float64)


@pytest.mark.parametrize("name", list(STATES))
def test_the_random_drive_draws_as_the_host_does(name):
    s, b, target, left = STATES[name]
    ah, th, lh = _host_draws(s, b, target, left)
    ad, td, ld = (
        np.asarray(v, np.float64) for v in _device_draws(jnp.asarray(s), jnp.asarray(b), target, left)
    )
    _same_distribution(ah, ad, f"{name}: action")
    _same_distribution(th, td, f"{name}: target")
    _same_distribution(lh[:, None], ld[:, None], f"{name}: steps left")


def test_the_random_drives_rules_on_the_device():
    s, b, target, left = STATES["unbalanced"]
    a, _, _ = (np.asarray(v) for v in _device_draws(jnp.asarray(s), jnp.asarray(b), target, left))
    dv = G.belt_accel_limit * G.control_dt
    # the held target approached at the acceleration limit, unless the action is a uniformly random one
    # (which hits these speeds with probability 0)
    approach = np.asarray(b) + np.clip(np.asarray(target) - np.asarray(b), -dv, dv)
    driven = np.all(np.abs(a[:, :2] - approach) < 1e-6, axis=1)
    assert abs(driven.mean() - (1 - rules.P_RANDOM_DRIVE)) < 3 * np.sqrt(0.25 * 0.75 / N)
    # a balance error of +2 cm: exactly one carriage steps, towards +y, between STEP_MIN and the hardware's
    steps = a[driven, 2:]
    assert np.all(np.sum(steps != 0, axis=1) == 1)
    moved = steps[steps != 0]
    assert np.all((moved >= rules.STEP_MIN - 1e-7) & (moved <= G.max_position_step + 1e-7))
    assert abs(np.mean(steps[:, 0] != 0) - 0.5) < 3 * np.sqrt(0.25 / driven.sum())  # either carriage


@pytest.mark.parametrize("planned", [[0.05, -0.05, 0.002, -0.001], [0.24, -0.2, 0.0095, 0.0]])
def test_the_noisy_action_draws_as_the_host_does(planned):
    cap = G.belt_speed_limit
    scales = device.noise_scales(cfg, jax.random.PRNGKey(4))
    sv, sp = float(scales[0]), float(scales[2])
    assert float(scales[1]) == sv and float(scales[3]) == sp
    assert rules.NOISE_SPEED[0] <= sv <= rules.NOISE_SPEED[1]
    assert rules.NOISE_POSITION[0] <= sp <= rules.NOISE_POSITION[1]
    p = jnp.asarray(planned, jnp.float32)
    ad = _device(lambda k: device.noisy_action(cfg, k, p, scales, cap))
    rng = np.random.default_rng(0)
    ah = np.stack(
        [host.perturb(cfg, rng, np.asarray(planned), np.asarray(scales, np.float64), cap) for _ in range(N)]
    )
    hi = np.array([cap, cap, G.max_position_step, G.max_position_step])
    assert np.all(np.abs(ad) <= hi + 1e-7)
    _same_distribution(ah, ad, f"noisy {planned}")


def test_noise_scales_cover_their_ranges():
    sc = _device(lambda k: device.noise_scales(cfg, k))
    for c, (lo, hi) in ((0, rules.NOISE_SPEED), (2, rules.NOISE_POSITION)):
        assert lo <= sc[:, c].min() < lo + 0.01 * (hi - lo) and hi - 0.01 * (hi - lo) < sc[:, c].max() <= hi


@pytest.mark.slow
def test_mjx_collection_gives_every_kind_in_the_hosts_form():
    small = cfg.replace(task=dataclasses.replace(cfg.task, max_steps=60))
    truth = massdist.named("A", small.box)
    eps = host.collect(small, truth, 5, seed=0, progress=False, backend="mjx")
    assert [e["kind"] for e in eps] == list(rules.KINDS)
    assert [e["explore"] for e in eps] == [True, False, False, False, False]
    for e in eps:
        T = e["actions"].shape[0]
        assert e["s"].shape == (T + 1, 5) and e["belt_speed"].shape == (T + 1, 2)
        assert 0 < T <= 60 and np.all(np.isfinite(e["s"]))
        assert e["outcome"] in host.OUTCOMES
    # the prior kind with the exploration begins with the fixed sequence
    np.testing.assert_allclose(
        eps[0]["actions"][: explore.N_STEPS], explore.exploration_actions(small), atol=1e-6
    )
    tr = host.transitions_of(eps)
    assert tr["action"].shape[0] == sum(e["actions"].shape[0] for e in eps)
    with pytest.raises(ValueError, match="unknown backend"):
        host.collect(small, truth, 2, backend="gpu")
