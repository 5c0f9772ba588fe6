"""How much an MJX world's trajectory depends on the program it is stepped in: the same box, key and
actions (the exploration's first `--steps` steps) stepped by the one-world jitted step (`MjxEnv.step`), by
a vmapped step of width 1, by a vmapped step of width 2 beside another box, and by native MuJoCo. The
largest planar differences from the one-world step over the steps, per box. Why an evaluation of the
on-device loop cannot be replayed (`boxjax.experiments.evaluation.NO_MJX_REPLAY`).

Prints ONE JSON object (the last line).
Run: python benchmarks/mjx_sensitivity.py [--steps 10] [--boxes A uniform C] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit_to, machine  # noqa: E402

from boxjax import massdist  # noqa: E402
from boxjax.config import DEFAULT as cfg  # noqa: E402
from boxjax.estimator import explore  # noqa: E402
from boxjax.sim.mjx_backend import env_for, stack  # noqa: E402
from boxjax.sim.native import NativeEnv  # noqa: E402


def _vmapped(env, dists, key, actions) -> np.ndarray:
    """(T+1, 5) planar states of world 0 of a vmapped step over `dists`, each stepped with `actions`."""
    params = stack([env.box_params(d) for d in dists])
    states = jax.vmap(env.pure_init)(params, jnp.stack([key] * len(dists)))
    step = jax.jit(jax.vmap(env.pure_step))
    out = [np.asarray(states.s[0])]
    for a in actions:
        states = step(states, jnp.asarray(np.stack([a] * len(dists)), jnp.float32))
        out.append(np.asarray(states.s[0]))
    return np.stack(out)


def _single(env, dist, key, actions) -> np.ndarray:
    st = env.reset(key, dist)
    out = [np.asarray(st.s)]
    for a in actions:
        st = env.step(st, a)
        out.append(np.asarray(st.s))
    return np.stack(out)


def _diff(a, b) -> dict:
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    return {"x_mm": 1e3 * d[:, 2].max(), "y_mm": 1e3 * d[:, 3].max(), "yaw_deg": np.degrees(d[:, 4].max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--boxes", nargs="+", default=["A", "uniform", "C"])
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if not 1 <= args.steps <= explore.N_STEPS:
        ap.error(f"--steps must be in [1, {explore.N_STEPS}]")
    env = env_for(cfg)
    actions = explore.exploration_actions(cfg)[: args.steps]
    key = jax.random.PRNGKey(2)
    other = massdist.named("B", cfg.box)
    rows = {}
    for name in args.boxes:
        d = massdist.named(name, cfg.box)
        one = _single(env, d, key, actions)
        native = _single(NativeEnv(cfg), d, key, actions)
        rows[name] = {
            "vmapped_width_1": _diff(one, _vmapped(env, [d], key, actions)),
            "vmapped_width_2": _diff(one, _vmapped(env, [d, other], key, actions)),
            "native": _diff(one, native),
        }
    emit_to({"benchmark": "mjx_sensitivity", "steps": args.steps, **machine(), "boxes": rows}, args.out)


if __name__ == "__main__":
    main()
