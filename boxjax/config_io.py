"""Configs as TOML files (`--config FILE.toml`), and the check that shipped models fit a config.

A config file has up to three tables, ``[box]``, ``[gripper]`` and ``[task]``, holding fields of the
frozen dataclasses in `boxjax.config` (`BoxConfig`, `GripperConfig`, `TaskConfig`); a field left out keeps
its default. Units are SI (m, kg, s, rad). `dumps()` writes the defaults in this form (``boxjax config``),
and ``load(path)`` reads one back: unknown tables or keys, wrong types and wrong tuple lengths are refused
by name, and the dataclasses' own checks (hardware limits, grid divisible by 4, ...) then apply. A
``[faults]`` table (`boxjax.sim.faults.Faults`: pose noise, latencies, friction mismatch, a mass shift) may
stand beside them; it is not part of the Config, the CLI reads it with `load_table`.

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
from typing import Any

from boxjax.config import DEFAULT, BoxConfig, Config, ConfigError, GripperConfig, TaskConfig
from boxjax.fileio import atomic_path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover (Python 3.10: the backport, a dependency there)
    import tomli as tomllib

SECTIONS: dict[str, type] = {"box": BoxConfig, "gripper": GripperConfig, "task": TaskConfig}
# Tables a config file may hold beside the Config's: how the simulated world differs from the controller's
# (`boxjax.sim.faults.Faults`, read by the CLI: `load_table(path, "faults")`).
OTHER_SECTIONS = ("faults",)
# The exploration data H learns from depends on the box, the whole gripper, the initial pose noise and the
# exploration sequence (the dataset is gathered open loop, so the task's success and failure rules do not
# enter it).
# The gripper a model (H, W, PETS) or dataset was made for: every GripperConfig field but MJX's contact
# finder, which, like the backend itself (recorded in the reports), says how the data were simulated, not
# what gripper they describe.
GRIPPER_FIELDS = tuple(
    f"gripper.{f.name}" for f in dataclasses.fields(GripperConfig) if f.name != "mjx_box_contacts"
)
ESTIMATOR_FIELDS = (
    *(f"box.{f.name}" for f in dataclasses.fields(BoxConfig)),
    *GRIPPER_FIELDS,
    "task.init_xy_noise",
    "task.init_yaw_noise",
    "task.exploration",
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
    """A Config from a TOML document's dict (the defaults for everything not given). The tables of
    `OTHER_SECTIONS` are not part of the Config (`load_table` reads them)."""
    parts = {}
    for section, table in doc.items():
        if section in OTHER_SECTIONS:
            continue
        if section not in SECTIONS:
            raise _unknown(source, section, [*SECTIONS, *OTHER_SECTIONS])
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


def _read(path) -> str:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigFileError(f"{path}: no such config file")
    try:
        with open(path, "rb") as f:
            return f.read().decode()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigFileError(f"{path}: unreadable config file ({e})") from e


def load(path) -> Config:
    """The Config in a TOML file. Raises ConfigFileError (a ValueError) naming the problem."""
    return loads(_read(path), os.fspath(path))


def load_table(path, section: str) -> dict:
    """The table `section` (one of OTHER_SECTIONS) of a TOML config file as a dict ({} when absent)."""
    if section not in OTHER_SECTIONS:
        raise ValueError(f"{section!r} is not one of the extra tables {OTHER_SECTIONS}")
    try:
        doc = tomllib.loads(_read(path))
    except tomllib.TOMLDecodeError as e:
        raise ConfigFileError(f"{path}: not valid TOML ({e})") from e
    table = doc.get(section, {})
    if not isinstance(table, dict):
        raise ConfigFileError(f"{path}: [{section}] must be a table of keys, got {table!r}")
    return table


def save(path, cfg: Config) -> str:
    """Write `cfg` as TOML, atomically. Returns the path."""

    with atomic_path(path, suffix=".toml") as tmp:
        with open(tmp, "w") as f:
            f.write(dumps(cfg))
    return os.fspath(path)


# ----------------------------------------------------------------------------------------------------------
# Do the shipped models fit a config?


def _get(cfg_dict: dict, dotted: str):
    out = cfg_dict
    for part in dotted.split("."):
        out = out[part]
    return out


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return a == b


MISSING = object()  # `field_mismatches`: the stored dict has no such field


def field_mismatches(stored: dict, expected: dict, fields) -> list[tuple[str, Any, Any]]:
    """(name, stored value or MISSING, expected value) for each dotted field name where two config
    dicts differ (floats compared to 1e-9): how a model or calibration file is checked against a config.
    A field the stored dict lacks was added to the Config after it was saved, so it was made with that
    field's default: it matches an expected default value and nothing else."""
    defaults = DEFAULT.to_dict()
    out = []
    for name in fields:
        want = _get(expected, name)
        try:
            have = _get(stored, name)
        except (KeyError, TypeError):
            if not _same(_get(defaults, name), want):
                out.append((name, MISSING, want))
            continue
        if not _same(have, want):
            out.append((name, have, want))
    return out


def differences(stored: dict, cfg: Config, fields) -> list[str]:
    """'name: model has X, config has Y' for each of `fields` (dotted) where `stored` (a Config's
    `to_dict()`) and `cfg` differ; a field missing from `stored` counts as its default
    (`field_mismatches`)."""

    return [
        f"{name}: not recorded in the model (made with the default {_get(DEFAULT.to_dict(), name)!r}), "
        f"config has {w!r}"
        if have is MISSING
        else f"{name}: model has {have!r}, config has {list(w) if isinstance(w, tuple) else w!r}"
        for name, have, w in field_mismatches(stored, cfg.to_dict(), fields)
    ]
