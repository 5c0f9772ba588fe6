"""Simulation of the two-belt gripper: one MJCF, two backends behind one Env API.

    env = make_env(cfg, backend)          # "native" (MuJoCo, default on a CPU) or "mjx" (JAX)
    state = env.reset(key, dist)          # the box `dist` at rest on the belts
    state = env.step(state, action)       # one 20 Hz control step; the action is checked, bad input raises

Both backends behave the same through this API (the MJX step is compiled once per config and reused).
The MJX env's pure functions (`pure_init`, `pure_step`) are for jit / vmap / scan from outside;
`boxjax.sim.gym` wraps the task as a Gymnasium env.
"""

from boxjax.config import DEFAULT
from boxjax.sim import mjx_backend
from boxjax.sim.core import ACTION_NAMES, ACTION_UNITS, State, check_action
from boxjax.sim.mjx_backend import MjxEnv
from boxjax.sim.model import box_model, mjcf
from boxjax.sim.native import NativeEnv

BACKENDS = ("native", "mjx")


def make_env(cfg=None, backend: str = "native"):
    """The gripper environment. backend: 'native' (default on CPU) or 'mjx' (one env per config, so its
    compiled step is shared by every caller)."""
    cfg = DEFAULT if cfg is None else cfg
    if backend == "native":
        return NativeEnv(cfg)
    if backend == "mjx":
        return mjx_backend.env_for(cfg)
    raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")


__all__ = [
    "ACTION_NAMES",
    "MjxEnv",
    "NativeEnv",
    "ACTION_UNITS",
    "BACKENDS",
    "State",
    "check_action",
    "box_model",
    "make_env",
    "mjcf",
]
