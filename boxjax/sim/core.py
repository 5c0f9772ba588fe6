"""Backend-independent pieces of one control step (pure jnp, one world; vmap for batches).

An action is a = (v1, v2, dp1, dp2):
- v1, v2: belt surface speed setpoints (m/s, along +x of the conveyor frame), |v_i| <= belt_speed_limit.
  The belt reaches the setpoint at no more than belt_accel_limit (MuJoCo enforces both, see model.py).
- dp1, dp2: belt position increments (m, along y), |dp_i| <= max_position_step per control step; the
  carriage position target P_i + dp_i is also clipped to the belt's range (p1_range / p2_range).
Values outside the limits are clipped and the state's `clipped` flag says so. Non-finite actions are
rejected on the host with a ValueError; inside jit/vmap (where raising is impossible) they stop the
belts where they are and end the episode with reason `invalid_action`.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, task
from boxjax.config import Config
from boxjax.sim.model import BELT1_V, BELT2_V, CARRIAGE1_P, CARRIAGE2_P, Ids

ACTION_NAMES = ("v1", "v2", "dp1", "dp2")
ACTION_UNITS = ("m/s", "m/s", "m", "m")


class State(NamedTuple):
    """One world's state after a control step (Brax style: a pytree, vmappable over worlds).

    physics: the backend's physics state (native: np.ndarray of mjSTATE_INTEGRATION; mjx: mjx.Data).
    model: the box's model (native: a mujoco.MjModel; mjx: dict of per-box fields, see model.BOX_FIELDS).
    s: (5,) planar state (P1, P2, x, y, yaw) in m, m, m, m, rad (conveyor frame).
    s1, s2: (nx, ny) float masks of bottom-layer voxels resting on belt 1 / belt 2 (paper eq. 2).
    belt_speed: (2,) belt surface speeds (m/s) as measured on the belt joints.
    p_target: (2,) carriage position targets (m).
    target_yaw: () rad.
    r1, r2: () rewards of paper eq. 1 at s.
    balance_error, max_balance_error: () m, now and the worst so far in the episode.
    t: () int32 control steps taken.
    reason: () int32, task.RUNNING while the episode goes on, else why it ended (task.REASONS).
    clipped: () bool, the last action was outside the limits and was clipped.
    """

    physics: Any
    model: Any
    s: Any
    s1: Any
    s2: Any
    belt_speed: Any
    p_target: Any
    target_yaw: Any
    r1: Any
    r2: Any
    balance_error: Any
    max_balance_error: Any
    t: Any
    reason: Any
    clipped: Any

    @property
    def done(self):
        return self.reason != task.RUNNING

    @property
    def success(self):
        return self.reason == task.SUCCESS

    def summary(self) -> dict:
        """Plain-Python summary of an unbatched state (for logs and `--json`)."""
        reason = int(self.reason)
        return {
            "steps": int(self.t),
            "state": {n: float(v) for n, v in zip(geometry.STATE_NAMES, np.asarray(self.s), strict=True)},
            "final_yaw_rad": float(self.s[geometry.YAW]),
            "final_yaw_error_rad": float(self.s[geometry.YAW] - self.target_yaw),
            "balance_error_m": float(self.balance_error),
            "max_balance_error_m": float(self.max_balance_error),
            "success": reason == task.SUCCESS,
            "done": reason != task.RUNNING,
            "failed_reason": None if reason in (task.RUNNING, task.SUCCESS) else task.REASONS[reason],
        }


def check_action(action) -> np.ndarray:
    """Host-side validation of one action; returns it as float64 (4,).

    Raises:
      ValueError: wrong shape, or NaN / inf (naming the offending components).
    """
    a = np.asarray(action, dtype=np.float64)
    if a.shape != (4,):
        raise ValueError(f"action must have shape (4,) = {ACTION_NAMES}, got shape {a.shape}")
    bad = [n for n, v in zip(ACTION_NAMES, a, strict=True) if not np.isfinite(v)]
    if bad:
        raise ValueError(f"action has non-finite components {bad}: {a.tolist()}")
    return a


def command(cfg: Config, action, act_speed, p_target):
    """Turn an action into actuator controls for the whole control step.

    Args:
      action: (4,) (v1, v2, dp1, dp2).
      act_speed: (2,) the belt actuators' current commanded speeds (their activation), m/s.
      p_target: (2,) current carriage targets, m.
    Returns:
      ctrl (4,) [belt1 accel, belt2 accel, carriage1 target, carriage2 target], new p_target (2,),
      clipped (bool), valid (bool: all components finite).
    """
    g = cfg.gripper
    valid = jnp.all(jnp.isfinite(action))
    action = jnp.where(valid, action, jnp.concatenate([act_speed, jnp.zeros(2)]))
    v = jnp.clip(action[:2], -g.belt_speed_limit, g.belt_speed_limit)
    dp = jnp.clip(action[2:], -g.max_position_step, g.max_position_step)
    lo = jnp.array([g.p1_range[0], g.p2_range[0]])
    hi = jnp.array([g.p1_range[1], g.p2_range[1]])
    new_target = jnp.clip(p_target + dp, lo, hi)
    clipped = jnp.any(v != action[:2]) | jnp.any(dp != action[2:]) | jnp.any(new_target != p_target + dp)
    # Constant acceleration over the step that lands exactly on the setpoint, or as close as the
    # acceleration limit allows (the actuator clamps ctrl to +-belt_accel_limit).
    accel = jnp.clip((v - act_speed) / g.control_dt, -g.belt_accel_limit, g.belt_accel_limit)
    ctrl = jnp.zeros(4)
    ctrl = ctrl.at[BELT1_V].set(accel[0]).at[BELT2_V].set(accel[1])
    ctrl = ctrl.at[CARRIAGE1_P].set(new_target[0]).at[CARRIAGE2_P].set(new_target[1])
    return ctrl, new_target, clipped, valid


def planar_state(idx: Ids, qpos, prev_yaw=0.0):
    """(5,) planar state (P1, P2, x, y, yaw) from qpos.

    The yaw is continuous over an episode (not wrapped): it is the angle closest to `prev_yaw` with the
    box's orientation, which is exact as long as the box turns less than pi per control step. A box that
    turns the wrong way by 3 pi / 2 therefore does not count as having turned by + pi / 2.
    """
    b = idx.box_qpos
    yaw = geometry.yaw_from_quat(qpos[b + 3 : b + 7])
    yaw = prev_yaw + geometry.wrap_angle(yaw - prev_yaw)
    return jnp.stack([qpos[idx.carriage_qpos[0]], qpos[idx.carriage_qpos[1]], qpos[b], qpos[b + 1], yaw])


def observe(cfg: Config, idx: Ids, qpos, qvel, prev_yaw, prev_max_balance, t, target_yaw, valid):
    """Everything the State derives from the physics after a step.

    Returns a dict with s, s1, s2, belt_speed, r1, r2, balance_error, max_balance_error, reason.
    """
    s = planar_state(idx, qpos, prev_yaw)
    s1, s2 = geometry.contact_masks(s, cfg.box, cfg.gripper)
    b = idx.box_qpos
    z, quat = qpos[b + 2], qpos[b + 3 : b + 7]
    off_belts = (z < cfg.box.half_size[2] - cfg.task.drop_limit) | (
        jnp.abs(s[geometry.X]) > cfg.gripper.belt_length / 2
    )
    tipped = geometry.tilt_from_quat(quat) > cfg.task.tip_limit
    bal = geometry.balance_error(s)
    reason = task.status(s, target_yaw, t, off_belts, tipped, cfg.task)
    reason = jnp.where(valid, reason, task.INVALID_ACTION)
    return dict(
        s=s,
        s1=s1,
        s2=s2,
        belt_speed=jnp.stack([qvel[idx.belt_dof[0]], qvel[idx.belt_dof[1]]]),
        r1=task.reward_pose(s, target_yaw, cfg.task),
        r2=task.reward_balance(s, cfg.task),
        balance_error=bal,
        max_balance_error=jnp.maximum(prev_max_balance, bal),
        reason=reason,
    )


def freeze_if_done(old: State, new: State) -> State:
    """Keep `old` where its episode had already ended (for vmapped worlds that end at different steps)."""
    return jax.tree.map(lambda a, b: jnp.where(old.done, a, b) if hasattr(a, "shape") else b, old, new)
