"""Configs as TOML (`--config FILE.toml`, `boxjax config`) and the refusal of models made for another
configuration."""

from __future__ import annotations

import json

import pytest

from boxjax import config_io
from boxjax.cli import main
from boxjax.cli import models as cli_models
from boxjax.config import DEFAULT


def _toml(tmp_path, text: str, name: str = "c.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _last_json(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_dumps_loads_back_to_the_defaults():
    assert config_io.loads(config_io.dumps()) == DEFAULT
    other = DEFAULT.replace(gripper=DEFAULT.gripper.__class__(friction=0.8, p1_range=(-0.22, -0.07)))
    assert config_io.loads(config_io.dumps(other)) == other


def test_config_command_prints_toml_that_loads_to_the_defaults(tmp_path, capsys):
    assert main(["config"]) == 0
    text = capsys.readouterr().out
    assert "[gripper]" in text and "friction = 0.5" in text and "# m/s" in text
    assert config_io.loads(text) == DEFAULT
    out = tmp_path / "d.toml"
    assert main(["config", "--out", str(out)]) == 0
    assert config_io.load(out) == DEFAULT
    assert main(["config", "--config", _toml(tmp_path, "[gripper]\nfriction = 0.7\n")]) == 0
    assert config_io.loads(capsys.readouterr().out).gripper.friction == 0.7


def test_partial_file_changes_only_its_keys(tmp_path):
    cfg = config_io.load(
        _toml(tmp_path, "[task]\nmax_steps = 80\nbalance_limit = 0.05\n[box]\nsize = [0.4, 0.3, 0.1]\n")
    )
    assert cfg.task.max_steps == 80 and cfg.task.balance_limit == 0.05 and cfg.box.size == (0.4, 0.3, 0.1)
    assert cfg.gripper == DEFAULT.gripper and cfg.task.yaw_tolerance == DEFAULT.task.yaw_tolerance
    assert config_io.load(_toml(tmp_path, "[gripper]\nfriction = 1\n")).gripper.friction == 1.0


@pytest.mark.parametrize(
    "text, message",
    [
        ("[gripper]\nfrictoin = 0.4\n", "unknown key 'frictoin' (did you mean 'friction'?)"),
        ("[belts]\nfriction = 0.4\n", "unknown key 'belts'"),
        ("[box]\ngrid = [8, 8]\n", "box.grid must be an array of 3 values"),
        ("[task]\nmax_steps = 1.5\n", "task.max_steps must be int"),
        ('[gripper]\nfriction = "high"\n', "gripper.friction must be float"),
        ("[gripper]\nbelt_speed_limit = 0.5\n", "beyond the hardware"),
        ("[box]\ngrid = [6, 8, 4]\n", "divisible by 4"),
        ("[gripper\nfriction = 0.4\n", "not valid TOML"),
        ("gripper = 3\n", "[gripper] must be a table"),
    ],
)
def test_bad_config_file_is_refused_by_name(tmp_path, capsys, text, message):
    path = _toml(tmp_path, text)
    with pytest.raises(config_io.ConfigFileError) as e:
        config_io.load(path)
    assert message in str(e.value) and path in str(e.value)
    assert main(["simulate", "--steps", "1", "--config", path]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_missing_config_file_exits_2(capsys):
    assert main(["rotate", "--config", "/nonexistent/c.toml"]) == 2
    assert "no such config file" in capsys.readouterr().err


def test_another_friction_coefficient_changes_the_episode(tmp_path, capsys):
    argv = ["simulate", "--distribution", "C", "--steps", "40", "--json"]
    assert main(argv) == 0
    base = _last_json(capsys)
    assert main([*argv, "--config", _toml(tmp_path, "[gripper]\nfriction = 0.2\n")]) == 0
    slippery = _last_json(capsys)
    assert slippery["config"].endswith("c.toml")
    assert abs(slippery["final_yaw_rad"] - base["final_yaw_rad"]) > 0.02
    assert main([*argv, "--config", _toml(tmp_path, config_io.dumps(), "d.toml")]) == 0
    assert _last_json(capsys)["final_yaw_rad"] == base["final_yaw_rad"]  # the defaults as a file: no change


def test_rotate_and_evaluate_run_with_the_files_config(tmp_path, monkeypatch, capsys):
    """The config reaches the controller and the evaluation (spies; no episode is run)."""
    from boxjax.control import episode as controller
    from boxjax.experiments import evaluation as experiments

    seen = []

    def spy(cfg, *args, **kwargs):
        seen.append(cfg)
        raise ValueError("spy: stop here")

    monkeypatch.setattr(controller, "run_episode", spy)
    monkeypatch.setattr(experiments, "make_boxes", spy)
    path = _toml(tmp_path, "[gripper]\nfriction = 0.3\n[task]\nmax_steps = 90\n")
    assert main(["rotate", "--config", path]) == 2
    assert main(["evaluate", "--boxes", "1", "--quiet", "--config", path]) == 2
    assert [c.gripper.friction for c in seen] == [0.3, 0.3] and seen[0].task.max_steps == 90


def test_a_config_with_another_grid_makes_the_learned_estimator_refuse(tmp_path, capsys):
    path = _toml(tmp_path, "[box]\ngrid = [12, 8, 4]\n")
    for argv in (
        ["rotate", "--estimator", "learned", "--distribution", "C"],
        ["demo", "--plot", ""],
        ["evaluate", "--boxes", "1", "--estimator", "learned"],
        ["estimator-eval", "--boxes", "1"],
    ):
        assert main([*argv, "--config", path]) == 2, argv
        err = capsys.readouterr().err
        assert "box.grid: model has [8, 8, 4], config has [12, 8, 4]" in err, argv
        assert f"boxjax train-estimator --config {path} --out h_run" in err and "--weights" in err
    # the oracle needs no trained model: the same config runs (on a box of its own grid)
    assert main(["simulate", "--steps", "2", "--config", path, "--json"]) == 0


def test_shipped_calibration_and_w_refuse_another_gripper(tmp_path, capsys):
    path = _toml(tmp_path, "[gripper]\nfriction = 0.3\n")
    assert main(["rotate", "--variant", "paper", "--config", path]) == 2
    err = capsys.readouterr().err
    assert "gripper.friction: file has 0.5, expected 0.3" in err
    assert f"boxjax calibrate --config {path} --out cal.npz" in err
    assert main(["rotate", "--model", "blackbox", "--config", path]) == 2
    assert f"boxjax train-baseline --config {path}" in capsys.readouterr().err
    # a config that changes only the task's rules keeps the shipped H
    cli_models.require_models(config_io.loads("[task]\nbalance_limit = 0.05\n"), estimator=True)
