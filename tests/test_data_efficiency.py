"""The data-efficiency curve (boxjax/data_efficiency.py): W's episode subsets, the curve file's schema,
the figure, and one tiny W point end to end (a tiny W, a short step cap)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from boxjax.blackbox import baseline
from boxjax.config import DEFAULT
from boxjax.experiments import data_efficiency as D
from boxjax.experiments import evaluation as experiments
from boxjax.training import baseline as T


def _dataset(path, episodes: int = 10, steps: int = 30) -> dict:
    """A W dataset file (baseline_train's format) of `episodes` short synthetic episodes of box A's
    kinds in baseline_train's order; the states drift slowly so that every transition is valid."""
    rng = np.random.default_rng(0)
    eps = []
    for i in range(episodes):
        s0 = np.array([-0.1, 0.1, 0.0, 0.0, 0.0])
        s = s0 + np.cumsum(rng.normal(0, 1e-4, (steps + 1, 5)), axis=0)
        b = np.zeros((steps + 1, 2))
        eps.append({"s": s, "belt_speed": b, "actions": np.zeros((steps, 4)), "outcome": "step_cap", "i": i})
    tr = T.transitions_of(eps)
    kinds = np.array([T.KINDS[i % len(T.KINDS)] for i in range(episodes)])
    np.savez(path, **tr, episode_kind=kinds, episode_outcome=np.array([f"o{i}" for i in range(episodes)]))
    return T.load_dataset(path)


def test_w_episodes_are_the_first_n_in_the_datasets_order(tmp_path):
    tr = _dataset(tmp_path / "d.npz")
    sub = D.w_episodes(tr, 5)
    assert sorted(np.unique(sub["episode"])) == [0, 1, 2, 3, 4]
    assert sub["action"].shape[0] == int(np.sum(tr["episode"] < 5)) < tr["action"].shape[0]
    assert list(sub["episode_kind"]) == ["prior", "prior", "prior-noisy", "prior-noisy", "random"]
    assert list(sub["episode_outcome"]) == ["o0", "o1", "o2", "o3", "o4"]
    for k in ("window", "belt_speed", "s_next"):  # the rows kept together
        np.testing.assert_array_equal(sub[k], tr[k][tr["episode"] < 5])
    assert D.w_episodes(tr, 10)["action"].shape[0] == tr["action"].shape[0]
    for bad in (1, 11):
        with pytest.raises(ValueError, match="2 <= episodes <= 10"):
            D.w_episodes(tr, bad)


def _point(name: str, size: int, k: int, shipped: bool = False) -> dict:
    lo, hi = experiments.wilson_interval(k, 30)
    p = {"transitions": size * (45 if name == "H" else 340), "safe_success": k, "safe_boxes": 30}
    p.update(ci95=[lo, hi], train_s=1.0, eval_s=2.0, shipped=shipped)
    return {**p, "boxes": size} if name == "H" else {**p, "episodes": size, "adapt_every": 20}


def _doc() -> dict:
    return {
        "H": [_point("H", 100, 0), _point("H", 2000, 20), _point("H", 288000, 27, True)],
        "W": [_point("W", 10, 3), _point("W", 200, 21, True)],
        "eval_seed": 0,
        "command": "test",
    }


def test_curve_file_schema_round_trip_and_refusals(tmp_path):
    path = D.write_curve(_doc(), tmp_path / "c.json")
    with open(path) as f:
        back = json.load(f)
    assert D.check_curve(back) == _doc()
    for name, keys in (("H", D.H_KEYS), ("W", D.W_KEYS)):
        assert set(keys) <= set(back[name][0])
    doc = _doc()
    del doc["W"][1]["adapt_every"]
    with pytest.raises(ValueError, match=r"W\[1\] lacks \['adapt_every'\]"):
        D.write_curve(doc, tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()
    doc = _doc()
    doc["H"][0]["safe_success"] = 31
    with pytest.raises(ValueError, match="impossible count"):
        D.check_curve(doc)
    with pytest.raises(ValueError, match="missing 'eval_seed'"):
        D.check_curve({"H": [], "W": [], "command": "x"})


def test_format_table_has_one_row_per_point():
    lines = D.format_table(_doc()).splitlines()
    assert len(lines) == 2 + 5
    assert "| prior MPC + H | 288,000 boxes (shipped) | 12,960,000 | 27/30 |" in lines[4]
    assert "| W | 10 episodes, adapted every 20 | 3,400 | 3/30 |" in lines[5]


def test_plot_curve_writes_a_png_and_plot_only_redraws_it(tmp_path):
    path = D.plot_curve(_doc(), tmp_path / "c.png")
    with open(path, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    assert D.plot_curve({**_doc(), "W": []}, tmp_path / "h_only.png")  # one line alone draws too
    D.write_curve(_doc(), tmp_path / "c.json")
    argv = ["--out", str(tmp_path / "c.json"), "--plot", str(tmp_path / "again.png"), "--plot-only"]
    assert D.main(argv) == 0 and (tmp_path / "again.png").stat().st_size > 10000


TINY_W = baseline.BaselineConfig(hidden=(16,), epochs=1)


def test_w_point_counts_what_random_safe_returns(tmp_path, monkeypatch):
    """W trained on the first 4 of 5 episodes; the evaluation replaced by two known rows."""
    from boxjax.experiments import comparison

    _dataset(tmp_path / "d.npz", episodes=5)
    seen = {}

    def fake_random_safe(cfg, n, seed, methods, model, adapt_every, progress):
        seen.update(n=n, seed=seed, methods=methods, adapt_every=adapt_every, model=model)
        row = {"wall_s": 2.0, "adapt_s": 0.5}
        return [
            {**row, "success": True, "outcome": "success"},
            {**row, "success": False, "outcome": "unbalanced"},
        ]

    monkeypatch.setattr(comparison, "random_safe", fake_random_safe)
    p = D.w_point(4, str(tmp_path / "d.npz"), 7, adapt_every=20, n_eval=2, config=TINY_W, progress=False)
    assert (
        seen["n"] == 2
        and seen["seed"] == 7
        and seen["methods"] == ("blackbox",)
        and seen["adapt_every"] == 20
    )
    assert isinstance(seen["model"], baseline.BlackBoxModel)
    assert (p["safe_success"], p["safe_boxes"], p["failures"]) == (1, 2, {"unbalanced": 1})
    assert p["ci95"] == list(experiments.wilson_interval(1, 2)) and p["adapt_every"] == 20
    assert p["episodes_by_kind"] == {"prior": 2, "prior-noisy": 2}  # the first 4: no random episode yet
    assert p["train_transitions"] + p["heldout_transitions"] == p["transitions"] == 4 * 30
    assert p["heldout_transitions"] == 30  # one of 4 episodes held out, as train_baseline splits
    assert set(D.W_KEYS) <= set(p) and p["episode_wall_s_mean"] == 2.0


@pytest.mark.slow
def test_a_tiny_w_point_end_to_end(tmp_path):
    """A W of one 16-unit layer trained 1 epoch on 4 synthetic episodes, on 2 random safe boxes with a
    12-step cap and no adaptation, through the real episodes (~45 s, mostly compilation)."""
    _dataset(tmp_path / "d.npz", episodes=4)
    cfg = dataclasses.replace(DEFAULT, task=dataclasses.replace(DEFAULT.task, max_steps=12))
    p = D.w_point(4, str(tmp_path / "d.npz"), 0, cfg, adapt_every=0, n_eval=2, config=TINY_W, progress=False)
    assert set(D.W_KEYS) <= set(p) and p["episodes"] == 4 and p["adapt_every"] == 0
    assert p["safe_boxes"] == 2 and p["safe_success"] == 0  # 12 steps cannot turn a box
    assert sum(p["failures"].values()) == 2
    assert p["ci95"] == list(experiments.wilson_interval(0, 2))
