"""Boxes as files: .npz grids and .json mixture specs, `boxjax box`, and `--box FILE` on the episodes."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from boxjax import boxfile, massdist
from boxjax.cli import main
from boxjax.config import DEFAULT

SPEC_A = {  # named box A's mixture, written out as a user would
    "means": [[0.08, -0.06, -0.03], [-0.08, 0.06, 0.0]],
    "stds": [[0.08, 0.06, 0.05], [0.05, 0.05, 0.04]],
    "weights": [1.0, 0.8],
    "threshold": 0.4,
    "total_mass": 5.0,
}


def _last_json(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def _npz(path, occupancy, total_mass=3.0):
    np.savez(path, occupancy=np.asarray(occupancy), total_mass=np.asarray(total_mass))
    return str(path)


def test_saved_random_box_loads_back_unchanged(tmp_path):
    dist = boxfile.random_box(7)
    path = boxfile.save(tmp_path / "b.npz", dist, meta={"seed": 7})
    back = boxfile.load(path)
    assert np.array_equal(back.occupancy, dist.occupancy) and float(back.total_mass) == float(dist.total_mass)
    expected = massdist.sample(jax.random.PRNGKey(7), DEFAULT.box)
    assert np.array_equal(back.occupancy, np.asarray(expected.occupancy))


def test_plain_user_npz_and_json_spec_load(tmp_path):
    occ = np.zeros(DEFAULT.box.grid)
    occ[3:5, 3:5, :2] = 1
    d = boxfile.load(_npz(tmp_path / "mine.npz", occ, 4.2))
    assert d.occupancy.dtype == np.float32 and float(d.total_mass) == pytest.approx(4.2)
    (tmp_path / "a.json").write_text(json.dumps(SPEC_A))
    a = boxfile.load(str(tmp_path / "a.json"))
    assert np.array_equal(a.occupancy, np.asarray(massdist.named("A").occupancy)) and float(a.total_mass) == 5
    (tmp_path / "d.json").write_text(json.dumps({**SPEC_A, "region": "U4"}))
    assert int(massdist.hazard_region(boxfile.load(str(tmp_path / "d.json")))) == 3


def test_report_has_mass_com_fill_and_hazard():
    r = boxfile.report(massdist.named("D"))
    assert r["hazardous"] and r["hazard_region"] == "U4" and r["total_mass_kg"] == 7.0
    assert r["com_m"][1] == pytest.approx(0.113, abs=1e-3) and r["occupied_voxels"] == 39
    assert 0 < r["fill"] < 1 and len(r["inertia_diag_kg_m2"]) == 3


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: _npz(p / "g.npz", np.ones((8, 8, 3))), "box grid needs shape (8, 8, 4)"),
        (lambda p: _npz(p / "e.npz", np.zeros((8, 8, 4))), "no mass"),
        (lambda p: _npz(p / "n.npz", np.full((8, 8, 4), np.nan)), "NaN"),
        (lambda p: _npz(p / "m.npz", np.ones((8, 8, 4)), -2.0), "total_mass must be finite and > 0"),
        (lambda p: _npz(p / "f.npz", np.ones((8, 8, 4)), np.nan), "total_mass must be finite and > 0"),
        (lambda p: _npz(p / "h.npz", np.full((8, 8, 4), 0.5)), "must be 0 or 1"),
        (lambda p: str(p / "missing.npz"), "no such box file"),
        (lambda p: str(p / "box.txt"), "must end in .npz"),
    ],
)
def test_bad_npz_is_refused_naming_the_problem(tmp_path, make, message):
    with pytest.raises(boxfile.BoxFileError, match=None) as e:
        boxfile.load(make(tmp_path))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_npz_with_other_arrays_is_refused(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, occupancy=np.ones((8, 8, 4)), total_mass=1.0, density=np.ones(3))
    with pytest.raises(boxfile.BoxFileError, match="unknown array"):
        boxfile.load(str(path))
    np.savez(path, occ=np.ones((8, 8, 4)), total_mass=1.0)
    with pytest.raises(boxfile.BoxFileError, match="missing array"):
        boxfile.load(str(path))


@pytest.mark.parametrize(
    "change, message",
    [
        ({"mass": 3.0}, "unknown key(s) ['mass']"),
        ({"total_mass": -1.0}, "'total_mass' must be > 0 kg"),
        ({"stds": [[0.1, 0.1, 0.1]]}, "'stds' must have shape (2 x 3)"),
        ({"means": [[0.0, float("nan"), 0.0], [0.0, 0.0, 0.0]]}, "'means' contains NaN"),
        ({"threshold": 1.5}, "'threshold' must lie in (0, 1]"),
        ({"region": "U5"}, "'region' must be null or one of"),
    ],
)
def test_bad_json_spec_is_refused_naming_the_problem(tmp_path, change, message):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**SPEC_A, **change}).replace("NaN", "NaN"))
    with pytest.raises(boxfile.BoxFileError) as e:
        boxfile.load(str(path))
    assert message in str(e.value)


def test_box_command_makes_and_inspects_a_file(tmp_path, capsys):
    out, png = tmp_path / "r.npz", tmp_path / "r.png"
    assert main(["box", "--random", "11", "--out", str(out), "--json"]) == 0
    made = _last_json(capsys)
    assert made["file"] == str(out) and made["grid"] == [8, 8, 4]
    assert main(["box", str(out), "--plot", str(png), "--json"]) == 0
    seen = _last_json(capsys)
    for k in ("total_mass_kg", "com_m", "fill", "hazardous", "hazard_region", "occupied_voxels"):
        assert seen[k] == made[k], k
    assert png.stat().st_size > 10_000
    assert main(["box", str(out)]) == 0
    assert "centre of mass" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["box"], "give either a box FILE"),
        (["box", "x.npz", "--random", "1"], "give either a box FILE"),
        (["box", "--out", "x.npz"], "--out does nothing without --random"),
        (["box", "/nonexistent/b.npz"], "no such box file"),
        (["simulate", "--box", "/nonexistent/b.json"], "no such box file"),
        (["rotate", "--box", "b.npz", "--distribution", "C"], "--distribution does nothing with --box"),
    ],
)
def test_box_cli_bad_input_exits_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_bad_box_file_on_rotate_exits_2_with_one_line(tmp_path, capsys):
    bad = _npz(tmp_path / "g.npz", np.ones((4, 8, 4)))
    assert main(["rotate", "--box", bad]) == 2
    err = capsys.readouterr().err
    assert "occupancy has shape (4, 8, 4)" in err and bad in err and err.count("\n") == 1


def _round_trip(tmp_path, capsys, seed: int, *extra: str) -> tuple[dict, dict]:
    """box --random SEED -> file -> rotate --box FILE, and controller.run_episode on the same
    distribution and key: (CLI summary, API summary)."""
    from boxjax.control.episode import run_episode

    path = tmp_path / "mine.npz"
    assert main(["box", "--random", str(seed), "--out", str(path), "--json"]) == 0
    capsys.readouterr()
    assert main(["rotate", "--box", str(path), "--seed", "2", *extra, "--json"]) == 0
    cli = _last_json(capsys)
    api = run_episode(DEFAULT, boxfile.random_box(seed), jax.random.PRNGKey(2)).summary
    assert cli["distribution"] == str(path)
    for k, v in api.items():
        if k not in ("wall_s", "plan_ms_median", "adapt_s"):
            assert cli[k] == v, k
    return cli, api


def test_user_box_round_trip_rotate_matches_the_python_api(tmp_path, capsys):
    """Seed 5 draws a hazardous box (all mass over the right belt): the 45-step exploration runs, then the
    refusal; the CLI episode is the API's to the last bit (balance error, yaw, refusal text)."""
    cli, _ = _round_trip(tmp_path, capsys, 5)
    assert cli["aborted"] and cli["steps"] == 45 and "U4" in cli["abort_reason"]


@pytest.mark.slow
def test_user_box_round_trip_turns_the_box(tmp_path, capsys):
    """A safe random box (seed 6) turned by the default planner (compiles it: about a minute here)."""
    cli, _ = _round_trip(tmp_path, capsys, 6)
    assert cli["success"] and cli["steps"] > 100


def test_evaluate_a_box_file_and_replay_one_of_its_episodes(tmp_path, capsys):
    """evaluate --box FILE --boxes 2: two episodes of the user's box (seed 5: hazardous, refused), written
    with its config; rotate --replay gives the same row back."""
    path = boxfile.save(tmp_path / "h.npz", boxfile.random_box(5))
    out = tmp_path / "ev"
    assert main(["evaluate", "--box", path, "--boxes", "2", "--out", str(out), "--quiet", "--json"]) == 0
    summary = _last_json(capsys)
    assert summary["box"] == path and summary["hazardous_boxes"] == 2 and summary["hazard_aborted"] == 2
    assert (out / "config.toml").is_file() and json.loads((out / "cli.json").read_text())["box"] == path
    row = json.loads((out / "evaluation.json").read_text())["rows"][1]
    assert main(["rotate", "--replay", str(out), "--index", "1", "--json"]) == 0
    rep = _last_json(capsys)
    assert rep["outcome"] == row["outcome"] == "aborted" and rep["steps"] == row["steps"]
