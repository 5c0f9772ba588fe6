"""`boxjax reproduce`: the quick run's report has every table and figure, and its numbers are results.json's;
bad input (a non-empty --out, a missing weight file) is refused; an interrupted run leaves no report.

The report's checks run in the default suite on a recorded quick run (tests/data/reproduce_quick_results.json,
rendered again by `report.render`), and behind the slow marker on a fresh `reproduce --quick` (74 s of the
default suite's time on 2 cores, nearly all of it compiling programs other tests compile too). Regenerate the
record after changing what results.json holds: `boxjax reproduce --out DIR --quick`, then copy
DIR/results.json."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from boxjax.cli import main
from boxjax.experiments import comparison, reproduce

# The paper's own numbers (Tables 1 and §4.3 of Salehi & Doncieux 2024), written out here, not read from
# boxjax, so that a wrong constant in the code fails the test.
PAPER_T1 = {
    ("A", "prior"): ("100 %", "238.8"),
    ("A", "blackbox"): ("100 %", "367.4"),
    ("B", "prior"): ("100 %", "389.2"),
    ("B", "blackbox"): ("100 %", "269.6"),
    ("C", "prior"): ("100 %", "527.8"),
    ("C", "blackbox"): ("60 %", "401.0"),
    ("D", "prior"): ("aborts", "-"),
    ("D", "blackbox"): ("0 %", "-"),
}
METHOD_CELL = {"physical priors (learned H)": "prior", "black box W (baseline)": "blackbox"}


def _sections(md: str) -> dict[str, str]:
    """{'## heading' text: its body up to the next '## ' heading}."""
    parts = re.split(r"^(## .*)$", md, flags=re.M)
    return {parts[i].strip(): parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def _tables(text: str) -> list[list[dict]]:
    """The markdown tables of `text`, each a list of {column header: cell}."""
    out, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and re.match(r"^\|( --- \|)+$", lines[i + 1]):
            head = [c.strip() for c in lines[i].strip("|").split("|")]
            rows, i = [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                cells = [c.strip() for c in lines[i].strip("|").split("|")]
                rows.append(dict(zip(head, cells, strict=True)))
                i += 1
            out.append(rows)
        else:
            i += 1
    return out


def _section(md, start):
    found = [body for head, body in _sections(md).items() if head.startswith(start)]
    assert len(found) == 1, f"report has no single section starting {start!r}"
    return found[0]


def _num(cell: str) -> float:
    return float(re.match(r"^[-+]?\d+(\.\d+)?", cell).group(0))


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    import jax

    out = tmp_path_factory.mktemp("reproduce") / "out"
    cache = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    # The command keeps compiled programs on disk: in the session's folder (tests/conftest.py), where the
    # modules before it left the planners they compiled; nothing is written to the user's cache.
    try:
        assert main(["reproduce", "--out", str(out), "--quick", "--json"]) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", cache[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", cache[1])
    with open(out / "results.json") as f:
        results = json.load(f)
    return out, results, (out / "report.md").read_text()


RECORDED = Path(__file__).parent / "data" / "reproduce_quick_results.json"


@pytest.fixture(scope="module")
def recorded():
    """A quick run's results.json, recorded (2026-12-06), and the report rendered from it now."""
    from boxjax.experiments import report

    results = json.loads(RECORDED.read_text())
    return None, results, report.render(results)


@pytest.fixture(params=["recorded", pytest.param("quick", marks=pytest.mark.slow)])
def run(request):
    """(the output folder or None, results, report.md) of the recorded or of a fresh quick run."""
    return request.getfixturevalue(request.param)


def test_recorded_run_is_a_quick_run_of_every_part():
    res = json.loads(RECORDED.read_text())
    assert res["mode"]["quick"] and set(res["wall_s"]) == {*reproduce.PARTS, "total"}


def test_quick_report_has_every_table_and_figure(run):
    out, res, md = run
    for start in (
        "## Table 1",
        "## Table 2",
        "## §4.3",
        "## Fig. 3 (a, b)",
        "## Data efficiency",
        "## Machine, versions, seeds",
    ):
        _section(md, start)
    assert "### Fig. 3 (c)" in md and "### Fig. 2 (c, d)" in md
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    figures = [res["validation"]["fig3c"], res["validation"]["fig2"]["figure"], res["force_map"]["figure"]]
    if res["data_efficiency"]["measured"]:
        figures.append(res["data_efficiency"]["figure"])
    else:
        assert "python -m boxjax.experiments.data_efficiency" in _section(md, "## Data efficiency")
    assert sorted(links) == sorted(figures)
    for link in links:
        assert not link.startswith("/"), "figures are linked relative to the report"
        if out is not None:  # a fresh run: the figures are there
            assert (out / link).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert res["command"].startswith("boxjax reproduce --out ") and f"`{res['command']}`" in md
    assert res["reductions"] and all(r in md for r in res["reductions"])  # quick says what it left out


def test_quick_table1_numbers_are_the_results(run):
    _, res, md = run
    body = _section(md, "## Table 1")
    agg, episodes = _tables(body)
    assert len(agg) == len(res["table1"]["table"]) and len(episodes) == len(res["table1"]["rows"])
    by_key = {(r["box"], r["method"]): r for r in res["table1"]["table"]}
    for row in agg:
        key = (row["box"], METHOD_CELL[row["method"]])
        r = by_key.pop(key)
        ok, n = (int(x) for x in row["success"].split("/"))
        assert n == r["episodes"] and ok / n == pytest.approx(r["success_ratio"])
        assert int(row["refused"]) == r["refused"]
        if r["mean_steps_successes"] is None:
            assert row["steps"] == "-"
        else:
            assert _num(row["steps"]) == pytest.approx(r["mean_steps_successes"], abs=0.05)
        if r["worst_balance_m"] is not None:
            assert _num(row["worst balance"]) == pytest.approx(100 * r["worst_balance_m"], abs=0.005)
        assert _num(row["wall s / episode"]) == pytest.approx(r["mean_wall_s"], abs=0.05)
        assert (row["paper success"], row["paper steps"]) == PAPER_T1[key]
    assert not by_key
    for row, r in zip(episodes, res["table1"]["rows"], strict=True):
        assert (row["box"], row["method"], int(row["seed"])) == (r["box"], r["method"], r["seed"])
        assert (row["outcome"], int(row["steps"])) == (r["outcome"], r["steps"])
    # the quick run's boxes: the prior refuses D, and its rows came from the batched path
    prior_d = [r for r in res["table1"]["rows"] if r["box"] == "D" and r["method"] == "prior"]
    assert prior_d and all(r["outcome"] == "refused" and r["batched"] for r in prior_d)


def test_quick_table2_validation_and_timing_numbers_are_the_results(run):
    _, res, md = run
    (t2,) = _tables(_section(md, "## Table 2"))
    assert [int(r["transitions"]) for r in t2] == [r["transitions"] for r in res["table2"]["rows"]]
    (val,) = _tables(_section(md, "## §4.3"))
    first, whole = val
    for row, s in ((first, res["validation"]["first"]), (whole, res["validation"]["summary"])):
        assert row["safe turned"] == f"{s['safe_success']}/{s['safe_boxes']}"
        assert _num(row["rate"]) == pytest.approx(100 * s["safe_success_rate"], abs=0.05)
        lo, hi = (float(x) for x in row["95 % CI (Wilson)"].rstrip(" %").split("-"))
        assert (lo, hi) == pytest.approx([100 * x for x in s["safe_success_ci95"]], abs=0.05)
        assert int(row["false aborts"]) == s["false_aborts"]
    s = res["validation"]["summary"]
    assert whole["hazardous refused"] == f"{s['hazard_aborted']}/{s['hazardous_boxes']}"
    assert first["paper"] == "25/30 = 83.3 %"
    assert res["validation"]["first"]["safe_boxes"] == reproduce.QUICK.val_first
    # the first safe boxes' row is computed from the first rows of the whole run (the same boxes)
    k = res["validation"]["first"]["safe_boxes"]
    turned = sum(r["outcome"] == "success" for r in res["validation"]["rows"][:k])
    assert res["validation"]["first"]["safe_success"] == turned
    assert f"IoU {res['validation']['fig2']['iou']:.3f}" in _section(md, "## §4.3")
    # wall time per part, as measured
    header = _section(md, "## Machine, versions, seeds")
    tables = _tables(header)
    machine = {r["item"]: r["value"] for r in tables[0]}
    assert machine["cores"] == str(res["machine"]["cores"])
    load = [float(x) for x in machine["load average at start (1 / 5 / 15 min)"].split(" / ")]
    assert load == pytest.approx(res["machine"]["load_average"], abs=0.005)
    walls = {r["part"]: float(r["wall s"]) for r in tables[1]}
    assert walls == pytest.approx(res["wall_s"], abs=0.05)
    assert set(walls) == {*reproduce.PARTS, "total"}
    fm = res["force_map"]
    (forces,) = _tables(_section(md, "## Fig. 3 (a, b)"))
    for row in forces:
        lo, hi = (float(x.strip().rstrip(" N")) for x in row["mean range"].split(".."))
        assert [lo, hi] == pytest.approx(fm["forces"][row["force"]]["mean_range_N"], abs=0.005)


def test_non_empty_out_is_refused_without_force(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    assert main(["reproduce", "--out", str(out), "--quick"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--force" in err[0] and str(out) in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    (tmp_path / "afile").write_text("x")
    assert main(["reproduce", "--out", str(tmp_path / "afile")]) == 2
    assert "is a file" in capsys.readouterr().err


@pytest.mark.parametrize(
    "module, attr, command",
    [
        ("blackbox.baseline", "shipped_path", "boxjax train-baseline --episodes 200"),
        ("estimator.shipped", "SHIPPED_WEIGHTS", "boxjax train-estimator"),
        ("prior.force_map", "SHIPPED_CALIBRATION", "boxjax calibrate --transitions 2000"),
        ("blackbox.pets", "shipped_path", "python -m boxjax.training.pets"),
    ],
)
def test_missing_weight_file_is_named_with_its_command(tmp_path, capsys, monkeypatch, module, attr, command):
    import importlib

    mod = importlib.import_module(f"boxjax.{module}")
    missing = tmp_path / "gone.npz"
    monkeypatch.setattr(mod, attr, (lambda: str(missing)) if attr == "shipped_path" else missing)
    out = tmp_path / "out"
    assert main(["reproduce", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and command in err[0]
    assert not out.exists()


def _stub_parts(monkeypatch, failing: str):
    """Parts that return at once, `failing` raising (an interrupted run)."""

    def boom(*a, **k):
        raise RuntimeError("interrupted")

    for name in reproduce.PARTS:
        monkeypatch.setattr(reproduce, name, boom if name == failing else (lambda *a, **k: {}))


def test_interrupted_run_leaves_no_report(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.md").write_text("an old report")
    (out / "results.json").write_text("{}")
    _stub_parts(monkeypatch, "validation")
    with pytest.raises(RuntimeError, match="interrupted"):
        reproduce.run(out, quick=True, force=True)
    assert not (out / "report.md").exists() and not (out / "results.json").exists()
    # a writer that fails after every part ran leaves no report either (both files are written last)
    _stub_parts(monkeypatch, "none")
    monkeypatch.setattr(reproduce, "_relative", lambda r, o: r)
    from boxjax.experiments import report

    monkeypatch.setattr(report, "render", lambda r: (_ for _ in ()).throw(RuntimeError("interrupted")))
    with pytest.raises(RuntimeError, match="interrupted"):
        reproduce.run(out, quick=True, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["figures"]


def test_batched_prior_rows_are_prior_episode_rows():
    """Table 1's batched prior episodes give the one-box rows' fields; on D (refused after exploring, no
    planning) the same outcome, steps and worst balance (the physics is bit-identical)."""
    from boxjax.config import DEFAULT

    one = comparison.prior_episode(DEFAULT, "D", 0)
    (batched,) = comparison.prior_episodes(DEFAULT, [("D", 0)])
    assert set(batched) == set(one) | {"batched"}
    for k in ("outcome", "steps", "max_balance_error_m", "success"):
        assert batched[k] == one[k], k
    assert one["outcome"] == "refused"


@pytest.mark.slow
def test_quick_retrain_uses_its_own_weights(tmp_path):
    """--quick --retrain makes a calibration, H and W into OUT/weights and runs every part with them
    (about 3.5 min on 2 loaded cores)."""
    import jax

    out = tmp_path / "out"
    cache = jax.config.jax_compilation_cache_dir
    try:
        assert main(["reproduce", "--out", str(out), "--quick", "--retrain", "--json"]) == 0
    finally:
        jax.config.update("jax_compilation_cache_dir", cache)
    res = json.loads((out / "results.json").read_text())
    q = reproduce.QUICK
    assert res["mode"] == {"quick": True, "retrain": True}
    assert res["retrain"]["estimator"]["boxes"] == q.h_boxes
    assert res["retrain"]["baseline"]["episodes"] == q.w_episodes
    for name in ("calibration.npz", "h/estimator.npz", "w/baseline.npz"):
        assert (out / "weights" / name).is_file()
    h_row, w_row = res["table2"]["rows"]  # no PETS row: PETS is not retrained
    assert h_row["transitions"] == res["retrain"]["estimator"]["transitions"] == 45 * q.h_boxes
    assert w_row["transitions"] == res["retrain"]["baseline"]["transitions"]
    assert res["force_map"]["file"] == str(out / "weights" / "calibration.npz")
    assert res["force_map"]["refit_max_abs_mean_diff_N"] == 0.0  # its own samples, not collected again
    md = (out / "report.md").read_text()
    assert "### Retrained weights (--retrain)" in md
    assert any("--retrain: H on" in r for r in res["reductions"])


def test_data_efficiency_curve_is_guarded(tmp_path, monkeypatch):
    """Without its results file, with an unreadable one or without the module, the part says the curve was
    not measured and names the command that measures it; the report says so too."""
    import sys

    from boxjax.experiments import report

    monkeypatch.setattr(reproduce, "DATA_EFFICIENCY_JSON", tmp_path / "missing.json")
    res = reproduce.data_efficiency(str(tmp_path))
    assert not res["measured"] and "does not exist" in res["reason"]
    text = "\n".join(report._data_efficiency(res))
    assert "Not measured" in text and "`python -m boxjax.experiments.data_efficiency`" in text
    bad = tmp_path / "bad.json"
    bad.write_text('{"H": [')
    monkeypatch.setattr(reproduce, "DATA_EFFICIENCY_JSON", bad)
    assert "cannot be read" in reproduce.data_efficiency(str(tmp_path))["reason"]
    bad.write_text('{"H": []}')
    import boxjax.experiments

    monkeypatch.setitem(sys.modules, "boxjax.experiments.data_efficiency", None)  # the module is not there
    monkeypatch.delattr(boxjax.experiments, "data_efficiency", raising=False)
    res = reproduce.data_efficiency(str(tmp_path))
    assert not res["measured"] and "cannot be imported" in res["reason"]
    assert not list(tmp_path.glob("*.png"))
