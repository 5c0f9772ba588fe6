"""The estimator H (paper §2.2): exploration trajectory -> voxel occupancy grid and total mass.

Data (one box; batches carry a leading axis B), as `boxjax.explore.trajectory` builds it:
  traj: (T, 11) float32, T = 45 exploration steps. Row t is the planar state s_t = (P1, P2, x, y, yaw)
    (m, m, m, m, rad, conveyor frame) BEFORE step t, the action a_t = (v1, v2, dp1, dp2) (m/s, m/s, m, m)
    as applied during it (belt speeds: the ramped setpoints reached at its end, see
    `explore.applied_actions`), and the belt surface speeds w_t (m/s) MEASURED at its end.
  final: (5,) the planar state after the last step. Transitions are (traj[t, :5], traj[t, 5:9], s_{t+1})
    with s_{t+1} = traj[t + 1, :5], or `final` for the last step.
  occupancy: (nx, ny, nz) float32 in {0, 1}; total_mass: () kg (targets, `boxjax.massdist`).

Features (`features`, 20 per step, flattened to (T * 20,)): what the box did in response to known actions.
Under Coulomb friction the belts' pull on the box is proportional to the normal load each belt carries, so
the split of translation and rotation between the belts reveals where the mass sits over each belt, and
the transient of the 3-step action holds reveals the inertia. Absolute pose says little, so only relative
quantities enter:
  * ds = s' - s (5): belt moves and box displacement, with the yaw change wrapped to [-pi, pi);
  * the box displacement in the box frame at s (2): (dx, dy) rotated by -yaw, i.e. the response as the box
    itself feels it (the mass distribution is fixed in the box frame);
  * belt centre-lines relative to the box centre, P1 - y and P2 - y (2): which voxel rows rest on each belt;
  * carriage lag after the step (2): P_i(t+1) - (P_i(0) + sum of the applied dp_i so far), i.e. measured
    minus commanded belt position. The carriage servo (kp = 5e4 N/m) gives way by the lateral friction
    force / kp, so this is a force gauge: together with the belt lag, the clearest trace of the total MASS,
    which pure Coulomb friction otherwise hides (accelerations under friction do not depend on the mass);
  * belt speed lag after the step (2): commanded (ramped) minus measured belt speed, v_i - w_i; the belt
    servo (kv = 2e4 N s/m) is slowed by the friction force along x / kv (plus a load-independent
    acceleration term);
  * the box pose after the step relative to the start (3): x - x0, y - y0, yaw - yaw0;
  * the action a (4): fixed in the paper's exploration, so normally constant; kept so H stays valid if
    the exploration sequence is changed or perturbed.
Each feature is standardised with mean / std over the training set (constant features keep std 1), and
the total mass is standardised the same way; both statistics are stored with the model.

Model: one MLP trunk (`EstimatorConfig.hidden`, activation after every layer) and three linear heads:
occupancy logits (nx * ny * nz) trained with binary cross-entropy, the standardised mass with MSE, and a
hazard logit trained with binary cross-entropy on the paper's hazard label of the true distribution.
Loss = BCE + mass_weight * MSE (paper footnote on H) + hazard_weight * hazard BCE, optionally
+ com_weight * (soft centre-of-mass error / 5 cm)^2 and + iou_weight * soft Jaccard loss
(`loss_and_metrics`). `members` > 1 trains an ensemble of independently initialised nets side by side
(vmap over a leading member axis) and averages their probabilities and masses. This class's defaults: one
net 900 -> 512 -> 512 -> 512 -> (256 | 1 | 1), 1.1e6 parameters; the shipped H
(`boxjax.estimator_pipeline.DEFAULT_ESTIMATOR`) is 5 members of 900 -> 256 -> 256 -> 256 -> (256 | 1 | 1),
2.1e6 parameters in all (the paper's H has ~2e6).

Why a hazard head: the hazard rule is a sharp function of the occupancy (every occupied voxel inside one
outer quarter), and thresholding a predicted occupancy grid decides it from per-voxel marginals. Learning
the decision directly is more precise at the recall that matters (measured with the same data: see
`boxjax.estimator_pipeline.DEFAULT_ESTIMATOR`'s comment). The occupancy rule stays available as
`occupancy_hazard` for estimators without the head.

Decisions (`calibrate`, on held-out boxes): a voxel is occupied when its probability exceeds
`occupancy_threshold` (chosen for the best median IoU); the box is hazardous when the hazard head's
probability exceeds `hazard_threshold` (chosen for the best precision at a hazard recall >= 0.99). Both
are stored in the checkpoint.

Training (`train`): held-out validation split, AdamW with global-norm clipping, one jitted `lax.scan`
over the shuffled minibatches of each epoch (faster on a 2-core CPU than one jitted call per minibatch:
see `train`), early stopping on the validation loss (per member) that returns the best parameters seen.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from boxjax import __version__ as boxjax_version
from boxjax import massdist, mlp
from boxjax.config import BoxConfig, ConfigError
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta
from boxjax.geometry import P1, P2, YAW, X, Y, wrap_angle
from boxjax.massdist import MassDistribution, iou

__all__ = [
    "CheckpointError",
    "EstimatorConfig",
    "EstimatorParams",
    "Normaliser",
    "Batch",
    "features",
    "init_net",
    "init_members",
    "make_optimizer",
    "make_train_step",
    "loss_and_metrics",
    "train",
    "losses",
    "predict",
    "predict_batch",
    "predict_checked",
    "predict_hazard",
    "occupancy_hazard",
    "hazard_labels",
    "Prediction",
    "HEADS",
    "estimate",
    "calibrate",
    "to_distribution",
    "iou",
    "mass_rel_error",
    "com_error_cm",
    "hazard_precision_recall",
    "hazard_curve",
    "evaluate",
    "save",
    "load",
    "FORMAT",
    "FORMAT_VERSION",
]

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


COM_SCALE = 0.05  # m: a 5 cm centre-of-mass error costs 1 in the com loss


def loss_and_metrics(
    net: dict, batch: Batch, cfg: EstimatorConfig, box: BoxConfig | None = None, key: jax.Array | None = None
) -> tuple[jax.Array, dict]:
    """Training objective over a batch:

      mean voxel BCE + mass_weight * MSE(standardised mass) + hazard_weight * hazard BCE
      + iou_weight * mean soft Jaccard loss + com_weight * mean |soft com - com|^2 / COM_SCALE^2,

    the soft quantities computed from the occupancy probabilities p = sigmoid(logits) (soft centre of mass
    = sum p_v c_v / sum p_v over voxel centres c_v, needs `box` and batch.com). With `key` and
    cfg.input_noise > 0, gaussian noise of that std is added to the standardised features (training
    augmentation). Metrics: every term and the mean IoU at threshold 0.5.
    """
    x = batch.x
    if key is not None and cfg.input_noise > 0:
        x = x + cfg.input_noise * jax.random.normal(key, x.shape, x.dtype)
    logits, mass, hazard_logit = jax.vmap(_forward, in_axes=(None, 0, None))(net, x, cfg)
    bce = jnp.mean(optax.sigmoid_binary_cross_entropy(logits, batch.occ))
    mse = jnp.mean((mass - batch.mass) ** 2)
    p = jax.nn.sigmoid(logits)
    inter = jnp.sum(p * batch.occ, axis=1)
    jaccard = jnp.mean(1.0 - (inter + 1e-6) / (jnp.sum(p + batch.occ, axis=1) - inter + 1e-6))
    loss = bce + cfg.mass_weight * mse + cfg.iou_weight * jaccard
    metrics = {"bce": bce, "mass_mse": mse, "jaccard": jaccard}
    if batch.hazard is not None:
        hazard_bce = jnp.mean(optax.sigmoid_binary_cross_entropy(hazard_logit, batch.hazard))
        loss = loss + cfg.hazard_weight * hazard_bce
        metrics["hazard_bce"] = hazard_bce
    if box is not None and batch.com is not None:
        centres = jnp.asarray(massdist.voxel_centres(box)).reshape(-1, 3)
        com_p = (p @ centres) / jnp.sum(p, axis=1, keepdims=True)
        com_loss = jnp.mean(jnp.sum((com_p - batch.com) ** 2, axis=1)) / COM_SCALE**2
        loss = loss + cfg.com_weight * com_loss
        metrics["com_loss"] = com_loss
    mean_iou = jnp.mean(jax.vmap(iou)(logits > 0.0, batch.occ))
    return loss, {"loss": loss, **metrics, "iou": mean_iou}


def make_optimizer(cfg: EstimatorConfig) -> optax.GradientTransformation:
    """Global-norm clipping, then AdamW (decoupled weight decay)."""
    return optax.chain(
        optax.clip_by_global_norm(cfg.grad_clip),
        optax.adamw(cfg.learning_rate, weight_decay=cfg.weight_decay),
    )


def _train_step(cfg: EstimatorConfig, optimizer: optax.GradientTransformation, box: BoxConfig | None = None):
    def step(net, opt_state, batch: Batch, key=None):
        (_, metrics), grads = jax.value_and_grad(loss_and_metrics, has_aux=True)(net, batch, cfg, box, key)
        updates, opt_state = optimizer.update(grads, opt_state, net)
        return optax.apply_updates(net, updates), opt_state, metrics

    return step


def make_train_step(
    cfg: EstimatorConfig, optimizer: optax.GradientTransformation, box: BoxConfig | None = None
):
    """Jitted pure step `(net, opt_state, batch: Batch, key=None) -> (net, opt_state, metrics)` (`box`
    enables the centre-of-mass loss, `key` the input noise; see `loss_and_metrics`)."""
    return jax.jit(_train_step(cfg, optimizer, box))


def _make_train_epoch(
    cfg: EstimatorConfig, optimizer: optax.GradientTransformation, batch_size: int, box: BoxConfig | None
):
    """Jitted `(net, opt_state, data: Batch, key) -> (net, opt_state, mean metrics)`: one pass over a fresh
    permutation of `data` as a `lax.scan` over n // batch_size minibatches (the remainder, different every
    epoch, is skipped), each with its own noise key."""
    step = _train_step(cfg, optimizer, box)

    @jax.jit
    def epoch(net, opt_state, data: Batch, key):
        n = data.x.shape[0]
        n_batches = n // batch_size
        key_perm, key_noise = jax.random.split(key)
        order = jax.random.permutation(key_perm, n)[: n_batches * batch_size].reshape(n_batches, batch_size)

        def body(carry, xs):
            idx, key_batch = xs
            net, opt_state = carry
            net, opt_state, metrics = step(net, opt_state, jax.tree.map(lambda a: a[idx], data), key_batch)
            return (net, opt_state), metrics

        xs = (order, jax.random.split(key_noise, n_batches))
        (net, opt_state), metrics = jax.lax.scan(body, (net, opt_state), xs)
        return net, opt_state, jax.tree.map(jnp.mean, metrics)

    return epoch


def _compile_key(cfg: EstimatorConfig) -> EstimatorConfig:
    """cfg with the fields that do not change the compiled computations set to fixed values, so that runs
    differing only in epochs, patience, split or seed share compiled functions."""
    return dataclasses.replace(cfg, max_epochs=1, patience=1, val_fraction=0.5, seed=0)


@functools.lru_cache(maxsize=16)
def _cached_train_epoch(cfg: EstimatorConfig, batch_size: int, box: BoxConfig | None = None):
    """The epoch of `_make_train_epoch` vmapped over ensemble members (stacked nets, optimiser states and
    keys; the data are shared)."""
    epoch = _make_train_epoch(cfg, make_optimizer(cfg), batch_size, box)
    return jax.jit(jax.vmap(epoch, in_axes=(0, 0, None, 0)))


# ----------------------------------------------------------------------------------------------------------
# Data handling (host side).


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
            f"step, see boxjax.explore.trajectory), got {traj.shape}"
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


_batched_features = jax.jit(jax.vmap(features))


def _standardise(x: jax.Array, norm: Normaliser) -> jax.Array:
    return (x - norm.feat_mean) / norm.feat_std


def _fit_normaliser(x: np.ndarray, mass: np.ndarray) -> Normaliser:
    """Statistics over the training rows. A feature (or mass) that never varies keeps std 1: dividing by a
    tiny std would blow up any test input that differs from the training constant."""
    std = x.std(axis=0)
    std = np.where(std > 1e-8 * (1.0 + np.abs(x.mean(axis=0))), std, 1.0)
    m_std = float(mass.std())
    m_std = m_std if m_std > 1e-8 * (1.0 + abs(float(mass.mean()))) else 1.0
    return Normaliser(
        jnp.asarray(x.mean(axis=0), jnp.float32),
        jnp.asarray(std, jnp.float32),
        jnp.asarray(mass.mean(), jnp.float32),
        jnp.asarray(m_std, jnp.float32),
    )


@functools.partial(jax.jit, static_argnums=0)
def hazard_labels(box: BoxConfig, occ: jax.Array) -> jax.Array:
    """(B,) float32 in {0, 1}: `massdist.is_hazardous` of each occupancy grid (B, nx, ny, nz) (the total mass
    does not enter the rule)."""
    dists = MassDistribution(occ, jnp.ones(occ.shape[0], occ.dtype))
    return jax.vmap(massdist.is_hazardous, in_axes=(0, None))(dists, box).astype(jnp.float32)


def _make_batch(x: jax.Array, occ: np.ndarray, mass: np.ndarray, norm: Normaliser, box: BoxConfig) -> Batch:
    flat = occ.reshape(occ.shape[0], -1).astype(np.float32)
    centres = massdist.voxel_centres(box).reshape(-1, 3)
    com = flat @ centres / np.maximum(flat.sum(axis=1, keepdims=True), 1.0)
    return Batch(
        _standardise(jnp.asarray(x), norm),
        jnp.asarray(flat),
        (jnp.asarray(mass, jnp.float32) - norm.mass_mean) / norm.mass_std,
        jnp.asarray(com, jnp.float32),
        hazard_labels(box, jnp.asarray(occ, jnp.float32)),
    )


def _key_data(key: jax.Array) -> list[int]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return [int(v) for v in np.asarray(key).reshape(-1)]


def _split_indices(key: jax.Array, n: int, val_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(train_index, val_index): a random split with max(1, round(val_fraction * n)) validation boxes."""
    if n < 2:
        raise ValueError(f"need at least 2 boxes to hold one out for validation, got {n}")
    n_val = min(n - 1, max(1, round(val_fraction * n)))
    perm = np.asarray(jax.random.permutation(key, n))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


# ----------------------------------------------------------------------------------------------------------
# Training.


def train(
    key: jax.Array | None,
    dataset,
    cfg: EstimatorConfig = EstimatorConfig(),
    *,
    box: BoxConfig | None = None,
    progress: bool = True,
    provenance: Mapping[str, Any] | None = None,
) -> tuple[EstimatorParams, dict]:
    """Fit H on a dataset of exploration trajectories, with early stopping on a held-out split.

    Args:
      key: PRNG key (None: `jax.random.key(cfg.seed)`); split into the validation split, the init and the
        per-epoch shuffles.
      dataset: mapping (dict or loaded .npz) or object with `traj` (B, T, 11), `final` (B, 5),
        `occupancy` (B, nx, ny, nz) in {0, 1} and `total_mass` (B,) kg.
      cfg: EstimatorConfig.
      box: the BoxConfig the occupancy grids refer to (default `BoxConfig()`); its grid must match.
      progress: show a tqdm bar (epochs, rate, ETA, current train / validation losses).
      provenance: extra JSON-serialisable facts to store with the model (e.g. how the data was made).
    Returns:
      (model, history). model holds the parameters with the lowest validation loss. history: per-epoch
      lists "train_loss", "train_bce", "train_mass_mse", "train_hazard_bce", the same four "val_..." and
      "val_iou";
      "best_epoch" (0-based), "best_val_loss", "epochs_run", "stopped_early", "seconds",
      "train_index", "val_index" (numpy int arrays into the dataset).

    Batching: each epoch is ONE jitted call, a `lax.scan` over the shuffled minibatches. Measured on the
    2-core CPU with the default config (1.0e6 parameters), 1700 training boxes = 26 minibatches of 64,
    interleaved rounds of 5 epochs, while other jobs shared the cores (so best-of-rounds / median):
    scan 0.19-0.24 / 0.47 s per epoch; one call of the jitted `make_train_step` per minibatch with
    numpy-sliced batches 0.28-0.35 / 0.51 s, with device-gathered batches 0.43-0.54 / 0.68 s. Compile
    time is ~4-5 s either way. The scan wins by removing per-minibatch dispatch and host round trips.
    Validation is one full-batch jitted call per epoch. Buffers are not donated: the best parameters
    seen so far are kept by reference.
    """
    box = BoxConfig() if box is None else box
    traj, final, occ, mass = _dataset_arrays(dataset, box)
    key_given = key is not None
    key = jax.random.key(cfg.seed) if key is None else key
    key_split, key_init, key_epochs = jax.random.split(key, 3)
    train_index, val_index = _split_indices(key_split, traj.shape[0], cfg.val_fraction)

    x_all = _batched_features(jnp.asarray(traj), jnp.asarray(final))
    norm = _fit_normaliser(np.asarray(x_all)[train_index], mass[train_index])
    train_data = _make_batch(x_all[train_index], occ[train_index], mass[train_index], norm, box)
    val_data = _make_batch(x_all[val_index], occ[val_index], mass[val_index], norm, box)

    k = cfg.members
    net = init_members(key_init, x_all.shape[1], box.n_voxels, cfg)
    # Start the occupancy head at the training set's per-voxel occupancy rate: the first epochs then
    # learn the distribution-specific part instead of the prior.
    rate = jnp.clip(jnp.mean(train_data.occ, axis=0), 0.01, 0.99)
    net["occ"][-1]["b"] = jnp.broadcast_to(jnp.log(rate) - jnp.log1p(-rate), (k, box.n_voxels))

    optimizer = make_optimizer(cfg)
    opt_state = jax.vmap(optimizer.init)(net)
    batch_size = min(cfg.batch_size, len(train_index))
    run_epoch = _cached_train_epoch(_compile_key(cfg), batch_size, box)

    # Early stopping per member: each keeps its own best parameters; training ends when no member has
    # improved for `patience` epochs. History rows are means over the members.
    names = ("loss", "bce", "mass_mse", "hazard_bce")
    history: dict[str, Any] = {f"{p}_{k}": [] for p in ("train", "val") for k in names}
    history["val_iou"] = []
    best_net = net
    best_loss = np.full(k, np.inf)
    best_epoch = np.full(k, -1)
    start = time.perf_counter()
    bar = tqdm(range(cfg.max_epochs), desc="train H", unit="epoch", disable=not progress, leave=False)
    stopped_early = False
    for epoch in bar:
        key_epochs, key_shuffle = jax.random.split(key_epochs)
        net, opt_state, train_m = run_epoch(net, opt_state, train_data, jax.random.split(key_shuffle, k))
        val_m = _member_metrics_jit(net, val_data, _compile_key(cfg), box)
        train_m, val_m = jax.device_get((train_m, val_m))
        for name in names:
            history[f"train_{name}"].append(float(np.mean(train_m[name])))
            history[f"val_{name}"].append(float(np.mean(val_m[name])))
        history["val_iou"].append(float(np.mean(val_m["iou"])))
        val_loss = np.asarray(val_m["loss"], np.float64)
        if not np.all(np.isfinite(val_loss)):
            raise FloatingPointError(f"validation loss became {val_loss} at epoch {epoch}; lower the rate")
        improved = val_loss < best_loss
        if np.any(improved):
            best_net = _select_members(jnp.asarray(improved), net, best_net)
            best_loss = np.where(improved, val_loss, best_loss)
            best_epoch = np.where(improved, epoch, best_epoch)
        bar.set_postfix(
            train=f"{history['train_loss'][-1]:.4f}",
            val=f"{history['val_loss'][-1]:.4f}",
            iou=f"{history['val_iou'][-1]:.3f}",
            best=f"{np.mean(best_loss):.4f}@{int(best_epoch.max())}",
            refresh=False,
        )
        if epoch - int(best_epoch.max()) >= cfg.patience:
            stopped_early = True
            break
    bar.close()

    best_epoch_all = int(best_epoch.max())
    history.update(
        best_epoch=best_epoch_all,
        best_val_loss=float(np.mean(best_loss)),
        member_best_epochs=[int(e) for e in best_epoch],
        epochs_run=len(history["val_loss"]),
        stopped_early=stopped_early,
        seconds=time.perf_counter() - start,
        train_index=train_index,
        val_index=val_index,
    )
    best_loss = float(np.mean(best_loss))
    best_epoch = best_epoch_all
    prov = {
        "seed": cfg.seed if not key_given else None,
        "key_data": _key_data(key),
        "n_boxes": int(traj.shape[0]),
        "n_train": int(len(train_index)),
        "n_val": int(len(val_index)),
        "best_epoch": int(best_epoch),
        "best_val_loss": float(best_loss),
        "epochs_run": int(history["epochs_run"]),
        "boxjax_version": boxjax_version,
        "jax_version": jax.__version__,
        "optax_version": optax.__version__,
        "created_unix": time.time(),
        **(dict(provenance) if provenance else {}),
    }
    model = EstimatorParams(
        net=best_net,
        norm=norm,
        cfg=cfg,
        box=box,
        n_steps=int(traj.shape[1]),
        provenance_json=json.dumps(prov, sort_keys=True),
    )
    return model, history


def losses(model: EstimatorParams, dataset) -> dict:
    """Training objective of `model` on a whole dataset (fields as for `train`): Python floats "loss",
    "bce", "mass_mse" (standardised mass, as trained), "hazard_bce", "jaccard", "com_loss" and "iou" (mean,
    threshold 0.5), each the mean over the ensemble members (as in the training history)."""
    traj, final, occ, mass = _dataset_arrays(dataset, model.box, model.n_steps)
    batch = _make_batch(
        _batched_features(jnp.asarray(traj), jnp.asarray(final)), occ, mass, model.norm, model.box
    )
    metrics = _member_metrics_jit(model.net, batch, _compile_key(model.cfg), model.box)
    return {k: float(np.mean(v)) for k, v in metrics.items()}


_member_metrics_jit = jax.jit(
    lambda net, batch, cfg, box: jax.vmap(lambda n: loss_and_metrics(n, batch, cfg, box)[1])(net),
    static_argnums=(2, 3),
)


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


# ----------------------------------------------------------------------------------------------------------
# Metrics (pure; `iou` is `massdist.iou`).


def mass_rel_error(pred_mass: jax.Array, true_mass: jax.Array) -> jax.Array:
    """|pred - true| / true (dimensionless), elementwise."""
    return jnp.abs(pred_mass - true_mass) / true_mass


def com_error_cm(pred: MassDistribution, true: MassDistribution, box: BoxConfig) -> jax.Array:
    """() cm: distance between the centres of mass of ONE predicted and true distribution (box frame)."""
    com_p = massdist.mass_properties(pred, box).com
    com_t = massdist.mass_properties(true, box).com
    return 100.0 * jnp.linalg.norm(com_p - com_t)


def hazard_precision_recall(pred_hazard: jax.Array, true_hazard: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Precision and recall of the hazard flag over boxes, "hazardous" being the positive class.

    Args:
      pred_hazard, true_hazard: (B,) bool.
    Returns:
      (precision, recall) float32 scalars; NaN where undefined (no predicted / no true hazardous box).
    """
    p, t = jnp.asarray(pred_hazard, bool), jnp.asarray(true_hazard, bool)
    tp = jnp.sum(p & t)
    n_pred, n_true = jnp.sum(p), jnp.sum(t)
    precision = jnp.where(n_pred > 0, tp / jnp.maximum(n_pred, 1), jnp.nan)
    recall = jnp.where(n_true > 0, tp / jnp.maximum(n_true, 1), jnp.nan)
    return precision.astype(jnp.float32), recall.astype(jnp.float32)


def predict_hazard(model: EstimatorParams, hazard_prob: jax.Array) -> jax.Array:
    """The calibrated hazard decision (pure; any shape): the hazard head's probability exceeds
    `model.hazard_threshold`."""
    return jnp.asarray(hazard_prob) > model.hazard_threshold


def occupancy_hazard(prob: jax.Array, threshold, box: BoxConfig) -> jax.Array:
    """() bool, the hazard rule applied to an occupancy prediction (ONE box; vmap for batches):
    `massdist.is_hazardous` of the distribution thresholded at `threshold` (with `to_distribution`'s
    fallback to the most probable voxel), i.e. every voxel outside one of the regions U1..U4 has an
    occupancy probability <= threshold. For estimators without a hazard head (scripts/estimator_ceiling.py);
    H's own decision is its hazard head (`predict_hazard`), which is more precise at the same recall."""
    return massdist.is_hazardous(to_distribution(prob, jnp.ones(()), threshold), box)


def estimate(model: EstimatorParams, traj, final) -> dict:
    """Everything the controller needs from ONE exploration trajectory (host side, validated input).

    Args:
      traj: (T, 11), final: (5,) as built by `boxjax.explore.trajectory` / `explore.run`.
    Returns:
      dict: "prob" (nx, ny, nz) numpy occupancy probabilities; "distribution" the MassDistribution
      thresholded at model.occupancy_threshold with the predicted total mass; "members" the same for
      each ensemble member (`predict_members`); "total_mass" float kg;
      "hazard_prob" float, the hazard head's probability; "hazardous" bool (`predict_hazard`).
    Raises:
      ValueError for a trajectory of the wrong shape / length or with NaN / inf (`predict_checked`).
    """
    prob, mass, hazard = predict_checked(model, traj, final)
    dist = to_distribution(jnp.asarray(prob), jnp.asarray(mass), model.occupancy_threshold)
    mem = _predict_members_jit(model, jnp.asarray(traj, jnp.float32), jnp.asarray(final, jnp.float32))
    members = [
        to_distribution(mem.prob[e], mem.mass[e], model.occupancy_threshold) for e in range(mem.mass.shape[0])
    ]
    return {
        "prob": prob,
        "distribution": dist,
        "members": [jax.tree.map(np.asarray, m) for m in members],
        "total_mass": float(mass),
        "hazard_prob": float(hazard),
        "hazardous": bool(predict_hazard(model, hazard)),
    }


_predict_members_jit = jax.jit(predict_members)


@functools.partial(jax.jit, static_argnums=0)
def thresholded_metrics(
    box: BoxConfig, prob, pred_mass, occ, mass, occ_threshold, hazard_threshold, hazard_prob=None
):
    """Per-box metrics of batched predictions: prob (B, nx, ny, nz) occupancy probabilities, pred_mass (B,)
    kg against the truth occ, mass. The hazard flag is hazard_prob (B,) > hazard_threshold when the
    hazard head's probabilities are given, else `occupancy_hazard(prob, hazard_threshold)`. Returns
    {"iou", "mass_rel_error", "com_error_cm", "pred_hazard", "true_hazard"}, each (B,). Both thresholds
    are traced (no recompile per value)."""
    pred = jax.vmap(to_distribution, in_axes=(0, 0, None))(prob, pred_mass, occ_threshold)
    true = MassDistribution(occ, mass)
    if hazard_prob is None:
        pred_hazard = jax.vmap(occupancy_hazard, in_axes=(0, None, None))(prob, hazard_threshold, box)
    else:
        pred_hazard = hazard_prob > hazard_threshold
    return {
        "iou": jax.vmap(iou)(pred.occupancy, occ),
        "mass_rel_error": mass_rel_error(pred_mass, mass),
        "com_error_cm": jax.vmap(com_error_cm, in_axes=(0, 0, None))(pred, true, box),
        "pred_hazard": pred_hazard,
        "true_hazard": jax.vmap(massdist.is_hazardous, in_axes=(0, None))(true, box),
    }


def _predictions(model: EstimatorParams, dataset, chunk: int):
    """(Prediction of numpy arrays with a leading axis B, occ, mass), predicting in chunks of boxes."""
    traj, final, occ, mass = _dataset_arrays(dataset, model.box, model.n_steps)
    parts = [
        jax.device_get(predict_batch(model, traj[i : i + chunk], final[i : i + chunk]))
        for i in range(0, traj.shape[0], chunk)
    ]
    return Prediction(*(np.concatenate(arrays) for arrays in zip(*parts, strict=True))), occ, mass


def _per_box_metrics(model: EstimatorParams, predictions, occ_threshold: float, hazard_threshold: float):
    (prob, pred_mass, hazard), occ, mass = predictions
    out = thresholded_metrics(
        model.box, prob, pred_mass, occ, mass, jnp.float32(occ_threshold), jnp.float32(hazard_threshold),
        hazard,
    )
    return {k: np.asarray(v) for k, v in out.items()}


def evaluate(model: EstimatorParams, dataset, threshold: float | None = None, chunk: int = 1024) -> dict:
    """Prediction quality of H on a dataset (same fields as for `train`), in chunks of `chunk` boxes.

    IoU and the centre-of-mass error use the distribution thresholded at `threshold` (default: the
    model's calibrated `occupancy_threshold`); the hazard flag is `predict_hazard` (the hazard head at the
    model's `hazard_threshold`).

    Returns a dict of Python numbers: iou_median, iou_mean, mass_rel_error_median, mass_rel_error_mean,
    com_error_cm_median, com_error_cm_mean, hazard_precision, hazard_recall (NaN when undefined),
    hazard_true, hazard_pred (counts), boxes.
    """
    threshold = model.occupancy_threshold if threshold is None else float(threshold)
    m = _per_box_metrics(model, _predictions(model, dataset, chunk), threshold, model.hazard_threshold)
    precision, recall = hazard_precision_recall(m["pred_hazard"], m["true_hazard"])
    return {
        "iou_median": float(np.median(m["iou"])),
        "iou_mean": float(np.mean(m["iou"])),
        "mass_rel_error_median": float(np.median(m["mass_rel_error"])),
        "mass_rel_error_mean": float(np.mean(m["mass_rel_error"])),
        "com_error_cm_median": float(np.median(m["com_error_cm"])),
        "com_error_cm_mean": float(np.mean(m["com_error_cm"])),
        "hazard_precision": float(precision),
        "hazard_recall": float(recall),
        "hazard_true": int(np.sum(m["true_hazard"])),
        "hazard_pred": int(np.sum(m["pred_hazard"])),
        "boxes": int(len(m["iou"])),
    }


OCCUPANCY_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(2, 19))  # 0.10 .. 0.90
HAZARD_THRESHOLDS = tuple(round(0.01 * i, 2) for i in range(1, 100))  # 0.01 .. 0.99


def hazard_curve(hazard_prob, true_hazard, thresholds=HAZARD_THRESHOLDS) -> list[tuple[float, ...]]:
    """[(threshold, precision, recall), ...] of the decision hazard_prob > threshold against true_hazard
    (both (B,)), for every threshold at once; precision / recall NaN where undefined, as in
    `hazard_precision_recall`."""
    t = np.asarray(thresholds, np.float64)[:, None]
    pred = np.asarray(hazard_prob)[None, :] > t
    true = np.asarray(true_hazard, bool)[None, :]
    tp, n_pred, n_true = np.sum(pred & true, 1), np.sum(pred, 1), np.sum(true)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(n_pred > 0, tp / n_pred, np.nan)
        recall = np.where(n_true > 0, tp / n_true, np.nan)
    return [(float(a), float(b), float(c)) for a, b, c in zip(t[:, 0], precision, recall, strict=True)]


def choose_hazard_threshold(curve, recall_target: float) -> float:
    """The hazard threshold to use, from `curve` = [(threshold, precision, recall), ...] measured on
    held-out boxes: among the thresholds whose recall reaches the target, the one with the highest
    precision (ties: the lower threshold); if none reaches it, the one with the highest recall."""
    ok = [c for c in curve if c[2] >= recall_target and not math.isnan(c[1])]
    if ok:
        return max(ok, key=lambda c: (c[1], -c[0]))[0]
    return max(curve, key=lambda c: (c[2], c[1]))[0]


def calibrate(
    model: EstimatorParams, dataset, hazard_recall_target: float = 0.99
) -> tuple[EstimatorParams, dict]:
    """Choose the model's two decision thresholds on held-out boxes (never the training boxes).

    occupancy_threshold: the value in 0.10..0.90 (step 0.05) with the highest median IoU.
    hazard_threshold: on the hazard head's probability, among 0.01..0.99 (step 0.01, `hazard_curve`), the
    values whose hazard recall on `dataset` is >= the target, the one with the highest precision (ties:
    the lower threshold); if none reaches the target, the one with the highest recall. Undefined when
    `dataset` holds no hazardous box: then 0.5 is kept.

    Returns (model with both thresholds set, a dict of what was chosen and the per-threshold curves).
    """
    ious = []
    predictions = _predictions(model, dataset, 1024)
    for t in OCCUPANCY_THRESHOLDS:
        m = _per_box_metrics(model, predictions, t, 0.5)
        ious.append(float(np.median(m["iou"])))
    true_h = m["true_hazard"]
    haz_curve = hazard_curve(predictions[0].hazard, true_h)
    occ_t = OCCUPANCY_THRESHOLDS[int(np.argmax(ious))]
    haz_t = choose_hazard_threshold(haz_curve, hazard_recall_target) if np.any(true_h) else 0.5
    info = {
        "occupancy_threshold": occ_t,
        "hazard_threshold": haz_t,
        "hazard_recall_target": hazard_recall_target,
        "boxes": int(len(true_h)),
        "hazardous_boxes": int(np.sum(true_h)),
        "iou_median_by_threshold": dict(zip(OCCUPANCY_THRESHOLDS, ious, strict=True)),
        "hazard_precision_recall_by_threshold": {t: (p, r) for t, p, r in haz_curve},
    }
    return dataclasses.replace(model, occupancy_threshold=occ_t, hazard_threshold=haz_t), info


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
