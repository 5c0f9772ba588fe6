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


def test_a_late_loop_slows_the_sampling_planner_by_the_delay_rule(monkeypatch):
    """Past `delay_reference` steps of delay the sampling planner's caps shrink by (1 + ref) / (1 + delay);
    at or under it, with the paper planner or with the rule off, the controller is unchanged. The
    episode builds its planner from the world's delay (4 steps of sensor latency here)."""
    from boxjax.control import episode
    from boxjax.control.config import for_delay
    from boxjax.planners import sampling
    from boxjax.sim.faults import Faults

    ctrl = ControllerConfig()
    assert for_delay(CFG, ctrl, 2) is ctrl and for_delay(CFG, ctrl, 0) is ctrl
    assert for_delay(CFG, ControllerConfig(planner="paper"), 9).planner == "paper"
    assert for_delay(CFG, ControllerConfig(delay_reference=None), 9).sampling is None
    late = for_delay(CFG, ctrl, 4).sampling
    assert late.speed_cap == pytest.approx(0.12 * 3 / 5)
    assert late.position_cap == pytest.approx(CFG.gripper.max_position_step * 3 / 5)
    assert late.horizon == sampling.SamplingOptions().horizon  # the rest of the options kept
    hi = np.asarray(
        sampling.clip_actions(np.full(4, 1.0, np.float32), CFG, late.speed_cap, 0.0, late.position_cap)
    )
    np.testing.assert_allclose(hi, [late.speed_cap, late.speed_cap, late.position_cap, late.position_cap])
    with pytest.raises(ValueError, match="delay_reference"):
        ControllerConfig(delay_reference=-1)
    with pytest.raises(ValueError, match="position_cap"):
        sampling.SamplingOptions(position_cap=0.0)

    built = []

    class Built(Exception):
        pass

    def spy(cfg, c):
        built.append(c)
        raise Built

    monkeypatch.setattr(episode, "make_planner", spy)
    with pytest.raises(Built):
        run_episode(
            CFG, massdist.named("uniform", CFG.box), jax.random.PRNGKey(0), faults=Faults(obs_latency=4)
        )
    assert built[0].sampling.position_cap == pytest.approx(late.position_cap)
