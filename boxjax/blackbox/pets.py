"""PETS (Chua et al. 2018; the default of mbrl-lib): a probabilistic ensemble with trajectory sampling,
as a particle model for the planners' slot (`planning` module docstring).

What. E members (`GaussianMember`), each a fully connected network that maps W's 22 inputs
(`baseline.features`: the same translation-invariant window, belt speeds, belt-speed change and position
steps, standardised with the same statistics) to a gaussian over W's target, the standardised second
difference r = (s_{t+1} - 2 s_t + s_{t-1} - y_mean) / y_std: a mean (5,) and a log-variance (5,). The
log-variance is softly bounded between learned per-output bounds (mbrl-lib's `GaussianMLP`, Chua et al.
appendix A.1):
    logvar = max_logvar - softplus(max_logvar - raw);  logvar = min_logvar + softplus(logvar - min_logvar)
trained with the gaussian negative log-likelihood plus `logvar_penalty` * (sum max_logvar - sum
min_logvar), which keeps the bounds tight. Each member trains on its own bootstrap sample of the
transitions (drawn once, reshuffled every epoch; mbrl-lib's `BootstrapIterator`).

The model is `planning.Ensemble(members, particles_per_member)` with the members stacked on a leading
axis: every planner and tool that takes a model takes it. In the sampling planner each candidate sequence
becomes E * particles_per_member particles; particle e * k + j keeps member e over the whole horizon
(TS-inf) and samples each step's next state from that member's gaussian (`GaussianMember.rollout_sample`:
one standard normal (H, 5) per particle from the planner's per-step key), and the candidate's cost is
the particles' aggregate (`SamplingOptions.particle_risk`, mean by default as in mbrl-lib). The plain
slot (`rollout_sequence`) is the members' mean of their noise-free rollouts (one-step error tables, the
paper planner). No centre of mass: `stability_margin` is `planning.NO_MARGIN`.

Size. 5 members x 22 -> 200 x 4 -> 10 (mbrl-lib's default network: 4 hidden layers of 200, SiLU; Chua et
al. used 5 members), 636,100 trainable parameters in all, a quarter of W's 2,453,005. A planning step
evaluates every candidate as P = E x particles_per_member particles, so its cost is P x (member size)
per rollout step: with the default 2 particles per member (P = 10) a plan costs about what W's single
2.45e6-parameter trajectory costs (measured on this CPU under load: 41 ms for P = 10, 68 ms for
mbrl-lib's P = 20, 25 ms for P = 5; W ~50 ms), and the 20 Hz control period is the budget. P is a
planning-time choice: `dataclasses.replace(model, particles_per_member=k)`.

Online adaptation (`make_adapter`, as W's): `epochs` epochs of Adam on all of the episode's
transitions, every member on the same data in its own order (no bootstrap: an episode is small), the
normalisation kept; pure in (model, data).

Checkpoints (`save` / `load`): arrays layer{i}_w (E, in, out), layer{i}_b (E, out), min_logvar,
max_logvar (E, 5), the normalisation; metadata: PETSConfig, gripper, seed, features, training info.
`load` refuses (PETSCheckpointError, a BaselineCheckpointError, naming the field) another format (a W
file too), another config than expected, another gripper or feature set, or arrays of other shapes.
Training on the W dataset: `training.pets.py`.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import mlp, planning
from boxjax.blackbox import baseline
from boxjax.config import DEFAULT, GripperConfig
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta

FORMAT = "boxjax-pets"
VERSION = 1
N_OUT = 5
ACTIVATIONS = {"silu": jax.nn.silu, "gelu": jax.nn.gelu, "relu": jax.nn.relu}


class PETSCheckpointError(baseline.BaselineCheckpointError):
    """A PETS checkpoint that is missing, corrupt, or of another format, shape or configuration."""


@dataclasses.dataclass(frozen=True)
class PETSConfig:
    """The ensemble, its planning particles and its training (static).

    members, hidden, activation: E networks 22 -> hidden -> 10 (mean and raw log-variance).
    particles_per_member: TS-inf particles per member when planning (E x this = P; mbrl-lib: 20).
    init_min_logvar, init_max_logvar, logvar_penalty: the soft bounds (mbrl-lib: -10, 0.5, 0.01).
    lr, batch, epochs, weight_decay, bootstrap: offline training (AdamW, cosine decay; per member).
    adapt_lr, adapt_batch: online adaptation (Adam; epochs are an adapter argument).
    """

    members: int = 5
    hidden: tuple[int, ...] = (200, 200, 200, 200)
    activation: str = "silu"
    particles_per_member: int = 2
    init_min_logvar: float = -10.0
    init_max_logvar: float = 0.5
    logvar_penalty: float = 0.01
    lr: float = 1e-3
    batch: int = 256
    epochs: int = 30
    weight_decay: float = 3e-5
    bootstrap: bool = True
    adapt_lr: float = 1e-4
    adapt_batch: int = 64

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if self.members < 1 or self.particles_per_member < 1:
            raise ValueError(f"need members >= 1 and particles_per_member >= 1, got {self.members}, "
                             f"{self.particles_per_member}")  # fmt: skip
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"need at least one hidden layer of width >= 1, got {self.hidden}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {self.activation!r}; choose one of {tuple(ACTIVATIONS)}")
        if not self.init_min_logvar < self.init_max_logvar:
            raise ValueError("need init_min_logvar < init_max_logvar")
        if min(self.lr, self.adapt_lr) <= 0 or min(self.batch, self.adapt_batch, self.epochs) < 1:
            raise ValueError("learning rates must be > 0, batch sizes and epochs >= 1")

    @property
    def sizes(self) -> tuple[int, ...]:
        return (baseline.N_FEATURES, *self.hidden, 2 * N_OUT)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d


# ----------------------------------------------------------------------------------------------------------
# One member (a pytree; stacked on a leading axis inside planning.Ensemble).


def bounded_logvar(raw, min_logvar, max_logvar):
    """The soft bounds of mbrl-lib's GaussianMLP (Chua et al. A.1), elementwise."""
    lv = max_logvar - jax.nn.softplus(max_logvar - raw)
    return min_logvar + jax.nn.softplus(lv - min_logvar)


def _head(params, x, min_logvar, max_logvar, activation: str):
    """(mean (5,), logvar (5,)) in standardised target units for ONE standardised input x (F,)."""
    out = mlp.apply(params, x, ACTIVATIONS[activation])
    return out[:N_OUT], bounded_logvar(out[N_OUT:], min_logvar, max_logvar)


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["params", "min_logvar", "max_logvar", "x_mean", "x_std", "y_mean", "y_std"],
    meta_fields=["config", "gripper"],
)
@dataclasses.dataclass(frozen=True)
class GaussianMember:
    """One probabilistic network with the (shared) normalisation of W's features and target.

    params: mlp params of sizes config.sizes; min_logvar, max_logvar: (5,); x_mean, x_std: (22,);
    y_mean, y_std: (5,).
    """

    params: list
    min_logvar: jax.Array
    max_logvar: jax.Array
    x_mean: jax.Array
    x_std: jax.Array
    y_mean: jax.Array
    y_std: jax.Array
    config: PETSConfig
    gripper: GripperConfig

    def distribution(self, window, belt_speed, action):
        """(mean (5,), logvar (5,)) of the standardised target for ONE transition."""
        w = jnp.asarray(window, jnp.float32)[-baseline.HISTORY :]
        x = (baseline.features(w, belt_speed, action, self.gripper) - self.x_mean) / self.x_std
        return _head(self.params, x, self.min_logvar, self.max_logvar, self.config.activation)

    def predict(self, window, belt_speed, action, eps=None) -> jax.Array:
        """(5,) s_{t+1}: the mean, or with `eps` (5,) standard normal, a sample of the member's gaussian."""
        w = jnp.asarray(window, jnp.float32)[-baseline.HISTORY :]
        mu, lv = self.distribution(w, belt_speed, action)
        r = mu if eps is None else mu + jnp.exp(0.5 * lv) * eps
        return 2.0 * w[-1] - w[-2] + self.y_mean + self.y_std * r

    def _rollout(self, window, belt_speed, actions, eps) -> jax.Array:
        def step(carry, xs):
            w, b = carry
            a, e = xs
            s = self.predict(w, b, a, e)
            return (jnp.concatenate([w[1:], s[None]]), planning.next_belt_speed(self, b, a)), s

        carry = (jnp.asarray(window, jnp.float32)[-baseline.HISTORY :], jnp.asarray(belt_speed, jnp.float32))
        acts = jnp.asarray(actions, jnp.float32)
        if eps is None:
            _, states = jax.lax.scan(lambda c, a: step(c, (a, None)), carry, acts)
        else:
            _, states = jax.lax.scan(step, carry, (acts, eps))
        return states

    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        """(H, 5) the member's mean prediction fed back step by step (as W's `rollout_sequence`)."""
        return self._rollout(window, belt_speed, actions, None)

    def rollout_sample(self, key, window, belt_speed, actions) -> jax.Array:
        """(H, 5) one sampled trajectory: each step's next state drawn from the member's gaussian."""
        eps = jax.random.normal(key, (jnp.shape(actions)[0], N_OUT), jnp.float32)
        return self._rollout(window, belt_speed, actions, eps)

    def stability_margin(self, s) -> jax.Array:
        """No centre of mass: planning.NO_MARGIN (m)."""
        return jnp.zeros_like(jnp.asarray(s, jnp.float32)[0]) + planning.NO_MARGIN


def init_model(
    key,
    config: PETSConfig = PETSConfig(),
    gripper: GripperConfig = DEFAULT.gripper,
    stats: dict | None = None,
) -> planning.Ensemble:
    """A fresh ensemble (He init per member, one key each); `stats` as baseline.init_model's."""
    stats = stats or {
        "x_mean": np.zeros(baseline.N_FEATURES),
        "x_std": np.ones(baseline.N_FEATURES),
        "y_mean": np.zeros(N_OUT),
        "y_std": np.ones(N_OUT),
    }
    st = {k: jnp.asarray(stats[k], jnp.float32) for k in ("x_mean", "x_std", "y_mean", "y_std")}
    members = [
        GaussianMember(
            params=mlp.init(k, config.sizes),
            min_logvar=jnp.full(N_OUT, config.init_min_logvar, jnp.float32),
            max_logvar=jnp.full(N_OUT, config.init_max_logvar, jnp.float32),
            **st,
            config=config,
            gripper=gripper,
        )
        for k in jax.random.split(key, config.members)
    ]
    return planning.Ensemble(planning.stack(members), config.particles_per_member)


def config_of(model: planning.Ensemble) -> PETSConfig:
    return model.members.config


def n_params(model: planning.Ensemble) -> int:
    """Trainable scalars: the networks and the log-variance bounds (not the normalisation)."""
    m = model.members
    return mlp.n_params(m.params) + int(np.size(m.min_logvar) + np.size(m.max_logvar))


def is_pets(model) -> bool:
    return isinstance(model, planning.Ensemble) and isinstance(model.members, GaussianMember)


# ----------------------------------------------------------------------------------------------------------
# Training (offline and online): all members at once, each on its own batch.


def _trainable(model: planning.Ensemble) -> dict:
    m = model.members
    return {"params": m.params, "min_logvar": m.min_logvar, "max_logvar": m.max_logvar}


def _with(model: planning.Ensemble, t: dict) -> planning.Ensemble:
    return dataclasses.replace(model, members=dataclasses.replace(model.members, **t))


def gaussian_nll(mu, logvar, y):
    """Elementwise gaussian negative log-likelihood without the constant: 0.5 (logvar + (y - mu)^2 / var)."""
    return 0.5 * (logvar + jnp.square(y - mu) * jnp.exp(-logvar))


def _member_loss(t, x, y, w, activation):
    mu, lv = jax.vmap(lambda xi: _head(t["params"], xi, t["min_logvar"], t["max_logvar"], activation))(x)
    nll = jnp.mean(gaussian_nll(mu, lv, y), axis=-1)
    return jnp.sum(w * nll) / jnp.maximum(jnp.sum(w), 1.0)


def loss(t, x, y, w, activation: str, logvar_penalty: float):
    """Sum over members of the weighted mean NLL of each member's batch (x (E, B, F), y (E, B, 5), w (E, B))
    plus the bounds' penalty (mbrl-lib's `_nll_loss`)."""
    per = jax.vmap(lambda tm, xm, ym, wm: _member_loss(tm, xm, ym, wm, activation))(t, x, y, w)
    return jnp.sum(per) + logvar_penalty * (jnp.sum(t["max_logvar"]) - jnp.sum(t["min_logvar"]))


@functools.lru_cache(maxsize=16)
def make_step(optimizer: optax.GradientTransformation, activation: str, logvar_penalty: float):
    """A jitted `step(t, opt_state, x, y, w) -> (t, opt_state, loss)` on standardised data."""

    @jax.jit
    def step(t, opt_state, x, y, w):
        value, g = jax.value_and_grad(loss)(t, x, y, w, activation, logvar_penalty)
        updates, opt_state = optimizer.update(g, opt_state, t)
        return optax.apply_updates(t, updates), opt_state, value

    return step


def standardise(model: planning.Ensemble, X, Y):
    m = model.members
    return (jnp.asarray(X) - m.x_mean[0]) / m.x_std[0], (jnp.asarray(Y) - m.y_mean[0]) / m.y_std[0]


def member_indices(n: int, members: int, bootstrap: bool, rng: np.random.Generator) -> np.ndarray:
    """(E, n) row indices each member trains on: a bootstrap sample (with replacement) or all rows."""
    if bootstrap:
        return rng.integers(0, n, size=(members, n))
    return np.tile(np.arange(n), (members, 1))


def run_epochs(model, Xn, Yn, optimizer, opt_state, epochs, batch, rng, index_sets, progress=None):
    """`epochs` epochs; in each, member e visits its `index_sets[e]` in a fresh order, one batch of each
    member per step (the last padded with weight 0, so every step has one shape). Returns (model,
    opt_state, per-epoch mean losses)."""
    Xn, Yn = np.asarray(Xn, np.float32), np.asarray(Yn, np.float32)
    cfg = config_of(model)
    step = make_step(optimizer, cfg.activation, cfg.logvar_penalty)
    e, n = index_sets.shape
    nb = max(1, -(-n // batch))
    pad = nb * batch - n
    t, losses = _trainable(model), []
    for _ in range(epochs):
        order = np.stack([rng.permutation(idx) for idx in index_sets])
        order = np.concatenate([order, order[:, :pad] if pad <= n else np.resize(order, (e, pad))], axis=1)
        wts = np.concatenate([np.ones((e, n), np.float32), np.zeros((e, pad), np.float32)], axis=1)
        tot = 0.0
        for b in range(nb):
            sl = order[:, b * batch : (b + 1) * batch]
            t, opt_state, value = step(t, opt_state, Xn[sl], Yn[sl], wts[:, b * batch : (b + 1) * batch])
            tot += float(value)
            if progress is not None:
                progress.update(1)
        losses.append(tot / nb)
    return _with(model, t), opt_state, losses


def adapt(model: planning.Ensemble, data: dict, epochs: int = 1, seed: int = 0) -> planning.Ensemble:
    """`epochs` epochs of Adam (config.adapt_lr, adapt_batch) on all transitions of `data` (s (T+1, 5),
    belt_speed (T+1, 2), actions (T, 4)), every member in its own order; normalisation kept. Pure."""
    if epochs < 1:
        return model
    tr = baseline.episode_transitions(data)
    n = tr["action"].shape[0]
    if n == 0:
        return model
    if not np.all(np.isfinite(tr["window"])) or not np.all(np.isfinite(tr["s_next"])):
        raise ValueError("adaptation data contains NaN or inf states")
    cfg = config_of(model)
    X, Y = baseline.batch_features(tr, model.members.gripper)
    Xn, Yn = standardise(model, X, Y)
    opt = _adapt_optimizer(cfg.adapt_lr)
    rng = np.random.default_rng(seed + n)
    idx = member_indices(n, model.n_members, False, rng)
    model, _, _ = run_epochs(
        model, Xn, Yn, opt, opt.init(_trainable(model)), epochs, cfg.adapt_batch, rng, idx
    )
    return model


@functools.lru_cache(maxsize=8)
def _adapt_optimizer(lr: float):
    return optax.adam(lr)


def make_adapter(epochs: int = 1, seed: int = 0):
    """Online adaptation as `callable(model, data) -> model` for `controller.run_episode(...,
    adapter=...)` (ControllerConfig(adapt_every=20): the paper's schedule for W)."""
    if epochs < 1:
        raise ValueError(f"an adapter needs epochs >= 1, got {epochs} (use no adapter to turn it off)")
    return functools.partial(_adapter, epochs=epochs, seed=seed)


def _adapter(model, data, epochs, seed):
    inner = getattr(model, "model", None)  # a wrapper (planning.DriftCorrected): adapt the ensemble inside
    if not is_pets(model) and is_pets(inner):
        return dataclasses.replace(model, model=adapt(inner, data, epochs=epochs, seed=seed))
    return adapt(model, data, epochs=epochs, seed=seed)


# ----------------------------------------------------------------------------------------------------------
# Calibration of the predicted distribution.


@jax.jit
def _predictive(members, x):
    mu, lv = jax.vmap(lambda m: jax.vmap(lambda xi: _head(m.params, xi, m.min_logvar, m.max_logvar,
                                                          m.config.activation))(x))(members)  # fmt: skip
    return mu, lv  # (E, N, 5)


def calibration(model: planning.Ensemble, transitions: dict, chunk: int = 8192) -> dict:
    """How well the ensemble's predictive distribution (the equal mixture of its members' gaussians, mean
    and variance by moments) covers the true standardised targets of `transitions`: the mean NLL per
    output (nats, gaussian approximation, constant included), the fraction within 1 and 2 predicted
    stds (a gaussian: 0.683, 0.954), and the predicted std against the RMS error, per output."""
    X, Y = baseline.batch_features(transitions, model.members.gripper)
    Xn, Yn = standardise(model, X, Y)
    Xn, Yn = np.asarray(Xn), np.asarray(Yn)
    mus, lvs = [], []
    for i in range(0, Xn.shape[0], chunk):
        mu, lv = _predictive(model.members, jnp.asarray(Xn[i : i + chunk]))
        mus.append(np.asarray(mu))
        lvs.append(np.asarray(lv))
    mu_e, var_e = np.concatenate(mus, axis=1), np.exp(np.concatenate(lvs, axis=1))
    mu = mu_e.mean(0)
    var = var_e.mean(0) + mu_e.var(0)
    z = np.abs(Yn - mu) / np.sqrt(var)
    nll = 0.5 * (np.log(2 * np.pi * var) + (Yn - mu) ** 2 / var)
    names = ("P1", "P2", "x", "y", "yaw")
    return {
        "nll_per_output": float(nll.mean()),
        "within_1_std": {k: float(np.mean(z[:, i] < 1)) for i, k in enumerate(names)},
        "within_2_std": {k: float(np.mean(z[:, i] < 2)) for i, k in enumerate(names)},
        "predicted_std_rms": {k: float(np.sqrt(var[:, i].mean())) for i, k in enumerate(names)},
        "error_rms": {k: float(np.sqrt(np.mean((Yn[:, i] - mu[:, i]) ** 2))) for i, k in enumerate(names)},
        "epistemic_fraction_of_variance": float(mu_e.var(0).sum() / var.sum()),
        "units": "standardised second difference (baseline target / y_std)",
    }


# ----------------------------------------------------------------------------------------------------------
# Checkpoints.


def save(path, model: planning.Ensemble, seed: int, info: dict | None = None) -> str:
    """Write the ensemble (stacked layers, bounds, normalisation, config, gripper, seed, `info`) as one
    compressed .npz, atomically."""
    m = model.members
    arrays = {f"layer{i}_{k}": np.asarray(layer[k]) for i, layer in enumerate(m.params) for k in ("w", "b")}
    arrays.update({k: np.asarray(getattr(m, k)) for k in ("min_logvar", "max_logvar")})
    arrays.update({k: np.asarray(getattr(m, k)[0]) for k in ("x_mean", "x_std", "y_mean", "y_std")})
    meta = {
        "config": m.config.to_dict(),
        "gripper": baseline._gripper_dict(m.gripper),
        "seed": int(seed),
        "n_params": n_params(model),
        "features": list(baseline.FEATURE_NAMES),
        "info": baseline.json_safe(info or {}),
    }
    return write_npz_with_meta(path, arrays, meta, FORMAT, VERSION)


def _array(arrays, path, name, shape, finite=False):
    a = arrays.get(name)
    if a is None or a.shape != shape:
        got = None if a is None else a.shape
        raise PETSCheckpointError(f"{path}: {name} has shape {got}, the configuration needs {shape}")
    if finite and not np.all(np.isfinite(a)):
        raise PETSCheckpointError(f"{path}: {name} is not finite")
    return jnp.asarray(a, jnp.float32)


def load(
    path,
    expected_config: PETSConfig | None = None,
    gripper: GripperConfig = DEFAULT.gripper,
    with_meta: bool = False,
):
    """The ensemble from `save`. Raises PETSCheckpointError for a missing or corrupt file, another format
    (a W checkpoint included), a PETSConfig other than `expected_config` (when given), another gripper,
    other features, or arrays whose shapes do not match the configuration (named)."""
    arrays, meta = read_npz_with_meta(path, PETSCheckpointError, "PETS checkpoint", FORMAT, VERSION)
    try:
        config = PETSConfig(**{**meta["config"], "hidden": tuple(meta["config"]["hidden"])})
    except (KeyError, TypeError, ValueError) as e:
        raise PETSCheckpointError(f"{path}: unreadable PETS configuration ({e})") from e
    if expected_config is not None and config != expected_config:
        diff = baseline.config_diff(config, expected_config)
        raise PETSCheckpointError(f"{path}: PETS configuration differs from the expected one: {diff} "
                                  "(file, expected)")  # fmt: skip
    if bad := baseline.gripper_mismatches(meta.get("gripper"), gripper):
        raise PETSCheckpointError(
            f"{path}: PETS was trained for another gripper configuration (differs in {bad})"
        )
    if meta.get("features") != list(baseline.FEATURE_NAMES):
        raise PETSCheckpointError(f"{path}: PETS was trained on other input features {meta.get('features')}")
    e, sizes = config.members, config.sizes
    params = [
        {
            "w": _array(arrays, path, f"layer{i}_w", (e, n_in, n_out)),
            "b": _array(arrays, path, f"layer{i}_b", (e, n_out)),
        }
        for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True))
    ]
    if f"layer{len(sizes) - 1}_w" in arrays:
        raise PETSCheckpointError(f"{path}: more layers than the configuration {sizes}")
    bounds = {k: _array(arrays, path, k, (e, N_OUT), finite=True) for k in ("min_logvar", "max_logvar")}
    f = baseline.N_FEATURES
    stats = {
        k: jnp.tile(_array(arrays, path, k, (n,), finite=True)[None], (e, 1))
        for k, n in (("x_mean", f), ("x_std", f), ("y_mean", N_OUT), ("y_std", N_OUT))
    }
    members = GaussianMember(params=params, **bounds, **stats, config=config, gripper=gripper)
    model = planning.Ensemble(members, config.particles_per_member)
    return (model, meta) if with_meta else model


SHIPPED = "data/pets.npz"


def shipped_path() -> str:
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), SHIPPED)


@functools.lru_cache(maxsize=2)
def default_model(gripper: GripperConfig = DEFAULT.gripper) -> planning.Ensemble:
    """The PETS ensemble shipped with boxjax (boxjax/data/pets.npz)."""
    return load(shipped_path(), gripper=gripper)
