"""`boxjax evaluate` (paper §4.3 validation): intervals, boxes from a seed, outcomes that never raise, the
files it writes and the replay of one box, and bad input at the CLI."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from boxjax import control as controller
from boxjax import massdist, prior
from boxjax.cli import main
from boxjax.config import DEFAULT, TaskConfig
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import run_episode
from boxjax.control.monitor import MonitorConfig
from boxjax.experiments import evaluation as experiments

CFG = DEFAULT


def test_wilson_interval_reference_values():
    """Against the closed form: p = 0.5, n = 100 -> 0.5 -+ 0.0962 (1.96 * sqrt(0.25 / 100) / (1 + 1.96^2 /
    100)); 0 / 10 -> [0, z^2 / (n + z^2)] = [0, 0.2775]; n / n mirrors it."""
    lo, hi = experiments.wilson_interval(50, 100)
    np.testing.assert_allclose([lo, hi], [0.4038, 0.5962], atol=1e-4)
    np.testing.assert_allclose(experiments.wilson_interval(0, 10), [0.0, 0.2775], atol=1e-4)
    np.testing.assert_allclose(experiments.wilson_interval(10, 10), [0.7225, 1.0], atol=1e-4)


def test_boxes_come_from_the_seed_and_follow_their_labels():
    a = experiments.make_boxes(CFG, 6, 3, seed=4)
    b = experiments.make_boxes(CFG, 6, 3, seed=4)
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    np.testing.assert_array_equal(a.keys, b.keys)
    assert not a.hazardous[:6].any() and a.hazardous[6:].all()
    assert list(a.family) == ["safe"] * 6 + ["gaussian"] * 3
    # Box j's episode key does not depend on how many boxes there are (so any box replays alone).
    c = experiments.make_boxes(CFG, 2, 0, seed=4)
    np.testing.assert_array_equal(c.keys, a.keys[:2])
    assert not np.array_equal(experiments.make_boxes(CFG, 6, 0, seed=5).occupancy, a.occupancy[:6])


@pytest.mark.parametrize("family", ["items", "slabs", "scatter"])
def test_safe_boxes_of_another_family(family):
    """--safe-family F: the label-safe draws of F's free sampler, in sequence from the safe key (so the
    hazardous boxes and every episode key are those of the default family's evaluation)."""
    base = experiments.make_boxes(CFG, 4, 2, seed=3)
    other = experiments.make_boxes(CFG, 4, 2, seed=3, safe_family=family)
    assert list(other.family) == [f"safe-{family}"] * 4 + ["gaussian"] * 2
    assert not other.hazardous[:4].any()
    np.testing.assert_array_equal(other.occupancy[4:], base.occupancy[4:])
    np.testing.assert_array_equal(other.keys, base.keys)
    key_safe = jax.random.split(jax.random.PRNGKey(3), 3)[0]
    draw = massdist.sampler(family, hazardous=False)
    expect = [draw(jax.random.fold_in(key_safe, i), CFG.box) for i in range(40)]
    expect = [d for d in expect if not bool(massdist.is_hazardous(d, CFG.box))][:4]
    np.testing.assert_array_equal(other.occupancy[:4], np.stack([np.asarray(d.occupancy) for d in expect]))
    with pytest.raises(ValueError, match="unknown safe-box family"):
        experiments.make_boxes(CFG, 1, 0, seed=0, safe_family="bricks")


def test_summary_counts_and_interval():
    rows = [
        {
            "hazardous": False,
            "outcome": "success",
            "steps": 200,
            "max_balance_error_m": 0.01,
            "lost_exploring": False,
            "min_stability_margin_m": 0.03,
        },
        {
            "hazardous": False,
            "outcome": "unbalanced",
            "steps": 90,
            "max_balance_error_m": 0.05,
            "lost_exploring": False,
            "min_stability_margin_m": 0.0015,
        },
        {
            "hazardous": False,
            "outcome": "aborted",
            "steps": 45,
            "max_balance_error_m": 0.002,
            "lost_exploring": False,
            "min_stability_margin_m": -0.01,
        },
        {
            "hazardous": True,
            "outcome": "aborted",
            "steps": 45,
            "max_balance_error_m": 0.01,
            "lost_exploring": False,
        },
        {
            "hazardous": True,
            "outcome": "step_cap",
            "steps": 600,
            "max_balance_error_m": 0.03,
            "lost_exploring": False,
        },
    ]
    s = experiments.summarize(rows)
    assert (s["safe_boxes"], s["safe_success"], s["false_aborts"]) == (3, 1, 1)
    assert s["failures"] == {"unbalanced": 1}
    assert (s["hazardous_boxes"], s["hazard_aborted"], s["hazard_recall"]) == (2, 1, 0.5)
    assert s["safe_success_ci95"] == list(experiments.wilson_interval(1, 3))
    assert s["max_balance_error_m"] == pytest.approx(
        {"median": 0.03, "max": 0.05}
    )  # refused ones not counted
    # the smallest true stability margins: the refused box and the one without a value not counted
    assert s["min_stability_margin_m"] == pytest.approx({"median": 0.01575, "min": 0.0015, "near_tips": 1})


def test_a_box_lost_while_exploring_is_an_outcome_not_an_exception():
    """With a 2 mm balance limit the box is lost inside the fixed exploration; the estimator must not be
    asked (a learned H needs the full 45 steps) and the episode ends as a failure."""
    cfg = CFG.replace(task=TaskConfig(balance_limit=0.002))

    def estimator(exploration):
        raise AssertionError("the estimator was called on a box lost while exploring")

    paper = ControllerConfig(explore_guard=None)  # the paper's fixed exploration, no guard
    res = run_episode(
        cfg, massdist.named("B", cfg.box), jax.random.PRNGKey(0), estimator=estimator, ctrl=paper
    )
    s = res.summary
    assert s["lost_exploring"] and not s["success"] and not s["aborted"]
    assert s["failed_reason"] == "unbalanced" and s["exploration_steps"] < 45
    assert res.belief is None


def test_the_exploration_guard_refuses_a_box_the_fixed_sequence_would_lose():
    """Box B under a 2 mm balance limit crosses it within the fixed exploration (above). With the guard
    (the default) the balance error passing 0.875 x 2 mm stops the sequence: the belts stop, the
    carriages follow the box, and the episode is a refusal that says why, on the one-box path, the
    batched path and the replay of its recorded actions alike; the estimator is never asked."""
    from boxjax.control import batch
    from boxjax.estimator import explore

    cfg = CFG.replace(task=TaskConfig(balance_limit=0.002))

    def estimator(exploration):
        raise AssertionError("the estimator was called on a box the guard refused")

    truth, key = massdist.named("B", cfg.box), jax.random.PRNGKey(0)
    one = run_episode(cfg, truth, key, estimator=estimator)
    s = one.summary
    assert s["aborted"] and not s["lost_exploring"] and not s["success"]
    assert "refused during the exploration" in s["abort_reason"] and "0.2 cm" in s["abort_reason"]
    bal = np.abs(one.trace.balance_error)
    # The first step that is not the fixed sequence's: the guard tripped on the state before it, at the
    # latest the first state past 0.875 x 2 mm (it looks ahead along the trend: `explore_guard_lead`).
    sent = one.trace.actions
    fixed = explore.exploration_actions(cfg)[: len(sent)]
    tripped = int(np.argmax(np.any(sent[: len(fixed)] != fixed, axis=1)))
    past = bal > 0.875 * 0.002
    assert 0 < tripped < 45 and bal.max() <= 0.002
    assert not past.any() or tripped <= int(np.argmax(past))
    assert s["exploration_steps"] == tripped + explore.GUARD_STEPS
    # the re-centring steps: belts stopped, both carriages stepped alike towards the box
    rec = one.trace.actions[tripped:]
    assert np.all(rec[:, :2] == 0) and np.all(rec[:, 2] == rec[:, 3])
    # the same decision batched and replayed
    (b,) = batch.run_episodes(cfg, [truth], [key], estimator=estimator)
    for k in ("aborted", "abort_reason", "exploration_steps", "lost_exploring", "steps"):
        assert b.summary[k] == s[k], k
    again = batch.replay_episode(cfg, truth, key, one.trace.actions, estimator=estimator)
    for k in ("aborted", "abort_reason", "exploration_steps", "lost_exploring", "steps"):
        assert again.summary[k] == s[k], k
    other = one.trace.actions.copy()
    other[tripped, 2] += 0.001  # not the re-centring step the guard sends
    with pytest.raises(ValueError, match="exploration's"):
        batch.replay_episode(cfg, truth, key, other, estimator=estimator)


def test_the_exploration_guard_is_a_fraction_of_the_limit():
    with pytest.raises(ValueError, match="explore_guard"):
        ControllerConfig(explore_guard=1.5)
    with pytest.raises(ValueError, match="fraction"):
        from boxjax.estimator import explore

        explore.Guarded(CFG, 0.0)


def test_evaluate_cli_writes_rows_and_a_box_replays_to_the_same_summary(tmp_path, capsys):
    out = tmp_path / "ev"
    png = tmp_path / "ev.png"
    # A step cap of 200 and a planner without gradient steps keep the suite's time bounded (seed 3's first
    # safe box runs to the 600-step cap; the gradient's program is 3/4 of the default planner's compile
    # time); the replay must then simulate the evaluation's config and controller, not the defaults.
    conf = tmp_path / "short.toml"
    conf.write_text("[task]\nmax_steps = 200\n")
    argv = [
        "evaluate",
        "--config",
        str(conf),
        "--boxes",
        "2",
        "--hazardous",
        "1",
        "--seed",
        "3",
        "--gradient-steps",
        "0",
        "--out",
        str(out),
        "--plot",
        str(png),
    ]
    assert main([*argv, "--quiet", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for k in (
        "safe_boxes",
        "safe_success",
        "safe_success_rate",
        "safe_success_ci95",
        "false_aborts",
        "failures",
        "hazardous_boxes",
        "hazard_aborted",
        "steps_success",
        "max_balance_error_m",
        "wall_s",
    ):
        assert k in summary, k
    assert summary["safe_boxes"] == 2 and summary["hazardous_boxes"] == 1
    doc = json.loads((out / "evaluation.json").read_text())
    assert len(doc["rows"]) == 3 and doc["summary"]["seed"] == 3
    assert png.stat().st_size > 10_000
    row = doc["rows"][1]
    assert main(["rotate", "--replay", str(out), "--index", "1", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rep["outcome"] == row["outcome"] and rep["steps"] == row["steps"]
    assert rep["max_balance_error_m"] == pytest.approx(row["max_balance_error_m"], abs=1e-7)
    # An existing non-empty --out is not overwritten without --force.
    assert main([*argv, "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluate", "--boxes", "0"], "--boxes"),
        (["evaluate", "--boxes", "3", "--hazardous", "-1"], "--hazardous"),
        (
            ["evaluate", "--boxes", "3", "--planner", "simulator", "--samples", "20"],
            "paper and sampling planners",
        ),
        (["rotate", "--index", "2"], "--replay"),
        (["evaluate", "--boxes", "3", "--planner", "paper", "--gradient-steps", "5"], "sampling planner"),
        (["evaluate", "--boxes", "3", "--gradient-steps", "-1"], "--gradient-steps"),
        (["rotate", "--replay", "/nonexistent/dir", "--index", "0"], "no such"),
        (["evaluate", "--boxes", "3", "--belief", "ensemble"], "learned estimator"),
        (["evaluate", "--boxes", "3", "--animate-failures"], "--out"),
        (["evaluate", "--boxes", "3", "--slots", "4", "--one-at-a-time"], "one by one"),
        (["evaluate", "--boxes", "3", "--slots", "0"], "--slots"),
        (["evaluate", "--boxes", "3", "--planner", "simulator", "--one-at-a-time"], "batched"),
        (["rotate", "--estimator", "learned", "--planner", "paper", "--belief", "ensemble"], "sampling"),
        (["evaluate", "--boxes", "3", "--explore-guard", "off", "--guard-lead", "2"], "--guard-lead"),
        (["evaluate", "--boxes", "3", "--guard-lead", "-1"], "--guard-lead"),
        (["evaluate", "--boxes", "3", "--explore-guard", "off", "--guard-stop", "hold"], "--guard-stop"),
        (["evaluate", "--boxes", "3", "--hazard-family", "scatter"], "--hazardous 0"),
        (["train-moments", "--boxes", "40", "--out", "m.txt"], ".npz"),
        (["estimator-eval", "--boxes", "2", "--moments", "/nonexistent.npz"], "nonexistent"),
    ],
)
def test_bad_input_exits_2_naming_the_problem(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_the_guard_holds_when_the_pose_is_noisy_or_late():
    """ "auto" holds when the controller sees the pose through a noisy or late sensor and re-centres on the
    exact pose (dropped frames alone or a plant mismatch leave it exact); a stop named is kept."""
    from boxjax.control.episode import guard_stop
    from boxjax.sim.faults import Faults

    auto = ControllerConfig()
    assert guard_stop(auto, Faults()) == "recentre"
    assert guard_stop(auto, Faults(friction=0.4, carriage_gain=0.8)) == "recentre"
    assert guard_stop(auto, Faults(drop_rate=0.05)) == "recentre"
    for fault in ({"obs_noise_mm": 1.0}, {"obs_latency": 1}, {"obs_noise_deg": 1.0}):
        assert guard_stop(auto, Faults(**fault)) == "hold", fault
    assert guard_stop(ControllerConfig(explore_guard_stop="recentre"), Faults(obs_latency=2)) == "recentre"
    assert guard_stop(ControllerConfig(explore_guard_stop="hold"), Faults()) == "hold"
    with pytest.raises(ValueError, match="explore_guard_stop must be one of"):
        ControllerConfig(explore_guard_stop="brake")
    # an evaluation written before the stop was chosen re-centred whatever the sensor: replayed so
    from boxjax.experiments.evaluation import controller_from_settings, settings

    old = settings("oracle", ControllerConfig(), 0, "gaussian", Faults(), "gaussian")
    del old["controller"]["explore_guard_stop"]
    assert controller_from_settings(old).explore_guard_stop == "recentre"


@pytest.mark.parametrize("value", ["1.5", "0", "lots"])
def test_a_bad_exploration_guard_is_refused_by_argparse(value, capsys):
    with pytest.raises(SystemExit) as e:
        main(["evaluate", "--boxes", "1", "--explore-guard", value])
    assert e.value.code == 2
    assert "--explore-guard" in capsys.readouterr().err


def test_unknown_planner_is_refused_by_argparse(capsys):
    with pytest.raises(SystemExit) as e:
        main(["evaluate", "--planner", "genetic"])
    assert e.value.code == 2


def test_controller_settings_round_trip():
    ctrl = ControllerConfig(planner="paper", rule="lexicographic", n_samples=30)
    st = json.loads(json.dumps(experiments.settings("oracle", ctrl, 1, "gaussian")))
    assert experiments.controller_from_settings(st) == ctrl
    tuned = ControllerConfig(prior_params=prior.PriorParams(carriage_omega=30.0, slip_eps=0.02))
    st = json.loads(json.dumps(experiments.settings("oracle", tuned, 1, "gaussian")))
    assert experiments.controller_from_settings(st) == tuned
    robust = ControllerConfig(friction_set=(0.35, 0.5, 0.65))
    st = json.loads(json.dumps(experiments.settings("oracle", robust, 1, "gaussian")))
    assert experiments.controller_from_settings(st) == robust
    late = ControllerConfig(delay_reference=3)
    st = json.loads(json.dumps(experiments.settings("oracle", late, 1, "gaussian")))
    assert experiments.controller_from_settings(st) == late
    del st["controller"]["delay_reference"]  # written before a late loop slowed the planner: it never did
    assert experiments.controller_from_settings(st).delay_reference is None
    assert experiments.controller_from_settings(st).monitor.recover_until_worse
    del st["controller"]["monitor"]["recover_until_worse"]  # written before recoveries could end
    assert not experiments.controller_from_settings(st).monitor.recover_until_worse
    # the tipping watch as it is, and written before it or its modes existed: what those runs ran with
    assert experiments.controller_from_settings(st).monitor.tip_uncertainty == "sigma"
    for name, then in (("tip_drag_std", 0.0), ("tip_uncertainty", "y"), ("tip_stop", 0.0)):
        del st["controller"]["monitor"][name]
        assert getattr(experiments.controller_from_settings(st).monitor, name) == then
    own = ControllerConfig(  # the monitor's own prior and the drag bound travel too
        monitor=MonitorConfig(prior_params=prior.PriorParams(carriage_omega=30.0), drag_bound=0.5)
    )
    st = json.loads(json.dumps(experiments.settings("oracle", own, 1, "gaussian")))
    assert experiments.controller_from_settings(st) == own


def test_the_controllers_prior_settings_reach_the_planners_model():
    cfg = DEFAULT
    box = massdist.named("A", cfg.box)
    params = prior.PriorParams(carriage_omega=30.0, n_substeps=3)
    model = controller.planning_model(cfg, ControllerConfig(prior_params=params), box)
    assert model.params == params
    assert controller.planning_model(cfg, ControllerConfig(), box).params == prior.PriorParams()
    with pytest.raises(ValueError, match="variant"):
        ControllerConfig(variant="paper", prior_params=params)
    with pytest.raises(ValueError, match="PriorParams"):
        ControllerConfig(prior_params={"carriage_omega": 30.0})


def test_failures_are_animated_from_their_recorded_actions(tmp_path):
    """With a 2 mm balance limit boxes B and D are lost while exploring (failures, no planner needed):
    their GIFs are written from the episodes' recorded actions; a refused box gets none."""
    from PIL import Image

    from boxjax.control import batch

    cfg = CFG.replace(task=TaskConfig(balance_limit=0.002))
    dists = [massdist.named("B", cfg.box), massdist.named("D", cfg.box)]
    keys = np.stack([np.asarray(jax.random.PRNGKey(0))] * 2).astype(np.uint32)
    paper = ControllerConfig(explore_guard=None)  # no guard: the fixed exploration loses both
    res = batch.run_episodes(cfg, dists, [jax.random.wrap_key_data(k) for k in keys], ctrl=paper)
    assert res[0].summary["lost_exploring"] and res[1].summary["lost_exploring"]
    boxes = experiments.EvalBoxes(
        occupancy=np.stack([np.asarray(d.occupancy, np.float32) for d in dists]),
        total_mass=np.asarray([float(d.total_mass) for d in dists], np.float32),
        hazardous=np.asarray([False, True]),
        family=np.asarray(["safe", "gaussian"]),
        keys=keys,
    )
    rows = [experiments._row(j, boxes, r, cfg) for j, r in enumerate(res)]
    ev = experiments.Evaluation(
        experiments.settings("oracle", paper, 0, "gaussian"),  # the replay explores as they did
        rows,
        boxes,
        [r.trace.balance_error for r in res],
        [r.trace.actions for r in res],
    )
    paths = experiments.animate_failures(ev, cfg, tmp_path, max_frames=8)
    assert paths == [str(tmp_path / "failures" / f"box_{j}.gif") for j in (0, 1)]
    refused = [rows[0], {**rows[1], "outcome": "aborted"}]
    assert experiments.animate_failures(ev._replace(rows=refused), cfg, tmp_path, max_frames=8) == paths[:1]
    with Image.open(paths[0]) as gif:
        assert gif.n_frames >= 2
    with pytest.raises(ValueError, match="no actions"):
        experiments.animate_failures(ev._replace(actions=None), cfg, tmp_path)
