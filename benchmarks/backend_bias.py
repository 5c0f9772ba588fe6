"""Are native MuJoCo and MJX the same simulator for this gripper, in distribution? Paired statistics over
random boxes, not single trajectories (a slipping box is chaotic: one trajectory says little).

Every box of `--boxes` (`massdist.sample`, `--seed`) runs the same open-loop action sequences (the 45-step
exploration H reads; 2 s of spin with the belts at +-0.1 m/s; 2 s of spin with carriage moves) in:

- native MuJoCo (the reference),
- native MuJoCo with the box's start moved by a random shift of at most 1e-6 m (`TaskConfig.init_xy_noise`):
  what chaos alone gives (the control),
- MJX with each box-belt collider of `config.MJX_BOX_CONTACTS` (MJX's own; "polygon"; "native", native
  MuJoCo's rules: `boxjax.sim.mjx_contacts`), each also with the 1e-6 m shift (its own sensitivity).

For each sequence and simulator: the paired difference of the final yaw, x and y from the reference (mean,
standard error, median of the absolute values). A mean several standard errors from 0 where the control's
is not is a systematic difference between the simulators, which statistics of their episodes inherit.

Prints ONE JSON object (the last line).
Run: python benchmarks/backend_bias.py [--boxes 64] [--seed 123] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time

import jax
import mujoco
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit_to, machine  # noqa: E402

from boxjax import massdist  # noqa: E402
from boxjax.config import DEFAULT, MJX_BOX_CONTACTS  # noqa: E402
from boxjax.estimator import explore  # noqa: E402
from boxjax.sim import core, mjx_backend, model, native  # noqa: E402

SHIFT = 1e-6  # m


def sequences(cfg) -> dict[str, np.ndarray]:
    spin = np.array([0.1, -0.1, 0.0, 0.0])
    return {
        "exploration": np.asarray(explore.exploration_actions(cfg), np.float64),
        "spin": np.tile(spin, (40, 1)),
        "spin_carriage": np.concatenate(
            [
                np.tile(spin, (10, 1)),
                np.tile(spin + [0, 0, 0, 0.005], (10, 1)),
                np.tile(spin + [0, 0, 0, -0.005], (20, 1)),
            ]
        ),
    }


def with_shift(cfg):
    """The config whose start pose is shifted by U(-SHIFT, SHIFT) in x and y (MJX's rollouts draw it)."""
    return cfg.replace(task=dataclasses.replace(cfg.task, init_xy_noise=SHIFT))


@functools.lru_cache(maxsize=4)
def _command(cfg):
    """`core.command` jitted once per config: (action, belt activations, targets) -> ctrl, targets."""
    return jax.jit(lambda a, v, p: core.command(cfg, a, v, p)[:2])


def native_final(cfg, dist, actions, key=None) -> np.ndarray:
    """(5,) planar state after `actions`, native MuJoCo, stepped as `NativeEnv` steps it; with `key`, the
    start moved by U(-SHIFT, SHIFT) in x and y (in float64, nothing else rounded)."""
    m = model.box_model(cfg, dist)
    idx = model.ids(m)
    d = mujoco.MjData(m)
    d.qpos[:] = model.initial_qpos(cfg, m)
    if key is not None:
        d.qpos[idx.box_qpos : idx.box_qpos + 2] += np.asarray(
            jax.random.uniform(key, (2,), minval=-SHIFT, maxval=SHIFT)
        )
    p = np.asarray(cfg.gripper.belt_y0)
    d.ctrl[model.CARRIAGE1_P], d.ctrl[model.CARRIAGE2_P] = p
    for a in actions:
        ctrl, p = _command(cfg)(a, d.act[[model.BELT1_V, model.BELT2_V]], p)
        d.ctrl[:] = np.asarray(ctrl)
        p = np.asarray(p)
        for _ in range(cfg.gripper.n_substeps):
            mujoco.mj_step(m, d)
        native.recentre_belts(idx, d.qpos)
    return np.asarray(core.planar_state(idx, d.qpos))


def paired(finals: np.ndarray, reference: np.ndarray) -> dict:
    """Mean, standard error and median |.| of final - reference for yaw (deg), x and y (mm)."""
    d = finals - reference
    n = len(d)
    out = {}
    for j, name, scale in ((4, "yaw_deg", 180 / np.pi), (2, "x_mm", 1e3), (3, "y_mm", 1e3)):
        v = d[:, j] * scale
        out[name] = {
            "mean": float(v.mean()),
            "se": float(v.std(ddof=1) / np.sqrt(n)),
            "median_abs": float(np.median(np.abs(v))),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", type=int, default=64)
    ap.add_argument("--seed", type=int, default=123)
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if args.boxes < 2:
        ap.error("--boxes must be >= 2 (a standard error needs two)")
    cfg = DEFAULT
    dists = [massdist.sample(k, cfg.box) for k in jax.random.split(jax.random.PRNGKey(args.seed), args.boxes)]
    shift_keys = jax.random.split(jax.random.PRNGKey(args.seed + 1), args.boxes)
    results = {}
    t_all = time.perf_counter()
    for name, actions in sequences(cfg).items():
        t0 = time.perf_counter()
        ref = np.stack([native_final(cfg, d, actions) for d in dists])
        shifted = [native_final(cfg, d, actions, k) for d, k in zip(dists, shift_keys, strict=True)]
        rows = {"native_shifted": paired(np.stack(shifted), ref)}
        for contacts in MJX_BOX_CONTACTS:
            c = cfg.replace(gripper=dataclasses.replace(cfg.gripper, mjx_box_contacts=contacts))
            plain = mjx_backend.rollout(c, dists, actions)["s"][:, -1]
            shifted = mjx_backend.rollout(
                with_shift(c), dists, actions, key=jax.random.PRNGKey(args.seed + 1)
            )["s"][:, -1]
            rows[f"mjx_{contacts}"] = paired(plain, ref)
            rows[f"mjx_{contacts}_shifted_vs_itself"] = paired(shifted, plain)
        rows["native_mean_final_yaw_deg"] = float(np.degrees(ref[:, 4]).mean())
        rows["seconds"] = time.perf_counter() - t0
        results[name] = rows
        print(f"{name}: {rows['seconds']:.0f} s", file=sys.stderr, flush=True)
    emit_to(
        {
            "benchmark": "backend_bias",
            "boxes": args.boxes,
            "seed": args.seed,
            "shift_m": SHIFT,
            **machine(),
            "sequences": results,
            "wall_s": time.perf_counter() - t_all,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
