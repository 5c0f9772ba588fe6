"""The black-box baseline W (paper §4.1): a fully connected network as a model for the planners' slot.

The paper's classical MPC predicts s_{t+1} = W(s_t, a_t) with a fully connected network of ~2.5e6
parameters, trained on ~200 episodes of ONE environment (box A) and re-trained online for one epoch on
the current episode's data every 20 steps. Here W is a pure-JAX MLP (`boxjax.mlp`, optax for training)
that fills the same model slot as the physics prior (`planning.Model`): the planners do not know which
model they plan with.

What W sees (one transition t -> t+1; `features`, 22 numbers, standardised with the training set's
mean and std):
  * the last 3 planar states s_{t-2..t} (the same window the prior sees, `planning.MIN_WINDOW`), made
    translation-invariant: the belts are endless along x, so x itself is dropped; y enters only relative
    to each belt (y - P1, y - P2: where the box lies on the belts decides which belt drags how much);
    the carriages' absolute positions P1, P2 stay (their travel ends clip a position step); the yaw
    enters as (cos, sin) (the box's orientation relative to the belts, without a 2 pi jump);
  * velocities as finite differences of the window: s_t - s_{t-1} and s_{t-1} - s_{t-2} (5 each, per
    control step; the second gives the acceleration before the action, as the prior's window does);
  * the measured belt speeds (2,) m/s, the belt-speed change the action will cause (2,) m/s (the setpoint
    reached at <= belt_accel_limit, the rule `planning.next_belt_speed` states: a property of the gripper,
    not of the box) and the position steps dp1, dp2 (2,) m, clipped to the hardware as the simulator does.
What W predicts: the standardised residual of the state delta over constant velocity,
  r = (s_{t+1} - s_t) - (s_t - s_{t-1})    (5,), i.e. the second difference;
  s_{t+1} = s_t + (s_t - s_{t-1}) + y_mean + y_std * W(x).
Why a delta and why over constant velocity: absolute states are dominated by where the box happens to
be, and a network of this size reproduces its input to ~1e-3 of its spread at best, which is millimetres;
the one-step change is what the physics decides, and most of it is the velocity the window already
shows (constant velocity alone is a strong predictor: ~0.5 mm, ~0.06 deg one-step error,
docs/results/black-boxes.md). The
standardised residual puts the network's capacity on the part constant velocity gets wrong.

W knows no centre of mass: `stability_margin` returns `planning.NO_MARGIN`, so the planners' tipping
barrier is inert (the paper's baseline has none either).

Online adaptation (`make_adapter`): `callable(model, data) -> model` for `controller.run_episode(...,
adapter=...)`: `epochs` epochs of Adam over all transitions of the episode so far, with the checkpoint's
normalisation kept (fresh optimiser state at each call, so the adapted model is a pure function of the
model and the data).

Checkpoints (`save` / `load`, `fileio.write_npz_with_meta`): the layer arrays, the normalisation stats,
and in the metadata the BaselineConfig, the gripper config, the seed and how it was trained. `load`
refuses (BaselineCheckpointError, naming the field) a file of another format, another BaselineConfig
than expected, another gripper, or arrays of the wrong shapes.

Training data and the CLI's `train-baseline` are in `training.baseline.py`.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import config_io, geometry, mlp, planning
from boxjax.config import DEFAULT, GripperConfig
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta

FORMAT = "boxjax-blackbox-W"
VERSION = 1
HISTORY = planning.MIN_WINDOW  # states W sees: s_{t-2}, s_{t-1}, s_t
FEATURE_NAMES = (
    "cos_yaw",
    "sin_yaw",
    "y_minus_P1",
    "y_minus_P2",
    "P1",
    "P2",
    "dP1_t",
    "dP2_t",
    "dx_t",
    "dy_t",
    "dyaw_t",
    "dP1_t-1",
    "dP2_t-1",
    "dx_t-1",
    "dy_t-1",
    "dyaw_t-1",
    "belt_speed1",
    "belt_speed2",
    "dv1",
    "dv2",
    "dp1",
    "dp2",
)
N_FEATURES = len(FEATURE_NAMES)


class BaselineCheckpointError(ValueError):
    """A W checkpoint that is missing, corrupt, or of another format, shape or configuration."""


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """The network and its training (static).

    hidden: hidden layer widths; (1100, 1100, 1100) gives 2.45e6 parameters (paper: ~2.5e6).
    lr, batch, epochs, weight_decay: offline training (AdamW, cosine decay).
    adapt_lr, adapt_batch: online adaptation (Adam, constant rate; epochs are an adapter argument).
    """

    hidden: tuple[int, ...] = (1100, 1100, 1100)
    lr: float = 1e-3
    batch: int = 256
    epochs: int = 12
    weight_decay: float = 1e-5
    adapt_lr: float = 1e-4
    adapt_batch: int = 64

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"need at least one hidden layer of width >= 1, got {self.hidden}")
        if min(self.lr, self.adapt_lr) <= 0 or min(self.batch, self.adapt_batch, self.epochs) < 1:
            raise ValueError("learning rates must be > 0, batch sizes and epochs >= 1")

    @property
    def sizes(self) -> tuple[int, ...]:
        return (N_FEATURES, *self.hidden, 5)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d


def _gripper_dict(g: GripperConfig) -> dict:
    return json_safe(dataclasses.asdict(g))


def gripper_mismatches(stored, gripper: GripperConfig) -> list[str]:
    """The gripper fields (`config_io.GRIPPER_FIELDS`) where a checkpoint's recorded gripper differs from
    `gripper`; a field the file does not record was added later and counts as its default. Not a dict at
    all: ["gripper"]."""
    if not isinstance(stored, dict):
        return ["gripper"]
    found = config_io.field_mismatches(
        {"gripper": stored}, {"gripper": _gripper_dict(gripper)}, config_io.GRIPPER_FIELDS
    )
    return [name for name, _, _ in found]


def json_safe(x):
    """Tuples -> lists and infinities -> strings, recursively (JSON round trip equality)."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return x


# ----------------------------------------------------------------------------------------------------------
# Features and targets (pure jnp, ONE transition; vmap for batches).


def features(window, belt_speed, action, gripper: GripperConfig) -> jax.Array:
    """(N_FEATURES,) unnormalised inputs of W for one transition (see module docstring).

    window: (W >= 3, 5) planar states s_{t-W+1..t}; belt_speed: (2,) m/s; action: (4,) as sent.
    """
    w = jnp.asarray(window, jnp.float32)[-HISTORY:]
    s, d1, d2 = w[-1], w[-1] - w[-2], w[-2] - w[-3]
    b = jnp.asarray(belt_speed, jnp.float32)
    a = jnp.asarray(action, jnp.float32)
    sp = jnp.clip(a[:2], -gripper.belt_speed_limit, gripper.belt_speed_limit)
    dvmax = gripper.belt_accel_limit * gripper.control_dt
    dv = jnp.clip(sp - b, -dvmax, dvmax)
    dp = jnp.clip(a[2:], -gripper.max_position_step, gripper.max_position_step)
    yaw = s[geometry.YAW]
    pose = jnp.stack(
        [jnp.cos(yaw), jnp.sin(yaw), s[geometry.Y] - s[geometry.P1], s[geometry.Y] - s[geometry.P2]]
    )
    return jnp.concatenate([pose, s[:2], d1, d2, b, dv, dp])


def target(window, s_next) -> jax.Array:
    """(5,) the second difference s_{t+1} - 2 s_t + s_{t-1} (what W predicts, before standardising)."""
    w = jnp.asarray(window, jnp.float32)
    return jnp.asarray(s_next, jnp.float32) - 2.0 * w[-1] + w[-2]


def episode_transitions(data: dict) -> dict:
    """The transitions of one episode's arrays (s (T+1, 5), belt_speed (T+1, 2), actions (T, 4)) as
    windows (T, 3, 5) (the initial state repeated before the start: the box is at rest), belt_speed
    (T, 2), action (T, 4), s_next (T, 5); numpy float32."""
    s = np.asarray(data["s"], np.float32)
    acts = np.asarray(data["actions"], np.float32).reshape(-1, 4)
    n = acts.shape[0]
    if s.shape != (n + 1, 5):
        raise ValueError(f"s must have shape (T+1, 5) = ({n + 1}, 5) for {n} actions, got {s.shape}")
    padded = np.concatenate([np.repeat(s[:1], HISTORY - 1, axis=0), s])
    idx = np.arange(n)[:, None] + np.arange(HISTORY)[None]
    return {
        "window": padded[idx],
        "belt_speed": np.asarray(data["belt_speed"], np.float32)[:n],
        "action": acts,
        "s_next": s[1:],
    }


# ----------------------------------------------------------------------------------------------------------
# The model (a pytree for the planners' slot).


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["params", "x_mean", "x_std", "y_mean", "y_std"],
    meta_fields=["config", "gripper"],
)
@dataclasses.dataclass(frozen=True)
class BlackBoxModel:
    """W with its normalisation (a pytree; config and gripper are static).

    params: mlp params of sizes config.sizes; x_mean, x_std: (N_FEATURES,); y_mean, y_std: (5,).
    """

    params: list
    x_mean: jax.Array
    x_std: jax.Array
    y_mean: jax.Array
    y_std: jax.Array
    config: BaselineConfig
    gripper: GripperConfig

    def predict(self, window, belt_speed, action) -> jax.Array:
        """(5,) s_{t+1} for ONE action (pure jnp; vmap over actions)."""
        w = jnp.asarray(window, jnp.float32)[-HISTORY:]
        x = (features(w, belt_speed, action, self.gripper) - self.x_mean) / self.x_std
        r = self.y_mean + self.y_std * mlp.apply(self.params, x)
        return 2.0 * w[-1] - w[-2] + r

    # The model slot of the planners (`planning.Model`).
    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        """(H, 5) predicted states for `actions` (H, 4), each prediction fed back as the newest state of
        the window; belt speeds follow the setpoints at <= belt_accel_limit (`planning.next_belt_speed`)."""

        def step(carry, a):
            w, b = carry
            s = self.predict(w, b, a)
            return (jnp.concatenate([w[1:], s[None]]), planning.next_belt_speed(self, b, a)), s

        carry = (jnp.asarray(window, jnp.float32)[-HISTORY:], jnp.asarray(belt_speed, jnp.float32))
        _, states = jax.lax.scan(step, carry, jnp.asarray(actions, jnp.float32))
        return states

    def stability_margin(self, s) -> jax.Array:
        """A black box knows no centre of mass: planning.NO_MARGIN (m), so margin barriers are inert."""
        return jnp.zeros_like(jnp.asarray(s, jnp.float32)[0]) + planning.NO_MARGIN


def check_window(window, belt_speed=None, actions=None) -> np.ndarray:
    """Host-side checks of W's inputs (planning.check_window's rules: shape (W >= 3, 5), finite; belt_speed
    (2,) finite; actions (H, 4) finite). Raises ValueError naming the problem."""
    w = planning.check_window(window, belt_speed)
    if actions is not None:
        a = np.asarray(actions, np.float64)
        if a.ndim != 2 or a.shape[1] != 4:
            raise ValueError(f"actions must have shape (H, 4), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("actions contain NaN or inf")
    return w


def rollout(model: BlackBoxModel, window, belt_speed, actions) -> np.ndarray:
    """Host-checked `model.rollout_sequence` (a NaN window raises ValueError here, not NaN states)."""
    w = check_window(window, belt_speed, actions)
    return np.asarray(_rollout_jit(model, w, jnp.asarray(belt_speed, jnp.float32), jnp.asarray(actions)))


@jax.jit
def _rollout_jit(model, window, belt_speed, actions):
    return model.rollout_sequence(window, belt_speed, actions)


def init_model(
    key,
    config: BaselineConfig = BaselineConfig(),
    gripper: GripperConfig = DEFAULT.gripper,
    stats: dict | None = None,
) -> BlackBoxModel:
    """A fresh W (He init, `mlp.init`); `stats` {x_mean, x_std, y_mean, y_std} (default: identity)."""
    stats = stats or {
        "x_mean": np.zeros(N_FEATURES),
        "x_std": np.ones(N_FEATURES),
        "y_mean": np.zeros(5),
        "y_std": np.ones(5),
    }
    return BlackBoxModel(
        params=mlp.init(key, config.sizes),
        **{k: jnp.asarray(stats[k], jnp.float32) for k in ("x_mean", "x_std", "y_mean", "y_std")},
        config=config,
        gripper=gripper,
    )


def n_params(model: BlackBoxModel) -> int:
    return mlp.n_params(model.params)


# ----------------------------------------------------------------------------------------------------------
# Training (offline and online).


def batch_features(transitions: dict, gripper: GripperConfig) -> tuple[jax.Array, jax.Array]:
    """(X (N, N_FEATURES), Y (N, 5)) unnormalised features and targets of a transitions dict."""
    f = jax.vmap(lambda w, b, a: features(w, b, a, gripper))
    X = f(
        jnp.asarray(transitions["window"]),
        jnp.asarray(transitions["belt_speed"]),
        jnp.asarray(transitions["action"]),
    )
    Y = jax.vmap(target)(jnp.asarray(transitions["window"]), jnp.asarray(transitions["s_next"]))
    return X, Y


def normalisation(X, Y) -> dict:
    """Mean and std of features and targets (std floored so constant features stay finite)."""
    X, Y = np.asarray(X, np.float64), np.asarray(Y, np.float64)
    return {
        "x_mean": X.mean(0),
        "x_std": np.maximum(X.std(0), 1e-6),
        "y_mean": Y.mean(0),
        "y_std": np.maximum(Y.std(0), 1e-9),
    }


def _loss(params, x, y, w):
    pred = jax.vmap(mlp.apply, in_axes=(None, 0))(params, x)
    err = jnp.mean(jnp.square(pred - y), axis=-1)
    return jnp.sum(w * err) / jnp.maximum(jnp.sum(w), 1.0)


@functools.lru_cache(maxsize=16)
def make_step(optimizer: optax.GradientTransformation):
    """A jitted `step(params, opt_state, x (B, F), y (B, 5), w (B,)) -> (params, opt_state, loss)` on
    standardised data; w weights rows (0 = padding, so every batch has one shape and compiles once)."""

    @jax.jit
    def step(params, opt_state, x, y, w):
        loss, g = jax.value_and_grad(_loss)(params, x, y, w)
        updates, opt_state = optimizer.update(g, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def standardise(model: BlackBoxModel, X, Y):
    return (jnp.asarray(X) - model.x_mean) / model.x_std, (jnp.asarray(Y) - model.y_mean) / model.y_std


def run_epochs(
    model: BlackBoxModel, Xn, Yn, optimizer, opt_state, epochs: int, batch: int, rng, progress=None
) -> tuple[BlackBoxModel, object, list]:
    """`epochs` shuffled epochs of minibatch steps on standardised (Xn, Yn); the last batch is padded
    (weight 0). Returns (model, opt_state, per-epoch mean losses). `progress`: a tqdm bar to update per
    batch, or None."""
    Xn, Yn = np.asarray(Xn, np.float32), np.asarray(Yn, np.float32)
    n = Xn.shape[0]
    step = make_step(optimizer)
    params, losses = model.params, []
    nb = max(1, -(-n // batch))
    for _ in range(epochs):
        perm = rng.permutation(n)
        pad = nb * batch - n
        idx = np.concatenate([perm, perm[:pad] if pad <= n else np.resize(perm, pad)])
        wts = np.concatenate([np.ones(n, np.float32), np.zeros(pad, np.float32)])
        tot = 0.0
        for b in range(nb):
            sl = idx[b * batch : (b + 1) * batch]
            params, opt_state, loss = step(
                params, opt_state, Xn[sl], Yn[sl], wts[b * batch : (b + 1) * batch]
            )
            tot += float(loss)
            if progress is not None:
                progress.update(1)
        losses.append(tot / nb)
    return dataclasses.replace(model, params=params), opt_state, losses


def adapt(model: BlackBoxModel, data: dict, epochs: int = 1, seed: int = 0) -> BlackBoxModel:
    """`epochs` epochs of Adam (config.adapt_lr, config.adapt_batch) over all transitions of `data`
    (s (T+1, 5), belt_speed (T+1, 2), actions (T, 4)), normalisation kept. Pure in (model, data)."""
    if epochs < 1:
        return model
    tr = episode_transitions(data)
    if tr["action"].shape[0] == 0:
        return model
    if not np.all(np.isfinite(tr["window"])) or not np.all(np.isfinite(tr["s_next"])):
        raise ValueError("adaptation data contains NaN or inf states")
    X, Y = batch_features(tr, model.gripper)
    Xn, Yn = standardise(model, X, Y)
    opt = _adapt_optimizer(model.config.adapt_lr)
    rng = np.random.default_rng(seed + tr["action"].shape[0])
    model, _, _ = run_epochs(
        model, Xn, Yn, opt, opt.init(model.params), epochs, model.config.adapt_batch, rng
    )
    return model


@functools.lru_cache(maxsize=8)
def _adapt_optimizer(lr: float):
    return optax.adam(lr)


def make_adapter(epochs: int = 1, seed: int = 0):
    """The online adaptation of paper §4.1 as `callable(model, data) -> model` for
    `controller.run_episode(..., adapter=...)` (with ControllerConfig(adapt_every=20))."""
    if epochs < 1:
        raise ValueError(f"an adapter needs epochs >= 1, got {epochs} (use no adapter to turn it off)")
    return functools.partial(_adapter, epochs=epochs, seed=seed)


def _adapter(model, data, epochs, seed):
    inner = getattr(model, "model", None)  # a wrapper of W (planning.DriftCorrected): adapt W inside it
    if not isinstance(model, BlackBoxModel) and isinstance(inner, BlackBoxModel):
        return dataclasses.replace(model, model=adapt(inner, data, epochs=epochs, seed=seed))
    return adapt(model, data, epochs=epochs, seed=seed)


def one_step_errors(model, transitions: dict, chunk: int = 4096) -> dict:
    """Per-transition one-step errors of `model.rollout_sequence` (any model of the slot): position of
    the geometric centre (mm) and yaw (degrees), numpy arrays (N,)."""
    f = jax.jit(jax.vmap(lambda m, w, b, a: m.rollout_sequence(w, b, a[None])[0], in_axes=(None, 0, 0, 0)))
    preds = []
    n = transitions["action"].shape[0]
    for i in range(0, n, chunk):
        sl = slice(i, i + chunk)
        preds.append(
            np.asarray(
                f(
                    model,
                    jnp.asarray(transitions["window"][sl]),
                    jnp.asarray(transitions["belt_speed"][sl]),
                    jnp.asarray(transitions["action"][sl]),
                )
            )
        )
    return errors_of(np.concatenate(preds) if preds else np.zeros((0, 5)), transitions["s_next"])


def constant_velocity_errors(transitions: dict, gripper: GripperConfig = DEFAULT.gripper) -> dict:
    """The same errors for constant velocity (x, y, yaw at t + (s_t - s_{t-1}))."""
    w = np.asarray(transitions["window"], np.float64)
    pred = 2 * w[:, -1] - w[:, -2]
    return errors_of(pred, transitions["s_next"])


def errors_of(pred, s_next) -> dict:
    pred, s_next = np.asarray(pred, np.float64), np.asarray(s_next, np.float64)
    pos = 1e3 * np.hypot(
        pred[:, geometry.X] - s_next[:, geometry.X], pred[:, geometry.Y] - s_next[:, geometry.Y]
    )
    yaw = np.degrees(np.abs(pred[:, geometry.YAW] - s_next[:, geometry.YAW]))
    return {"position_mm": pos, "yaw_deg": yaw}


def summarise_errors(err: dict) -> dict:
    """Median, p90 and mean of each error array (plain floats)."""
    out = {}
    for k, v in err.items():
        v = np.asarray(v)
        out[k] = (
            {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "mean": float(v.mean())}
            if v.size
            else None
        )
    return out


# ----------------------------------------------------------------------------------------------------------
# Checkpoints.


def save(path, model: BlackBoxModel, seed: int, info: dict | None = None) -> str:
    """Write W (params, normalisation, config, gripper, seed, `info`) atomically as one .npz."""
    arrays = {
        f"layer{i}_{k}": np.asarray(layer[k]) for i, layer in enumerate(model.params) for k in ("w", "b")
    }
    arrays.update({k: np.asarray(getattr(model, k)) for k in ("x_mean", "x_std", "y_mean", "y_std")})
    meta = {
        "config": model.config.to_dict(),
        "gripper": _gripper_dict(model.gripper),
        "seed": int(seed),
        "n_params": n_params(model),
        "features": list(FEATURE_NAMES),
        "info": json_safe(info or {}),
    }
    return write_npz_with_meta(path, arrays, meta, FORMAT, VERSION)


def config_diff(config, expected) -> dict:
    """{field: (value in the file, expected value)} of two configurations (dataclasses) that differ."""
    return {
        k: (v, getattr(expected, k))
        for k, v in dataclasses.asdict(config).items()
        if v != getattr(expected, k)
    }


def load(
    path,
    expected_config: BaselineConfig | None = None,
    gripper: GripperConfig = DEFAULT.gripper,
    with_meta: bool = False,
):
    """W from `save`. Raises BaselineCheckpointError for a missing or corrupt file, another format, a
    BaselineConfig other than `expected_config` (when given), another gripper, other features, or arrays
    whose shapes do not match the configuration."""
    arrays, meta = read_npz_with_meta(
        path, BaselineCheckpointError, "black-box W checkpoint", FORMAT, VERSION
    )
    try:
        config = BaselineConfig(**{**meta["config"], "hidden": tuple(meta["config"]["hidden"])})
    except (KeyError, TypeError, ValueError) as e:
        raise BaselineCheckpointError(f"{path}: unreadable W configuration ({e})") from e
    if expected_config is not None and config != expected_config:
        diff = config_diff(config, expected_config)
        raise BaselineCheckpointError(
            f"{path}: W configuration differs from the expected one: {diff} (file, expected)"
        )
    if bad := gripper_mismatches(meta.get("gripper"), gripper):
        raise BaselineCheckpointError(
            f"{path}: W was trained for another gripper configuration (differs in {bad})"
        )
    if meta.get("features") != list(FEATURE_NAMES):
        raise BaselineCheckpointError(f"{path}: W was trained on other input features {meta.get('features')}")
    sizes = config.sizes
    params = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        for k, shape in (("w", (n_in, n_out)), ("b", (n_out,))):
            a = arrays.get(f"layer{i}_{k}")
            if a is None or a.shape != shape:
                got = None if a is None else a.shape
                raise BaselineCheckpointError(
                    f"{path}: layer{i}_{k} has shape {got}, configuration needs {shape}"
                )
        params.append(
            {
                "w": jnp.asarray(arrays[f"layer{i}_w"], jnp.float32),
                "b": jnp.asarray(arrays[f"layer{i}_b"], jnp.float32),
            }
        )
    if f"layer{len(sizes) - 1}_w" in arrays:
        raise BaselineCheckpointError(f"{path}: more layers than the configuration {sizes}")
    stats = {}
    for k, n in (("x_mean", N_FEATURES), ("x_std", N_FEATURES), ("y_mean", 5), ("y_std", 5)):
        a = arrays.get(k)
        if a is None or a.shape != (n,) or not np.all(np.isfinite(a)):
            raise BaselineCheckpointError(f"{path}: normalisation {k} missing, not ({n},) or not finite")
        stats[k] = jnp.asarray(a, jnp.float32)
    model = BlackBoxModel(params=params, **stats, config=config, gripper=gripper)
    return (model, meta) if with_meta else model


SHIPPED = "data/baseline.npz"


def shipped_path() -> str:
    import os

    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), SHIPPED)


@functools.lru_cache(maxsize=2)
def default_model(gripper: GripperConfig = DEFAULT.gripper) -> BlackBoxModel:
    """The W shipped with boxjax (boxjax/data/baseline.npz)."""
    return load(shipped_path(), gripper=gripper)
