"""Refuse, before any work, a command whose models were made for another config than the one given: the
learned H, the shipped calibration (paper prior) and W. The messages name the command that makes one.
The models are imported by the check that needs them (the CLI's start-up time: `boxjax.cli`)."""

from __future__ import annotations

import dataclasses

from boxjax.config import DEFAULT, Config, ConfigError
from boxjax.config_io import ESTIMATOR_FIELDS, differences


def _config_flag(config_path, cfg: Config) -> str:
    """The options that make a model for `cfg`: its --config (a placeholder when the config came from
    elsewhere) and a non-default --exploration."""
    flag = f" --config {config_path}" if config_path else ""
    if not config_path and cfg.replace(task=dataclasses.replace(cfg.task, exploration="fixed")) != DEFAULT:
        flag = " --config FILE.toml"
    if cfg.task.exploration != DEFAULT.task.exploration:
        flag += f" --exploration {cfg.task.exploration}"
    return flag


def estimator_mismatch(cfg: Config, weights=None) -> list[str]:
    """The fields (ESTIMATOR_FIELDS) where the config H was trained for (the shipped two, or `weights`)
    differs from `cfg`; [] when it fits or records no config (a checkpoint made outside
    `train_estimator`: its grid is still checked on load)."""
    from boxjax.estimator.io import load
    from boxjax.estimator.shipped import SHIPPED_SENSOR_WEIGHTS, SHIPPED_WEIGHTS

    out = []
    for path in (SHIPPED_WEIGHTS, SHIPPED_SENSOR_WEIGHTS) if weights is None else (weights,):
        stored = load(path).provenance.get("config")
        out += (
            [] if stored is None else [d for d in differences(stored, cfg, ESTIMATOR_FIELDS) if d not in out]
        )
    return out


def require_models(
    cfg: Config,
    *,
    estimator: bool = False,
    weights=None,
    calibration: bool = False,
    baseline: bool = False,
    baseline_weights=None,
    config_path=None,
) -> None:
    """Refuse (ConfigError) when a model the command will use was made for another config than `cfg`:
    the learned H (`estimator`, the shipped one or `weights`), the shipped calibration (`calibration`,
    for the paper prior) or the black box W (`baseline`, the shipped one or `baseline_weights`). The
    message names the fields that differ and the command that makes a model for this config."""
    flag = _config_flag(config_path, cfg)
    if estimator:
        diffs = estimator_mismatch(cfg, weights)
        if diffs:
            which = "the shipped estimator H" if weights is None else f"estimator {weights}"
            raise ConfigError(
                f"{which} was trained for another configuration ({'; '.join(diffs)}); it would misjudge "
                f"every box. Train one for this configuration: `boxjax train-estimator{flag} --out h_run` "
                "and pass `--weights h_run/estimator.npz`"
            )
    if calibration and cfg != DEFAULT:
        from boxjax.prior import force_map as calibrate

        try:
            calibrate.load(calibrate.SHIPPED_CALIBRATION, cfg)
        except calibrate.CalibrationError as e:
            raise ConfigError(
                f"the shipped calibration (paper prior, --variant paper) does not fit this config: {e}. Make "
                f"one: `boxjax calibrate{flag} --out cal.npz` and pass `--calibration cal.npz` to `boxjax "
                "rotate` (evaluate uses the shipped calibration only)"
            ) from e
    if baseline:
        from boxjax.blackbox import baseline as B

        stored_path = B.shipped_path() if baseline_weights is None else baseline_weights
        try:
            B.load(stored_path, gripper=cfg.gripper)
        except B.BaselineCheckpointError as e:
            if "another gripper" not in str(e):
                raise
            raise ConfigError(
                f"{e}. Train W for this configuration: `boxjax train-baseline{flag} --out w_run` and pass "
                "`--model-weights w_run/baseline.npz`"
            ) from e
