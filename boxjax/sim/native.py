"""Native MuJoCo backend: single episodes, and CPU batches through `mujoco.rollout` on all threads."""

from __future__ import annotations

import os
from functools import lru_cache, partial

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


class NativeBatch:
    """B worlds on native MuJoCo stepped together, for closed loops over many boxes (`boxjax.control.batch`).

    Each box keeps its own MjModel and MjData and is stepped by `mj_step` exactly as `NativeEnv.step`
    steps it (mjSTATE_INTEGRATION is all the integrator reads, so a persistent MjData and NativeEnv's
    get / set round trip take the same steps); the command and the observation of all B worlds are one
    vmapped call each, the part of a control step that costs most for one box (more than its physics:
    docs/results/batched-episodes.md). Worlds whose episode has ended, and worlds not `active` in a
    step, are not stepped: their state stays as it was (a paused world does not evolve).

    Fields (numpy, leading axis B): s (B, 5), belt_speed (B, 2), p_target (B, 2), target_yaw (B,),
    balance_error, max_balance_error (B,) m, t (B,) int32 steps taken, reason (B,) int32, clipped (B,).
    """

    backend = "native"

    def __init__(self, cfg: Config, dists, keys):
        dists = _as_list(dists)
        if len(keys) != len(dists):
            raise ValueError(f"need one key per box, got {len(keys)} keys for {len(dists)} boxes")
        self.cfg = cfg
        self.models = [model.box_model(cfg, d) for d in dists]
        self.ids = model.ids(self.models[0])
        self.datas = [mujoco.MjData(m) for m in self.models]
        B = len(dists)
        yaw0 = np.empty(B)
        for b, (m, d) in enumerate(zip(self.models, self.datas, strict=True)):
            mujoco.mj_resetData(m, d)
            d.qpos[:] = np.asarray(initial_qpos(cfg, m, keys[b]))
            d.ctrl[model.CARRIAGE1_P : model.CARRIAGE2_P + 1] = cfg.gripper.belt_y0
            mujoco.mj_forward(m, d)
            yaw0[b] = float(core.planar_state(self.ids, d.qpos)[4])
        self._command = _batched_command(cfg)
        self._observe = _batched_observe(cfg, self.ids)
        self.target_yaw = (yaw0 + cfg.task.target_yaw_delta).astype(np.float32)
        self.p_target = np.tile(np.asarray(cfg.gripper.belt_y0, np.float32), (B, 1))
        self.t = np.zeros(B, np.int32)
        self.clipped = np.zeros(B, bool)
        self.s = np.zeros((B, 5), np.float32)
        self.max_balance_error = np.zeros(B, np.float32)
        self._update(np.ones(B, bool), yaw0.astype(np.float32), np.zeros(B, np.float32), np.ones(B, bool))

    def __len__(self) -> int:
        return len(self.models)

    @property
    def done(self) -> np.ndarray:
        return self.reason != task.RUNNING

    def _update(self, mask, prev_yaw, prev_max, valid):
        qpos = np.stack([d.qpos for d in self.datas])
        qvel = np.stack([d.qvel for d in self.datas])
        obs = self._observe(qpos, qvel, prev_yaw, prev_max, self.t, self.target_yaw, valid)
        for k, v in obs.items():
            v = np.asarray(v)
            old = getattr(self, k, None)
            setattr(self, k, v if old is None else np.where(mask.reshape(-1, *([1] * (v.ndim - 1))), v, old))

    def step(self, actions, active=None) -> None:
        """One control step of the `active` (B,) worlds (default: all not done) with actions (B, 4) (rows
        of the other worlds are ignored).

        Raises:
          ValueError: wrong shape, or a non-finite action for an active world (naming the world).
        """
        B = len(self)
        a = np.asarray(actions, np.float64)
        if a.shape != (B, 4):
            raise ValueError(f"actions must have shape ({B}, 4), got {a.shape}")
        active = ~self.done if active is None else np.asarray(active, bool) & ~self.done
        bad = np.flatnonzero(active & ~np.all(np.isfinite(a), axis=1))
        if bad.size:
            raise ValueError(f"non-finite actions for worlds {bad.tolist()}: {a[bad].tolist()}")
        a = np.where(active[:, None], a, 0.0)
        act_speed = np.stack([d.act[[model.BELT1_V, model.BELT2_V]] for d in self.datas])
        ctrl, p_target, clipped, valid = (np.asarray(x) for x in self._command(a, act_speed, self.p_target))
        ns = self.cfg.gripper.n_substeps
        for b in np.flatnonzero(active):
            m, d = self.models[b], self.datas[b]
            d.ctrl[:] = ctrl[b]
            mujoco.mj_step(m, d, nstep=ns)
            recentre_belts(self.ids, d.qpos)
        prev_yaw, prev_max = self.s[:, 4].copy(), self.max_balance_error.copy()
        self.t = np.where(active, self.t + 1, self.t).astype(np.int32)
        self.p_target = np.where(active[:, None], p_target, self.p_target)
        self.clipped = np.where(active, clipped, self.clipped)
        self._update(active, prev_yaw, prev_max, valid)

    def state(self, b: int) -> core.State:
        """World b as a `core.State` (no physics or model: for its `summary()` and `done`)."""
        return core.State(
            physics=None,
            model=None,
            p_target=self.p_target[b],
            target_yaw=self.target_yaw[b],
            t=self.t[b],
            clipped=self.clipped[b],
            **{k: getattr(self, k)[b] for k in _OBS_FIELDS},
        )


_OBS_FIELDS = ("s", "s1", "s2", "belt_speed", "r1", "r2", "balance_error", "max_balance_error", "reason")


@lru_cache(maxsize=8)
def _batched_command(cfg: Config):
    return jax.jit(jax.vmap(partial(core.command, cfg)))


@lru_cache(maxsize=8)
def _batched_observe(cfg: Config, idx: model.Ids):
    return jax.jit(jax.vmap(partial(core.observe, cfg, idx)))


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
