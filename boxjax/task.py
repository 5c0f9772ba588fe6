"""The rotation task: rewards R1, R2 (paper eq. 1), and the success / failure rules.

Rules (docs/design.md#task-rules):
- success: |yaw - target| <= yaw_tolerance while the balance error never exceeded balance_limit;
- failure: balance error above balance_limit, box off the belts (fell or slid past a belt's end),
  box tipped beyond tip_limit, or the step cap reached (and, inside jit where no error can be raised, a
  non-finite action: `invalid_action`);
- an episode ends at its first success or failure. Failure wins a tie (a step that both reaches the
  target and breaks the balance limit is a failure).
"""

from __future__ import annotations

import jax.numpy as jnp

from boxjax.config import TaskConfig
from boxjax.geometry import YAW, balance_error

# Why an episode ended. Integers so they live inside jitted state; names for people.
RUNNING, SUCCESS, UNBALANCED, OFF_BELTS, TIPPED, STEP_CAP, INVALID_ACTION = range(7)
REASONS = ("running", "success", "unbalanced", "off_belts", "tipped", "step_cap", "invalid_action")


def yaw_error(s, target_yaw):
    """Signed yaw error (rad) of the planar state s (5,) to the target.

    Not wrapped: the state's yaw is continuous over an episode (see sim.core.planar_state), so turning
    the wrong way round never reaches the target.
    """
    return s[YAW] - target_yaw


def reward_pose(s, target_yaw, task: TaskConfig):
    """R1 = 1 / (yaw_error^2 + eps) (paper eq. 1, planar rotation as the minimal representation)."""
    return 1.0 / (yaw_error(s, target_yaw) ** 2 + task.reward_eps)


def reward_balance(s, task: TaskConfig):
    """R2 = 1 / (balance_error^2 + eps) (paper eq. 1)."""
    return 1.0 / (balance_error(s) ** 2 + task.reward_eps)


def status(s, target_yaw, t, off_belts, tipped, task: TaskConfig):
    """Reason code for the state reached after control step t (1-based count of steps taken).

    Args:
      s: (5,) planar state after the step.
      target_yaw: rad.
      t: number of control steps taken so far (int array).
      off_belts, tipped: bool arrays from the simulator.
    Returns:
      int32 reason code (RUNNING if the episode goes on).
    """
    unbalanced = balance_error(s) > task.balance_limit
    reached = jnp.abs(yaw_error(s, target_yaw)) <= task.yaw_tolerance
    code = jnp.where(t >= task.max_steps, STEP_CAP, RUNNING)
    code = jnp.where(reached, SUCCESS, code)
    code = jnp.where(tipped, TIPPED, code)
    code = jnp.where(off_belts, OFF_BELTS, code)
    code = jnp.where(unbalanced, UNBALANCED, code)
    return code.astype(jnp.int32)
