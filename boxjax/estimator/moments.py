"""The box's physical moments from its exploration, with calibrated uncertainty (issue 30, item 1).

MuJoCo simulates the box as one rigid body: its voxels reach the motion only through the mass, the centre
of mass and the inertia. This estimator reads those quantities from the 45-step exploration directly,
each with a standard deviation that covers the truth at its stated rate on held-out boxes
(`boxjax estimator-eval` reports the coverage):

  mass            kg   total mass
  com_x/_y/_z     m    centre of mass, box frame
  spread_x/_y/_z  m    the mass's spread about the centre of mass along each box axis, sqrt(S_aa / M) with
                       S = sum m r r^T (the voxels' own extent included, as `massdist.mass_properties`)
  gyration_z      m    the planar radius of gyration sqrt(I_zz / M) = sqrt(spread_x^2 + spread_y^2): the
                       one inertia the planar motion on the belts shows (yaw acceleration = torque / I_zz)

The model (`MomentsModel`) is an ensemble of K MLPs on H's exploration features (`net.features`); each
member predicts a gaussian (mean, std) per standardised quantity, trained by its negative log-likelihood
(`boxjax.training.moments`). The prediction is the ensemble's mixture: mean of the means, variance = mean
of the variances (what a member cannot resolve) + variance of the means (where members disagree), and
the std is then multiplied by a per-quantity factor fitted on the validation split so that the +-1 std
and the +-1.96 std intervals cover at least 68.3 % and 95 % there (`calibration_scale`). A quantity the
planar motion cannot show (the spreads along x and y separately: only their planar sum, I_zz, moves the
box on the belts) is estimated from what the training families make likely, and its std says so.

Hazard decision on the moments (`hazard_posterior`): a Bayes rule with an explicit prior, a library of
boxes of the training families (gaussian mixtures, items, slabs; no simulation is needed, only their exact
moments and labels). Each library box i is weighted by the likelihood of the estimate given its moments,
w_i = prod_q N(estimate_q; q_i, std_q^2), so a quantity the exploration did not resolve (large std) hardly
matters; P(hazardous | estimate) = sum of w_i over hazardous library boxes / sum of w_i, and per region
the share of the weight on boxes hazardous in that region. Mass is left out (the rule is mass-free).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist, mlp
from boxjax.config import BoxConfig
from boxjax.estimator import net as E
from boxjax.fileio import read_npz_with_meta, write_npz_with_meta

QUANTITIES = ("mass", "com_x", "com_y", "com_z", "spread_x", "spread_y", "spread_z", "gyration_z")
UNITS = ("kg", "m", "m", "m", "m", "m", "m", "m")
N_Q = len(QUANTITIES)
DECISION = tuple(range(1, N_Q))  # the quantities the hazard rule uses: all but the mass
FORMAT = "boxjax-moments"
FORMAT_VERSION = 1
_STD_FLOOR = 1e-3  # standardised units


class MomentsError(ValueError):
    """A moments checkpoint cannot be loaded: missing, corrupt, another format or version, another grid."""


class Moments(NamedTuple):
    """Estimated moments of one box (leading batch axes allowed). mean, std: (8,) in QUANTITIES' units."""

    mean: jax.Array
    std: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MomentsModel:
    """A trained moments estimator. net: list of layer dicts with a leading member axis K; feat_mean,
    feat_std: (F,) feature statistics; q_mean, q_std: (8,) target statistics; scale: (8,) the calibration
    factors of the std; grid, hidden and members: static."""

    net: list
    feat_mean: jax.Array
    feat_std: jax.Array
    q_mean: jax.Array
    q_std: jax.Array
    scale: jax.Array
    grid: tuple = dataclasses.field(metadata=dict(static=True), default=(8, 8, 4))


def true_moments(dist: massdist.MassDistribution, box: BoxConfig) -> jax.Array:
    """(8,) the exact QUANTITIES of one distribution (pure jnp; vmap for batches)."""
    mp = massdist.mass_properties(dist, box)
    inertia = mp.inertia
    second = 0.5 * jnp.trace(inertia) * jnp.eye(3, dtype=inertia.dtype) - inertia  # sum m r r^T
    spread = jnp.sqrt(jnp.maximum(jnp.diag(second), 0.0) / mp.mass)
    gyration = jnp.sqrt(inertia[2, 2] / mp.mass)
    return jnp.concatenate([mp.mass[None], mp.com, spread, gyration[None]]).astype(jnp.float32)


def true_moments_batch(dists: massdist.MassDistribution, box: BoxConfig) -> np.ndarray:
    """(B, 8) `true_moments` of a batch of distributions."""
    return np.asarray(_true_moments_vmapped(box)(dists))


@functools.cache
def _true_moments_vmapped(box: BoxConfig):
    return jax.jit(jax.vmap(functools.partial(true_moments, box=box)))


def init_members(key: jax.Array, n_features: int, hidden: tuple[int, ...], members: int) -> list:
    """`members` MLPs (n_features -> hidden... -> 2 x 8: mean and raw std), stacked on a leading axis."""
    return jax.vmap(lambda k: mlp.init(k, (n_features, *hidden, 2 * N_Q)))(jax.random.split(key, members))


def member_outputs(net_k: list, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One member on ONE standardised feature vector: (mean, std) in standardised target units."""
    out = mlp.apply(net_k, x)
    return out[:N_Q], jax.nn.softplus(out[N_Q:]) + _STD_FLOOR


def standardise(model: MomentsModel, traj: jax.Array, final: jax.Array) -> jax.Array:
    return (E.features(traj, final) - model.feat_mean) / model.feat_std


def predict_members(model: MomentsModel, traj: jax.Array, final: jax.Array) -> Moments:
    """(K, 8) each member's mean and std (uncalibrated), in QUANTITIES' units, for ONE exploration."""
    x = standardise(model, traj, final)
    mu, sd = jax.vmap(member_outputs, in_axes=(0, None))(model.net, x)
    return Moments(model.q_mean + mu * model.q_std, sd * model.q_std)


def mixture(members: Moments) -> Moments:
    """The ensemble's mixture of K gaussians as one (mean, std) per quantity (axis -2 is the member)."""
    mean = jnp.mean(members.mean, axis=-2)
    var = jnp.mean(jnp.square(members.std), axis=-2) + jnp.var(members.mean, axis=-2)
    return Moments(mean, jnp.sqrt(var))


def predict_uncalibrated(model: MomentsModel, traj: jax.Array, final: jax.Array) -> Moments:
    return mixture(predict_members(model, traj, final))


def predict(model: MomentsModel, traj: jax.Array, final: jax.Array) -> Moments:
    """The calibrated estimate (mean, std) of ONE exploration (traj (T, 11), final (5,); `net.features`).
    Pure jnp; vmap over explorations (`predict_batch`)."""
    m = predict_uncalibrated(model, traj, final)
    return Moments(m.mean, m.std * model.scale)


predict_batch = jax.jit(jax.vmap(predict, in_axes=(None, 0, 0)))


def coverage(estimate: Moments, truth: jax.Array, levels=(0.5, 0.683, 0.9, 0.95)) -> dict:
    """Per quantity, the share of boxes whose truth lies inside the central gaussian interval of each
    level (estimate, truth: (B, 8)). A calibrated std covers at its stated level."""
    z = np.abs((np.asarray(truth) - np.asarray(estimate.mean)) / np.asarray(estimate.std))
    out = {}
    for level in levels:
        half = float(jax.scipy.stats.norm.ppf(0.5 + level / 2))
        out[f"{level:g}"] = {q: float(np.mean(z[:, i] <= half)) for i, q in enumerate(QUANTITIES)}
    return out


def calibration_scale(estimate: Moments, truth: np.ndarray, levels=(0.683, 0.95)) -> np.ndarray:
    """(8,) factors of the std, each the smallest that makes the central interval of every one of `levels`
    cover at least that share of these boxes. The errors have heavier tails than a gaussian (a factor fitted
    at 68.3 % alone left the 95 % interval covering 89-93 % of held-out boxes), so the default fits both."""
    z = np.abs((np.asarray(truth) - np.asarray(estimate.mean)) / np.asarray(estimate.std))
    factors = [np.quantile(z, lv, axis=0) / float(jax.scipy.stats.norm.ppf(0.5 + lv / 2)) for lv in levels]
    return np.max(factors, axis=0).astype(np.float32)


def as_dict(estimate: Moments) -> dict:
    """{quantity: {"mean": float, "std": float}} of ONE estimate, in QUANTITIES' units (JSON-ready)."""
    m, s = np.asarray(estimate.mean, np.float64), np.asarray(estimate.std, np.float64)
    return {q: {"mean": float(m[i]), "std": float(s[i])} for i, q in enumerate(QUANTITIES)}


def describe(estimate: Moments) -> str:
    """ONE estimate in words: each quantity with its calibrated std (kg, cm)."""
    m, s = np.asarray(estimate.mean, np.float64), np.asarray(estimate.std, np.float64)
    cm = lambda i: f"{100 * m[i]:+.1f} +- {100 * s[i]:.1f}"  # noqa: E731
    sp = lambda i: f"{100 * m[i]:.1f} +- {100 * s[i]:.1f}"  # noqa: E731
    return (
        f"mass {m[0]:.2f} +- {s[0]:.2f} kg; centre of mass ({cm(1)}, {cm(2)}, {cm(3)}) cm (box frame); "
        f"spread about it ({sp(4)}, {sp(5)}, {sp(6)}) cm; planar radius of gyration {sp(7)} cm (1 std)"
    )


# ----------------------------------------------------------------------------------------------------------
# The hazard decision on the moments.


class Library(NamedTuple):
    """Exact moments of boxes from the training families: q (N, 8); region (N,) int, -1 safe, 0..3 U1..U4."""

    q: jax.Array
    region: jax.Array


def make_library(dists: massdist.MassDistribution, box: BoxConfig) -> Library:
    """The library of a batch of distributions (their exact moments and hazard regions)."""
    region = jax.vmap(functools.partial(massdist.hazard_region, box=box))(dists)
    return Library(jnp.asarray(true_moments_batch(dists, box)), jnp.asarray(region, jnp.int32))


class Posterior(NamedTuple):
    """P(hazardous | estimate) and its split over U1..U4 (shares of the library weight); n_eff: the
    library's effective sample size under the weights (small: few library boxes look like this one)."""

    hazardous: jax.Array
    region: jax.Array
    n_eff: jax.Array


def hazard_posterior(estimate: Moments, library: Library) -> Posterior:
    """The Bayes rule of the module docstring for ONE estimate. Pure jnp."""
    idx = jnp.asarray(DECISION)
    z = (library.q[:, idx] - estimate.mean[idx]) / estimate.std[idx]
    logw = -0.5 * jnp.sum(z * z, axis=-1)
    w = jnp.exp(logw - jnp.max(logw))
    w = w / jnp.sum(w)
    region = jnp.stack([jnp.sum(jnp.where(library.region == r, w, 0.0)) for r in range(4)])
    return Posterior(jnp.sum(region), region, 1.0 / jnp.sum(w * w))


hazard_posterior_batch = jax.jit(jax.vmap(hazard_posterior, in_axes=(0, None)))


def explain(estimate: Moments, posterior: Posterior, box: BoxConfig) -> str:
    """The moments and the decision's evidence in physical terms (cm, kg)."""
    m, s = np.asarray(estimate.mean), np.asarray(estimate.std)
    cm = lambda i: f"{100 * m[i]:+.1f} +- {100 * s[i]:.1f}"  # noqa: E731
    r = int(np.argmax(np.asarray(posterior.region)))
    a = (0, 0, 1, 1)[r]  # the box axis the region's boundary is normal to
    sg = (-1.0, 1.0, -1.0, 1.0)[r]
    quarter = box.size[a] / 4
    depth = 100 * (sg * m[1 + a] - quarter)  # cm, positive inside
    return (
        f"mass {m[0]:.2f} +- {s[0]:.2f} kg; centre of mass ({cm(1)}, {cm(2)}, {cm(3)}) cm; spread about it "
        f"(x, y) ({100 * m[4]:.1f} +- {100 * s[4]:.1f}, {100 * m[5]:.1f} +- {100 * s[5]:.1f}) cm, planar "
        f"radius of gyration {100 * m[7]:.1f} +- {100 * s[7]:.1f} cm; centre of mass {abs(depth):.1f} cm "
        f"{'inside' if depth >= 0 else 'short of'} {massdist.REGION_NAMES[r]}; P(all mass in one quarter | "
        f"these moments) = {float(posterior.hazardous):.2f} (in {massdist.REGION_NAMES[r]}: "
        f"{float(posterior.region[r]):.2f})"
    )


# ----------------------------------------------------------------------------------------------------------
# Checkpoints: one compressed .npz with a JSON header, no pickle.


def save(path, model: MomentsModel, meta: dict | None = None) -> str:
    arrays = {f"net_{i}_{k}": np.asarray(v) for i, layer in enumerate(model.net) for k, v in layer.items()}
    for name in ("feat_mean", "feat_std", "q_mean", "q_std", "scale"):
        arrays[name] = np.asarray(getattr(model, name))
    head = {
        "grid": list(model.grid),
        "layers": len(model.net),
        "quantities": list(QUANTITIES),
        **(meta or {}),
    }
    return write_npz_with_meta(path, arrays, head, FORMAT, FORMAT_VERSION)


def load(path, box: BoxConfig | None = None) -> tuple[MomentsModel, dict]:
    """(model, meta) from `save`'s file; MomentsError naming the problem (missing, corrupt, another
    format / version, another grid, other quantities)."""
    arrays, meta = read_npz_with_meta(path, MomentsError, "moments checkpoint", FORMAT, FORMAT_VERSION)
    if meta.get("quantities") != list(QUANTITIES):
        raise MomentsError(
            f"{path}: estimates {meta.get('quantities')}, this boxjax expects {list(QUANTITIES)}"
        )
    if box is not None and tuple(meta.get("grid", ())) != tuple(box.grid):
        raise MomentsError(f"{path}: trained for grid {meta.get('grid')}, the box has grid {list(box.grid)}")
    try:
        net = [
            {k: jnp.asarray(arrays[f"net_{i}_{k}"]) for k in ("w", "b")} for i in range(int(meta["layers"]))
        ]
        fields = {n: jnp.asarray(arrays[n]) for n in ("feat_mean", "feat_std", "q_mean", "q_std", "scale")}
    except KeyError as e:
        raise MomentsError(f"{path}: missing array {e}") from e
    if fields["scale"].shape != (N_Q,) or net[-1]["w"].shape[-1] != 2 * N_Q:
        raise MomentsError(f"{path}: array shapes do not match {N_Q} quantities")
    return MomentsModel(net=net, grid=tuple(meta["grid"]), **fields), meta
