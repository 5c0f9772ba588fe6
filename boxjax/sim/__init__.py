"""Simulation of the two-belt gripper: one MJCF, two backends behind one Env API."""

from boxjax.sim.core import ACTION_NAMES, ACTION_UNITS, State, check_action
from boxjax.sim.model import box_model, mjcf
from boxjax.sim.native import NativeEnv

BACKENDS = ("native", "mjx")


def make_env(cfg=None, backend: str = "native"):
    """The gripper environment. backend: 'native' (default on CPU) or 'mjx' (jittable, vmappable)."""
    from boxjax.config import DEFAULT

    cfg = DEFAULT if cfg is None else cfg
    if backend == "native":
        return NativeEnv(cfg)
    if backend == "mjx":
        from boxjax.sim.mjx_backend import MjxEnv

        return MjxEnv(cfg)
    raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")


__all__ = [
    "ACTION_NAMES",
    "ACTION_UNITS",
    "BACKENDS",
    "State",
    "check_action",
    "box_model",
    "make_env",
    "mjcf",
]
