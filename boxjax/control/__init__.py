"""The controller: one episode (`run_episode`: explore, estimate, refuse or turn) and many at once
(`run_episodes`: worlds stepped together, the planner vmapped over boxes).

Modules: `config` (ControllerConfig), `models` (the model in the planner's slot, built from the belief),
`episode` (one episode), `batch` (batched episodes and their replay). The estimator slot's functions
(`learned_estimator`, `oracle_estimator`, `decide`) live in `boxjax.estimator.belief`, the planners by name
in `boxjax.planners.registry`; both are re-exported here for convenience.
"""

from boxjax.control.batch import replay_episode, run_episodes
from boxjax.control.config import BELIEFS, PLANNERS, ControllerConfig, for_delay
from boxjax.control.episode import (
    EpisodeResult,
    env_for,
    episode_summary,
    first_window,
    run_episode,
    timed_calls,
    true_stability_margins,
)
from boxjax.control.models import planning_model
from boxjax.estimator.belief import decide, hazard_explanation, learned_estimator, oracle_estimator
from boxjax.planners.registry import make_planner

__all__ = [
    "BELIEFS",
    "PLANNERS",
    "ControllerConfig",
    "EpisodeResult",
    "decide",
    "env_for",
    "episode_summary",
    "first_window",
    "for_delay",
    "hazard_explanation",
    "learned_estimator",
    "make_planner",
    "oracle_estimator",
    "planning_model",
    "replay_episode",
    "run_episode",
    "run_episodes",
    "timed_calls",
    "true_stability_margins",
]
