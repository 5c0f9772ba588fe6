"""Exploration datasets for the estimator H (paper §2.2, Table 2): many random boxes, one batched run.

`generate(key, n_boxes, cfg)` samples `n_boxes` mass distributions (one vmapped, jitted call of
`massdist.sample_mixed`), runs the fixed exploration phase (`boxjax.estimator.explore`, 45 steps) on all of
them in
one batched open-loop rollout, and returns the estimator's training arrays. The default 2000 boxes give
90 000 transitions, the paper's ~90k.

Hazardous and safe boxes (documented proportion): each box is drawn from `massdist.sample_hazardous` with
probability `p_hazardous` (default 0.25, all mass inside one random region U1..U4) and otherwise from
`massdist.sample` (a free mixture of 1..3 gaussian bumps, itself hazardous about 4 % of the time). The
expected hazardous fraction is therefore p + (1 - p) x 0.042 = 28 % at the default; the realised labels
are stored (`hazardous`). Hazardous boxes are over-represented on purpose (4 % in the free prior): the
hazard check needs recall >= 0.98 and H must see enough of them.

Backends: "native" (`mujoco.rollout` on all CPU threads, the default: on the 2-core CPU it is much faster
than MJX for this workload, see `benchmark_backends`) or "mjx" (vmapped over boxes; the path for
accelerators). Both give the same arrays. The box count is processed in chunks (`chunk` boxes) so memory
stays bounded and the progress bar (tqdm, rate and ETA in transitions) moves.

Arrays (B boxes, T = 45 steps, grid nx x ny x nz):
  traj (B, T, 11) float32: per step the planar state before it (P1, P2, x, y, yaw; m, rad), the applied
    action (v1, v2 m/s, dp1, dp2 m) and the belt speeds measured at its end (m/s) (`explore.trajectory`);
  final (B, 5) float32: the planar state after the last step;
  occupancy (B, nx, ny, nz) float32 in {0, 1}; total_mass (B,) float32 kg;
  hazardous (B,) bool (`massdist.is_hazardous`);
  max_balance_error (B,) float32 m: the largest |y - (P1 + P2) / 2| during the phase (how safe it was);
  clipped (B,) bool: whether any action was clipped (never, with the default config).

Files (`save` / `load`): one compressed .npz, written atomically, with a JSON "__meta__" entry holding the
format version, the full Config, the seed, p_hazardous, backend, the exploration actions and timings.
`load` checks all of it against the expected config and raises `DatasetError` naming the problem.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from boxjax import config_io, geometry, massdist
from boxjax.config import DEFAULT, BoxConfig, Config, GripperConfig, TaskConfig
from boxjax.estimator import explore
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta
from boxjax.sim import mjx_backend, native

FORMAT = "boxjax-exploration-dataset"
FORMAT_VERSION = 1
P_HAZARDOUS = 0.25
DEFAULT_BOXES = 2000
ARRAYS = ("traj", "final", "occupancy", "total_mass", "hazardous", "max_balance_error", "clipped")
REQUIRED_META = ("config", "seed", "p_hazardous", "backend")


class DatasetError(ValueError):
    """A dataset file cannot be used: missing, corrupt, another format / version, or another config."""


@partial(jax.jit, static_argnums=1)
def _sample_boxes(keys, box, p_hazardous) -> massdist.MassDistribution:
    return jax.vmap(lambda k: massdist.sample_mixed(k, box, p_hazardous))(keys)


def sample_boxes(key: jax.Array, n_boxes: int, cfg: Config = DEFAULT, p_hazardous: float = P_HAZARDOUS):
    """`n_boxes` random distributions in one jitted, vmapped call (batched MassDistribution, leading axis
    n_boxes): hazardous with probability `p_hazardous`, else from the free prior (module docstring)."""
    if n_boxes < 1:
        raise ValueError(f"n_boxes must be >= 1, got {n_boxes}")
    if not 0.0 <= p_hazardous <= 1.0:
        raise ValueError(f"p_hazardous must be in [0, 1], got {p_hazardous}")
    return _sample_boxes(jax.random.split(key, n_boxes), cfg.box, jnp.float32(p_hazardous))


_trajectories = jax.jit(jax.vmap(explore.trajectory, in_axes=(0, 0, None)))


def _rollout(cfg: Config, dists, actions, backend: str, progress) -> dict:
    if backend == "native":
        return native.rollout(cfg, dists, actions, progress=progress)
    if backend == "mjx":
        out = mjx_backend.rollout(cfg, dists, actions)
        progress(actions.shape[0])
        return out
    raise ValueError(f"unknown backend {backend!r}; choose 'native' or 'mjx'")


def simulate(
    cfg: Config,
    dists: massdist.MassDistribution,
    *,
    backend: str = "native",
    progress: bool = True,
    chunk: int = 500,
) -> dict:
    """Run the exploration phase on given boxes (batched MassDistribution, leading axis B).

    Returns the dataset arrays (module docstring) for these boxes. Raises ValueError on an unknown backend.
    """
    if backend not in ("native", "mjx"):
        raise ValueError(f"unknown backend {backend!r}; choose 'native' or 'mjx'")
    occ = np.asarray(dists.occupancy, np.float32)
    mass = np.asarray(dists.total_mass, np.float32)
    n = occ.shape[0]
    actions = explore.exploration_actions(cfg)
    applied = jnp.asarray(explore.applied_actions(cfg))
    parts = []
    bar = tqdm(
        total=n * explore.N_STEPS,
        desc=f"explore ({backend})",
        unit="transition",
        unit_scale=True,
        disable=not progress,
        leave=False,
    )
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        done = [0]

        def tick(t, width=hi - lo, done=done):
            bar.update(width * (t - done[0]))
            done[0] = t

        out = _rollout(cfg, massdist.MassDistribution(occ[lo:hi], mass[lo:hi]), actions, backend, tick)
        traj, final = _trajectories(out["s"], out["belt_speed"], applied)
        s = out["s"]
        bal = np.abs(s[..., geometry.Y] - 0.5 * (s[..., geometry.P1] + s[..., geometry.P2]))
        parts.append(
            dict(
                traj=np.asarray(traj),
                final=np.asarray(final),
                max_balance_error=bal.max(axis=1).astype(np.float32),
                clipped=np.asarray(out["clipped"]).any(axis=1),
            )
        )
    bar.close()
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    hazardous = jax.jit(jax.vmap(lambda d: massdist.is_hazardous(d, cfg.box)))(
        massdist.MassDistribution(jnp.asarray(occ), jnp.asarray(mass))
    )
    data.update(occupancy=occ, total_mass=mass, hazardous=np.asarray(hazardous))
    if not np.all(np.isfinite(data["traj"])):
        raise FloatingPointError("the simulation produced NaN / inf in an exploration trajectory")
    return {k: data[k] for k in ARRAYS}


def generate(
    key: jax.Array,
    n_boxes: int = DEFAULT_BOXES,
    cfg: Config = DEFAULT,
    *,
    p_hazardous: float = P_HAZARDOUS,
    backend: str = "native",
    progress: bool = True,
    chunk: int = 500,
) -> dict:
    """Exploration trajectories of `n_boxes` random boxes (arrays listed in the module docstring).

    Args:
      key: PRNG key; split into the boxes' keys (the rollout itself is deterministic).
      n_boxes: number of boxes (default 2000 = 90k transitions).
      cfg: the Config (box grid, gripper).
      p_hazardous: probability that a box is drawn hazardous (module docstring).
      backend: "native" or "mjx".
      progress: show a tqdm bar (transitions, rate, ETA).
      chunk: boxes per batched rollout call.
    Returns:
      dict of numpy arrays; plus "seconds" is NOT included (time it from outside).
    """
    key_boxes, _ = jax.random.split(key)
    dists = sample_boxes(key_boxes, n_boxes, cfg, p_hazardous)
    return simulate(cfg, dists, backend=backend, progress=progress, chunk=chunk)


def make_meta(cfg: Config, seed, p_hazardous: float, backend: str, **extra) -> dict:
    """The metadata `save` requires: config, seed, p_hazardous, backend (+ any JSON-serialisable extras)."""
    return {
        "config": cfg.to_dict(),
        "seed": seed,
        "p_hazardous": float(p_hazardous),
        "backend": backend,
        **extra,
    }


def summary(data: dict) -> dict:
    """Plain-number summary: boxes, transitions, hazardous fraction, balance error during exploration."""
    bal = np.asarray(data["max_balance_error"])
    return {
        "boxes": int(len(bal)),
        "transitions": int(np.prod(np.shape(data["traj"])[:2])),
        "hazardous_fraction": float(np.mean(data["hazardous"])),
        "max_balance_error_cm_median": float(100 * np.median(bal)),
        "max_balance_error_cm_p95": float(100 * np.quantile(bal, 0.95)),
        "max_balance_error_cm_safe_p95": float(100 * np.quantile(bal[~np.asarray(data["hazardous"])], 0.95))
        if np.any(~np.asarray(data["hazardous"]))
        else float("nan"),
        "any_clipped": bool(np.any(data["clipped"])),
    }


def _described(section, part: str) -> dict:
    """A config section as the dataset check compares it: every field but MJX's contact finder (how the data
    were simulated, like the backend, not what they describe: `config_io.GRIPPER_FIELDS`)."""
    d = dataclasses.asdict(section)
    return _canonical(
        {k: v for k, v in d.items() if part != "gripper" or f"gripper.{k}" in config_io.GRIPPER_FIELDS}
    )


def _canonical(x):
    return json.loads(json.dumps(x))


def save(path: str | os.PathLike, data: dict, meta: dict) -> str:
    """Write `data` (the arrays of `generate`) and `meta` (see `make_meta`) to ONE compressed .npz,
    atomically (a crash never leaves a half-written file under `path`). The exploration actions, format
    name and version are added to the metadata. Returns the path."""
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise ValueError(f"dataset metadata lacks {missing} (use make_meta)")
    absent = [k for k in ARRAYS if k not in data]
    if absent:
        raise ValueError(f"dataset lacks arrays {absent}")
    cfg = _config_from_dict(meta["config"])
    full = dict(meta, exploration_actions=explore.exploration_actions(cfg).tolist())
    arrays = {k: np.asarray(data[k]) for k in ARRAYS}
    return write_npz_with_meta(path, arrays, _canonical(full), FORMAT, FORMAT_VERSION)


def _config_from_dict(d: dict) -> Config:

    def tup(sub):
        return {k: tuple(v) if isinstance(v, list) else v for k, v in sub.items()}

    return Config(
        box=BoxConfig(**tup(d["box"])),
        gripper=GripperConfig(**tup(d["gripper"])),
        task=TaskConfig(**tup(d["task"])),
    )


def load(path: str | os.PathLike, expected_cfg: Config | None = DEFAULT) -> tuple[dict, dict]:
    """Read a dataset written by `save`: (arrays dict, meta dict).

    Args:
      expected_cfg: the Config the data must have been generated with (box and gripper must match: they
        shape the trajectories); None skips the check.
    Raises:
      DatasetError naming the problem: missing file, not a dataset / corrupt, other format version, other
      box or gripper config, other exploration sequence, missing arrays or inconsistent shapes, NaN.
    """
    path = os.fspath(path)
    arrays, meta = read_npz_with_meta(path, DatasetError, "dataset", FORMAT, FORMAT_VERSION)
    try:
        cfg = _config_from_dict(meta["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: unreadable config in the dataset metadata ({e})") from e
    if expected_cfg is not None:
        for part in ("box", "gripper"):
            got, want = (_described(getattr(c, part), part) for c in (cfg, expected_cfg))
            if got != want:
                diff = sorted(k for k in want if got.get(k) != want[k])
                got_d, want_d = {k: got.get(k) for k in diff}, {k: want[k] for k in diff}
                raise DatasetError(
                    f"{path}: generated with another {part} config (differs in {diff}: "
                    f"{got_d} vs expected {want_d})"
                )
        want_actions = explore.exploration_actions(expected_cfg)
        got_actions = np.asarray(meta.get("exploration_actions", []), np.float32)
        if got_actions.shape != want_actions.shape or not np.allclose(got_actions, want_actions, atol=1e-7):
            raise DatasetError(
                f"{path}: generated with a different exploration sequence than "
                "boxjax.estimator.explore's; regenerate it"
            )
    missing = [k for k in ARRAYS if k not in arrays]
    if missing:
        raise DatasetError(f"{path}: missing arrays {missing}")
    b = arrays["traj"].shape[0]
    grid = tuple(cfg.box.grid)
    shapes = {
        "traj": (b, explore.N_STEPS, explore.N_TRAJ_COLUMNS),
        "final": (b, 5),
        "occupancy": (b, *grid),
        "total_mass": (b,),
        "hazardous": (b,),
        "max_balance_error": (b,),
        "clipped": (b,),
    }
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise DatasetError(f"{path}: array {k!r} has shape {arrays[k].shape}, expected {shape}")
    for k in ("traj", "final", "occupancy", "total_mass"):
        if not np.all(np.isfinite(arrays[k])):
            raise DatasetError(f"{path}: array {k!r} contains NaN or inf")
    return arrays, meta


def benchmark_backends(cfg: Config = DEFAULT, n_boxes: int = 64, seed: int = 0) -> dict:
    """Wall time of the exploration rollout of `n_boxes` boxes on each backend (first call = compile +
    run, second = run), and the largest state difference between them."""
    dists = sample_boxes(jax.random.key(seed), n_boxes, cfg)
    res, outs = {}, {}
    for backend in ("native", "mjx"):
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            outs[backend] = simulate(cfg, dists, backend=backend, progress=False, chunk=n_boxes)
            times.append(time.perf_counter() - t0)
        res[backend] = {
            "first_s": times[0],
            "second_s": times[1],
            "transitions_per_s": n_boxes * explore.N_STEPS / times[1],
        }
    res["max_abs_traj_diff"] = float(np.max(np.abs(outs["native"]["traj"] - outs["mjx"]["traj"])))
    res["boxes"] = n_boxes
    return res
