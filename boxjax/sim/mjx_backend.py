"""MJX backend: the same gripper, jittable, vmappable over boxes and shardable across devices.

Per-box model fields (mass, centre of mass, inertia and MuJoCo's derived constants) travel inside the
State (`state.model`, a dict of arrays), so `jax.vmap(env.pure_step)` over a batch of states simulates a batch
of different boxes with no extra `in_axes` bookkeeping. The fields are computed on the host from a native
model per box after `mj_setConst` (docs/design.md#simulation-pitfalls: MJX does not recompute derived
constants).
"""

from __future__ import annotations

import contextlib
import io
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from boxjax import massdist
from boxjax.config import Config
from boxjax.sim import core, model
from boxjax.sim.mjx_contacts import box_contacts
from boxjax.sim.native import _as_list, initial_qpos, recentre_belts


def _mjx():
    """mujoco.mjx, imported on first use (it is slow to import). Its optional-Warp probe prints
    "Failed to import warp" to stdout on machines without Warp; that is not an error, so we hide it."""
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


class MjxEnv:
    """The gripper on MJX, with the Env API of `NativeEnv`: `reset(key, dist)` and `step(state, action)`
    (the action checked on the host, the step compiled once per env and reused: call it in a loop).

    The pure, jittable and vmappable functions are `pure_init(params, key)` and `pure_step(state, action)`
    (and `physics_step`, which ignores termination): jit, vmap and scan them from outside. For batches
    use `box_params` per box + `stack` + `jax.vmap(env.pure_init)`.
    """

    backend = "mjx"

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.contacts = cfg.gripper.mjx_box_contacts  # the box-belt collider (`boxjax.sim.mjx_contacts`)
        self._template = model.template(cfg)
        self.ids = model.ids(self._template)
        self.mx = _mjx().put_model(self._template, impl="jax")
        self._init_jit = jax.jit(self.pure_init)
        self._step_jit = jax.jit(self.pure_step)

    # -- host-side helpers -------------------------------------------------------------------------
    def box_params(self, dist: massdist.MassDistribution) -> dict:
        """Per-box model fields for `dist` (host-side; validates the distribution)."""
        return {k: jnp.asarray(v) for k, v in model.box_params(model.box_model(self.cfg, dist)).items()}

    def reset(self, key, dist: massdist.MassDistribution) -> core.State:
        return self._init_jit(self.box_params(dist), key)

    def step(self, state: core.State, action) -> core.State:
        """Apply `action` (4,) = (v1, v2, dp1, dp2) for one control step: `pure_step`, compiled once, with
        host-side action validation. A finished episode stays as it was.

        Raises:
          ValueError: the action has the wrong shape or is not finite.
        """
        return self._step_jit(state, jnp.asarray(core.check_action(action), dtype=jnp.float32))

    # -- pure functions ----------------------------------------------------------------------------
    def _model(self, params: dict):
        return self.mx.tree_replace(params)

    def pure_init(self, params: dict, key) -> core.State:
        """Box at rest on the belts (pure; `params` from `box_params`)."""

        mjx = _mjx()
        m = self._model(params)
        qpos = initial_qpos(self.cfg, self._template, key).astype(jnp.float32)
        p0 = jnp.asarray(self.cfg.gripper.belt_y0, dtype=jnp.float32)
        with box_contacts(self.contacts):  # the contact arrays' size depends on the collider
            d = mjx.make_data(m)
        ctrl = d.ctrl.at[model.CARRIAGE1_P].set(p0[0]).at[model.CARRIAGE2_P].set(p0[1])
        # A strongly typed time: a weakly typed one makes MJX compile the step twice
        # (docs/design.md#simulation-pitfalls).
        # No mjx.forward here: the observation needs only qpos / qvel, and every step runs forward itself.
        d = d.replace(qpos=qpos, ctrl=ctrl, time=jnp.zeros((), jnp.float32))
        yaw0 = core.planar_state(self.ids, d.qpos)[4]
        target = yaw0 + self.cfg.task.target_yaw_delta
        obs = core.observe(self.cfg, self.ids, d.qpos, d.qvel, yaw0, 0.0, 0, target, True)
        return core.State(
            physics=d,
            model=params,
            p_target=p0,
            target_yaw=target.astype(jnp.float32),
            t=jnp.zeros((), jnp.int32),
            clipped=jnp.zeros((), bool),
            **obs,
        )

    def physics_step(self, state: core.State, action) -> core.State:
        """One control step that ignores episode termination (for open-loop data collection)."""
        mjx = _mjx()
        m = self._model(state.model)
        d = state.physics
        act_speed = d.act[jnp.array([model.BELT1_V, model.BELT2_V])]
        ctrl, p_target, clipped, valid = core.command(self.cfg, action, act_speed, state.p_target)
        d = d.replace(ctrl=ctrl.astype(d.ctrl.dtype))
        with box_contacts(self.contacts):
            d, _ = jax.lax.scan(
                lambda d, _: (mjx.step(m, d), None), d, None, length=self.cfg.gripper.n_substeps
            )
        d = d.replace(qpos=recentre_belts(self.ids, d.qpos))
        t = state.t + 1
        obs = core.observe(
            self.cfg,
            self.ids,
            d.qpos,
            d.qvel,
            state.s[4],
            state.max_balance_error,
            t,
            state.target_yaw,
            valid,
        )
        return state._replace(physics=d, p_target=p_target.astype(jnp.float32), t=t, clipped=clipped, **obs)

    def pure_step(self, state: core.State, action) -> core.State:
        """Apply `action` (4,) for one control step; a finished episode stays as it was (pure, unchecked)."""
        return core.freeze_if_done(state, self.physics_step(state, action))


class MjxBatch:
    """B worlds on MJX with `native.NativeBatch`'s interface (numpy fields s, belt_speed, balance_error,
    max_balance_error, target_yaw, t, clipped, reason, `done`; `step(actions, active)`; `state(b)`), so that
    host loops written for native worlds (`batch.run_episodes(..., backend="mjx")`) step MJX worlds too:
    the host loop on MJX physics, beside the on-device loop (`control.device_loop`) on the same physics.
    Every world is computed at every step (vmapped); worlds not `active` in a step, or whose episode has
    ended, keep their state."""

    backend = "mjx"

    def __init__(self, cfg: Config, dists, keys):
        dists = _as_list(dists)
        if len(keys) != len(dists):
            raise ValueError(f"need one key per box, got {len(keys)} keys for {len(dists)} boxes")
        env = env_for(cfg)
        self.cfg, self.ids = cfg, env.ids
        self.models = [None] * len(dists)  # the per-box fields travel in the state
        params = stack([env.box_params(d) for d in dists])
        self._state = jax.vmap(env.pure_init)(params, jnp.stack([jnp.asarray(k) for k in keys]))
        self._step = _batch_step(env)
        self._sync()

    def _sync(self) -> None:
        st = self._state
        for name in ("s", "belt_speed", "balance_error", "max_balance_error", "target_yaw", "t", "clipped"):
            setattr(self, name, np.asarray(getattr(st, name)))
        self.reason = np.asarray(st.reason)

    def __len__(self) -> int:
        return len(self.models)

    @property
    def done(self) -> np.ndarray:
        return np.asarray(self._state.done)

    def step(self, actions, active=None) -> None:
        a = np.asarray(actions, np.float64)
        if a.shape != (len(self), 4):
            raise ValueError(f"actions must have shape ({len(self)}, 4), got {a.shape}")
        active = ~self.done if active is None else np.asarray(active, bool) & ~self.done
        bad = np.flatnonzero(active & ~np.all(np.isfinite(a), axis=1))
        if bad.size:
            raise ValueError(f"non-finite actions for worlds {bad.tolist()}: {a[bad].tolist()}")
        self._state = self._step(
            self._state, jnp.asarray(np.where(active[:, None], a, 0.0), jnp.float32), active
        )
        self._sync()

    def state(self, b: int) -> core.State:
        """World b as a `core.State` (no physics or model: for its `summary()` and `done`)."""
        return jax.tree.map(lambda x: np.asarray(x[b]), self._state._replace(physics=None, model=None))


@lru_cache(maxsize=4)
def _batch_step(env: MjxEnv):
    def one(state, action, active):
        new = env.pure_step(state, action)
        return jax.tree.map(lambda a, b: jnp.where(active, a, b), new, state)

    return jax.jit(jax.vmap(one))


@lru_cache(maxsize=4)
def env_for(cfg: Config) -> MjxEnv:
    """One MjxEnv per config, so that jitted functions keyed on the env compile once per config."""
    return MjxEnv(cfg)


def stack(trees):
    """Stack a list of pytrees along a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def batch_sharding(n: int):
    """A NamedSharding that splits a leading batch axis of size n over all devices (None if one device,
    or if n does not divide evenly)."""
    devices = jax.devices()
    if len(devices) < 2 or n % len(devices):
        return None
    mesh = Mesh(np.array(devices), ("batch",))
    return NamedSharding(mesh, PartitionSpec("batch"))


# On CPU, jaxlib's batched LAPACK Cholesky (which MJX calls for the mass matrix, the implicit integrator
# and the Newton solver) splits large batches over its thread pool and can hang forever (seen with
# jax 0.10.2 from 768 worlds up on 2 cores: every thread parked in ParallelBatchMap / BlockingCounter).
# Vmapping at most CPU_CHUNK worlds at a time, with lax.map over the chunks, avoids it.
CPU_CHUNK = 256


def default_chunk() -> int | None:
    """Worlds vmapped at once: CPU_CHUNK on CPU, all of them on accelerators."""
    return CPU_CHUNK if jax.default_backend() == "cpu" else None


def chunked_vmap(fn, chunk: int | None = None):
    """jax.vmap(fn) over the leading axis, evaluated `chunk` worlds at a time (lax.map over chunks).

    The batch size must be a multiple of `chunk` when it is larger (pad it, see `rollout`).
    """
    vfn = jax.vmap(fn)
    if chunk is None:
        return vfn

    def run(*args):
        b = jax.tree.leaves(args)[0].shape[0]
        if b <= chunk:
            return vfn(*args)
        if b % chunk:
            raise ValueError(f"batch {b} is not a multiple of the chunk size {chunk}")
        split = lambda x: x.reshape(b // chunk, chunk, *x.shape[1:])  # noqa: E731
        out = jax.lax.map(lambda a: vfn(*a), jax.tree.map(split, args))
        return jax.tree.map(lambda x: x.reshape(b, *x.shape[2:]), out)

    return run


@partial(jax.jit, static_argnums=(0, 3))
def _rollout_jit(env: MjxEnv, states: core.State, actions, chunk):
    def one(state, acts):
        def body(st, a):
            st2 = env.physics_step(st, a)
            applied = jnp.concatenate([st2.physics.act[:2], st2.p_target - st.p_target])
            return st2, dict(
                s=st2.s,
                belt_speed=st2.belt_speed,
                s1=st2.s1,
                s2=st2.s2,
                actions=applied,
                qpos=st2.physics.qpos,
                clipped=st2.clipped,
            )

        return jax.lax.scan(body, state, acts)[1]

    return chunked_vmap(one, chunk)(states, actions)


def rollout(cfg: Config, dists, actions, *, env: MjxEnv | None = None, key=None) -> dict:
    """Open-loop rollouts of many boxes with MJX, vmapped and (with several devices) sharded.

    Same arguments and outputs as `boxjax.sim.native.rollout` (numpy arrays). Task termination is
    ignored: every world runs all T steps.
    """
    env = env or env_for(cfg)
    dists = _as_list(dists)
    B = len(dists)
    acts = np.asarray(actions, dtype=np.float32)
    if acts.ndim == 2:
        acts = np.broadcast_to(acts, (B, *acts.shape))
    if acts.ndim != 3 or acts.shape[0] != B or acts.shape[-1] != 4:
        raise ValueError(f"actions must have shape (B={B}, T, 4) or (T, 4), got {np.shape(actions)}")
    if not np.all(np.isfinite(acts)):
        raise ValueError("actions contain NaN or inf")
    key = jax.random.PRNGKey(0) if key is None else key
    # Pad the batch (repeating the last box) to equal shares per device, each a multiple of the chunk.
    n_dev, chunk = jax.device_count(), default_chunk()
    per_dev = -(-B // n_dev)
    if chunk is not None and per_dev > chunk:
        per_dev = -(-per_dev // chunk) * chunk
    else:
        chunk = None
    Bp = per_dev * n_dev
    dists = dists + [dists[-1]] * (Bp - B)
    acts = np.concatenate([acts, np.repeat(acts[-1:], Bp - B, axis=0)])
    params = stack([env.box_params(d) for d in dists])
    states = jax.vmap(env.pure_init)(params, jax.random.split(key, Bp))
    sharding = batch_sharding(Bp)
    acts = jnp.asarray(acts)
    if sharding is not None:
        states, acts = jax.device_put((states, acts), sharding)
    out = jax.tree.map(lambda x: np.asarray(x)[:B], _rollout_jit(env, states, acts, chunk))
    s0 = jax.tree.map(lambda x: np.asarray(x)[:B], states)
    first = dict(s=s0.s, belt_speed=s0.belt_speed, s1=s0.s1, s2=s0.s2, qpos=s0.physics.qpos)
    res = {k: np.concatenate([first[k][:, None], out[k]], axis=1) if k in first else out[k] for k in out}
    return res
