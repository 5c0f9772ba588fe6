"""Robust planning over the belt friction (`ControllerConfig.friction_set`): one physics prior per
friction coefficient in a `planning.Mixture`, the sampling planner scoring each candidate over them."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from boxjax import massdist, planning
from boxjax.config import DEFAULT as CFG
from boxjax.control.config import ControllerConfig
from boxjax.control.models import planning_model
from boxjax.prior import PriorParams

FRICTIONS = (0.35, 0.5, 0.65)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"friction_set": (0.5,)}, "two or more"),
        ({"friction_set": (0.3, -0.1)}, "friction coefficients"),
        ({"friction_set": [0.3, 0.6]}, "tuple"),
        ({"friction_set": FRICTIONS, "planner": "paper"}, "sampling planner"),
        (
            {"friction_set": FRICTIONS, "prior_params": (PriorParams(), PriorParams(n_substeps=4))},
            "one prior",
        ),
    ],
)
def test_a_friction_set_the_planner_cannot_use_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ControllerConfig(**kwargs)


def test_the_planner_plans_over_one_prior_per_friction_on_the_same_box():
    box = massdist.named("C", CFG.box)
    model = planning_model(CFG, ControllerConfig(friction_set=FRICTIONS), box)
    plain = planning_model(CFG, ControllerConfig(), box)
    assert isinstance(model, planning.Mixture) and planning.n_particles(model) == 3
    assert [m.gripper.friction for m in model.members] == list(FRICTIONS)
    for m in model.members:  # the box is the same: only the friction differs
        np.testing.assert_array_equal(np.asarray(m.masses), np.asarray(plain.masses))
        assert m.params == plain.params and m.box == plain.box
    # the member with the gripper's own friction predicts exactly what the plain prior does, and the
    # friction changes the prediction of a box slipping on belts driven apart
    window = planning.initial_window(np.array([-0.1, 0.1, 0.0, 0.0, 0.0], np.float32))
    belt, acts = np.zeros(2, np.float32), np.tile(np.array([0.12, -0.12, 0.0, 0.0], np.float32), (6, 1))
    rolls = model.rollout_particles(None, window, belt, acts)
    np.testing.assert_allclose(rolls[1], plain.rollout_sequence(window, belt, acts), atol=1e-6)
    assert not np.allclose(rolls[0], rolls[2], atol=1e-4)


@pytest.mark.slow  # 18 s of the default suite, nearly all compiling; the planner over the set is tested above
def test_an_episode_plans_over_the_friction_set():
    from boxjax.control.episode import run_episode
    from boxjax.planners.sampling import SamplingOptions
    from boxjax.sim.faults import Faults

    ctrl = ControllerConfig(
        friction_set=FRICTIONS, sampling=SamplingOptions(gradient_steps=0, particle_risk="worst")
    )
    res = run_episode(CFG, massdist.named("A", CFG.box), jax.random.PRNGKey(1), ctrl=ctrl, max_steps=70,
                      faults=Faults(friction=0.65))  # fmt: skip
    assert np.all(np.isfinite(res.trace.actions)) and len(res.trace.actions) == 70
