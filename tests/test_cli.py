"""The command line: JSON summaries on the last line, clear errors with exit status 2."""

from __future__ import annotations

import json

import pytest

from boxjax.cli import main


def _last_json(capsys):
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


def test_simulate_json_summary(capsys):
    assert main(["simulate", "--distribution", "uniform", "--steps", "5", "--json"]) == 0
    res = _last_json(capsys)
    for k in (
        "distribution",
        "backend",
        "steps",
        "final_yaw_rad",
        "max_balance_error_m",
        "success",
        "failed_reason",
        "wall_s",
    ):
        assert k in res
    assert res["steps"] == 5 and res["distribution"] == "uniform" and res["backend"] == "native"


def test_rotate_refuses_D(capsys, tmp_path):
    png = tmp_path / "d.png"
    assert main(["rotate", "--distribution", "D", "--json", "--plot", str(png)]) == 0
    res = _last_json(capsys)
    assert res["aborted"] and not res["success"] and res["estimator"] == "oracle"
    assert png.stat().st_size > 10_000


def test_bad_input_exits_2(capsys, tmp_path):
    assert main(["simulate", "--speed", "0.5"]) == 2  # beyond the belt speed limit
    assert "belt speed limit" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_text("not a checkpoint")
    assert main(["estimator-eval", "--boxes", "2", "--weights", str(bad)]) == 2
    assert "not a boxjax checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", "--distribution", "E"])


def test_demo_refuses_D_with_the_learned_estimator(capsys):
    assert main(["demo", "--distribution", "D", "--json", "--plot", ""]) == 0
    res = _last_json(capsys)
    assert res["aborted"] and not res["success"] and res["estimator"] == "learned"
    assert res["steps"] == res["exploration_steps"] == 45 and res["truth_hazardous"]
    assert res["hazard_prob"] > 0.5 and "probability" in res["abort_reason"]
    for k in ("iou", "mass_error_kg", "com_error_cm"):
        assert k in res


def test_demo_turns_A_and_draws_the_figure(capsys, tmp_path):
    png = tmp_path / "demo.png"
    assert main(["demo", "--distribution", "A", "--json", "--plot", str(png)]) == 0
    res = _last_json(capsys)
    assert res["success"] and not res["aborted"] and res["max_balance_error_m"] < 0.04
    assert res["hazard_prob"] < 0.5 and abs(res["mass_error_kg"]) < 0.5 and res["plot"] == str(png)
    assert png.stat().st_size > 10_000


def test_estimator_commands_pass_backend_and_chunk(capsys, monkeypatch, tmp_path):
    """--backend and --chunk reach the dataset generator; a chunk of 0 boxes is refused by name."""
    from boxjax import dataset

    seen = []
    generate = dataset.generate

    def spy(*args, **kwargs):
        seen.append((kwargs["backend"], kwargs["chunk"]))
        return generate(*args, **{**kwargs, "backend": "native"})

    monkeypatch.setattr(dataset, "generate", spy)
    assert main(["estimator-eval", "--boxes", "3", "--backend", "mjx", "--chunk", "2", "--json"]) == 0
    assert _last_json(capsys)["boxes"] == 3 and seen == [("mjx", 2)]
    assert main(["estimator-eval", "--boxes", "3", "--chunk", "0"]) == 2
    assert "--chunk must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train-estimator", "--out", str(tmp_path), "--backend", "gpu"])


def test_estimator_eval_on_mjx(capsys):
    """The accelerator path end to end on the CPU: 4 boxes simulated with MJX in chunks of 2 (16 s on the
    2-core CPU)."""
    assert main(["estimator-eval", "--boxes", "4", "--backend", "mjx", "--chunk", "2", "--json"]) == 0
    res = _last_json(capsys)
    assert res["boxes"] == 4 and 0 <= res["iou_median"] <= 1 and res["mass_rel_error_median"] < 0.5
