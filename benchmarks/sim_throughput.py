"""Simulation throughput: native MuJoCo, mujoco.rollout on all threads, MJX at several batch sizes.

Prints one JSON object. "steps" are physics steps (GripperConfig.timestep = 2 ms); a world-step is one
physics step of one world. Compile time and run time are reported separately; run times are medians.

    python benchmarks/sim_throughput.py [--batches 1 64 512 2048] [--collider-batches 64] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from _util import emit, machine, timed
from mujoco import rollout as mj_rollout

from boxjax import massdist
from boxjax.config import DEFAULT, MJX_BOX_CONTACTS
from boxjax.sim import model
from boxjax.sim.mjx_backend import MjxEnv, chunked_vmap, default_chunk

ROTATE = np.array([0.15, -0.15, 0.0, 0.0])


def native_single(cfg, dist, nstep: int, repeats: int) -> float:
    """Physics steps per second on one thread, box turning between the belts."""
    m = model.box_model(cfg, dist)
    d = mujoco.MjData(m)
    rates = []
    for _ in range(repeats):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = model.initial_qpos(cfg, m)
        d.ctrl[:] = [0.6, -0.6, *cfg.gripper.belt_y0]
        t0 = time.perf_counter()
        mujoco.mj_step(m, d, nstep=nstep)
        rates.append(nstep / (time.perf_counter() - t0))
    return statistics.median(rates)


def native_rollout(cfg, dist, nbatch: int, nstep: int, repeats: int) -> float:
    """World-steps per second through mujoco.rollout on all threads."""
    m = model.box_model(cfg, dist)
    nthread = os.cpu_count() or 1
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    d = datas[0]
    d.qpos[:] = model.initial_qpos(cfg, m)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s0, spec)
    init = np.tile(s0, (nbatch, 1))
    ctrl = np.tile(np.array([0.6, -0.6, *cfg.gripper.belt_y0]), (nbatch, nstep, 1))
    rates = []
    with mj_rollout.Rollout(nthread=nthread) as r:
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            r.rollout(m, datas, init, ctrl)
            rates.append(nbatch * nstep / (time.perf_counter() - t0))
    return statistics.median(rates[1:])


def mjx_batch(env: MjxEnv, params, batch: int, n_control: int, repeats: int) -> dict:
    """World-steps/s of jit(vmap(scan(env.pure_step))) over `batch` worlds for n_control control steps."""
    p = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), params)
    states = jax.jit(jax.vmap(env.pure_init))(p, jax.random.split(jax.random.PRNGKey(0), batch))
    acts = jnp.broadcast_to(jnp.asarray(ROTATE, jnp.float32), (batch, n_control, 4))

    chunk = default_chunk() if batch > (default_chunk() or batch) else None

    @jax.jit
    def run(states, acts):
        def one(s, a):
            return jax.lax.scan(lambda s, a: (env.pure_step(s, a), None), s, a)[0]

        return chunked_vmap(one, chunk)(states, acts).s

    first, med, _ = timed(run, states, acts, repeats=repeats)
    steps = batch * n_control * env.cfg.gripper.n_substeps
    return {
        "batch": batch,
        "vmap_chunk": chunk,
        "compile_s": first - med,
        "run_s": med,
        "world_steps_per_s": steps / med,
    }


def _log(msg: str):
    sys.stderr.write(f"[sim_throughput] {msg}\n")
    sys.stderr.flush()


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 512, 2048])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and steps (for smoke tests)")
    ap.add_argument(
        "--collider-batches",
        type=int,
        nargs="*",
        default=[64],
        help="MJX batches also timed with each other gripper.mjx_box_contacts (none: skip)",
    )
    args = ap.parse_args()
    cfg, dist = DEFAULT, massdist.named("A")
    reps = 2 if args.quick else 5
    out = {"benchmark": "sim_throughput", "machine": machine(), "physics_timestep_s": cfg.gripper.timestep}
    _log("native single thread")
    out["native_steps_per_s_1thread"] = native_single(cfg, dist, 2000 if args.quick else 20000, reps)
    _log("native mujoco.rollout")
    out["native_rollout_world_steps_per_s"] = native_rollout(cfg, dist, 64, 250 if args.quick else 1000, reps)
    out["native_rollout_threads"] = os.cpu_count()
    env = MjxEnv(cfg)
    params = env.box_params(dist)
    out["mjx"] = []
    for b in args.batches:
        # about the same number of world-steps per timed call at every batch size (>= 50k when b >= 64)
        n_control = 1 if args.quick else max(1, min(40, 2048 // max(b, 1)))
        _log(f"mjx batch {b}: {n_control} control steps per call")
        out["mjx"].append(mjx_batch(env, params, b, n_control, min(reps, 3)))
    out["mjx_box_contacts"] = cfg.gripper.mjx_box_contacts
    for kind in MJX_BOX_CONTACTS:
        if kind == cfg.gripper.mjx_box_contacts:
            continue
        other = MjxEnv(cfg.replace(gripper=dataclasses.replace(cfg.gripper, mjx_box_contacts=kind)))
        out[f"mjx_{kind}_contacts"] = []
        for b in args.collider_batches:
            n_control = 1 if args.quick else max(1, min(40, 2048 // max(b, 1)))
            _log(f"mjx batch {b}, {kind} contacts: {n_control} control steps per call")
            row = mjx_batch(other, other.box_params(dist), b, n_control, min(reps, 3))
            out[f"mjx_{kind}_contacts"].append(row)
    best = max(r["world_steps_per_s"] for r in out["mjx"])
    out["mjx_best_world_steps_per_s"] = best
    out["ratio_mjx_best_over_native_1thread"] = best / out["native_steps_per_s_1thread"]
    out["ratio_mjx_best_over_native_rollout"] = best / out["native_rollout_world_steps_per_s"]
    emit(out)


if __name__ == "__main__":
    main()
