"""A learned residual on the physics prior: the prior's rollout, corrected step by step by a small MLP.

Why. The "slip" prior is a rigid, quasi-static contact model. Along the controller's own closed loop its
10-step balance error is several times that of random actions, and its known bias
(docs/results/random-boxes.md, "What is not
met, and why") is the drag of a carriage move under a turning or slipping box: in the simulator the box
hops clear of the belts for a few milliseconds of each carriage pulse, which no rigid-contact prior
has. The simulator-planner reference turns every failure of the default controller with the same
planner and cost, so the remaining failures are model error. A residual keeps the prior's structure
(the centre of mass, the loads, the friction law) and learns only what it gets wrong.

The model (`Residual`, a `planning.Model`): the prior's `rollout_sequence` with a `correction` after
every step (`prior.rollout_sequence(..., correction=...)`). From the step's physical quantities
(`features`: the carried start velocity, the prior's predicted displacement and end velocity, the belt
speeds and setpoints, the carriage move, the balance offset, the box's yaw, its centre of mass in the
conveyor frame, mass, radius of gyration, the prior's normal loads and friction) the MLP gives a
bounded correction to the step's displacement (x, y, yaw) and to the velocity the next step starts
from: |dx|, |dy| <= `ResidualConfig.max_position`, |dyaw| <= max_yaw, |dv| <= max_velocity,
|domega| <= max_omega (tanh). Its last layer starts at zero, so an untrained residual is the prior
exactly (a test).

Training (`fit`): through the whole H-step rollout (the prior is differentiable:
docs/design.md#differentiable), on segments of closed-loop episodes of the default controller, the loss a
smooth L1 (pseudo-Huber) of the predicted (x, y, yaw) against the simulator's, per step, in mm and
units of `ResidualConfig.yaw_unit`. Episodes of the controller's own loop, because the prior's error
there is what the planner meets (`benchmarks/closed_loop_error.py` collects them). The prior stays
frozen: only the MLP learns.

Checkpoints: `save` / `load` (npz; the config and the layer sizes travel with the weights).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import mlp, planning
from boxjax.config import DEFAULT
from boxjax.fileio import atomic_path
from boxjax.geometry import rot2
from boxjax.prior import predictor as prior

N_FEATURES = 30
N_OUT = 6  # dx, dy, dyaw of the step; dvx, dvy, domega of the carried velocity


@dataclasses.dataclass(frozen=True)
class ResidualConfig:
    """The residual's shape and bounds (static)."""

    hidden: tuple[int, ...] = (64, 64)
    max_position: float = 0.004  # m per step, bound on the x / y correction
    max_yaw: float = 0.01  # rad per step
    max_velocity: float = 0.05  # m/s, bound on the carried velocity's correction
    max_omega: float = 0.5  # rad/s
    yaw_unit: float = 0.005  # rad counted as 1 mm in the training loss (~ the box's half-width times it)

    def __post_init__(self):
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden layer widths must be >= 1, got {self.hidden}")
        if min(self.max_position, self.max_yaw, self.max_velocity, self.max_omega, self.yaw_unit) <= 0:
            raise ValueError("the residual's bounds and yaw unit must be > 0")

    def bounds(self) -> jax.Array:
        return jnp.asarray(
            [self.max_position, self.max_position, self.max_yaw]
            + [self.max_velocity, self.max_velocity, self.max_omega],
            jnp.float32,
        )


def init(key: jax.Array, cfg: ResidualConfig = ResidualConfig()) -> mlp.Params:
    """MLP weights with a zero last layer: the residual starts as no correction at all."""
    net = mlp.init(key, (N_FEATURES, *cfg.hidden, N_OUT))
    net[-1] = {"w": jnp.zeros_like(net[-1]["w"]), "b": jnp.zeros_like(net[-1]["b"])}
    return net


def features(model: prior.PriorModel, w, b, a, u, s, info) -> jax.Array:
    """(N_FEATURES,) the step's physical quantities, scaled to O(1) (conveyor frame; see module doc)."""
    gr = model.gripper
    s_t = w[-1]
    th = s_t[4]
    mg = model.mass * gr.gravity
    com = rot2(th) @ model.com[:2]
    sp = jnp.clip(a[:2], -gr.belt_speed_limit, gr.belt_speed_limit)
    v_end = info["velocity"]
    parts = [
        u[:2] / 0.1,
        u[2:] / 1.0,
        (s[2:4] - s_t[2:4]) / 0.005,
        (s[4:5] - s_t[4:5]) / 0.02,
        v_end[:2] / 0.1,
        v_end[2:] / 1.0,
        b / 0.12,
        sp / 0.12,
        (s[:2] - s_t[:2]) / 0.01,
        s_t[:2] / 0.2,
        (s_t[3:4] - 0.5 * (s_t[0:1] + s_t[1:2])) / 0.04,
        s_t[2:3] / 0.1,
        jnp.stack([jnp.cos(2 * th), jnp.sin(2 * th)]),
        com / 0.1,
        model.com[2:] / 0.05,
        jnp.reshape(model.mass / 5.0, (1,)),
        jnp.reshape(jnp.sqrt(model.izz / model.mass) / 0.1, (1,)),
        info["normal_load"] / mg,
        info["friction"] / (gr.friction * mg),
    ]
    x = jnp.concatenate([jnp.ravel(p) for p in parts])
    assert x.shape == (N_FEATURES,), x.shape
    return x


def correction(net: mlp.Params, cfg: ResidualConfig, model: prior.PriorModel) -> Callable:
    """The `prior.rollout_sequence` correction hook of the residual `net` for `model`'s box."""
    bounds = cfg.bounds()

    def correct(w, b, a, u, s, info):
        out = bounds * jnp.tanh(mlp.apply(net, features(model, w, b, a, u, s, info)))
        return s.at[2:].add(out[:3]), info["velocity"] + out[3:]

    return correct


@functools.partial(jax.tree_util.register_dataclass, data_fields=["prior", "net"], meta_fields=["cfg"])
@dataclasses.dataclass(frozen=True)
class Residual:
    """The physics prior with a learned residual: a `planning.Model` (a pytree; `cfg` static)."""

    prior: prior.PriorModel
    net: mlp.Params
    cfg: ResidualConfig = ResidualConfig()

    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        corr = correction(self.net, self.cfg, self.prior)
        return prior.rollout_sequence(self.prior, window, belt_speed, actions, correction=corr)

    def stability_margin(self, s) -> jax.Array:
        return self.prior.stability_margin(s)

    def planar_com(self) -> jax.Array:
        return self.prior.planar_com()


# ----------------------------------------------------------------------------------------------------------
# Training.


def segments(traces: dict, horizon: int, stride: int = 1, start: str = "exploration") -> dict:
    """Training cases from closed-loop episodes (`benchmarks/closed_loop_error.collect`'s dict: per box j
    s_j (T+1, 5), bs_j (T+1, 2), a_j (T, 4), m_j voxel masses, nx_j exploration steps): every `stride`-th
    step t with `horizon` steps left, from t = 2 ("all") or from the end of the exploration
    ("exploration", the steps the planner plans). Returns numpy {"window" (C, 3, 5), "belt_speed" (C, 2),
    "actions" (C, H, 4), "truth" (C, H, 5), "box" (C,) int index into "masses" (N, nx, ny, nz)}."""
    if start not in ("exploration", "all"):
        raise ValueError(f"start must be 'exploration' or 'all', got {start!r}")
    n = len(traces["success"])
    cols: dict[str, list] = {"window": [], "belt_speed": [], "actions": [], "truth": [], "box": []}
    w = planning.MIN_WINDOW
    for j in range(n):
        s, bs, a = traces[f"s_{j}"], traces[f"bs_{j}"], traces[f"a_{j}"]
        t0 = max(int(traces[f"nx_{j}"]) if start == "exploration" else 0, w - 1)
        for t in range(t0, len(a) - horizon + 1, stride):
            cols["window"].append(s[t - w + 1 : t + 1])
            cols["belt_speed"].append(bs[t])
            cols["actions"].append(a[t : t + horizon])
            cols["truth"].append(s[t + 1 : t + horizon + 1])
            cols["box"].append(j)
    out = {k: np.asarray(v, np.int32 if k == "box" else np.float32) for k, v in cols.items()}
    out["masses"] = np.stack([np.asarray(traces[f"m_{j}"], np.float32) for j in range(n)])
    return out


def _pseudo_huber(err: jax.Array, delta: float = 1.0) -> jax.Array:
    return delta * delta * (jnp.sqrt(1.0 + (err / delta) ** 2) - 1.0)


def rollout_loss(net, cfg: ResidualConfig, model, window, belt_speed, actions, truth) -> jax.Array:
    """() the smooth-L1 (x, y, yaw) error of ONE corrected rollout against the simulator's states, mean over
    steps and coordinates; mm for positions, cfg.yaw_unit for the yaw."""
    pred = Residual(model, net, cfg).rollout_sequence(window, belt_speed, actions)
    scale = jnp.asarray([1e3, 1e3, 1.0 / cfg.yaw_unit], jnp.float32)
    return jnp.mean(_pseudo_huber((pred[:, 2:] - truth[:, 2:]) * scale))


def _models(masses, cfg_sim, params: prior.PriorParams):
    """One prior per box (stacked pytree) from voxel masses (N, nx, ny, nz)."""

    def one(m):
        return prior.make_prior(m, None, cfg_sim.box, cfg_sim.gripper, params)

    return jax.jit(jax.vmap(one))(jnp.asarray(masses))


def fit(
    key: jax.Array,
    train: dict,
    val: dict | None = None,
    cfg: ResidualConfig = ResidualConfig(),
    sim_cfg=None,
    params: prior.PriorParams | None = None,
    steps: int = 2000,
    batch: int = 128,
    lr: float = 3e-4,
    clip: float = 100.0,
    eval_every: int = 250,
    progress: Callable[[int, dict], None] | None = None,
) -> tuple[mlp.Params, dict]:
    """Train a residual on `segments` cases (Adam with cosine decay, gradients clipped to a global norm of
    `clip`; the prior frozen). Returns (net, log):
    log has the loss before and after on `val` (the prior alone = the untrained residual) and the curve.
    """

    sim_cfg = sim_cfg or DEFAULT
    params = params or prior.PriorParams()
    k_init, key = jax.random.split(key)
    net = init(k_init, cfg)
    models_train = _models(train["masses"], sim_cfg, params)  # a prior the hook cannot correct raises
    # Clipped: along a chaotic rollout (a contact lost, a box starting to slide) a small correction can
    # change the outcome a lot, and per-case gradient norms are heavy-tailed.
    opt = optax.chain(
        optax.clip_by_global_norm(clip), optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05))
    )
    opt_state = opt.init(net)

    def batch_loss(net, models, idx, data):
        model_b = jax.tree.map(lambda x: x[data["box"][idx]], models)
        losses = jax.vmap(rollout_loss, in_axes=(None, None, 0, 0, 0, 0, 0))(
            net,
            cfg,
            model_b,
            data["window"][idx],
            data["belt_speed"][idx],
            data["actions"][idx],
            data["truth"][idx],
        )
        return jnp.mean(losses)

    @jax.jit
    def train_step(net, opt_state, idx, models, data):
        loss, g = jax.value_and_grad(batch_loss)(net, models, idx, data)
        upd, opt_state = opt.update(g, opt_state, net)
        return optax.apply_updates(net, upd), opt_state, loss

    dev_train = {k: jnp.asarray(v) for k, v in train.items() if k != "masses"}
    eval_loss = None
    if val is not None:
        models_val = _models(val["masses"], sim_cfg, params)
        dev_val = {k: jnp.asarray(v) for k, v in val.items() if k != "masses"}
        loss_val = jax.jit(batch_loss)

        def eval_loss(net):
            n = len(val["window"])
            vals = [
                float(loss_val(net, models_val, jnp.arange(i, min(i + 1024, n)), dev_val))
                * (min(i + 1024, n) - i)
                for i in range(0, n, 1024)
            ]
            return sum(vals) / n

    n = len(train["window"])
    log: dict = {"steps": steps, "batch": batch, "lr": lr, "clip": clip, "train_cases": n, "curve": []}
    if eval_loss is not None:
        log["val_cases"] = len(val["window"])
        log["val_loss_prior"] = eval_loss(net)
    t0 = time.perf_counter()
    for i in range(steps):
        key, k = jax.random.split(key)
        idx = jax.random.randint(k, (batch,), 0, n)
        net, opt_state, loss = train_step(net, opt_state, idx, models_train, dev_train)
        if (i + 1) % eval_every == 0 or i + 1 == steps:
            row = {"step": i + 1, "train_loss": float(loss), "s": time.perf_counter() - t0}
            if eval_loss is not None:
                row["val_loss"] = eval_loss(net)
            log["curve"].append(row)
            if progress is not None:
                progress(i + 1, row)
    if eval_loss is not None:
        log["val_loss"] = log["curve"][-1]["val_loss"]
    log["train_s"] = time.perf_counter() - t0
    return net, log


# ----------------------------------------------------------------------------------------------------------
# Checkpoints.


def save(
    path: str, net: mlp.Params, cfg: ResidualConfig = ResidualConfig(), meta: dict | None = None
) -> None:
    """Write the residual (weights, config, free-form `meta`) to `path` (npz, atomically)."""
    arrays = {f"l{i}_{k}": np.asarray(layer[k]) for i, layer in enumerate(net) for k in ("w", "b")}
    header = {"format": "boxjax-residual-1", "config": dataclasses.asdict(cfg), "meta": meta or {}}
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, header=np.asarray(json.dumps(header)), **arrays)


@functools.lru_cache(maxsize=4)
def load_cached(path: str) -> tuple[mlp.Params, ResidualConfig, dict]:
    """`load`, once per path (the controller builds a model per episode)."""
    return load(path)


def load(path: str) -> tuple[mlp.Params, ResidualConfig, dict]:
    """(net, cfg, meta) from a `save`d file; ValueError naming the file when it is not one."""
    try:
        with np.load(path) as z:
            header = json.loads(str(z["header"]))
            if header.get("format") != "boxjax-residual-1":
                raise ValueError("not a boxjax residual checkpoint")
            c = header["config"]
            cfg = ResidualConfig(**{**c, "hidden": tuple(c["hidden"])})
            n_layers = len(cfg.hidden) + 1
            net = [{k: jnp.asarray(z[f"l{i}_{k}"]) for k in ("w", "b")} for i in range(n_layers)]
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise ValueError(f"{path}: cannot read a residual checkpoint ({e})") from e
    sizes = mlp.sizes_of(net)
    if sizes != (N_FEATURES, *cfg.hidden, N_OUT):
        raise ValueError(f"{path}: layer sizes {sizes} do not match the config {cfg}")
    return net, cfg, header.get("meta", {})
