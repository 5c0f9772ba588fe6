"""A privileged reference planner: predictive sampling with the simulator itself as its model.

Why. Issue 11 asks which failures of the physics-prior controller no controller could avoid under the
4 cm rule within 600 steps, and which are ours. A planner that predicts with the very simulator that
then executes its action has no model error at all: what it fails is (up to its sampling budget and
horizon) beyond reach. It needs the truth, so it is `privileged`: the controller hands it the native
env's State in `obs.sim` (`boxjax.sim.core.State`: `.physics` the full mjSTATE_INTEGRATION state,
`.model` the box's mujoco.MjModel, `.p_target` the carriage targets) and it is oracle-only.

What. The same predictive sampling as `planners.sampling` (Howell et al. 2022; MuJoCo MPC's and hydrax's
default with a perfect model): keep a nominal plan of `horizon` actions, perturb it with gaussian noise
(the same `SamplingOptions` sigmas, clipping and speed cap), roll every candidate out, keep the best,
send its first action and shift it. Only the rollouts differ: each candidate runs in native MuJoCo from
the exact current state, reproducing `NativeEnv.step` bit for bit (tested): per control step the action
goes through the same jitted `core.command` (vmapped over candidates) into controls, 25 physics substeps
with `mujoco.mj_step`, then the belt slabs are re-centred.

Why not `mujoco.rollout`. It takes and returns mjSTATE_FULLPHYSICS states, without the constraint
solver's warm start (`qacc_warmstart`, part of the mjSTATE_INTEGRATION state NativeEnv keeps), and every
control step needs host work between substep blocks (controls from the belt actuators' activation, the
re-centring), so one `mujoco.rollout` call per control step restarts the solver cold every 25 substeps.
Measured: 3e-8 m off NativeEnv after the first contact change; the mj_step loop: 0. Speed is the same
(64 candidates x 25 substeps: `mujoco.rollout` 13.8 ms, this loop on 2 threads 16.8 ms, 1 thread
18.6 ms, on the shared 2-core CPU). MuJoCo's bindings release the GIL inside `mj_step`, so the candidates
are stepped by a pool of `nthread` Python threads (all cores by default), one MjData per candidate.

Score. `planners.sampling.rollout_cost` on the planar states the simulator reached (the same cost as the
default planner), with its tipping barrier from the model slot's `stability_margin`: under the oracle
estimator that is the physics prior built on the true voxel masses. On top, the simulator's own verdict
after each control step (`core.observe`, i.e. `task.status` with the simulator's z, tilt and the
episode's running maximum of the balance error, exactly what the env will report): a rollout that ends
the episode in a failure (unbalanced, off_belts, tipped) at step k of H pays
`w_fail * (2 - k / H)` (sooner is worse); the states after a rollout's terminal step (failure, success
or the step cap) are replaced by that terminal state, so a rollout that succeeds early stops paying.

Cost. N x H x 25 physics substeps per control step: it is slow by design. Measured with the default
32 x 10 on the shared 2-core CPU (docs/results/random-boxes.md): 112 ms median, 193 ms p99 per
step at load average ~3 (box C); 138 / 1540 ms over the 50-box evaluation at load 5-11 (30 min, 50/50
turned, where the default planner turned 43).
"""

from __future__ import annotations

import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from boxjax import geometry, planning, task
from boxjax.config import Config
from boxjax.planners import sampling as sp
from boxjax.sim import core, model
from boxjax.sim.native import STATE_SPEC

# Per-step latency log for measuring a CLI run: when set, every planning call appends its wall ms.
LATENCY_LOG_ENV = "BOXJAX_SIM_LATENCY_LOG"
_FAILURES = (task.UNBALANCED, task.OFF_BELTS, task.TIPPED, task.INVALID_ACTION)
STARTS = ("exact", "planar", "flat", "velocity")
MODELS = ("truth", "belief")


@dataclasses.dataclass(frozen=True)
class SimulatorOptions:
    """Settings of the simulator reference (hashable: part of the cached controller config).

    sampling: the predictive-sampling settings (samples, horizon, sigmas, speed cap, cost weights),
      shared with `planners.sampling`. Default 32 samples x 10 steps: 8000 substeps per control step.
    w_fail: cost of a rollout that ends the episode in a failure (see the module docstring).
    nthread: Python threads stepping the candidates (None: all cores).
    start: where each planning step's rollouts start. "exact" (default): the simulator's full state, the
      box's tilt, height and every velocity included. "planar": what a robot that sees the box's planar
      pose knows -- the carriages and belts exactly (their encoders), the box flat at its resting height,
      at the observed pose (the window's last state) and moving with the window's finite-difference
      velocities (vx, vy, omega; no vertical or tilting motion): the box's rocking on its contact points,
      which the planar observation does not show, is dropped (`planar_start`). "flat" and "velocity":
      its two halves apart (only the box flattened; only the planar velocities from finite differences).
    model: the box the rollouts simulate. "truth" (default): the true box (the env's own MjModel).
      "belief": the box the estimator believes in (`belief_model`: H's voxel estimate under the learned
      estimator), so with start="planar" nothing of the box's truth reaches the rollouts; the belts,
      carriages and the solver's warm start are still read from the simulator.
    """

    sampling: sp.SamplingOptions = sp.SamplingOptions(n_samples=32, horizon=10, gradient_steps=0)
    w_fail: float = 1.0e4
    nthread: int | None = None
    start: str = "exact"
    model: str = "truth"

    def __post_init__(self):
        if self.start not in STARTS:
            raise ValueError(f"SimulatorOptions.start={self.start!r}: expected one of {STARTS}")
        if self.model not in MODELS:
            raise ValueError(f"SimulatorOptions.model={self.model!r}: expected one of {MODELS}")


class SimulatorInfo(NamedTuple):
    """What one planning step considered. N = n_samples, H = horizon.

    nominal: (H, 4) the chosen sequence (row 0 is the action sent). states: (N, H, 5) the planar states
    the simulator reached. cost: (N,). best: () index of the chosen rollout (0: the old nominal).
    reason: (N,) int32 task.REASONS code of each rollout's first terminal step (RUNNING: none).
    sim_ms: wall milliseconds spent in the physics.
    """

    nominal: np.ndarray
    states: np.ndarray
    cost: np.ndarray
    best: int
    reason: np.ndarray
    sim_ms: float


def _sample(key, nominal, cfg: Config, o: sp.SamplingOptions):
    """(N, H, 4) the nominal and N - 1 gaussian perturbations of it, clipped as `planners.sampling.plan`."""
    sigma = jnp.array([o.speed_sigma, o.speed_sigma, o.position_sigma, o.position_sigma], jnp.float32)
    noise = jax.random.normal(key, (o.n_samples - 1, o.horizon, 4)) * sigma
    nominal = jnp.asarray(nominal, jnp.float32)
    return sp.clip_actions(jnp.concatenate([nominal[None], nominal[None] + noise]), cfg, o.speed_cap)


def _score(prior_model, qpos, qvel, seqs, yaw0, max_bal0, t0, target_yaw, cfg: Config, idx, o, w_fail):
    """Costs (N,), planar states (N, H, 5) and first terminal reasons (N,) of simulated rollouts.

    qpos (N, H, nq), qvel (N, H, nv): the physics after each control step; yaw0, max_bal0, t0: the env
    state's yaw, running max balance error and step count at the start.
    """
    H = seqs.shape[1]

    def one(q, v, seq):
        def step(carry, x):
            yaw, max_bal, t = carry
            qk, vk = x
            ob = core.observe(cfg, idx, qk, vk, yaw, max_bal, t + 1, target_yaw, True)
            return (ob["s"][geometry.YAW], ob["max_balance_error"], t + 1), (ob["s"], ob["reason"])

        _, (s, reason) = jax.lax.scan(step, (yaw0, max_bal0, t0), (q, v))
        ended = reason != task.RUNNING
        k_end = jnp.where(jnp.any(ended), jnp.argmax(ended), H - 1)
        first = jnp.where(jnp.any(ended), reason[k_end], task.RUNNING)
        s_masked = jnp.where((jnp.arange(H) > k_end)[:, None], s[k_end], s)
        cost = sp.rollout_cost(prior_model, s_masked, seq, target_yaw, cfg, o)
        failed = jnp.isin(first, jnp.array(_FAILURES))
        cost = cost + jnp.where(failed, w_fail * (2.0 - k_end / H), 0.0)
        return jnp.where(jnp.isfinite(cost), cost, jnp.inf), s, first

    return jax.vmap(one)(qpos, qvel, seqs)


class Rollouts:
    """Rolls N action sequences of H control steps out in native MuJoCo from one env state, exactly as
    `NativeEnv.step` would (one MjData per sequence, `nthread` Python threads; MuJoCo releases the GIL
    inside `mj_step`)."""

    def __init__(self, cfg: Config, n: int, horizon: int, nthread: int | None = None):
        template = model.template(cfg)
        self.n, self.horizon, self.ns = n, horizon, cfg.gripper.n_substeps
        self.belt_q = list(model.ids(template).belt_qpos)
        self.act_i = [model.BELT1_V, model.BELT2_V]
        nthread = max(1, min(nthread or os.cpu_count() or 1, n))
        self.chunks = [range(i, n, nthread) for i in range(nthread)]
        self.datas = [mujoco.MjData(template) for _ in range(n)]  # every box model has these sizes
        self.pool = ThreadPoolExecutor(nthread) if nthread > 1 else None
        self.command = jax.jit(jax.vmap(partial(core.command, cfg)))

    def _run(self, fn):
        if self.pool is None:
            for c in self.chunks:
                fn(c)
        else:
            list(self.pool.map(fn, self.chunks))

    def __call__(self, state: core.State, seqs) -> tuple[np.ndarray, np.ndarray]:
        """qpos (N, H, nq), qvel (N, H, nv) after each control step of each sequence seqs (N, H, 4), from
        the native env state `state` (its physics, box model and carriage targets)."""
        m, seqs = state.model, np.asarray(seqs, np.float64)
        N, H = self.n, self.horizon
        if seqs.shape != (N, H, 4):
            raise ValueError(f"sequences must have shape ({N}, {H}, 4), got {seqs.shape}")
        qpos, qvel = np.empty((N, H, m.nq)), np.empty((N, H, m.nv))
        act, ctrl = np.empty((N, 2)), np.empty((N, 4))
        datas, act_i = self.datas, self.act_i

        def reset(c):
            for i in c:
                mujoco.mj_setState(m, datas[i], state.physics, STATE_SPEC)
                act[i] = datas[i].act[act_i]

        def advance(c, k):
            for i in c:
                d = datas[i]
                d.ctrl[:] = ctrl[i]
                mujoco.mj_step(m, d, nstep=self.ns)
                d.qpos[self.belt_q] = 0.0  # re-centre the belt slabs, as NativeEnv.step
                qpos[i, k], qvel[i, k], act[i] = d.qpos, d.qvel, d.act[act_i]

        self._run(reset)
        p = np.tile(np.asarray(state.p_target), (N, 1))
        for k in range(H):
            c, p, _, _ = self.command(seqs[:, k], act, p)
            ctrl[:] = np.asarray(c)
            p = np.asarray(p)
            self._run(partial(advance, k=k))
        return qpos, qvel


def belief_model(cfg: Config, options: SimulatorOptions | None, belief) -> mujoco.MjModel | None:
    """The MjModel the rollouts simulate when `options.model == "belief"`: the believed box
    (`massdist.MassDistribution`) in the gripper (`sim.model.box_model`); None: the env's own (truth)."""
    if options is None or options.model == "truth":
        return None
    if belief is None:
        raise ValueError(
            "SimulatorOptions(model='belief') simulates the estimator's box, and this episode has no belief "
            "(a planning model was given instead of an estimator)"
        )
    return model.box_model(cfg, belief)


def _rotation(quat) -> np.ndarray:
    """(3, 3) the rotation matrix of a unit quaternion (w, x, y, z)."""
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, np.float64))
    return out.reshape(3, 3)


def box_velocity(m: mujoco.MjModel, qpos, qvel) -> tuple[np.ndarray, np.ndarray]:
    """The box's free-joint velocity in world axes, (6,) = (linear velocity of the body origin, the
    geometric centre; angular velocity), and its rotation matrix (3, 3), body -> world. MuJoCo keeps the
    free joint's angular velocity in body axes."""
    idx = model.ids(m)
    b, bv = idx.box_qpos, idx.box_dof
    rot = _rotation(qpos[b + 3 : b + 7])
    return np.concatenate([qvel[bv : bv + 3], rot @ qvel[bv + 3 : bv + 6]]), rot


def planar_start(
    cfg: Config, state: core.State, window, data: mujoco.MjData | None = None, start: str = "planar"
) -> np.ndarray:
    """The mjSTATE_INTEGRATION state a planar observation gives (`start="planar"`): `state.physics` with
    the box's free joint replaced by the box lying flat at its resting height (z = half the box's height,
    no tilt) at the window's last planar pose, with the linear and yaw velocities of the window's
    second-order backward differences (as the physics prior's `force_map.window_kinematics`) and no
    vertical or tilting velocity. The belts and carriages (the robot's own joints) and the solver's warm
    start are kept. The two halves apart, to tell which one matters: `start="flat"` only flattens the box
    (planar velocities exact), `start="velocity"` only replaces the planar velocities by the finite
    differences (the box's height, tilt and tilting motion exact).

    window: (W >= 3, 5) planar states at control_dt spacing (P1, P2, x, y, yaw), the geometric centre's.
    """
    if start not in STARTS[1:]:
        raise ValueError(f"start={start!r}: expected one of {STARTS[1:]}")
    m = state.model
    d = data if data is not None else mujoco.MjData(m)
    mujoco.mj_setState(m, d, state.physics, STATE_SPEC)
    w = np.asarray(window, np.float64)
    if w.ndim != 2 or w.shape[0] < 3 or w.shape[1] != 5:
        raise ValueError(f"window must be (W >= 3, 5) planar states, got shape {w.shape}")
    idx = model.ids(m)
    b, bv = idx.box_qpos, idx.box_dof
    vel, rot = box_velocity(m, d.qpos, d.qvel)  # world axes
    if start in ("planar", "velocity"):
        fd = (3.0 * w[-1] - 4.0 * w[-2] + w[-3]) / (2.0 * cfg.gripper.control_dt)
        vel[[0, 1, 5]] = fd[[geometry.X, geometry.Y, geometry.YAW]]
    if start in ("planar", "flat"):
        x, y, yaw = w[-1, geometry.X], w[-1, geometry.Y], w[-1, geometry.YAW]
        d.qpos[b : b + 7] = [x, y, cfg.box.half_size[2], np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
        vel[[2, 3, 4]] = 0.0  # no vertical or tilting motion
        rot = _rotation(d.qpos[b + 3 : b + 7])
    d.qvel[bv : bv + 3] = vel[:3]
    d.qvel[bv + 3 : bv + 6] = rot.T @ vel[3:]
    out = np.empty(mujoco.mj_stateSize(m, STATE_SPEC))
    mujoco.mj_getState(m, d, out, STATE_SPEC)
    return out


def make(cfg: Config, options: SimulatorOptions | None = None) -> planning.Planner:
    """The simulator reference behind the planner interface (`planning.Planner`, privileged): the plan
    state is the nominal sequence (H, 4); `optimize(key, model, obs, nominal)` needs `obs.sim`, a
    native-backend `core.State`. Not jitted (MuJoCo runs on the host); deterministic per key."""
    opts = options or SimulatorOptions()
    o = opts.sampling
    N, H = o.n_samples, o.horizon
    idx = model.ids(model.template(cfg))
    sample = jax.jit(partial(_sample, cfg=cfg, o=o))
    score = jax.jit(partial(_score, cfg=cfg, idx=idx, o=o, w_fail=opts.w_fail))

    rollouts = Rollouts(cfg, N, H, opts.nthread)
    scratch = mujoco.MjData(model.template(cfg))  # every box model has these sizes

    def init(obs: planning.Observation):
        return sp.initial_nominal(cfg, o, obs.belt_speed)

    def optimize(key, prior_model, obs: planning.Observation, nominal):
        sim = obs.sim
        if sim is None or not isinstance(sim.model, mujoco.MjModel):
            raise ValueError("the simulator planner needs obs.sim, the native env's State (oracle only)")
        t0 = time.perf_counter()
        seqs = np.asarray(sample(key, nominal), np.float64)  # float32 values, as the env receives them
        t1 = time.perf_counter()
        start = sim
        if opts.start != "exact":
            start = sim._replace(physics=planar_start(cfg, sim, obs.window, scratch, opts.start))
        qpos, qvel = rollouts(start, seqs)
        sim_ms = 1e3 * (time.perf_counter() - t1)
        cost, states, reason = score(
            prior_model,
            qpos,
            qvel,
            seqs,
            jnp.float32(sim.s[geometry.YAW]),
            jnp.float32(sim.max_balance_error),
            jnp.int32(sim.t),
            jnp.float32(sim.target_yaw),
        )
        cost = np.asarray(cost)
        best = int(np.argmin(cost))
        info = SimulatorInfo(seqs[best], np.asarray(states), cost, best, np.asarray(reason), sim_ms)
        path = os.environ.get(LATENCY_LOG_ENV)
        if path:
            with open(path, "a") as f:
                f.write(f"{1e3 * (time.perf_counter() - t0):.3f}\n")
        return (
            np.asarray(seqs[best, 0], np.float32),
            sp.shift_nominal(jnp.asarray(seqs[best], jnp.float32)),
            info,
        )

    return planning.Planner("simulator", init, optimize, privileged=True)
