"""The estimator H shipped with boxjax (`boxjax/data/estimator.npz` and its report), loaded once per config
and checked against the config's grid, box size and exploration sequence."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from boxjax.config import DEFAULT, Config
from boxjax.estimator import explore
from boxjax.estimator.io import CheckpointError, load
from boxjax.estimator.net import EstimatorParams

SHIPPED_WEIGHTS = Path(__file__).parent.parent / "data" / "estimator.npz"
SHIPPED_REPORT = Path(__file__).parent.parent / "data" / "estimator_report.json"


def check_exploration(model: EstimatorParams, cfg: Config, path) -> None:
    """A checkpoint trained on another exploration sequence would give silent garbage: refuse it."""
    stored = model.provenance.get("exploration_actions")
    if stored is None:
        return  # trained outside train_estimator (e.g. tests): nothing recorded to compare
    stored = np.asarray(stored, np.float32)
    current = explore.exploration_actions(cfg)
    if stored.shape != current.shape or not np.allclose(stored, current, atol=1e-7):
        raise CheckpointError(
            f"{path}: trained on a different exploration sequence than boxjax.estimator.explore's; retrain it"
        )


@functools.lru_cache(maxsize=4)
def _load_default(path: str, cfg: Config) -> EstimatorParams:
    model = load(path, expected_box_config=cfg.box)
    check_exploration(model, cfg, path)
    return model


def default_estimator(cfg: Config = DEFAULT) -> EstimatorParams:
    """The shipped H (boxjax/data/estimator.npz), loaded once per config and checked against `cfg`'s grid,
    box size and exploration sequence. Raises CheckpointError if the file is missing or incompatible
    (e.g. a config with another voxel grid: train one with `train_estimator`)."""
    return _load_default(str(SHIPPED_WEIGHTS), cfg)


def default_estimator_cache_clear() -> None:
    """Forget the loaded shipped H (after `ship_estimator` replaced the file)."""
    _load_default.cache_clear()
