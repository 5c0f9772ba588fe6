"""H's network and its prediction (`boxjax.estimator`): the settings and containers, the per-step
features of an exploration trajectory, the ensemble MLP's forward pass, the host-side reading and checks
of trajectories and datasets, and the prediction of occupancy, mass and hazard from one. Training,
metrics and checkpoints build on this module (`estimator`, `estimator.metrics`, `estimator.io`);
`estimator` re-exports all.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import mlp
from boxjax.config import BoxConfig, ConfigError
from boxjax.geometry import P1, P2, YAW, X, Y, wrap_angle
from boxjax.massdist import MassDistribution

N_STATE = 5  # (P1, P2, x, y, yaw)
N_ACTION = 4  # (v1, v2, dp1, dp2)
N_STEP_FEATURES = 20  # see `features`
N_TRAJ_COLUMNS = N_STATE + N_ACTION + 2  # + measured belt speeds (2)
MIN_MASS = 1e-3  # kg, floor on a predicted total mass (mass properties need M > 0)

_ACTIVATIONS = {"gelu": jax.nn.gelu, "relu": jax.nn.relu, "tanh": jnp.tanh}


# ----------------------------------------------------------------------------------------------------------
# Configuration and containers.


@dataclass(frozen=True)
class EstimatorConfig:
    """Size and training of H. Plain frozen dataclass (hashable, static under jit)."""

    hidden: tuple[int, ...] = (512, 512, 512)  # trunk widths; heads are linear on the last one
    activation: str = "gelu"  # one of "gelu", "relu", "tanh"
    learning_rate: float = 1e-3  # AdamW step size
    weight_decay: float = 1e-4  # AdamW decoupled weight decay
    grad_clip: float = 1.0  # global-norm gradient clipping
    batch_size: int = 64  # examples per minibatch (capped at the training-set size)
    max_epochs: int = 400
    patience: int = 40  # stop after this many epochs without a new best validation loss
    mass_weight: float = 1.0  # weight of the mass MSE (standardised mass) against the mean voxel BCE
    hazard_weight: float = 1.0  # weight of the hazard head's BCE (label: massdist.is_hazardous of the truth)
    iou_weight: float = 0.0  # weight of the soft Jaccard loss 1 - sum(p t) / sum(p + t - p t) per box
    com_weight: float = 0.0  # weight of the soft centre-of-mass error |com(p) - com|^2 / (5 cm)^2
    input_noise: float = 0.0  # std of gaussian noise added to the standardised features while training
    val_fraction: float = 0.15  # held-out share of the boxes (at least one box)
    members: int = 1  # ensemble size: independently initialised nets trained side by side (vmap)
    seed: int = 0  # used by `train` when no key is passed

    def __post_init__(self):
        if len(self.hidden) < 1 or min(self.hidden) < 1:
            raise ConfigError(f"hidden must be a non-empty tuple of positive widths, got {self.hidden}")
        if self.activation not in _ACTIVATIONS:
            raise ConfigError(f"activation {self.activation!r} not in {sorted(_ACTIVATIONS)}")
        if not (self.learning_rate > 0 and self.weight_decay >= 0 and self.grad_clip > 0):
            raise ConfigError("need learning_rate > 0, weight_decay >= 0, grad_clip > 0")
        if self.batch_size < 1 or self.max_epochs < 1 or self.patience < 1 or self.members < 1:
            raise ConfigError("batch_size, max_epochs, patience and members must be >= 1")
        if min(self.mass_weight, self.hazard_weight, self.iou_weight, self.com_weight, self.input_noise) < 0:
            raise ConfigError(
                "mass_weight, hazard_weight, iou_weight, com_weight and input_noise must be >= 0"
            )
        if not 0 < self.val_fraction < 1:
            raise ConfigError(f"val_fraction must be in (0, 1), got {self.val_fraction}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EstimatorConfig:
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ConfigError(f"unknown EstimatorConfig fields {sorted(unknown)}")
        d = dict(d)
        if "hidden" in d:
            d["hidden"] = tuple(int(h) for h in d["hidden"])
        return cls(**d)


class Normaliser(NamedTuple):
    """Training-set statistics. feat_mean, feat_std: (F,); mass_mean, mass_std: () kg."""

    feat_mean: jax.Array
    feat_std: jax.Array
    mass_mean: jax.Array
    mass_std: jax.Array


class Batch(NamedTuple):
    """Training examples, already standardised. x: (B, F); occ: (B, V) in {0, 1}; mass: (B,) standardised;
    com: (B, 3) m, centre of mass of the occupied voxels (box frame), or None (then com_weight is unused);
    hazard: (B,) in {0, 1}, the paper's hazard label of the truth, or None (then hazard_weight is unused)."""

    x: jax.Array
    occ: jax.Array
    mass: jax.Array
    com: jax.Array | None = None
    hazard: jax.Array | None = None


class Prediction(NamedTuple):
    """H's output for one box (or a batch, with a leading axis B), ensemble-averaged.

    prob: (nx, ny, nz) per-voxel occupancy probability; mass: () kg total mass (>= MIN_MASS);
    hazard: () probability that the box is hazardous (the hazard head; `predict_hazard` decides)."""

    prob: jax.Array
    mass: jax.Array
    hazard: jax.Array


@dataclass(frozen=True)
class EstimatorParams:
    """A trained H: a pytree whose leaves are the network and the normalisation statistics.

    net: {"trunk": mlp params, "occ": mlp params (one linear layer to V = nx*ny*nz logits),
          "mass": mlp params (one linear layer to 1), "hazard": mlp params (one linear layer to 1)},
          every leaf with a leading ensemble axis of size cfg.members (the members' predictions are
          averaged: probabilities, masses and hazard probabilities).
    norm: `Normaliser`.
    Static (pytree metadata, hashable): cfg, box (grid and size the occupancy refers to), n_steps (T the
    features were built for), provenance_json (JSON text: seed, data sizes, versions; see `provenance`),
    and the two calibrated decision thresholds (`calibrate`):
      occupancy_threshold: a voxel is occupied when its probability exceeds it (`to_distribution`);
      hazard_threshold: the box is declared hazardous when the hazard head's probability exceeds it
        (`predict_hazard`). A lower value flags more boxes: recall goes up, precision down.
    """

    net: dict
    norm: Normaliser
    cfg: EstimatorConfig
    box: BoxConfig
    n_steps: int
    provenance_json: str = "{}"
    occupancy_threshold: float = 0.5
    hazard_threshold: float = 0.5

    @property
    def provenance(self) -> dict:
        return json.loads(self.provenance_json)

    @property
    def n_features(self) -> int:
        return self.n_steps * N_STEP_FEATURES


jax.tree_util.register_dataclass(
    EstimatorParams,
    data_fields=["net", "norm"],
    meta_fields=["cfg", "box", "n_steps", "provenance_json", "occupancy_threshold", "hazard_threshold"],
)


# ----------------------------------------------------------------------------------------------------------
# Features and the network.


def features(traj: jax.Array, final: jax.Array) -> jax.Array:
    """(T * 20,) features of ONE exploration trajectory (module docstring lists them).

    Args:
      traj: (T, 11) states before each step (5), applied actions (4), belt speeds measured at the end of
        each step (2); see the module docstring for units.
      final: (5,) state after the last step.
    Returns:
      (T * 20,) float32, step-major: [ds (5), box-frame dx, dy (2), P1 - y, P2 - y (2), carriage lag (2),
      belt speed lag (2), pose after the step minus the start pose (x, y, yaw) (3), a (4)] for t = 0..T-1.
    """
    s = traj[:, :N_STATE]
    a = traj[:, N_STATE : N_STATE + N_ACTION]
    w = traj[:, N_STATE + N_ACTION :]
    s_next = jnp.concatenate([s[1:], final[None, :]], axis=0)
    ds = s_next - s
    ds = ds.at[:, YAW].set(wrap_angle(ds[:, YAW]))
    c, si = jnp.cos(s[:, YAW]), jnp.sin(s[:, YAW])
    dx_box = c * ds[:, X] + si * ds[:, Y]
    dy_box = -si * ds[:, X] + c * ds[:, Y]
    belts_rel = s[:, (P1, P2)] - s[:, Y : Y + 1]
    # Differences first, then sums: P ~ 0.1 m, the lags ~ 1e-4 m (float32 keeps ~1e-8 m either way).
    carriage_lag = jnp.cumsum(ds[:, (P1, P2)] - a[:, 2:4], axis=0)
    belt_lag = a[:, :2] - w
    pose = jnp.cumsum(ds[:, (X, Y, YAW)], axis=0)
    f = jnp.concatenate(
        [ds, dx_box[:, None], dy_box[:, None], belts_rel, carriage_lag, belt_lag, pose, a], axis=1
    )
    return f.reshape(-1).astype(jnp.float32)


def init_members(key: jax.Array, n_features: int, n_voxels: int, cfg: EstimatorConfig) -> dict:
    """`cfg.members` independently initialised nets stacked on a leading axis (the ensemble)."""
    return jax.vmap(lambda k: init_net(k, n_features, n_voxels, cfg))(jax.random.split(key, cfg.members))


def _select_members(mask: jax.Array, new: dict, old: dict) -> dict:
    """Per member (leading axis), `new` where mask else `old`."""
    return jax.tree.map(lambda a, b: jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), new, old)


def init_net(key: jax.Array, n_features: int, n_voxels: int, cfg: EstimatorConfig) -> dict:
    """Network params: trunk (F -> hidden...) and linear heads (-> V occupancy logits, -> 1 standardised
    mass, -> 1 hazard logit)."""
    key_trunk, key_occ, key_mass, key_hazard = jax.random.split(key, 4)
    width = cfg.hidden[-1]
    return {
        "trunk": mlp.init(key_trunk, (n_features, *cfg.hidden), last_scale=1.0),
        "occ": mlp.init(key_occ, (width, n_voxels)),
        "mass": mlp.init(key_mass, (width, 1)),
        "hazard": mlp.init(key_hazard, (width, 1)),
    }


HEADS = ("trunk", "occ", "mass", "hazard")  # the parts of one net, in checkpoint order


def _forward(net: dict, x: jax.Array, cfg: EstimatorConfig) -> tuple[jax.Array, jax.Array, jax.Array]:
    """ONE standardised feature vector (F,) -> (occupancy logits (V,), standardised mass (), hazard
    logit ())."""
    act = _ACTIVATIONS[cfg.activation]
    h = mlp.apply(net["trunk"], x, act, activate_last=True)
    return mlp.apply(net["occ"], h), mlp.apply(net["mass"], h)[0], mlp.apply(net["hazard"], h)[0]


# ----------------------------------------------------------------------------------------------------------
# Trajectories in, predictions out (host checks, standardisation).


def _get(dataset, name: str):
    if isinstance(dataset, Mapping) or hasattr(dataset, "files"):  # dict or np.load(...) of an .npz
        if name not in dataset:
            raise ValueError(f"dataset has no {name!r} array (need traj, final, occupancy, total_mass)")
        return dataset[name]
    if not hasattr(dataset, name):
        raise ValueError(f"dataset has no {name!r} field (need traj, final, occupancy, total_mass)")
    return getattr(dataset, name)


def _dataset_arrays(dataset, box: BoxConfig | None = None, n_steps: int | None = None):
    """Validated float32 numpy (traj (B,T,11), final (B,5), occupancy (B,nx,ny,nz), total_mass (B,))."""
    traj, final, occ, mass = (
        np.asarray(_get(dataset, k), np.float32) for k in ("traj", "final", "occupancy", "total_mass")
    )
    _check_traj(traj, final, n_steps, batched=True)
    b = traj.shape[0]
    if occ.ndim != 4 or occ.shape[0] != b:
        raise ValueError(f"occupancy must have shape (B={b}, nx, ny, nz), got {occ.shape}")
    if box is not None and occ.shape[1:] != tuple(box.grid):
        raise ValueError(
            f"occupancy grid {occ.shape[1:]} differs from the box grid {tuple(box.grid)}; pass the "
            "BoxConfig the dataset was generated with"
        )
    if mass.shape != (b,):
        raise ValueError(f"total_mass must have shape (B={b},), got {mass.shape}")
    if not (np.all(np.isfinite(occ)) and np.all(np.isfinite(mass))):
        raise ValueError("occupancy or total_mass contains NaN or inf")
    if np.any((occ != 0) & (occ != 1)):
        raise ValueError("occupancy must be 0 or 1 in every voxel")
    if np.any(mass <= 0):
        raise ValueError("total_mass must be > 0 kg for every box")
    return traj, final, occ, mass


def _check_traj(traj: np.ndarray, final: np.ndarray, n_steps: int | None, batched: bool) -> None:
    """Raise ValueError unless traj is ([B,] T, 11) and final ([B,] 5), finite, with T == n_steps if
    given."""
    lead = "(B, T, 11)" if batched else "(T, 11)"
    want_ndim = 3 if batched else 2
    if traj.ndim != want_ndim or traj.shape[-1] != N_TRAJ_COLUMNS:
        raise ValueError(
            f"trajectory must have shape {lead} (5 state + 4 action + 2 measured belt speed columns per "
            f"step, see boxjax.estimator.explore.trajectory), got {traj.shape}"
        )
    if n_steps is not None and traj.shape[-2] != n_steps:
        raise ValueError(
            f"trajectory has {traj.shape[-2]} steps but the estimator was trained on {n_steps}-step "
            "exploration trajectories"
        )
    if traj.shape[-2] < 1:
        raise ValueError("trajectory has no steps")
    if final.shape != (*traj.shape[:-2], N_STATE):
        raise ValueError(f"final state must have shape {(*traj.shape[:-2], N_STATE)}, got {final.shape}")
    for name, arr in (("trajectory", traj), ("final state", final)):
        bad = ~np.isfinite(arr)
        if np.any(bad):
            where = np.argwhere(bad)[0].tolist()
            raise ValueError(f"{name} contains NaN or inf ({int(bad.sum())} values; first at index {where})")


def _standardise(x: jax.Array, norm: Normaliser) -> jax.Array:
    return (x - norm.feat_mean) / norm.feat_std


# ----------------------------------------------------------------------------------------------------------
# Prediction.


def predict(model: EstimatorParams, traj: jax.Array, final: jax.Array) -> Prediction:
    """H on ONE exploration trajectory (pure; vmap over traj and final for batches).

    Args:
      model: a trained EstimatorParams.
      traj: (T, 11) with T == model.n_steps; final: (5,). Not validated here: see `predict_checked`.
    Returns:
      Prediction(prob (nx, ny, nz) per-voxel occupancy probability, mass () kg floored at MIN_MASS,
      hazard () probability of a hazardous box), each the mean over the ensemble members.
    """
    x = _standardise(features(traj, final), model.norm)
    logits, mass_std, hazard_logit = jax.vmap(_forward, in_axes=(0, None, None))(model.net, x, model.cfg)
    prob = jnp.mean(jax.nn.sigmoid(logits), axis=0)
    mass = jnp.mean(mass_std) * model.norm.mass_std + model.norm.mass_mean
    hazard = jnp.mean(jax.nn.sigmoid(hazard_logit))
    return Prediction(prob.reshape(model.box.grid), jnp.maximum(mass, MIN_MASS), hazard)


def predict_members(model: EstimatorParams, traj: jax.Array, final: jax.Array) -> Prediction:
    """H's ensemble members one by one on ONE trajectory: a Prediction whose fields have a leading axis
    of size cfg.members (`predict` is their mean). The members' spread is H's uncertainty about the box
    (the controller can plan over it: `ControllerConfig.belief = "ensemble"`)."""
    x = _standardise(features(traj, final), model.norm)
    logits, mass_std, hazard_logit = jax.vmap(_forward, in_axes=(0, None, None))(model.net, x, model.cfg)
    prob = jax.nn.sigmoid(logits).reshape(-1, *model.box.grid)
    mass = jnp.maximum(mass_std.reshape(-1) * model.norm.mass_std + model.norm.mass_mean, MIN_MASS)
    return Prediction(prob, mass, jax.nn.sigmoid(hazard_logit).reshape(-1))


# Jitted `predict` over a batch: traj (B, T, 11), final (B, 5) -> Prediction with a leading axis B.
predict_batch = jax.jit(jax.vmap(predict, in_axes=(None, 0, 0)))


def predict_checked(model: EstimatorParams, traj, final) -> Prediction:
    """Host-side `predict` that validates its input: one trajectory (T, 11) + (5,) or a batch (B, T, 11) +
    (B, 5).

    Raises ValueError for a wrong shape, a wrong number of steps (T != model.n_steps), NaN / inf, or a
    non-finite prediction; never returns a silent prediction on bad input.
    Returns a Prediction of numpy arrays (prob ([B,] nx, ny, nz), mass ([B,]) kg, hazard ([B,])).
    """
    try:
        traj = np.asarray(traj, np.float32)
        final = np.asarray(final, np.float32)
    except (TypeError, ValueError) as e:
        raise ValueError(f"trajectory and final state must be numeric arrays: {e}") from e
    batched = traj.ndim == 3
    _check_traj(traj, final, model.n_steps, batched=batched)
    if batched:
        out = predict_batch(model, jnp.asarray(traj), jnp.asarray(final))
    else:
        one = predict_batch(model, jnp.asarray(traj)[None], jnp.asarray(final)[None])
        out = jax.tree.map(lambda a: a[0], one)
    out = Prediction(*(np.asarray(a) for a in out))
    if not all(np.all(np.isfinite(a)) for a in out):
        raise ValueError("the estimator produced a non-finite prediction (corrupt parameters?)")
    return out


def to_distribution(prob: jax.Array, mass: jax.Array, threshold: float = 0.5) -> MassDistribution:
    """Binary MassDistribution from ONE prediction (pure; vmap for batches).

    Voxels with prob > threshold are occupied; if none is, the single most probable voxel is, so the
    distribution always has mass somewhere.

    Args:
      prob: (nx, ny, nz) occupancy probabilities; mass: () kg.
    """
    occ = prob > threshold
    fallback = jax.nn.one_hot(jnp.argmax(prob.reshape(-1)), prob.size, dtype=bool).reshape(prob.shape)
    occ = jnp.where(jnp.any(occ), occ, fallback)
    return MassDistribution(occ.astype(jnp.float32), jnp.asarray(mass, jnp.float32))
