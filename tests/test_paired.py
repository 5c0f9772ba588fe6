"""Paired comparison of two evaluations (boxjax.experiments.paired, scripts/compare_evaluations.py): the
sign test against scipy's, the counts box by box, the margins' paired differences, other boxes refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from boxjax.experiments import paired

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import compare_evaluations  # noqa: E402


@pytest.mark.parametrize("a, b", [(0, 0), (3, 0), (7, 1), (12, 24), (5, 5), (0, 9)])
def test_the_sign_test_is_the_exact_two_sided_binomial_test(a, b):
    expect = 1.0 if a + b == 0 else stats.binomtest(a, a + b, 0.5).pvalue
    assert paired.sign_test(a, b) == pytest.approx(expect, rel=1e-9)


def _row(i, outcome, margin, hazardous=False, **kw):
    return {
        "index": i,
        "family": "gaussian" if hazardous else "safe",
        "hazardous": hazardous,
        "total_mass_kg": 2.0 + i,
        "com_cm": [float(i), 0.0, 0.0],
        "outcome": outcome,
        "min_stability_margin_m": margin,
        # the turn's margin: none for a refused box, else at least the episode's (here 5 mm above it)
        "turn_min_stability_margin_m": None if outcome == "aborted" or margin is None else margin + 0.005,
        **kw,
    }


A = [
    _row(0, "success", 0.030),
    _row(1, "tipped", -0.004),
    _row(2, "success", 0.012),
    _row(3, "safe_stop", 0.001),
    _row(4, "aborted", 0.040),
    _row(5, "aborted", 0.020, hazardous=True),
    _row(6, "success", None, hazardous=True),
]
B = [
    _row(0, "step_cap", 0.031),
    _row(1, "success", 0.006),
    _row(2, "success", 0.010),
    _row(3, "unbalanced", 0.0015, unnoticed_crossing=True),
    _row(4, "success", 0.035),
    _row(5, "aborted", 0.020, hazardous=True),
    _row(6, "aborted", 0.020, hazardous=True),
]


def test_two_evaluations_are_compared_box_by_box():
    c = paired.compare(A, B)
    assert c["safe_boxes"] == 5 and c["hazardous_boxes"] == 2
    assert c["turned"] == {"a": 2, "b": 3}
    assert c["turned_only"]["a"] == 1 and c["turned_only"]["b"] == 2  # box 0; boxes 1 and 4
    assert c["turned_only"]["sign_test_p"] == pytest.approx(1.0)
    assert c["lost"] == {"a": 1, "b": 1, "boxes_a": [1], "boxes_b": [3]}
    assert c["safe_stops"] == {"a": 1, "b": 0} and c["false_aborts"] == {"a": 1, "b": 0}
    assert c["unnoticed_crossings"] == {"a": 0, "b": 1} and c["hazards_refused"] == {"a": 1, "b": 2}
    m = c["margins"]  # boxes 0-3: box 4 was refused by A, the hazardous ones are not safe boxes
    d = np.array([0.031 - 0.030, 0.006 + 0.004, 0.010 - 0.012, 0.0015 - 0.001])
    assert m["boxes"] == 4 and m["near_tips"] == {"a": 2, "b": 1}
    assert m["difference_m"]["mean"] == pytest.approx(d.mean())
    half = 1.959964 * d.std(ddof=1) / 2.0
    assert m["difference_m"]["ci95"] == pytest.approx([d.mean() - half, d.mean() + half])
    assert m["closer_to_tipping"] == {"a": 3, "b": 1}  # B kept 3 boxes further from tipping, A one
    assert m["median_m"]["a"] == pytest.approx(np.median([0.030, -0.004, 0.012, 0.001]))
    t = c["turn_margins"]  # the same boxes, each turn's margin 5 mm above its episode's
    assert t["boxes"] == 4 and t["difference_m"]["mean"] == pytest.approx(d.mean())
    assert t["median_m"]["a"] == pytest.approx(m["median_m"]["a"] + 0.005) and t["near_tips"]["a"] == 1
    # evaluations written before turn margins were recorded: the episode's margins only
    old = [{k: v for k, v in r.items() if k != "turn_min_stability_margin_m"} for r in A]
    assert paired.compare(old, old)["turn_margins"] is None
    # several evaluations pool by concatenating the rows
    assert paired.compare(A + A, B + B)["turned_only"] == {
        "a": 2,
        "b": 4,
        "sign_test_p": pytest.approx(2 * (1 + 6 + 15) / 64),
    }


def test_evaluations_of_other_boxes_are_refused():
    with pytest.raises(ValueError, match="3 and 7 boxes"):
        paired.compare(A[:3], B)
    other = [dict(r) for r in B]
    other[2]["com_cm"] = [9.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="box 2 differs"):
        paired.compare(A, other)


def test_the_script_pairs_directories_and_refuses_bad_input(tmp_path, capsys):
    dirs = []
    for name, rows in (("a", A), ("b", B)):
        d = tmp_path / name
        d.mkdir()
        (d / "evaluation.json").write_text(json.dumps({"rows": rows}))
        dirs.append(str(d))
    out = compare_evaluations.main([*dirs, *dirs, "--plot", str(tmp_path / "m.png")])
    assert len(out) == 3 and out[2]["pooled"] == 2 and out[2]["turned"] == {"a": 4, "b": 6}
    assert (tmp_path / "m.png").stat().st_size > 0
    compare_evaluations.main([*dirs, "--plot", str(tmp_path / "t.png"), "--turn"])
    assert (tmp_path / "t.png").stat().st_size > 0
    old = tmp_path / "old"
    old.mkdir()
    rows = [{k: v for k, v in r.items() if k != "turn_min_stability_margin_m"} for r in A]
    (old / "evaluation.json").write_text(json.dumps({"rows": rows}))
    for argv, msg in (
        ([dirs[0]], "in pairs"),
        ([dirs[0], str(tmp_path)], "no evaluation.json"),
        ([*dirs, "--plot", str(tmp_path / "nowhere" / "m.png")], "cannot be written"),
        ([*dirs, "--turn"], "give --plot"),
        ([str(old), str(old), "--plot", str(tmp_path / "o.png"), "--turn"], "no box has a turn's margin"),
    ):
        with pytest.raises(SystemExit) as e:
            compare_evaluations.main(argv)
        assert e.value.code == 2 and msg in capsys.readouterr().err
