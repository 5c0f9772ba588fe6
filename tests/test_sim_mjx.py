"""The MJX backend: per-world boxes in one batch, agreement with native MuJoCo, sharding over devices.

MJX compiles slowly on CPU (tens of seconds per shape), so these tests share a few compiled shapes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.sim.mjx_backend import rollout as mjx_rollout
from boxjax.sim.native import rollout as native_rollout

CFG = DEFAULT
T = 40  # control steps = 2 s
ACTIONS = np.tile([0.15, -0.15, 0.0, 0.0], (T, 1))


# slow: different boxes in one MJX batch, sharded, run in the default suite's on-device loop
# (tests/test_device_loop.py), which paid for its place with these two
@pytest.mark.slow
def test_batch_of_different_boxes():
    """Each world simulates its own box: swapping the boxes in the batch swaps the trajectories."""
    a, u = massdist.named("A", CFG.box), massdist.named("uniform", CFG.box)
    out1 = mjx_rollout(CFG, [a, u], ACTIONS[:10])
    out2 = mjx_rollout(CFG, [u, a], ACTIONS[:10])
    np.testing.assert_allclose(out1["s"][0], out2["s"][1], atol=1e-6)
    np.testing.assert_allclose(out1["s"][1], out2["s"][0], atol=1e-6)
    assert np.abs(out1["s"][0, -1] - out1["s"][1, -1]).max() > 1e-3  # the mass distribution matters
    assert out1["s"].shape == (2, 11, 5) and out1["s1"].shape == (2, 11, *CFG.box.grid[:2])


# Named tolerances of the backend agreement (issue: 1 mm and 0.5 degrees over >= 2 s).
POS_TOL_M = 1e-3
YAW_TOL_DEG = 0.5


def test_mjx_agrees_with_native_while_box_rides_the_belts():
    """Same boxes, same actions for 2 s (belts ramp to 0.15 m/s together, then a sideways carriage
    move): the planar poses agree between the backends.

    While the box slips in rotation the dynamics are chaotic (native MuJoCo disagrees with itself by
    centimetres for a 1e-7 m change of the start pose, README "Backend agreement"), so the rotation
    agreement is reported by the slow test below rather than asserted.
    """
    names = ("uniform", "A", "C")
    dists = [massdist.named(n, CFG.box) for n in names]
    acts = np.zeros((T, 4))
    acts[:, :2] = 0.15
    acts[25:30, 2:] = 0.005  # both carriages step sideways together
    n = native_rollout(CFG, dists, acts)
    m = mjx_rollout(CFG, dists, acts)
    for i, name in enumerate(names):
        pos = np.hypot(*(n["s"][i, :, 2:4] - m["s"][i, :, 2:4]).T).max()
        yaw = np.degrees(np.abs(n["s"][i, :, 4] - m["s"][i, :, 4]).max())
        print(f"native vs MJX over 2 s, {name}: {pos * 1e3:.3f} mm, {yaw:.3f} deg")
        assert pos < POS_TOL_M and yaw < YAW_TOL_DEG, (name, pos, yaw)
        np.testing.assert_allclose(n["s"][i, :, :2], m["s"][i, :, :2], atol=POS_TOL_M)  # belt positions
    assert n["s"][0, -1, 2] > 0.2  # the box really travelled with the belts


@pytest.mark.slow
def test_sharded_rollout_over_four_cpu_devices():
    """With 4 (forced host) devices the batch is split over all of them and gives the same result."""
    code = textwrap.dedent(
        """
        import json, numpy as np, jax
        from boxjax import massdist
        from boxjax.config import DEFAULT
        from boxjax.sim import mjx_backend
        assert jax.device_count() == 4, jax.devices()
        dists = [massdist.named(n) for n in ("A", "B", "C", "uniform")]
        acts = np.tile([0.15, -0.15, 0.0, -0.002], (5, 1))
        sh = mjx_backend.batch_sharding(4)
        assert sh is not None and len(sh.device_set) == 4
        out = mjx_backend.rollout(DEFAULT, dists, acts)
        print(json.dumps({"s": out["s"].tolist()}))
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    import json

    s = np.asarray(json.loads(res.stdout.strip().splitlines()[-1])["s"])
    assert s.shape == (4, 6, 5) and np.isfinite(s).all()
    # the four boxes differ, so the worlds really are different
    assert np.abs(s[0, -1] - s[3, -1]).max() > 1e-4


@pytest.mark.slow
def test_mjx_agreement_report_all_named():
    """Agreement of the backends on every named distribution (slow; prints a table)."""
    names = ("uniform", "A", "B", "C", "D")
    dists = [massdist.named(n, CFG.box) for n in names]
    n = native_rollout(CFG, dists, ACTIONS)
    m = mjx_rollout(CFG, dists, ACTIONS)
    for i, name in enumerate(names):
        pos = np.hypot(*(n["s"][i, :, 2:4] - m["s"][i, :, 2:4]).T).max()
        yaw = np.degrees(np.abs(n["s"][i, :, 4] - m["s"][i, :, 4]).max())
        print(f"{name:>8}: {pos * 1e3:8.3f} mm {yaw:7.3f} deg")


def _mappings() -> int:
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="counts the process's memory mappings")
def test_the_mjx_env_stepped_one_call_at_a_time_compiles_once():
    """The Env API as the README shows it, on MJX: `env.step` in a Python loop compiles on the first call
    and reuses that program (a step that re-traced per call took 8-13 s and, after ~30 steps, exhausted
    the process's memory mappings with compiled code)."""
    import time

    import jax

    from boxjax.sim import make_env

    env = make_env(CFG, backend="mjx")
    assert make_env(CFG, backend="mjx") is env  # one env per config: its compiled step is shared
    state = env.reset(jax.random.PRNGKey(0), massdist.named("A", CFG.box))
    action = [0.15, -0.15, 0.0, 0.0]
    for _ in range(3):  # the first call compiles
        state = env.step(state, action)
    maps, times = _mappings(), []
    for _ in range(47):
        t0 = time.perf_counter()
        state = env.step(state, action)
        jax.block_until_ready(state.s)
        times.append(time.perf_counter() - t0)
    assert int(state.t) == 50 and np.isfinite(np.asarray(state.s)).all()
    assert max(times) < 1.0, f"a later step took {max(times):.2f} s: it compiled again"
    assert env._step_jit._cache_size() == 1
    assert _mappings() - maps < 50, "compiled code keeps growing with every step"
    with pytest.raises(ValueError):
        env.step(state, [0.1, np.nan, 0.0, 0.0])
