"""The planners by name: `make_planner(cfg, ctrl)` builds the one `ctrl.planner` names, behind the one
planner interface (`planning.Planner`).

A factory takes the config and the controller's settings (any object with the fields it reads, normally
`control.ControllerConfig`) and returns a `planning.Planner`. The built-in ones:

  paper      the paper's one-step Pareto random shooting (`planners.paper`)
  sampling   predictive sampling over a horizon with gradient refinement (`planners.sampling`, default)
  simulator  the same sampling planner rolling out the simulator itself: a privileged reference (oracle)

`register(name, factory)` adds another (a new planner needs no change anywhere else); names are checked by
`ControllerConfig` and the CLI against `available()`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from typing import Any

from boxjax import planning
from boxjax.config import Config
from boxjax.planners import paper, sampling, simulator

Factory = Callable[[Config, Any], planning.Planner]


def _paper(cfg: Config, ctrl) -> planning.Planner:
    return paper.make(
        cfg,
        n_samples=ctrl.n_samples,
        rule=ctrl.rule,
        velocity=ctrl.velocity,
        horizon=ctrl.horizon,
        brake_steps=ctrl.brake_steps,
        speed_cap=ctrl.speed_cap,
        safe_balance=ctrl.safe_balance,
        y_margin=ctrl.y_margin,
    )


def _sampling(cfg: Config, ctrl) -> planning.Planner:
    return sampling.make(cfg, ctrl.sampling or sampling.SamplingOptions())


def _simulator(cfg: Config, ctrl) -> planning.Planner:
    return simulator.make(cfg, ctrl.simulator or simulator.SimulatorOptions())


_FACTORIES: dict[str, Factory] = {"paper": _paper, "sampling": _sampling, "simulator": _simulator}
PLANNERS = tuple(_FACTORIES)  # the built-in planners (simulator: privileged reference, oracle only)


def available() -> tuple[str, ...]:
    """The names `make_planner` accepts: the built-in planners and any registered since."""
    return tuple(_FACTORIES)


def register(name: str, factory: Factory) -> None:
    """Make `factory(cfg, ctrl) -> planning.Planner` available as `ControllerConfig(planner=name)`."""
    if not name or not isinstance(name, str):
        raise ValueError(f"a planner name must be a non-empty string, got {name!r}")
    if name in _FACTORIES:
        raise ValueError(f"a planner named {name!r} is already registered")
    _FACTORIES[name] = factory


@lru_cache(maxsize=8)
def make_planner(cfg: Config, ctrl) -> planning.Planner:
    """The planner `ctrl.planner` names; cached per (config, settings) so its jitted pieces compile once,
    not once per episode."""
    if ctrl.planner not in _FACTORIES:
        raise ValueError(f"unknown planner {ctrl.planner!r}; choose one of {available()}")
    return _FACTORIES[ctrl.planner](cfg, ctrl)
