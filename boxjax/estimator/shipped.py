"""The estimators H shipped with boxjax, loaded once per config and checked against the config's grid, box
size and exploration sequence: `boxjax/data/estimator.npz` (and its report), trained on the simulator's
exact explorations, for a perfect sensor; `boxjax/data/estimator_sensor.npz` (and its report), trained on
the same kind of explorations seen through randomised sensors (`boxjax.training.randomise`), for a camera's
noisy pose and dropped frames (docs/results/faults.md); `boxjax/data/moments.npz`, the moments estimator
(`boxjax.estimator.moments`), trained on exact explorations of the wide training mixture
(`boxjax.training.wide`)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from boxjax.config import DEFAULT, Config
from boxjax.estimator import explore
from boxjax.estimator.io import CheckpointError, load
from boxjax.estimator.moments import MomentsError, MomentsModel
from boxjax.estimator.moments import load as load_moments
from boxjax.estimator.net import EstimatorParams

SHIPPED_WEIGHTS = Path(__file__).parent.parent / "data" / "estimator.npz"
SHIPPED_REPORT = Path(__file__).parent.parent / "data" / "estimator_report.json"
SHIPPED_SENSOR_WEIGHTS = Path(__file__).parent.parent / "data" / "estimator_sensor.npz"
SHIPPED_SENSOR_REPORT = Path(__file__).parent.parent / "data" / "estimator_sensor_report.json"
SHIPPED_MOMENTS = Path(__file__).parent.parent / "data" / "moments.npz"


def check_exploration(model: EstimatorParams, cfg: Config, path) -> None:
    """A checkpoint trained on another exploration sequence would give silent garbage: refuse it."""
    stored = model.provenance.get("exploration_actions")
    if stored is None:
        return  # trained outside train_estimator (e.g. tests): nothing recorded to compare
    stored = np.asarray(stored, np.float32)
    current = explore.exploration_actions(cfg)
    if stored.shape != current.shape or not np.allclose(stored, current, atol=1e-7):
        raise CheckpointError(
            f"{path}: trained on a different exploration sequence than this config's "
            f"(task.exploration = {cfg.task.exploration!r}); train one with `boxjax train-estimator "
            f"--exploration {cfg.task.exploration}`"
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


def sensor_estimator(cfg: Config = DEFAULT) -> EstimatorParams:
    """The shipped H for an imperfect sensor (boxjax/data/estimator_sensor.npz), checked as
    `default_estimator`."""
    return _load_default(str(SHIPPED_SENSOR_WEIGHTS), cfg)


def imperfect_sensor(sensor) -> bool:
    """Whether the sensor's specification an exploration was seen through (`World.for_estimator`'s
    "sensor": pose noise in mm, share of dropped frames; None: a perfect sensor) shows a noisy pose or
    drops frames."""
    return sensor is not None and (sensor.get("obs_noise_mm", 0) > 0 or sensor.get("drop_rate", 0) > 0)


def default_estimator_cache_clear() -> None:
    """Forget the loaded shipped H (after `ship_estimator` replaced the file)."""
    _load_default.cache_clear()


@functools.lru_cache(maxsize=4)
def _load_moments(path: str, cfg: Config) -> MomentsModel:
    model, meta = load_moments(path, cfg.box)
    stored = meta.get("exploration_actions")
    current = explore.exploration_actions(cfg)
    if stored is not None and (
        np.shape(stored) != current.shape or not np.allclose(stored, current, atol=1e-7)
    ):
        raise MomentsError(
            f"{path}: trained on a different exploration sequence than this config's "
            f"(task.exploration = {cfg.task.exploration!r}); train one with `boxjax train-moments "
            f"--exploration {cfg.task.exploration}`"
        )
    # The shipped file predates the field: it was trained for the default box.
    size = meta.get("box_size", list(DEFAULT.box.size))
    if not np.allclose(size, cfg.box.size):
        raise MomentsError(f"{path}: trained for a {size} m box, this config's is {list(cfg.box.size)} m")
    return model


def default_moments(cfg: Config = DEFAULT) -> MomentsModel:
    """The shipped moments estimator, loaded once per config; MomentsError if missing or incompatible."""
    return _load_moments(str(SHIPPED_MOMENTS), cfg)


def moments_for(cfg: Config) -> tuple[MomentsModel | None, str | None]:
    """(the shipped moments estimator, None) when it fits `cfg` (its grid and exploration sequence), else
    (None, why not): a config of your own gripper or box grid runs without the moments until you train
    them (`boxjax train-moments --config ...`)."""
    try:
        return default_moments(cfg), None
    except MomentsError as e:
        return (
            None,
            f"the shipped moments estimator does not fit this config ({e}); train one with train-moments",
        )
