"""boxjax: safe, data-efficient box manipulation on a two-belt conveyor gripper.

MuJoCo / MJX simulation of the gripper, voxel mass distributions, and model-predictive control with
physics priors (Salehi & Doncieux, "Data-efficient, Explainable and Safe Box Manipulation", L4DC 2024).
"""

from boxjax.config import DEFAULT, BoxConfig, Config, ConfigError, GripperConfig, TaskConfig

__version__ = "0.1.0"
__all__ = ["DEFAULT", "BoxConfig", "Config", "ConfigError", "GripperConfig", "TaskConfig", "__version__"]
