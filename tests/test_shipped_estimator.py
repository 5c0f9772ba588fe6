"""The shipped estimator weights (boxjax/data/estimator.npz): where they came from, that they still reach
the accuracy reported in boxjax/data/estimator_report.json on fresh boxes, and that bad files are refused."""

from __future__ import annotations

import json
import os
import shutil

import jax
import pytest

from boxjax import estimator as E
from boxjax import massdist
from boxjax.config import DEFAULT, BoxConfig
from boxjax.estimator import explore
from boxjax.estimator import shipped as S
from boxjax.sim import make_env
from boxjax.training import estimator as P

CFG = DEFAULT


@pytest.fixture(scope="module")
def reported():
    with open(S.SHIPPED_REPORT) as f:
        return json.load(f)


@pytest.fixture(scope="module")
def fresh():
    """150 fresh boxes (a seed neither training nor the reported evaluation used)."""
    return P.evaluate_estimator(7, 150, None, CFG, progress=False)


def test_shipped_weights_provenance(reported):
    assert os.path.getsize(S.SHIPPED_WEIGHTS) <= 10 * 2**20
    model = S.default_estimator(CFG)
    assert model is S.default_estimator(CFG)  # loaded once
    assert tuple(model.box.grid) == tuple(CFG.box.grid) and model.n_steps == explore.N_STEPS
    prov = model.provenance
    # the shipped H was trained when the pipeline was boxjax.estimator_pipeline (renamed in the 0.1 layout)
    assert prov["trained_by"] in (
        "boxjax.training.estimator.train_estimator",
        "boxjax.estimator_pipeline.train_estimator",
    )
    assert prov["seed"] == reported["training"]["seed"] and prov["n_boxes"] == reported["training"]["boxes"]
    assert prov["config"]["box"]["grid"] == list(CFG.box.grid)
    assert model.cfg == E.EstimatorConfig.from_dict(reported["training"]["training"]["estimator_config"])
    assert model.hazard_threshold == reported["heldout"]["hazard_threshold"]


def test_shipped_weights_reach_the_reported_accuracy(fresh, reported):
    """Within the noise of 150 boxes (about 40 hazardous) around the 500-box held-out report."""
    ref = reported["heldout"]
    assert set(P.METRIC_KEYS) <= set(fresh) and fresh["boxes"] == 150
    assert fresh["iou_median"] >= ref["iou_median"] - 0.06
    assert fresh["mass_rel_error_median"] <= ref["mass_rel_error_median"] + 0.03
    assert fresh["com_error_cm_median"] <= ref["com_error_cm_median"] + 0.5
    assert fresh["hazard_recall"] >= 0.93
    assert fresh["hazard_precision"] >= ref["hazard_precision"] - 0.2


def test_named_boxes_hazard_decisions():
    """D (all mass over the right belt) is refused; uniform, A, B, C are not; masses within 10 %."""
    model = S.default_estimator(CFG)
    env = make_env(CFG, "native")
    for name in ("uniform", "A", "C", "D"):
        dist = massdist.named(name, CFG.box)
        state = env.reset(jax.random.PRNGKey(0), dist)
        state, traj, final = explore.run(env, state)
        out = E.estimate(model, traj, final)
        assert out["hazardous"] == (name == "D"), name
        assert abs(out["total_mass"] - float(dist.total_mass)) < 0.1 * float(dist.total_mass), name


def test_shipped_weights_refuse_bad_input(tmp_path):
    model = S.default_estimator(CFG)
    with pytest.raises(E.CheckpointError, match="grid"):
        E.load(S.SHIPPED_WEIGHTS, expected_box_config=BoxConfig(grid=(12, 12, 4)))
    with pytest.raises(E.CheckpointError, match="grid"):
        S.default_estimator(CFG.replace(box=BoxConfig(grid=(12, 12, 4))))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(S.SHIPPED_WEIGHTS.read_bytes()[: 2**20])
    with pytest.raises(E.CheckpointError, match="corrupt|truncated"):
        E.load(cut)
    with pytest.raises(E.CheckpointError, match="corrupt|truncated"):
        P.evaluate_estimator(0, 2, cut, CFG, progress=False)
    copy = tmp_path / "copy.npz"
    shutil.copyfile(S.SHIPPED_WEIGHTS, copy)
    assert E.load(copy, expected_box_config=CFG.box).cfg == model.cfg
    # A trajectory of the wrong length or with NaN: a clear error, never a silent prediction.
    traj = jax.numpy.zeros((explore.N_STEPS, explore.N_TRAJ_COLUMNS))
    final = jax.numpy.zeros(5)
    with pytest.raises(ValueError, match="44 steps"):
        E.estimate(model, traj[:44], final)
    with pytest.raises(ValueError, match="NaN"):
        E.estimate(model, traj.at[3, 2].set(jax.numpy.nan), final)
