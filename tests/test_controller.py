"""The controlled episode: explore -> estimate -> refuse or rotate (oracle estimator)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import run_episode
from boxjax.estimator.belief import hazard_explanation

CFG = DEFAULT


def test_oracle_turns_uniform_box():
    res = run_episode(CFG, massdist.named("uniform", CFG.box), jax.random.PRNGKey(0))
    s = res.summary
    assert s["success"] and not s["aborted"], s
    assert s["max_balance_error_m"] <= CFG.task.balance_limit
    assert abs(s["final_yaw_error_rad"]) <= CFG.task.yaw_tolerance
    assert s["exploration_steps"] == 45 and s["steps"] > 45
    assert np.isfinite(res.trace.actions).all()
    assert s["plan_ms_median"] is not None and s["plan_ms_median"] > 0


def test_hazardous_distribution_is_refused_after_exploration():
    d = massdist.named("D", CFG.box)
    res = run_episode(CFG, d, jax.random.PRNGKey(0))
    s = res.summary
    assert s["aborted"] and not s["success"]
    assert s["steps"] == s["exploration_steps"] == 45  # refused right after exploring
    assert "U4" in s["abort_reason"] and "centre of mass" in s["abort_reason"]


def test_hazard_explanation_names_region_and_centre_of_mass():
    assert hazard_explanation(massdist.named("A", CFG.box), CFG) is None
    why = hazard_explanation(massdist.named("D", CFG.box), CFG)
    assert "hazardous" in why and "cm" in why


def test_estimator_slot_is_used():
    """The controller acts on what the estimator believes, not on the truth."""
    truth = massdist.named("uniform", CFG.box)
    believed_d = lambda exploration: {"distribution": massdist.named("D", CFG.box), "hazardous": True}  # noqa: E731
    res = run_episode(CFG, truth, jax.random.PRNGKey(0), estimator=believed_d)
    assert res.summary["aborted"] and not res.summary["truth_hazardous"]


def test_bad_controller_options_raise():
    with pytest.raises(ValueError, match="rule"):
        ControllerConfig(rule="best-guess")
    with pytest.raises(ValueError, match="planner"):
        ControllerConfig(planner="cem")
    with pytest.raises(ValueError, match="variant"):
        ControllerConfig(variant="neural")


def test_papers_one_step_planner_turns_uniform_box():
    """The paper's planner (one-step Pareto random shooting) stays selectable and works on the easy box."""
    ctrl = ControllerConfig(planner="paper")
    res = run_episode(CFG, massdist.named("uniform", CFG.box), jax.random.PRNGKey(0), ctrl=ctrl)
    assert res.summary["success"], res.summary
