"""boxjax: safe, data-efficient box manipulation on a two-belt conveyor gripper.

MuJoCo / MJX simulation of the gripper, voxel mass distributions, and model-predictive control with
physics priors (Salehi & Doncieux, "Data-efficient, Explainable and Safe Box Manipulation", L4DC 2024).

The names a user needs are here; all but the config are imported on first use (importing boxjax does not
start JAX):

    from boxjax import DEFAULT, make_env, ControllerConfig, run_episode, learned_estimator, massdist

The package's folders are its layers, each importing only from those before it (tests/test_layers.py):
the shared modules at the top (config, fileio, geometry, mlp, planning, massdist, task, boxfile,
config_io, run_info), then viz, sim, prior, blackbox, estimator, planners, control, training,
experiments, cli.
"""

import importlib

from boxjax.config import DEFAULT, BoxConfig, Config, ConfigError, GripperConfig, TaskConfig

__version__ = "0.1.0"

# name -> the module that defines it (imported on first access)
_LAZY = {
    "make_env": "boxjax.sim",
    "ControllerConfig": "boxjax.control.config",
    "run_episode": "boxjax.control.episode",
    "run_episodes": "boxjax.control.batch",
    "learned_estimator": "boxjax.estimator.belief",
    "oracle_estimator": "boxjax.estimator.belief",
    "evaluate": "boxjax.experiments.evaluation",
    "compare": "boxjax.experiments.comparison",
    "load_box": "boxjax.boxfile",
}
_LAZY_MODULES = (
    "blackbox", "boxfile", "cli", "config_io", "control", "estimator", "experiments", "geometry", "massdist",
    "planners", "planning", "prior", "sim", "task", "training", "viz",
)  # fmt: skip

__all__ = [
    "DEFAULT",
    "BoxConfig",
    "Config",
    "ConfigError",
    "GripperConfig",
    "TaskConfig",
    "__version__",
    *_LAZY,
]


def __getattr__(name: str):
    if name in _LAZY:
        module = importlib.import_module(_LAZY[name])
        value = getattr(module, "load" if name == "load_box" else name)
    elif name in _LAZY_MODULES:
        value = importlib.import_module(f"boxjax.{name}")
    else:
        raise AttributeError(f"module 'boxjax' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY) | set(_LAZY_MODULES))
