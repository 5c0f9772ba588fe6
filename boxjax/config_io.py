"""Configs as TOML files (`--config FILE.toml`), and the check that shipped models fit a config.

A config file has up to three tables, ``[box]``, ``[gripper]`` and ``[task]``, holding fields of the
frozen dataclasses in `boxjax.config` (`BoxConfig`, `GripperConfig`, `TaskConfig`); a field left out keeps
its default. Units are SI (m, kg, s, rad). `dumps()` writes the defaults in this form (``boxjax config``),
and ``load(path)`` reads one back: unknown tables or keys, wrong types and wrong tuple lengths are refused
by name, and the dataclasses' own checks (hardware limits, grid divisible by 4, ...) then apply.

The shipped estimator H, calibration and black box W were made for the default config. `require_models`
refuses a config they were not made for, naming the fields that differ and the command that makes a
model for it: never plan with a model trained for another gripper.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import os
import re
import sys

from boxjax.config import DEFAULT, BoxConfig, Config, ConfigError, GripperConfig, TaskConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover (Python 3.10: the backport, a dependency there)
    import tomli as tomllib

SECTIONS: dict[str, type] = {"box": BoxConfig, "gripper": GripperConfig, "task": TaskConfig}
# The exploration data H learns from depends on the box, the whole gripper and the initial pose noise
# (the dataset is gathered open loop, so the task's success and failure rules do not enter it).
ESTIMATOR_FIELDS = (
    *(f"box.{f.name}" for f in dataclasses.fields(BoxConfig)),
    *(f"gripper.{f.name}" for f in dataclasses.fields(GripperConfig)),
    "task.init_xy_noise",
    "task.init_yaw_noise",
)


class ConfigFileError(ConfigError):
    """A config file is missing, not TOML, or holds unknown keys or values of the wrong type."""


def _field_comments(cls) -> dict[str, str]:
    """{field: its trailing comment in config.py} (units and meaning), for the TOML `dumps` writes."""
    try:
        src = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    pattern = r"^\s+(\w+): [^=\n]+=[^#\n]+#(.*)$"
    return {m[1]: m[2].strip() for m in re.finditer(pattern, src, re.M)}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise ConfigError(f"cannot write the non-finite value {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {type(v).__name__} {v!r} to TOML")


def dumps(cfg: Config = DEFAULT) -> str:
    """`cfg` as TOML that `loads` reads back to an equal Config (every field written, with its comment)."""
    lines = [
        "# boxjax configuration (SI units: m, kg, s, rad). Pass it with --config FILE.toml.",
        "# Keys left out keep their defaults; unknown keys are refused. `boxjax config` prints the defaults.",
    ]
    for name, cls in SECTIONS.items():
        lines += ["", f"[{name}]"]
        comments = _field_comments(cls)
        part = getattr(cfg, name)
        for f in dataclasses.fields(cls):
            line = f"{f.name} = {_toml_value(getattr(part, f.name))}"
            lines.append(f"{line}  # {comments[f.name]}" if f.name in comments else line)
    return "\n".join(lines) + "\n"


def _convert(where: str, value, default):
    """`value` from TOML in the type of the field's default, or ConfigFileError naming `where`."""
    if isinstance(default, tuple):
        if not isinstance(value, list) or len(value) != len(default):
            raise ConfigFileError(f"{where} must be an array of {len(default)} values, got {value!r}")
        return tuple(
            _convert(f"{where}[{i}]", v, d) for i, (v, d) in enumerate(zip(value, default, strict=True))
        )
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise ConfigFileError(f"{where} must be {type(default).__name__}, got {value!r}")
    return value


def _unknown(where: str, key: str, known) -> ConfigFileError:
    close = difflib.get_close_matches(key, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigFileError(f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(known)}")


def from_dict(doc: dict, source: str = "config") -> Config:
    """A Config from a TOML document's dict (the defaults for everything not given)."""
    parts = {}
    for section, table in doc.items():
        if section not in SECTIONS:
            raise _unknown(source, section, list(SECTIONS))
        if not isinstance(table, dict):
            raise ConfigFileError(f"{source}: [{section}] must be a table of keys, got {table!r}")
        cls = SECTIONS[section]
        defaults = getattr(DEFAULT, section)
        names = [f.name for f in dataclasses.fields(cls)]
        values = {}
        for key, value in table.items():
            if key not in names:
                raise _unknown(f"{source} [{section}]", key, names)
            values[key] = _convert(f"{source}: {section}.{key}", value, getattr(defaults, key))
        try:
            parts[section] = dataclasses.replace(defaults, **values)
        except ConfigError as e:
            raise ConfigFileError(f"{source}: [{section}] {e}") from e
    return DEFAULT.replace(**parts)


def loads(text: str, source: str = "config") -> Config:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigFileError(f"{source}: not valid TOML ({e})") from e
    return from_dict(doc, source)


def load(path) -> Config:
    """The Config in a TOML file. Raises ConfigFileError (a ValueError) naming the problem."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigFileError(f"{path}: no such config file")
    try:
        with open(path, "rb") as f:
            text = f.read().decode()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigFileError(f"{path}: unreadable config file ({e})") from e
    return loads(text, path)


def save(path, cfg: Config) -> str:
    """Write `cfg` as TOML, atomically. Returns the path."""
    from boxjax.fileio import atomic_path

    with atomic_path(path, suffix=".toml") as tmp:
        with open(tmp, "w") as f:
            f.write(dumps(cfg))
    return os.fspath(path)


# ----------------------------------------------------------------------------------------------------------
# Do the shipped models fit a config?


def differences(stored: dict, cfg: Config, fields) -> list[str]:
    """'name: model has X, config has Y' for each of `fields` (dotted) where `stored` (a Config's
    `to_dict()`) and `cfg` differ; a field missing from `stored` counts as different."""
    from boxjax.calibrate import MISSING, field_mismatches  # the calibration file's own comparison

    return [
        f"{name}: not recorded in the model, config has {w!r}"
        if have is MISSING
        else f"{name}: model has {have!r}, config has {list(w) if isinstance(w, tuple) else w!r}"
        for name, have, w in field_mismatches(stored, cfg.to_dict(), fields)
    ]


def _config_flag(config_path) -> str:
    return f" --config {config_path}" if config_path else " --config FILE.toml"


def estimator_mismatch(cfg: Config, weights=None) -> list[str]:
    """The fields (ESTIMATOR_FIELDS) where the config H was trained for differs from `cfg`; [] when it
    fits or records no config (a checkpoint made outside `train_estimator`: its grid is still checked on
    load)."""
    from boxjax import estimator as E
    from boxjax.estimator_pipeline import SHIPPED_WEIGHTS

    model = E.load(SHIPPED_WEIGHTS if weights is None else weights)
    stored = model.provenance.get("config")
    return [] if stored is None else differences(stored, cfg, ESTIMATOR_FIELDS)


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
    flag = _config_flag(config_path)
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
        from boxjax import calibrate

        try:
            calibrate.load(calibrate.SHIPPED_CALIBRATION, cfg)
        except calibrate.CalibrationError as e:
            raise ConfigError(
                f"the shipped calibration (paper prior, --variant paper) does not fit this config: {e}. Make "
                f"one: `boxjax calibrate{flag} --out cal.npz` and pass `--calibration cal.npz` to `boxjax "
                "rotate` (evaluate uses the shipped calibration only)"
            ) from e
    if baseline:
        from boxjax import baseline as B

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
