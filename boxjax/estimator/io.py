"""H's checkpoints (`boxjax.estimator`): one compressed .npz with a JSON header, no pickle; `load` checks
the format, version, box grid and every array's shape. `estimator` re-exports `save`, `load` and
`CheckpointError`.
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from boxjax.config import BoxConfig
from boxjax.estimator.net import (
    HEADS,
    N_STEP_FEATURES,
    EstimatorConfig,
    EstimatorParams,
    Normaliser,
    init_members,
)
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta

# ----------------------------------------------------------------------------------------------------------
# Checkpoints: one compressed .npz, no pickle.

FORMAT = "boxjax-estimator"
FORMAT_VERSION = 3  # 2: 11-column trajectories (measured belt speeds), 20 features per step; 3: hazard head


class CheckpointError(ValueError):
    """A checkpoint cannot be loaded: not a boxjax checkpoint, corrupt, wrong version, or incompatible."""


def _flat_arrays(model: EstimatorParams) -> dict[str, np.ndarray]:
    out = {}
    for part, layers in model.net.items():
        for i, layer in enumerate(layers):
            for name, arr in layer.items():
                out[f"net.{part}.{i}.{name}"] = np.asarray(arr, np.float32)
    for name, arr in model.norm._asdict().items():
        out[f"norm.{name}"] = np.asarray(arr, np.float32)
    return out


def _expected_shapes(cfg: EstimatorConfig, n_features: int, n_voxels: int) -> dict[str, tuple[int, ...]]:
    net = jax.eval_shape(lambda k: init_members(k, n_features, n_voxels, cfg), jax.random.key(0))
    shapes = {
        f"net.{part}.{i}.{name}": tuple(arr.shape)
        for part, layers in net.items()
        for i, layer in enumerate(layers)
        for name, arr in layer.items()
    }
    shapes.update(
        {
            "norm.feat_mean": (n_features,),
            "norm.feat_std": (n_features,),
            "norm.mass_mean": (),
            "norm.mass_std": (),
        }
    )
    return shapes


def save(path: str | os.PathLike, model: EstimatorParams) -> None:
    """Write the model to ONE compressed .npz at `path` (exactly that name), atomically.

    Contents: the network and normalisation arrays ("net.<part>.<layer>.<w|b>", "norm.<field>") and
    "__meta__", a one-element string array holding JSON: format name and version, EstimatorConfig,
    BoxConfig, n_steps, n_features and the provenance dict. Written to a temporary file in the same
    directory, flushed to disk, then renamed over `path`, so a crash never leaves a half-written
    checkpoint under the final name.
    """
    path = os.fspath(path)
    meta = {
        "estimator_config": model.cfg.to_dict(),
        "box": dataclasses.asdict(model.box),
        "n_steps": model.n_steps,
        "n_features": model.n_features,
        "provenance": model.provenance,
        "occupancy_threshold": model.occupancy_threshold,
        "hazard_threshold": model.hazard_threshold,
    }
    arrays = _flat_arrays(model)
    expected = _expected_shapes(model.cfg, model.n_features, model.box.n_voxels)
    got = {k: v.shape for k, v in arrays.items()}
    if got != expected:
        raise ValueError("model arrays do not match its own config; refusing to save an unloadable file")
    write_npz_with_meta(path, arrays, meta, FORMAT, FORMAT_VERSION)


def load(path: str | os.PathLike, expected_box_config: BoxConfig | None = None) -> EstimatorParams:
    """Read a checkpoint written by `save`.

    Args:
      path: the .npz file.
      expected_box_config: if given, the checkpoint's grid and box size must equal this config's.
    Raises:
      CheckpointError naming the problem: missing file, not a boxjax checkpoint or corrupt, unsupported
      format version, grid / box size different from the expected config, missing or unexpected arrays,
      shape mismatch, non-finite values.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":  # every .npz is a zip archive
        raise CheckpointError(f"{path}: not a boxjax checkpoint (not an .npz / zip file)")
    arrays, meta = read_npz_with_meta(path, CheckpointError, "checkpoint", FORMAT, FORMAT_VERSION)
    try:
        cfg = EstimatorConfig.from_dict(meta["estimator_config"])
        b = meta["box"]
        box = BoxConfig(**{**b, **{k: tuple(b[k]) for k in ("size", "grid", "mass_range")}})
        n_steps, n_features = int(meta["n_steps"]), int(meta["n_features"])
        provenance = meta.get("provenance", {})
        occupancy_threshold = float(meta.get("occupancy_threshold", 0.5))
        hazard_threshold = float(meta.get("hazard_threshold", 0.5))
        if not (0 < occupancy_threshold < 1 and 0 < hazard_threshold < 1):
            raise ValueError(f"thresholds must lie in (0, 1): {occupancy_threshold}, {hazard_threshold}")
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(
            f"{path}: unreadable checkpoint metadata (corrupt, or configs this boxjax does not know): "
            f"{type(e).__name__}: {e}"
        ) from e
    if n_features != n_steps * N_STEP_FEATURES:
        raise CheckpointError(
            f"{path}: {n_features} features for {n_steps} steps; this boxjax builds "
            f"{N_STEP_FEATURES} per step"
        )
    if expected_box_config is not None:
        if tuple(box.grid) != tuple(expected_box_config.grid):
            raise CheckpointError(
                f"{path}: checkpoint voxel grid {tuple(box.grid)} differs from the expected grid "
                f"{tuple(expected_box_config.grid)}"
            )
        if not np.allclose(box.size, expected_box_config.size):
            raise CheckpointError(
                f"{path}: checkpoint box size {tuple(box.size)} m differs from the expected "
                f"{tuple(expected_box_config.size)} m"
            )

    expected = _expected_shapes(cfg, n_features, box.n_voxels)
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise CheckpointError(f"{path}: missing arrays {missing}")
    unexpected = sorted(set(arrays) - set(expected))
    if unexpected:
        raise CheckpointError(f"{path}: unexpected arrays {unexpected} for the stored config")
    for k, shape in expected.items():
        if arrays[k].shape != shape:
            raise CheckpointError(f"{path}: array {k!r} has shape {arrays[k].shape}, expected {shape}")
        if not np.all(np.isfinite(arrays[k])):
            raise CheckpointError(f"{path}: array {k!r} contains NaN or inf")

    def layers(part: str) -> list[dict]:
        n = len([k for k in expected if k.startswith(f"net.{part}.") and k.endswith(".w")])
        return [
            {name: jnp.asarray(arrays[f"net.{part}.{i}.{name}"], jnp.float32) for name in ("w", "b")}
            for i in range(n)
        ]

    net = {part: layers(part) for part in HEADS}
    norm = Normaliser(*(jnp.asarray(arrays[f"norm.{f}"], jnp.float32) for f in Normaliser._fields))
    return EstimatorParams(
        net=net,
        norm=norm,
        cfg=cfg,
        box=box,
        n_steps=n_steps,
        provenance_json=json.dumps(provenance, sort_keys=True),
        occupancy_threshold=occupancy_threshold,
        hazard_threshold=hazard_threshold,
    )
