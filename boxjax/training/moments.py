"""Training the moments estimator (`boxjax.estimator.moments`) on exploration datasets.

`train(key, data, box)`: data holds the dataset arrays of `boxjax.training.dataset` (traj, final,
occupancy, total_mass). The targets are the exact moments of each box (`moments.true_moments`). A
validation split (10 %) picks each member's best epoch (early stopping on its gaussian negative
log-likelihood) and then the calibration factors of the std (`moments.calibration_scale`). Every member
sees every training box, in its own order from its own initialisation (the ensemble's diversity). The K
members train together: one vmapped AdamW step.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import massdist
from boxjax.config import DEFAULT, BoxConfig, Config
from boxjax.estimator import explore
from boxjax.estimator import moments as M
from boxjax.estimator import net as E
from boxjax.training import dataset, wide


def nll(net_k: list, x: jax.Array, y: jax.Array) -> jax.Array:
    """Mean gaussian negative log-likelihood (standardised units, constant dropped) of one member."""
    mu, sd = jax.vmap(M.member_outputs, in_axes=(None, 0))(net_k, x)
    return jnp.mean(0.5 * jnp.square((y - mu) / sd) + jnp.log(sd))


def _features(data: dict) -> np.ndarray:
    f = jax.jit(jax.vmap(E.features))
    n = len(data["traj"])
    return np.concatenate(
        [np.asarray(f(data["traj"][i : i + 4096], data["final"][i : i + 4096])) for i in range(0, n, 4096)]
    )


def targets(data: dict, box: BoxConfig) -> np.ndarray:
    """(B, 8) exact moments of the dataset's boxes."""
    dists = massdist.MassDistribution(jnp.asarray(data["occupancy"]), jnp.asarray(data["total_mass"]))
    return M.true_moments_batch(dists, box)


def train(
    key: jax.Array,
    data: dict,
    box: BoxConfig,
    *,
    members: int = 5,
    hidden: tuple[int, ...] = (256, 256),
    epochs: int = 60,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    weight_decay: float = 1e-4,
    patience: int = 8,
    val_fraction: float = 0.1,
    log=print,
) -> tuple[M.MomentsModel, dict]:
    """(model, report): the trained, calibrated estimator and its training record."""
    t0 = time.time()
    x = _features(data)
    y = targets(data, box)
    n = len(x)
    k_split, k_init, k_epochs = jax.random.split(key, 3)
    perm = np.asarray(jax.random.permutation(k_split, n))
    n_val = max(1, int(round(val_fraction * n)))
    val, tr = perm[:n_val], perm[n_val:]
    feat_mean, feat_std = x[tr].mean(0), x[tr].std(0) + 1e-6
    q_mean, q_std = y[tr].mean(0), y[tr].std(0) + 1e-9
    xs = ((x - feat_mean) / feat_std).astype(np.float32)
    ys = ((y - q_mean) / q_std).astype(np.float32)
    x_tr, y_tr, x_val, y_val = (
        jnp.asarray(xs[tr]),
        jnp.asarray(ys[tr]),
        jnp.asarray(xs[val]),
        jnp.asarray(ys[val]),
    )

    batch_size = min(batch_size, len(tr))
    net = M.init_members(k_init, x.shape[1], tuple(hidden), members)
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(learning_rate, weight_decay=weight_decay))
    state = jax.vmap(opt.init)(net)

    def member_step(net_k, state_k, idx):
        loss, g = jax.value_and_grad(nll)(net_k, x_tr[idx], y_tr[idx])
        upd, state_k = opt.update(g, state_k, net_k)
        return optax.apply_updates(net_k, upd), state_k, loss

    @jax.jit
    def epoch(net, state, key):
        steps = len(tr) // batch_size
        orders = jax.vmap(lambda k: jax.random.permutation(k, len(tr))[: steps * batch_size])(
            jax.random.split(key, members)
        )
        orders = orders.reshape(members, steps, batch_size).transpose(1, 0, 2)

        def body(carry, idx):
            net, state = carry
            net, state, loss = jax.vmap(member_step)(net, state, idx)
            return (net, state), loss

        (net, state), losses = jax.lax.scan(body, (net, state), orders)
        return net, state, losses.mean(0)

    val_nll = jax.jit(jax.vmap(nll, in_axes=(0, None, None)))
    best = jax.tree.map(lambda a: a, net)
    best_val = np.full(members, np.inf)
    since = np.zeros(members, int)
    history = []
    for ep in range(epochs):
        net, state, train_loss = epoch(net, state, jax.random.fold_in(k_epochs, ep))
        v = np.asarray(val_nll(net, x_val, y_val))
        better = v < best_val
        best = jax.tree.map(
            lambda b, c, keep=better: jnp.where(keep.reshape((-1,) + (1,) * (c.ndim - 1)), c, b), best, net
        )
        best_val = np.where(better, v, best_val)
        since = np.where(better, 0, since + 1)
        history.append({"epoch": ep, "train_nll": np.asarray(train_loss).tolist(), "val_nll": v.tolist()})
        log(
            f"epoch {ep:3d}  train nll {np.mean(train_loss):+.3f}  val nll {np.mean(v):+.3f}"
            f"  ({time.time() - t0:.0f} s)"
        )
        if np.all(since >= patience):
            break

    model = M.MomentsModel(
        net=best,
        feat_mean=jnp.asarray(feat_mean, jnp.float32),
        feat_std=jnp.asarray(feat_std, jnp.float32),
        q_mean=jnp.asarray(q_mean, jnp.float32),
        q_std=jnp.asarray(q_std, jnp.float32),
        scale=jnp.ones(M.N_Q, jnp.float32),
        grid=tuple(box.grid),
    )
    raw = jax.jit(jax.vmap(M.predict_uncalibrated, in_axes=(None, 0, 0)))(
        model, jnp.asarray(data["traj"][val]), jnp.asarray(data["final"][val])
    )
    scale = M.calibration_scale(raw, y[val])
    model = M.MomentsModel(**{**model.__dict__, "scale": jnp.asarray(scale)})
    report = {
        "boxes": n,
        "validation_boxes": int(n_val),
        "members": members,
        "hidden": list(hidden),
        "epochs_run": len(history),
        "best_val_nll": best_val.tolist(),
        "calibration_scale": dict(zip(M.QUANTITIES, scale.tolist(), strict=True)),
        "seconds": time.time() - t0,
        "history": history,
    }
    return model, report


def train_moments(
    seed: int,
    n_boxes: int,
    out,
    cfg: Config = DEFAULT,
    *,
    backend: str = "native",
    chunk: int = 1000,
    progress: bool = True,
    log=print,
) -> dict:
    """Simulate the exploration of `n_boxes` boxes of the wide training mixture (`training.wide`), train
    the moments estimator on them, save it to `out` (with the config's exploration sequence, so a
    mismatched file is refused at load) and return the training report (no history)."""
    key = jax.random.PRNGKey(seed)
    t0 = time.time()
    dists, _ = wide.sample_wide(jax.random.fold_in(key, 0), n_boxes, cfg)
    data = dataset.simulate(cfg, dists, backend=backend, progress=progress, chunk=chunk)
    simulate_s = time.time() - t0
    model, report = train(jax.random.fold_in(key, 1), data, cfg.box, log=log)
    report = {k: v for k, v in report.items() if k != "history"}
    meta = {
        "seed": seed,
        "boxes": n_boxes,
        "backend": backend,
        "training_mixture": [list(s) for s in wide.WIDE_SHARES],
        "exploration_actions": np.asarray(explore.exploration_actions(cfg)).tolist(),
        "box_size": list(cfg.box.size),
        "simulate_s": simulate_s,
        "report": report,
    }
    M.save(out, model, meta)
    return {**report, "simulate_s": simulate_s, "out": str(out)}
