"""The fault table's bookkeeping (boxjax.experiments.fault_table) and the fault options of the CLI."""

from __future__ import annotations

import json

import pytest

from boxjax.cli.main import main
from boxjax.config import DEFAULT
from boxjax.experiments import evaluation, fault_table


def _fake_evaluate(outcomes):
    """An `evaluation.evaluate` stand-in that returns `outcomes[(faults, monitor on?)]` as its rows."""
    calls = []

    def evaluate(cfg, n, hazardous, seed, *, estimator, ctrl, faults, progress, estimator_fn=None):
        calls.append((faults, ctrl.monitor.enabled))
        on = ctrl.monitor.enabled
        rows = [
            {"outcome": o, "hazardous": False, "lost_exploring": False, "steps": 100,
             "max_balance_error_m": 0.01, "crossing": o == "unbalanced",
             "unnoticed_crossing": o == "unbalanced" and not on, "monitor_stops": int(o == "safe_stop"),
             "min_stability_margin_m": 0.001 if o == "unbalanced" else 0.02,
             "turn_min_stability_margin_m": 0.001 if o == "unbalanced" else 0.03}
            for o in outcomes[on]
        ]  # fmt: skip
        return evaluation.Evaluation({**evaluation.summarize(rows), "wall_s": 1.0}, rows, None, [])

    return evaluate, calls


def test_false_stops_compare_the_same_boxes_with_and_without_the_monitor(monkeypatch, tmp_path):
    on = ["success", "safe_stop", "safe_stop", "success"]
    off = ["success", "success", "unbalanced", "step_cap"]
    fake, calls = _fake_evaluate({True: on, False: off})
    monkeypatch.setattr(evaluation, "evaluate", fake)
    out = tmp_path / "table.json"
    table = fault_table.run(DEFAULT, 4, 0, rows=("none",), out=str(out))
    e = table["rows"]["none"]
    assert e["monitor_effect"] == {
        "false_stops": 1,  # box 1: stopped, though turned without the monitor
        "stops_of_boxes_lost_without": 1,  # box 2: stopped, lost without it
        "turned_only_with_monitor": 1,  # box 3
        "turned_only_without_monitor": 1,  # box 1
    }
    assert e["on"]["safe_stops"] == 2 and e["off"]["unnoticed_crossings"] == 1
    md = fault_table.markdown(table)
    assert "| none | on | 2/4 |" in md and md.splitlines()[-1].endswith("| 1 |")  # off: box 2 near tipping
    assert e["off"]["min_stability_margins_m"] == [0.02, 0.02, 0.001, 0.02]
    assert e["off"]["turn_min_stability_margins_m"] == [0.03, 0.03, 0.001, 0.03]
    assert e["off"]["turn_min_stability_margin_m"] == {"median": 0.03, "min": 0.001, "near_tips": 1}
    # resumed from the file: nothing runs again; other settings in the same file are refused
    n = len(calls)
    fault_table.run(DEFAULT, 4, 0, rows=("none",), out=str(out))
    assert len(calls) == n
    with pytest.raises(ValueError, match="boxes"):
        fault_table.run(DEFAULT, 5, 0, rows=("none",), out=str(out))
    assert json.loads(out.read_text())["format"] == fault_table.FORMAT


def test_every_row_is_a_valid_fault_and_the_realistic_row_is_the_issues():
    assert fault_table.row("none").faults.any is False
    r = fault_table.row("realistic").faults
    assert (r.obs_noise_mm, r.obs_noise_deg, r.obs_latency, r.drop_rate, r.friction) == (3, 1.5, 2, 0.05, 0.4)
    with pytest.raises(ValueError, match="unknown fault row"):
        fault_table.row("earthquake")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluate", "--boxes", "2", "--out", "/proc/boxjax-x"], "--out"),
        (["evaluate", "--boxes", "2", "--drop-rate", "1"], "drop_rate"),
        (["evaluate", "--boxes", "2", "--obs-noise-mm", "-1"], "--obs-noise-mm"),
        (["evaluate", "--boxes", "2", "--obs-latency", "-1"], "--obs-latency"),
        (["evaluate", "--boxes", "2", "--friction-belt", "1"], "--friction"),
        (["rotate", "--obs-noise-mm", "3", "--backend", "mjx"], "native"),
        (["fault-table", "--boxes", "2", "--out", "/proc/boxjax-x/t.json"], "--out"),
    ],
)
def test_bad_fault_input_exits_2_before_any_episode(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_faults_table_in_the_config_file_is_read_and_overridden(tmp_path, monkeypatch):
    from boxjax.cli import episodes

    cfg = tmp_path / "c.toml"
    cfg.write_text("[gripper]\nfriction = 0.5\n\n[faults]\nobs_noise_mm = 2.0\nobs_latency = 1\n")
    seen = {}

    def fake(cfg_, n, hazardous, seed, **kw):
        seen.update(kw)
        raise ValueError("stop here")

    monkeypatch.setattr(evaluation, "evaluate", fake)
    assert main(["evaluate", "--boxes", "1", "--config", str(cfg), "--obs-latency", "3"]) == 2
    f = seen["faults"]
    assert (f.obs_noise_mm, f.obs_latency) == (2.0, 3)  # the file's noise, the option's latency
    bad = tmp_path / "bad.toml"
    bad.write_text("[faults]\nobs_noise = 2.0\n")
    assert main(["evaluate", "--boxes", "1", "--config", str(bad)]) == 2
    assert episodes.FAULT_FLAGS["friction"] == "friction"
