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
    from boxjax.training import dataset

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


@pytest.mark.slow
def test_estimator_eval_on_mjx(capsys):
    """The accelerator path end to end on the CPU: 4 boxes simulated with MJX in chunks of 2 (16-22 s on
    the 2-core CPU; slow: MJX's agreement with native is in the default suite, tests/test_sim_mjx.py)."""
    assert main(["estimator-eval", "--boxes", "4", "--backend", "mjx", "--chunk", "2", "--json"]) == 0
    res = _last_json(capsys)
    assert res["boxes"] == 4 and 0 <= res["iou_median"] <= 1 and res["mass_rel_error_median"] < 0.5


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["rotate", "--planner", "simulator", "--samples", "8"],
            "--samples is an option of the paper and sampling",
        ),
        (["rotate", "--samples", "1"], "--samples must be >= 2 with the sampling planner"),
        (["rotate", "--horizon", "0"], "--horizon is an option of the paper planner"),
        (["rotate", "--rule", "weighted"], "it does nothing with --planner sampling"),
        (["rotate", "--planner", "paper", "--samples", "-3"], "--samples must be >= 1, got -3"),
        (["rotate", "--planner", "paper", "--horizon", "0"], "--horizon must be >= 1, got 0"),
        (["rotate", "--planner", "paper", "--gradient-steps", "2"], "option of the sampling planner"),
        (["rotate", "--weights", "h.npz"], "--weights is an option of --estimator learned"),
        (["rotate", "--calibration", "c.npz"], "--calibration is an option of --variant paper"),
        (["rotate", "--adapt-every", "5"], "--adapt-every is an option of --model blackbox"),
        (
            ["rotate", "--model", "blackbox", "--estimator", "learned"],
            "--estimator is an option of --model prior",
        ),
        (["rotate", "--model", "blackbox", "--adapt-epochs", "-1"], "--adapt-epochs must be >= 0"),
        (
            ["rotate", "--replay", "ev", "--index", "0", "--planner", "paper"],
            "--planner does nothing with --replay",
        ),
        (["rotate", "--replay", "ev", "--index", "0", "--config", "c.toml"], "DIR/config.toml"),
        (["rotate", "--replay", "ev", "--index", "0", "--exploration", "designed"], "DIR/config.toml"),
        (
            ["rotate", "--estimator", "learned", "--exploration", "designed"],
            "train-estimator --exploration designed",
        ),
        (["rotate", "--replay", "ev"], "--replay DIR needs --index K"),
        (["simulate", "--policy", "random", "--speed", "0.1"], "--speed is an option of --policy naive"),
        (["simulate", "--steps", "0"], "--steps must be >= 1, got 0"),
        (["evaluate", "--force"], "--force does nothing without --out"),
        (
            ["evaluate", "--planner", "paper", "--slow-when-late", "3"],
            "--slow-when-late is an option of the sampling planner",
        ),
        (["evaluate", "--hazard-family", "items"], "does nothing with --hazardous 0"),
        (
            ["evaluate", "--monitor", "off", "--tip-stop-cm", "1"],
            "is an option of the runtime safety monitor",
        ),
        (["rotate", "--tip-stop-cm", "20"], "--tip-stop-cm must be in [0, 15), got 20.0"),
        (
            ["evaluate", "--monitor", "off", "--tip-uncertainty", "pose"],
            "is an option of the runtime safety monitor",
        ),
        (["evaluate", "--box", "b.npz", "--hazardous", "3"], "--hazardous does nothing with --box"),
        (["evaluate", "--box", "b.npz", "--safe-family", "items"], "--safe-family does nothing with --box"),
        (["evaluate", "--weights", "h.npz"], "--weights is an option of --estimator learned"),
        (["fault-table", "--weights", "h.npz"], "--weights is an option of --estimator learned"),
        (["fault-table", "--estimator", "learned", "--weights", "no/such.npz"], "no such checkpoint file"),
        (
            ["compare", "--methods", "prior", "--adapt-every", "3"],
            "--adapt-every is an option of the black boxes",
        ),
        (["compare", "--methods", "pets", "--model-weights", "w.npz"], "is an option of --methods blackbox"),
        (["rotate", "--model", "pets", "--variant", "paper"], "--variant is an option of --model prior"),
        (["train-estimator", "--out", "x", "--boxes", "5"], "--boxes must be >= 10"),
        (["calibrate", "--out", "x.npz", "--transitions", "4"], "--transitions must be >= 8"),
    ],
)
def test_an_option_that_does_nothing_is_refused(argv, message, capsys):
    """Every option acts or is refused, saying who uses it (one mechanism: boxjax.cli.args)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_help_shows_the_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["rotate", "--help"])
    out = capsys.readouterr().out
    assert "(default random)" in out and "--animate" in out and "--config" in out and "--box" in out
    assert "(default 1)" in out and "--samples" in out


def test_every_command_has_help(capsys):
    """`--help` of every subcommand formats (a '%' in a help string once broke fault-table's)."""
    import argparse

    from boxjax.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0, name
        assert "usage:" in capsys.readouterr().out


def test_commands_that_compile_keep_the_compilation_cache(capsys, monkeypatch, tmp_path):
    import jax

    from boxjax.run_info import CACHE_ENV

    saved = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    try:
        monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
        assert main(["config"]) == 0  # compiles nothing: the cache is left as it was
        assert jax.config.jax_compilation_cache_dir == saved[0]
        assert main(["simulate", "--distribution", "uniform", "--steps", "3", "--json"]) == 0
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache")
        assert (tmp_path / "cache").is_dir()
        (tmp_path / "file").write_text("")  # a folder that cannot be made: the command runs without it
        monkeypatch.setenv(CACHE_ENV, str(tmp_path / "file" / "cache"))
        assert main(["simulate", "--distribution", "uniform", "--steps", "3", "--json"]) == 0
        assert "not keeping compiled programs" in capsys.readouterr().err
        # every program is kept, unless JAX's own variable says otherwise
        from boxjax.run_info import use_compilation_cache

        monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
        assert use_compilation_cache(str(tmp_path / "cache")) == str(tmp_path / "cache")
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")
        use_compilation_cache(str(tmp_path / "cache"))
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.2
    finally:
        jax.config.update("jax_compilation_cache_dir", saved[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", saved[1])
    capsys.readouterr()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--friction-set", "0.5"], "two or more friction coefficients"),
        (["--friction-set", "0.4", "-1"], "two or more friction coefficients"),
        (["--friction-set", "0.4", "0.6", "--planner", "paper"], "option of the sampling planner"),
        (["--friction-set", "0.4", "0.6", "--belief", "ensemble", "--estimator", "learned"], "belief='mean'"),
    ],
)
def test_a_friction_set_the_controller_cannot_plan_over_is_refused_before_any_episode(argv, message, capsys):
    assert main(["evaluate", "--boxes", "1", *argv]) == 2
    assert message in capsys.readouterr().err


def test_the_friction_set_reaches_the_controller():
    from boxjax.cli.args import resolve
    from boxjax.cli.episodes import _controller_config
    from boxjax.cli.main import build_parser

    args = resolve(build_parser().parse_args(["evaluate", "--friction-set", "0.35", "0.5", "0.65"]))
    assert _controller_config(args).friction_set == (0.35, 0.5, 0.65)
    args = resolve(build_parser().parse_args(["evaluate"]))
    assert _controller_config(args).friction_set is None


def test_tip_stop_sets_the_monitors_tipping_watch():
    """--tip-stop-cm: the monitor's `tip_stop` in cm (0 turns the watch off); its default is the monitor's."""
    from boxjax.cli.args import resolve
    from boxjax.cli.episodes import _controller_config
    from boxjax.cli.main import build_parser
    from boxjax.control.monitor import MonitorConfig

    def monitor(*argv):
        return _controller_config(resolve(build_parser().parse_args(["rotate", *argv]))).monitor

    assert monitor() == MonitorConfig()
    assert monitor("--tip-stop-cm", "0").tip_stop == 0.0
    assert monitor("--tip-stop-cm", "2.5") == MonitorConfig(tip_stop=0.025)
    assert not monitor("--monitor", "off").enabled
    assert monitor("--tip-uncertainty", "pose") == MonitorConfig(tip_uncertainty="pose")
    assert monitor("--tip-uncertainty", "sigma") == MonitorConfig(tip_uncertainty="sigma")
    with pytest.raises(ValueError, match="tipping watch"):  # the watch it would widen is off
        monitor("--tip-uncertainty", "pose", "--tip-stop-cm", "0")


def test_samples_widen_the_planner_chosen():
    """--samples is the paper planner's actions per step and the sampling planner's rollouts per step."""
    from boxjax.cli.args import resolve
    from boxjax.cli.episodes import _controller_config
    from boxjax.cli.main import build_parser
    from boxjax.control.config import ControllerConfig
    from boxjax.planners.sampling import SamplingOptions

    def ctrl(*argv):
        return _controller_config(resolve(build_parser().parse_args(["evaluate", *argv])))

    wide = ctrl("--samples", "1024", "--gradient-steps", "0")
    assert wide.sampling == SamplingOptions(n_samples=1024, gradient_steps=0)
    assert wide.n_samples == ControllerConfig().n_samples  # the paper planner's, unused here
    assert ctrl("--samples", "128").sampling == SamplingOptions(n_samples=128)
    assert ctrl().sampling is None
    paper = ctrl("--planner", "paper", "--samples", "30")
    assert paper.n_samples == 30 and paper.sampling is None
