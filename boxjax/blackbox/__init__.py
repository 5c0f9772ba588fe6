"""The black-box dynamics models of the paper's baselines, in the planner's model slot: W (`baseline`:
an MLP on a window of states, paper §4.1) and PETS (`pets`: a probabilistic ensemble sampled by
trajectory sampling). `load_black_box(method)` gives the shipped (or a named) model, `adapter_for(model)`
its online adaptation. Their training is in `boxjax.training`."""

from boxjax.blackbox.baseline import BaselineCheckpointError, BaselineConfig, BlackBoxModel
from boxjax.blackbox.loading import BLACK_BOXES, adapter_for, load_black_box
from boxjax.blackbox.pets import GaussianMember, PETSCheckpointError, PETSConfig

__all__ = [
    "BLACK_BOXES",
    "BaselineCheckpointError",
    "BaselineConfig",
    "BlackBoxModel",
    "GaussianMember",
    "PETSCheckpointError",
    "PETSConfig",
    "adapter_for",
    "load_black_box",
]
