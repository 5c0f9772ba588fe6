"""The fault table: the controller in a world that differs from its model, with the runtime safety monitor
on and off (docs/results/faults.md).

Every row runs `evaluation.evaluate` on the SAME boxes and episode keys (one seed), so rows and the two
monitor settings differ only in the fault and the monitor: a fault's draws come from each episode's own
key (`boxjax.sim.faults`), and two levels of one fault share their underlying draws. Per row and monitor
setting: safe boxes turned (95 % Wilson interval), safe stops and their reasons, failures by reason,
crossings of the balance limit and the unnoticed ones, and, for the monitor on, its false stops: boxes it
stopped that the unmonitored controller turned on the same box and key.

`run(...)` writes its JSON after every (row, monitor) pair and, given the same file again, skips the
pairs already in it (`resume`): a table of ~3,000 episodes can be built over several runs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Any, NamedTuple

from boxjax.config import Config
from boxjax.control import monitor
from boxjax.control.config import ControllerConfig
from boxjax.estimator.belief import learned_estimator
from boxjax.experiments import evaluation
from boxjax.fileio import atomic_path
from boxjax.sim.faults import Faults

FORMAT = "boxjax-fault-table"


class Row(NamedTuple):
    name: str
    group: str  # the fault this row varies ("none", "pose noise", ...), for the figure
    level: float  # its level on the figure's x axis (mm, steps, %, mu, kg)
    faults: Faults


ROWS = (
    Row("none", "none", 0.0, Faults()),
    Row("noise 1 mm / 0.5 deg", "pose noise (mm)", 1.0, Faults(obs_noise_mm=1, obs_noise_deg=0.5)),
    Row("noise 3 mm / 1.5 deg", "pose noise (mm)", 3.0, Faults(obs_noise_mm=3, obs_noise_deg=1.5)),
    Row("noise 10 mm / 5 deg", "pose noise (mm)", 10.0, Faults(obs_noise_mm=10, obs_noise_deg=5)),
    Row("latency 1 step", "observation latency (steps)", 1.0, Faults(obs_latency=1)),
    Row("latency 2 steps", "observation latency (steps)", 2.0, Faults(obs_latency=2)),
    Row("latency 4 steps", "observation latency (steps)", 4.0, Faults(obs_latency=4)),
    Row("drops 5 %", "dropped frames (%)", 5.0, Faults(drop_rate=0.05)),
    Row("drops 20 %", "dropped frames (%)", 20.0, Faults(drop_rate=0.2)),
    Row("friction 0.35", "belt friction (model: 0.5)", 0.35, Faults(friction=0.35)),
    Row("friction 0.65", "belt friction (model: 0.5)", 0.65, Faults(friction=0.65)),
    Row(
        "friction 0.35, belt 1 only",
        "one belt's friction (model: 0.5)",
        0.35,
        Faults(friction=0.35, friction_belt="1"),
    ),
    Row("mass shift 1 kg", "mass shift (kg)", 1.0, Faults(mass_shift_kg=1.0)),
    Row(
        "realistic",
        "realistic",
        1.0,
        Faults(obs_noise_mm=3, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.05, friction=0.4),
    ),
)
ROW_NAMES = tuple(r.name for r in ROWS)
MONITOR = ("on", "off")


def row(name: str) -> Row:
    for r in ROWS:
        if r.name == name:
            return r
    raise ValueError(f"unknown fault row {name!r}; choose from {ROW_NAMES}")


def _entry(ev: evaluation.Evaluation) -> dict:
    s = ev.summary
    keep = (
        "safe_boxes", "safe_success", "safe_success_rate", "safe_success_ci95", "false_aborts",
        "safe_stops", "safe_stop_reasons", "failures", "crossings", "unnoticed_crossings", "monitor_stops",
        "monitor_recoveries", "hazardous_boxes", "hazard_aborted", "hazard_outcomes", "steps_success",
        "max_balance_error_m", "min_stability_margin_m", "turn_min_stability_margin_m", "wall_s",
    )  # fmt: skip
    out = {k: s[k] for k in keep if k in s}
    out["outcomes"] = [r["outcome"] for r in ev.rows]
    out["hazardous"] = [r["hazardous"] for r in ev.rows]
    out["min_stability_margins_m"] = [r.get("min_stability_margin_m") for r in ev.rows]  # paired comparisons
    out["turn_min_stability_margins_m"] = [r.get("turn_min_stability_margin_m") for r in ev.rows]
    return out


def false_stops(on: dict, off: dict) -> dict:
    """The monitor's false stops: safe boxes that ended `safe_stop` with it on and were turned with it off
    (same box, same key). Also how many of its stops were of boxes the unmonitored controller lost."""
    pairs = [
        (a, b) for a, b, h in zip(on["outcomes"], off["outcomes"], on["hazardous"], strict=True) if not h
    ]
    lost = ("unbalanced", "off_belts", "tipped")
    return {
        "false_stops": sum(a == "safe_stop" and b == "success" for a, b in pairs),
        "stops_of_boxes_lost_without": sum(a == "safe_stop" and b in lost for a, b in pairs),
        "turned_only_with_monitor": sum(a == "success" and b != "success" for a, b in pairs),
        "turned_only_without_monitor": sum(a != "success" and b == "success" for a, b in pairs),
    }


def run(
    cfg: Config,
    n_boxes: int,
    seed: int,
    *,
    rows: tuple[str, ...] = ROW_NAMES,
    monitors: tuple[str, ...] = MONITOR,
    estimator: str = "oracle",
    weights: str | None = None,
    hazardous: int = 0,
    ctrl: ControllerConfig = ControllerConfig(),  # noqa: B008 (frozen dataclass: immutable)
    out: str | None = None,
    progress: Any = None,
) -> dict:
    """The table (plain data). With `out`, written there after each (row, monitor) pair and resumed
    from it: pairs already in the file (for the same boxes, seed, estimator and controller) are not run
    again. `weights`: the learned H's checkpoint (None: the shipped one)."""
    if weights is not None and estimator != "learned":
        raise ValueError("weights are the learned estimator's checkpoint; estimator must be 'learned'")
    for name in rows:
        row(name)
    head = {
        "format": FORMAT,
        "boxes": n_boxes,
        "hazardous": hazardous,
        "seed": seed,
        "estimator": estimator,
        **({"weights": weights} if weights else {}),
        "controller": evaluation.settings(estimator, ctrl, seed, "gaussian")["controller"],
    }
    estimator_fn = learned_estimator(cfg, weights) if weights else None
    table = _load(out, head) if out else None
    table = table or {**head, "rows": {}}
    for name in rows:
        r = row(name)
        entry = table["rows"].setdefault(
            name, {"group": r.group, "level": r.level, "faults": r.faults.to_dict()}
        )
        for m in monitors:
            if m in entry:
                continue
            t0 = time.perf_counter()
            c = dataclasses.replace(ctrl, monitor=ctrl.monitor if m == "on" else monitor.OFF)
            if m == "on" and not c.monitor.enabled:
                c = dataclasses.replace(c, monitor=monitor.MonitorConfig())
            ev = evaluation.evaluate(
                cfg, n_boxes, hazardous, seed, estimator=estimator, ctrl=c, faults=r.faults, progress=False,
                estimator_fn=estimator_fn,
            )  # fmt: skip
            entry[m] = _entry(ev)
            if "on" in entry and "off" in entry:
                entry["monitor_effect"] = false_stops(entry["on"], entry["off"])
            if progress is not None:
                progress(name, m, entry[m], time.perf_counter() - t0)
            if out:
                _write(out, table)
    return table


def _load(path: str, head: dict) -> dict | None:
    if not os.path.exists(path):
        return None
    with open(path) as f:
        table = json.load(f)
    differs = [k for k in head if table.get(k) != head[k]]
    if differs:
        raise ValueError(
            f"{path} holds a fault table of other settings ({', '.join(differs)}); use another file"
        )
    return table


def _write(path: str, table: dict) -> None:
    with atomic_path(path, suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(table, f, indent=1)


def markdown(table: dict) -> str:
    """The table as markdown: one line per row and monitor setting."""
    lines = [
        "| row | monitor | safe turned | 95 % interval | safe stops | failures | crossings (unnoticed) "
        "| false stops | near tips |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, entry in table["rows"].items():
        for m in MONITOR:
            if m not in entry:
                continue
            e = entry[m]
            lo, hi = e["safe_success_ci95"]
            fails = ", ".join(f"{k} {v}" for k, v in e["failures"].items()) or "-"
            fs = entry.get("monitor_effect", {}).get("false_stops") if m == "on" else None
            near = (e.get("min_stability_margin_m") or {}).get("near_tips")  # tables before it: "-"
            lines.append(
                f"| {name} | {m} | {e['safe_success']}/{e['safe_boxes']} | {100 * lo:.1f}-{100 * hi:.1f} % "
                f"| {e['safe_stops']} | {fails} | {e['crossings']} ({e['unnoticed_crossings']}) "
                f"| {'-' if fs is None else fs} | {'-' if near is None else near} |"
            )
    return "\n".join(lines)
