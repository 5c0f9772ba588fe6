"""Native MuJoCo backend: single episodes, and CPU batches through `mujoco.rollout` on all threads."""

from __future__ import annotations

import os
from functools import partial

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from boxjax import massdist, task
from boxjax.config import Config
from boxjax.sim import core, model

# Everything needed to continue a simulation exactly: physics, controls and the solver's warm start.
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION


class NativeEnv:
    """The gripper on native MuJoCo. `reset(key, dist)` and `step(state, action)` are pure in the sense
    that `step` never mutates the state it is given (it returns a new one).

    Not jittable (MuJoCo runs on the host); see `MjxEnv` for the jittable, vmappable backend.
    """

    backend = "native"

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self._template = model.template(cfg)
        self.ids = model.ids(self._template)
        self._data = mujoco.MjData(self._template)  # scratch data; every box model has the same sizes
        self._command = jax.jit(partial(core.command, cfg))
        self._observe = jax.jit(partial(core.observe, cfg, self.ids))

    def reset(self, key, dist: massdist.MassDistribution) -> core.State:
        """Box `dist` at rest on the belts, yaw 0 (plus the task's optional initial-pose noise)."""
        m = model.box_model(self.cfg, dist)
        d = self._data
        mujoco.mj_resetData(m, d)
        d.qpos[:] = np.asarray(initial_qpos(self.cfg, m, key))
        d.ctrl[model.CARRIAGE1_P : model.CARRIAGE2_P + 1] = self.cfg.gripper.belt_y0
        mujoco.mj_forward(m, d)
        target_yaw = float(core.planar_state(self.ids, d.qpos)[4]) + self.cfg.task.target_yaw_delta
        yaw0 = float(core.planar_state(self.ids, d.qpos)[4])
        obs = self._observe(d.qpos, d.qvel, yaw0, 0.0, 0, target_yaw, True)
        return core.State(
            physics=_get_state(m, d),
            model=m,
            p_target=np.asarray(self.cfg.gripper.belt_y0, dtype=np.float32),
            target_yaw=np.float32(target_yaw),
            t=np.int32(0),
            clipped=np.bool_(False),
            **{k: np.asarray(v) for k, v in obs.items()},
        )

    def step(self, state: core.State, action) -> core.State:
        """Apply `action` (4,) = (v1, v2, dp1, dp2) for one control step.

        Raises:
          ValueError: the action has the wrong shape or is not finite.
        """
        a = core.check_action(action)
        if state.done:
            return state
        m, d = state.model, self._data
        mujoco.mj_setState(m, d, state.physics, STATE_SPEC)
        act_speed = d.act[[model.BELT1_V, model.BELT2_V]]
        ctrl, p_target, clipped, valid = self._command(a, act_speed, state.p_target)
        d.ctrl[:] = np.asarray(ctrl)
        mujoco.mj_step(m, d, nstep=self.cfg.gripper.n_substeps)
        recentre_belts(self.ids, d.qpos)
        t = state.t + 1
        obs = self._observe(d.qpos, d.qvel, state.s[4], state.max_balance_error, t, state.target_yaw, valid)
        return state._replace(
            physics=_get_state(m, d),
            p_target=np.asarray(p_target),
            t=np.int32(t),
            clipped=np.bool_(clipped),
            **{k: np.asarray(v) for k, v in obs.items()},
        )


def initial_qpos(cfg: Config, m: mujoco.MjModel, key) -> jnp.ndarray:
    """Resting pose, with the task's optional initial-pose noise drawn from `key`."""
    q = model.initial_qpos(cfg, m)  # float64: native MuJoCo starts exactly where the rollouts start
    t = cfg.task
    if t.init_xy_noise == 0 and t.init_yaw_noise == 0:
        return q
    q = jnp.asarray(q)
    key_xy, key_yaw = jax.random.split(key)
    # x, y of the box centre ~ U(-init_xy_noise, init_xy_noise) m each; yaw ~ U(-init_yaw_noise, ...) rad.
    dxy = jax.random.uniform(key_xy, (2,), minval=-t.init_xy_noise, maxval=t.init_xy_noise)
    yaw = jax.random.uniform(key_yaw, (), minval=-t.init_yaw_noise, maxval=t.init_yaw_noise)
    b = model.ids(m).box_qpos
    q = q.at[b : b + 2].add(dxy)
    return q.at[b + 3 : b + 7].set(jnp.array([jnp.cos(yaw / 2), 0.0, 0.0, jnp.sin(yaw / 2)]))


def recentre_belts(idx: model.Ids, qpos):
    """Move both belt slabs back to x = 0 (in place for numpy, functional for jnp). The slab is uniform,
    so the contact geometry is unchanged and the belt surface behaves as an endless conveyor."""
    if isinstance(qpos, np.ndarray):
        qpos[list(idx.belt_qpos)] = 0.0
        return qpos
    return qpos.at[jnp.array(idx.belt_qpos)].set(0.0)


def _get_state(m, d) -> np.ndarray:
    out = np.empty(mujoco.mj_stateSize(m, STATE_SPEC))
    mujoco.mj_getState(m, d, out, STATE_SPEC)
    return out


def rollout(cfg: Config, dists, actions, *, nthread: int | None = None, progress=None) -> dict:
    """Open-loop rollouts of many boxes on all CPU threads through `mujoco.rollout`.

    Task termination is ignored: every world runs all T steps (this is how exploration and calibration
    data are gathered).

    Args:
      dists: a batched MassDistribution (leading axis B) or a sequence of B distributions.
      actions: (B, T, 4) or (T, 4) actions (shared by all boxes); clipped to the limits as in `step`.
      nthread: threads (default: all cores).
      progress: optional callable(n_done_steps) called after each control step (e.g. a tqdm update).
    Returns:
      dict of numpy arrays: s (B, T+1, 5), belt_speed (B, T+1, 2), s1, s2 (B, T+1, nx, ny),
      actions (B, T, 4) as applied (after clipping), qpos (B, T+1, nq), clipped (B, T) bool.
    """
    dists = _as_list(dists)
    B = len(dists)
    acts = np.asarray(actions, dtype=np.float64)
    if acts.ndim == 2:
        acts = np.broadcast_to(acts, (B, *acts.shape))
    if acts.shape[0] != B or acts.shape[-1] != 4 or acts.ndim != 3:
        raise ValueError(f"actions must have shape (B={B}, T, 4) or (T, 4), got {np.shape(actions)}")
    if not np.all(np.isfinite(acts)):
        raise ValueError("actions contain NaN or inf")
    T = acts.shape[1]
    models = [model.box_model(cfg, dist) for dist in dists]
    idx = model.ids(models[0])
    nthread = nthread or os.cpu_count() or 1
    datas = [mujoco.MjData(models[0]) for _ in range(nthread)]
    fullphys = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(models[0], fullphys)
    state = np.empty((B, nstate))
    d = datas[0]
    for b, m in enumerate(models):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = model.initial_qpos(cfg, m)
        mujoco.mj_forward(m, d)
        mujoco.mj_getState(m, d, state[b], fullphys)
    # FULLPHYSICS layout: time, qpos, qvel, act, ...
    nq, nv = models[0].nq, models[0].nv
    sl_q = slice(1, 1 + nq)
    sl_v = slice(1 + nq, 1 + nq + nv)
    sl_a = slice(1 + nq + nv, 1 + nq + nv + models[0].na)
    command = jax.jit(jax.vmap(partial(core.command, cfg)))
    obs = jax.jit(jax.vmap(partial(_obs, cfg, idx)))
    p_target = np.tile(np.asarray(cfg.gripper.belt_y0), (B, 1))
    qpos = np.empty((B, T + 1, nq))
    qvel = np.empty((B, T + 1, nv))
    applied = np.empty((B, T, 4))
    clipped = np.empty((B, T), dtype=bool)
    qpos[:, 0], qvel[:, 0] = state[:, sl_q], state[:, sl_v]
    warm = np.zeros((B, nv))
    ns = cfg.gripper.n_substeps
    for t in range(T):
        act_speed = state[:, sl_a][:, [model.BELT1_V, model.BELT2_V]]
        ctrl, p_target_new, clip_t, _ = command(acts[:, t], act_speed, p_target)
        ctrl = np.asarray(ctrl, dtype=np.float64)
        applied[:, t, :2] = act_speed + ctrl[:, :2] * cfg.gripper.control_dt
        applied[:, t, 2:] = np.asarray(p_target_new) - p_target
        p_target = np.asarray(p_target_new)
        clipped[:, t] = np.asarray(clip_t)
        out, _ = mj_rollout.rollout(
            models, datas, state, ctrl[:, None, :], nstep=ns, initial_warmstart=warm, skip_checks=False
        )
        state = out[:, -1].copy()
        state[:, 1 + np.array(idx.belt_qpos)] = 0.0  # re-centre the belt slabs
        qpos[:, t + 1], qvel[:, t + 1] = state[:, sl_q], state[:, sl_v]
        if progress is not None:
            progress(t + 1)
    o = obs(qpos.reshape(B * (T + 1), nq), qvel.reshape(B * (T + 1), nv))
    shape = lambda x: np.asarray(x).reshape(B, T + 1, *x.shape[1:])  # noqa: E731
    s = shape(o["s"]).copy()
    s[..., 4] = np.unwrap(s[..., 4], axis=1)  # continuous yaw, as in NativeEnv.step
    return dict(
        s=s,
        belt_speed=shape(o["belt_speed"]),
        s1=shape(o["s1"]),
        s2=shape(o["s2"]),
        actions=applied,
        qpos=qpos,
        clipped=clipped,
    )


def _obs(cfg, idx, qpos, qvel):
    o = core.observe(cfg, idx, qpos, qvel, 0.0, 0.0, 0, 0.0, True)
    return {k: o[k] for k in ("s", "s1", "s2", "belt_speed")}


def _as_list(dists) -> list[massdist.MassDistribution]:
    if isinstance(dists, massdist.MassDistribution):
        occ = np.asarray(dists.occupancy)
        if occ.ndim == 3:
            return [dists]
        return [
            massdist.MassDistribution(o, m) for o, m in zip(occ, np.asarray(dists.total_mass), strict=True)
        ]
    return list(dists)


__all__ = ["NativeEnv", "rollout", "task"]
