"""The estimator H (paper §2.2): exploration trajectory -> voxel occupancy grid and total mass.

Data (one box; batches carry a leading axis B), as `boxjax.estimator.explore.trajectory` builds it:
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
(`boxjax.training.estimator.DEFAULT_ESTIMATOR`) is 5 members of 900 -> 256 -> 256 -> 256 -> (256 | 1 | 1),
2.1e6 parameters in all (the paper's H has ~2e6).

Why a hazard head: the hazard rule is a sharp function of the occupancy (every occupied voxel inside one
outer quarter), and thresholding a predicted occupancy grid decides it from per-voxel marginals. Learning
the decision directly is more precise at the recall that matters (measured with the same data: see
`boxjax.training.estimator.DEFAULT_ESTIMATOR`'s comment). The occupancy rule stays available as
`occupancy_hazard` for estimators without the head.

Decisions (`calibrate`, on held-out boxes): a voxel is occupied when its probability exceeds
`occupancy_threshold` (chosen for the best median IoU); the box is hazardous when the hazard head's
probability exceeds `hazard_threshold` (chosen for the best precision at a hazard recall >= 0.99). Both
are stored in the checkpoint.

Training (`train`): held-out validation split, AdamW with global-norm clipping, one jitted `lax.scan`
over the shuffled minibatches of each epoch (faster on a 2-core CPU than one jitted call per minibatch:
see `train`), early stopping on the validation loss (per member) that returns the best parameters seen.

Modules: this one holds the loss and the training; the network, its features and its prediction are
`estimator.net`, the metrics, `estimate`, `evaluate` and `calibrate` are `estimator.metrics`, the
checkpoints `estimator.io` (imports go one way: those never import this module). The package's face
(`boxjax.estimator`) re-exports every public name, so `from boxjax import estimator as E; E.load(...)`
works.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from boxjax import __version__ as boxjax_version
from boxjax import massdist
from boxjax.config import BoxConfig
from boxjax.estimator.net import (
    Batch,
    EstimatorConfig,
    EstimatorParams,
    Normaliser,
    _dataset_arrays,
    _forward,
    _select_members,
    _standardise,
    features,
    init_members,
)
from boxjax.massdist import MassDistribution, iou

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


_batched_features = jax.jit(jax.vmap(features))


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
    cfg: EstimatorConfig = EstimatorConfig(),  # noqa: B008 (frozen dataclass: immutable)
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
