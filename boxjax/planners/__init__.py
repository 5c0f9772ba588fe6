"""The MPC planners, all behind `boxjax.planning.Planner`: `paper` (one-step Pareto random shooting, paper
§2.3), `sampling` (predictive sampling over a horizon, MPPI / CEM, gradient refinement; the default),
`simulator` (the sampling planner rolling out the simulator: a privileged reference). `registry` builds one
by name (`make_planner(cfg, ctrl)`) and takes new ones (`register`); `terms` holds cost terms they share."""

from boxjax.planners.registry import PLANNERS, available, make_planner, register
from boxjax.planners.sampling import SamplingOptions
from boxjax.planners.simulator import SimulatorOptions

__all__ = ["PLANNERS", "SamplingOptions", "SimulatorOptions", "available", "make_planner", "register"]
