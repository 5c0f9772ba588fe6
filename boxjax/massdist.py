"""Box mass distributions as voxel occupancy grids (paper §2.1, §4, §4.2, Fig. 2 caption).

A distribution is a binary occupancy grid over the box's voxels plus a total mass M that the occupied voxels
share equally; every voxel additionally carries a tiny mass ``box.voxel_eps`` so that no voxel is massless
(friction at a contact never vanishes). Everything here is pure ``jnp`` on ONE box with fixed shapes, so it
can be jitted and vmapped over boxes or PRNG keys; the ``BoxConfig`` is static (pass it with
``functools.partial`` or as a closure when vmapping).

Box frame: origin at the box's geometric centre, x along the length (0.40 m), y along the width (0.30 m),
z up (0.15 m). Voxel (i, j, k) has its centre at ``-half_size + (idx + 0.5) * voxel_size`` per axis, so
index i runs along x, j along y, k along z.

Hazard regions (paper §4.2): with the box seen as [0, l] x [0, w] x [0, h], U1 / U2 are the first / last
quarter of the length and U3 / U4 the first / last quarter of the width. In the box frame, U1 is
x <= -l/4, U2 is x >= l/4, U3 is y <= -w/4 and U4 is y >= w/4; with the default 8 x 8 x 4 grid they are
voxel columns i in {0, 1}, i in {6, 7}, rows j in {0, 1}, j in {6, 7}. A distribution is hazardous when ALL
its occupied voxels lie inside one of them. At yaw 0 the belts run along the box's x axis, so U3 lies over
the left belt (y < 0) and U4 over the right belt (y > 0).

Random distributions (``sample``): a mixture of 1..3 axis-aligned 3D gaussian bumps evaluated at the voxel
centres and thresholded relative to its maximum (design and distributions in ``sample``). Measured over
4000 keys (``jax.random.split(jax.random.key(0), 4000)``) with the default box:

  * fill fraction (occupied / 256 voxels): min 0.8 %, 5 % quantile 4.7 %, median 20 %, mean 24 %,
    95 % quantile 58 %, max 94 %;
  * naturally hazardous: 4.2 % (about 1 % in each of U1..U4) -- small blobs near a side;
  * centre of mass 5..95 % range about -12..+12 cm in x and -9..+9 cm in y.

``sample_hazardous`` draws the same kind of mixture confined to one random quarter slab (fill fraction:
median 10 % of the box, i.e. 39 % of the slab; max 25 % = the whole slab). ``sample_mixed(p_hazardous=0.25)``
came out 27.2 % hazardous (expected 0.25 + 0.75 x 0.042 = 28.2 %).

Named distributions (paper §4.1 and its figure of distributions A-D; parameters written out in ``_NAMED`` so
they never depend on a PRNG implementation). Centres of mass below are for the default 8 x 8 x 4 grid, in cm,
box frame (x, y, z), including the eps mass:

  * ``A``: "randomly generated"-looking, two bumps (a large one low at +x / -y, a smaller one at -x / +y),
    5.0 kg, 48/256 voxels, COM (+4.3, -3.3, -1.6) cm.
  * ``B``: A with both means moved by about 2 cm, 5.5 kg, 52/256 voxels, IoU with A 0.72,
    COM (+6.2, -2.5, -1.8) cm.
  * ``C``: clearly unlike A: mass high up along the +y side, heaviest towards -x, 8.0 kg, 51/256 voxels,
    IoU with A 0.12, COM (-5.2, +6.8, +2.2) cm.
  * ``D``: heavily skewed, all mass in U4 (last quarter of the width, over the right belt at yaw 0), 7.0 kg,
    39/256 voxels, hazardous, COM (-2.1, +11.3, -2.2) cm.
  * ``uniform``: all voxels occupied, 5.0 kg, COM (0, 0, 0).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax.config import DEFAULT, BoxConfig

NAMES = ("A", "B", "C", "D", "uniform")
REGION_NAMES = ("U1", "U2", "U3", "U4")
_REGION_TEXT = (
    "U1, first quarter of the length (x <= -l/4)",
    "U2, last quarter of the length (x >= +l/4)",
    "U3, first quarter of the width (y <= -w/4, over the left belt at yaw 0)",
    "U4, last quarter of the width (y >= +w/4, over the right belt at yaw 0)",
)

# Sampler ranges (see `sample`).
_STD_RANGE = (0.3, 0.9)  # per-axis gaussian std, as a fraction of the box half-size along that axis
_WEIGHT_RANGE = (0.2, 1.0)  # relative peak height of each gaussian bump
_THRESHOLD_RANGE = (0.2, 0.7)  # occupancy threshold, as a fraction of the mixture's maximum over voxels


class DistributionError(ValueError):
    """A mass distribution is malformed (wrong shape, non-finite, non-binary, empty, bad mass)."""


class MassDistribution(NamedTuple):
    """One box's mass distribution (paper Fig. 2 caption). Leading batch axes are allowed under vmap.

    occupancy: (nx, ny, nz) float32 in {0., 1.}; index (i, j, k) along the box's x, y, z axes. Float, not
      bool, so voxel masses (and everything derived from them) stay differentiable w.r.t. it.
    total_mass: () float32, kg, shared equally by the occupied voxels. The per-voxel eps is NOT included.
    """

    occupancy: jax.Array
    total_mass: jax.Array


class MassProperties(NamedTuple):
    """Rigid-body mass properties in the box frame.

    mass: () kg, total, including the eps on every voxel.
    com: (3,) m, centre of mass in the box frame.
    inertia: (3, 3) kg m^2, inertia tensor about the centre of mass, box-frame axes.
    """

    mass: jax.Array
    com: jax.Array
    inertia: jax.Array


# ----------------------------------------------------------------------------------------------------------
# Geometry of the grid (host-side numpy; these are constants of the static BoxConfig).


def _voxel_centres64(box: BoxConfig) -> np.ndarray:
    axes = [
        -h + (np.arange(n, dtype=np.float64) + 0.5) * d
        for h, n, d in zip(box.half_size, box.grid, box.voxel_size, strict=True)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def voxel_centres(box: BoxConfig = DEFAULT.box) -> np.ndarray:
    """(nx, ny, nz, 3) float32 voxel centres in the box frame (m)."""
    return _voxel_centres64(box).astype(np.float32)


def _region_masks(box: BoxConfig) -> np.ndarray:
    """(4, nx, ny, nz) bool: voxels inside U1..U4. Quarter sizes come from the grid (nx // 4, ny // 4)."""
    nx, ny, nz = box.grid
    qx, qy = nx // 4, ny // 4
    i = np.arange(nx)[:, None, None]
    j = np.arange(ny)[None, :, None]
    shape = (nx, ny, nz)
    return np.stack(
        [
            np.broadcast_to(i < qx, shape),  # U1: first quarter of the length
            np.broadcast_to(i >= nx - qx, shape),  # U2: last quarter of the length
            np.broadcast_to(j < qy, shape),  # U3: first quarter of the width
            np.broadcast_to(j >= ny - qy, shape),  # U4: last quarter of the width
        ]
    )


def _region_bounds(box: BoxConfig) -> np.ndarray:
    """(4, 2, 3) float64 [lo, hi] box-frame corners (m) of U1..U4."""
    hx, hy, hz = box.half_size
    lx, ly, _ = box.size
    lo = np.array([-hx, -hy, -hz])
    hi = np.array([hx, hy, hz])
    out = np.stack([np.stack([lo, hi])] * 4).copy()
    out[0, 1, 0] = -hx + lx / 4  # U1
    out[1, 0, 0] = hx - lx / 4  # U2
    out[2, 1, 1] = -hy + ly / 4  # U3
    out[3, 0, 1] = hy - ly / 4  # U4
    return out


# ----------------------------------------------------------------------------------------------------------
# Mass properties.


def voxel_masses(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> jax.Array:
    """(nx, ny, nz) kg: ``total_mass * occ / sum(occ) + box.voxel_eps``.

    Differentiable w.r.t. both fields. An empty grid gives eps everywhere (its total mass is lost); `validate`
    rejects such a distribution.
    """
    occ = dist.occupancy
    n = jnp.sum(occ)
    # where(), not maximum(n, 1): a soft (predicted) occupancy may legitimately sum to less than one.
    n_safe = jnp.where(n > 0, n, 1.0)
    return dist.total_mass * occ / n_safe + box.voxel_eps


def mass_properties_from_masses(masses: jax.Array, box: BoxConfig = DEFAULT.box) -> MassProperties:
    """Mass, centre of mass and inertia of voxels with the given masses.

    Each voxel is a solid uniform cuboid of the voxel size (as MuJoCo treats a box geom), so the inertia is
    the sum of each voxel's own inertia about its centre, m (b^2 + c^2) / 12 etc., plus the parallel-axis
    term m (|r|^2 I - r r^T) with r the voxel centre relative to the centre of mass. (Paper §2.1 treats
    voxels as point particles; the own-inertia term is what makes a one-voxel box, or a thin slab, physical,
    and matches MuJoCo's inertia of the same voxels as box geoms.)

    Args:
      masses: (nx, ny, nz) kg, non-negative with a positive sum. The computation runs in masses' float dtype
        (float64 under x64), and is differentiable w.r.t. masses.
      box: the box; only its size and grid are used.
    Returns:
      MassProperties in the box frame (kg, m, kg m^2 about the centre of mass).
    """
    dtype = jnp.result_type(masses, jnp.float32)
    masses = jnp.asarray(masses, dtype)
    c = jnp.asarray(_voxel_centres64(box), dtype).reshape(-1, 3)
    m = masses.reshape(-1)
    total = jnp.sum(m)
    # Elementwise sums, not matmuls: on GPUs a float32 matmul may run in TF32 (~1e-3 relative error).
    com = jnp.sum(m[:, None] * c, axis=0) / total
    # About the centre of mass directly (not about the origin then shifted): keeps float32 cancellation small.
    r = c - com
    second = jnp.sum(m[:, None, None] * r[:, :, None] * r[:, None, :], axis=0)  # (3, 3) sum m r r^T
    parallel = jnp.trace(second) * jnp.eye(3, dtype=dtype) - second
    d2 = jnp.asarray(np.square(box.voxel_size), dtype)
    own = total * jnp.diag(jnp.stack([d2[1] + d2[2], d2[0] + d2[2], d2[0] + d2[1]])) / 12
    inertia = parallel + own
    # Exactly symmetric: XLA may round the two triangles of the reduction differently in float32.
    return MassProperties(mass=total, com=com, inertia=0.5 * (inertia + inertia.T))


def mass_properties(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> MassProperties:
    """Mass properties of a distribution (box frame; see `mass_properties_from_masses`)."""
    return mass_properties_from_masses(voxel_masses(dist, box), box)


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a proper rotation matrix (3, 3) (Shepperd's method)."""
    t = np.trace(r)
    candidates = np.array([t, r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = np.array([s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = np.array([(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = np.array([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = np.array([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4])
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def principal_axes(inertia) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments and frame of an inertia tensor, for MuJoCo's ``body_inertia`` / ``body_iquat``.

    Host-side numpy float64 (not traceable): call it when building a model.

    Args:
      inertia: (3, 3) kg m^2, symmetric positive (semi-)definite, about the centre of mass, box-frame axes.
    Returns:
      (diag, quat): diag (3,) kg m^2 ascending principal moments; quat (4,) unit (w, x, y, z), w >= 0, of the
      right-handed rotation R (det +1, columns = principal axes in the box frame) with
      R diag(diag) R^T == inertia.
    """
    a = np.asarray(inertia, dtype=np.float64)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"inertia must be a finite (3, 3) matrix, got shape {a.shape}")
    a = 0.5 * (a + a.T)
    diag, vecs = np.linalg.eigh(a)
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] = -vecs[:, 2]  # eigenvectors are defined up to sign; pick the right-handed frame
    return diag, _quat_from_matrix(vecs)


# ----------------------------------------------------------------------------------------------------------
# Hazard (paper §4.2).


def hazard_region(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> jax.Array:
    """() int32: -1 if not hazardous, else 0..3 for U1..U4 (the first that contains every occupied voxel).

    Only the occupancy counts (a voxel is occupied when occupancy > 0.5); the eps mass does not. A grid whose
    occupied voxels all lie in a corner belongs to two regions, and the lower index is returned. An empty
    grid is not hazardous (it is invalid, see `validate`).
    """
    occ = dist.occupancy > 0.5
    masks = jnp.asarray(_region_masks(box))
    outside = jnp.any(occ[None] & ~masks, axis=(1, 2, 3))  # (4,) some occupied voxel outside U_r
    inside = ~outside & jnp.any(occ)
    return jnp.where(jnp.any(inside), jnp.argmax(inside), -1).astype(jnp.int32)


def is_hazardous(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> jax.Array:
    """() bool: all occupied voxels lie inside one of U1..U4 (paper §4.2)."""
    return hazard_region(dist, box) >= 0


# ----------------------------------------------------------------------------------------------------------
# Sampling.


def _mixture_density(centres, means, stds, weights):
    """Unnormalised gaussian-bump mixture at points.

    centres (..., 3) m; means, stds (G, 3) m; weights (G,) -> (...,):
    sum_g w_g exp(-|(c - mu_g) / s_g|^2 / 2).
    Bumps peak at their weight (no 1/det normalisation), so a narrow bump is not automatically dominant.
    """
    z = (centres[..., None, :] - means) / stds  # (..., G, 3)
    return jnp.sum(weights * jnp.exp(-0.5 * jnp.sum(z * z, axis=-1)), axis=-1)


def _n_uniforms(max_gaussians: int) -> int:
    """How many U(0, 1) numbers one mixture draw consumes (see `_mixture_from_uniforms`)."""
    return 7 * max_gaussians + 3


def _lerp(u, lo, hi):
    return lo + (hi - lo) * u


def _mixture_from_uniforms(u, box: BoxConfig, max_gaussians: int, mean_lo, mean_hi, allowed):
    """One random distribution from a vector of U(0, 1) numbers.

    All the randomness of a draw comes from ONE ``jax.random.uniform`` call: every separate PRNG call inlines
    its own threefry kernel, and with six of them the vmapped sampler took several seconds to compile.

    Args:
      u: (7 G + 3,) float32 in [0, 1), G = max_gaussians.
      mean_lo, mean_hi: (3,) m, box-frame bounds of the gaussian means (the whole box or a hazard slab).
      allowed: (nx, ny, nz) bool, the voxels that may be occupied.
    Returns:
      MassDistribution with occupancy inside `allowed` and at least one voxel occupied.
    """
    g = max_gaussians
    u_mean = u[: 3 * g].reshape(g, 3)
    u_std = u[3 * g : 6 * g].reshape(g, 3)
    u_weight = u[6 * g : 7 * g]
    u_count, u_thr, u_mass = u[7 * g], u[7 * g + 1], u[7 * g + 2]
    half = jnp.asarray(box.half_size, jnp.float32)
    # Number of gaussians ~ U{1, ..., G}; the unused ones get weight 0 (fixed shapes).
    n = jnp.minimum(jnp.floor(u_count * g).astype(jnp.int32) + 1, g)
    active = jnp.arange(g) < n
    # Means ~ U(mean_lo, mean_hi) per axis (inside the box, or inside a hazard slab), box frame, m.
    means = _lerp(u_mean, mean_lo, mean_hi)
    # Per-axis std ~ U(0.3, 0.9) x the box half-size on that axis (6..18 cm along x, 2.25..6.75 cm in z), m.
    stds = half * _lerp(u_std, *_STD_RANGE)
    # Peak heights ~ U(0.2, 1), relative.
    weights = jnp.where(active, _lerp(u_weight, *_WEIGHT_RANGE), 0.0)
    # Threshold ~ U(0.2, 0.7) x the mixture's maximum over the allowed voxels: sets the fill fraction.
    thr = _lerp(u_thr, *_THRESHOLD_RANGE)
    rho = jnp.where(allowed, _mixture_density(jnp.asarray(voxel_centres(box)), means, stds, weights), -1.0)
    # The argmax voxel always passes (rho_max >= thr * rho_max), so at least one voxel is occupied.
    occ = allowed & (rho >= thr * jnp.max(rho))
    # Total mass ~ U(mass_range) kg (paper Fig. 2 caption: 1..10 kg by default).
    total_mass = _lerp(u_mass, *box.mass_range)
    return MassDistribution(occ.astype(jnp.float32), total_mass.astype(jnp.float32))


def _check_max_gaussians(max_gaussians: int):
    if max_gaussians < 1:
        raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")


def _sample_any(u, box: BoxConfig, max_gaussians: int) -> MassDistribution:
    half = np.asarray(box.half_size, np.float32)
    return _mixture_from_uniforms(u, box, max_gaussians, -half, half, np.ones(box.grid, bool))


def _sample_hazardous(u, box: BoxConfig, max_gaussians: int) -> MassDistribution:
    # Region ~ U{0, 1, 2, 3} (U1..U4), from the extra last number.
    region = jnp.minimum(jnp.floor(u[-1] * 4).astype(jnp.int32), 3)
    bounds = jnp.asarray(_region_bounds(box), jnp.float32)[region]
    allowed = jnp.asarray(_region_masks(box))[region]
    return _mixture_from_uniforms(u[:-1], box, max_gaussians, bounds[0], bounds[1], allowed)


def sample(key: jax.Array, box: BoxConfig = DEFAULT.box, max_gaussians: int = 3) -> MassDistribution:
    """A random distribution: a voxelised mixture of 1..max_gaussians axis-aligned 3D gaussians (paper §4).

    Random quantities (all independent):
      * number of gaussians ~ U{1, ..., max_gaussians};
      * each mean ~ U(-half_size, +half_size) per axis (inside the box);
      * each per-axis std ~ U(0.3, 0.9) x half_size on that axis;
      * each peak height ~ U(0.2, 1);
      * occupancy threshold t ~ U(0.2, 0.7): a voxel is occupied iff the mixture at its centre is >= t x the
        mixture's maximum over the voxel centres (so the densest voxel is always occupied);
      * total mass ~ U(box.mass_range).
    Statistics with the default box are in the module docstring (about 4 % come out hazardous; use
    `sample_mixed` to control the fraction, or reject with `is_hazardous`). Outputs are float32 whether or
    not x64 is enabled, and the same for a key either way.

    Args:
      key: PRNG key; vmap over keys with ``jax.vmap(functools.partial(sample, box=box))``.
      box: static box config. max_gaussians: static int >= 1.
    """
    _check_max_gaussians(max_gaussians)
    u = jax.random.uniform(key, (_n_uniforms(max_gaussians),), jnp.float32)
    return _sample_any(u, box, max_gaussians)


def sample_hazardous(
    key: jax.Array, box: BoxConfig = DEFAULT.box, max_gaussians: int = 3
) -> MassDistribution:
    """A random hazardous distribution: all occupied voxels inside one random region of U1..U4.

    Random quantities: region ~ U{U1, U2, U3, U4}; then as in `sample`, except that the means are drawn
    uniformly inside the region's slab and the threshold is taken relative to the maximum over the slab's
    voxels, with voxels outside the slab left empty.
    """
    _check_max_gaussians(max_gaussians)
    u = jax.random.uniform(key, (_n_uniforms(max_gaussians) + 1,), jnp.float32)
    return _sample_hazardous(u, box, max_gaussians)


def sample_mixed(
    key: jax.Array, box: BoxConfig = DEFAULT.box, p_hazardous: float = 0.25, max_gaussians: int = 3
) -> MassDistribution:
    """`sample_hazardous` with probability p_hazardous, else `sample` (both computed; selected by jnp.where).

    p_hazardous may be a traced scalar. Note that `sample` itself is hazardous about 4 % of the time with the
    default box, so the hazardous fraction of the output is about p + (1 - p) x 0.04.
    """
    _check_max_gaussians(max_gaussians)
    n = _n_uniforms(max_gaussians)
    u = jax.random.uniform(key, (2 * n + 2,), jnp.float32)
    # Hazardous ~ Bernoulli(p_hazardous).
    pick = u[0] < p_hazardous
    h = _sample_hazardous(u[1 : n + 2], box, max_gaussians)
    s = _sample_any(u[n + 2 :], box, max_gaussians)
    return jax.tree.map(lambda a, b: jnp.where(pick, a, b), h, s)


# Item samplers: a few small cuboid items instead of gaussian blobs (a box family H was not trained on).
_ITEM_MAX = 3  # at most this many items per box
_ITEM_SIZE_MAX = 2  # voxels per axis of one item (1 or 2)
_ITEM_VOXEL_BUDGET = 16  # occupied voxels in all, at most


def _n_item_uniforms() -> int:
    """U(0, 1) numbers one item draw consumes: item count, 6 per item (3 sizes, 3 offsets), mass, region."""
    return 1 + 6 * _ITEM_MAX + 1 + 1


def _index_ranges(box: BoxConfig) -> np.ndarray:
    """(5, 3, 2) int [lo, hi) voxel-index ranges per axis of U1..U4 and (last) the whole box."""
    nx, ny, nz = box.grid
    qx, qy = nx // 4, ny // 4
    whole = [[0, nx], [0, ny], [0, nz]]
    out = np.array([whole] * 5, np.int32)
    out[0, 0] = (0, qx)  # U1
    out[1, 0] = (nx - qx, nx)  # U2
    out[2, 1] = (0, qy)  # U3
    out[3, 1] = (ny - qy, ny)  # U4
    return out


def _items_from_uniforms(u, box: BoxConfig, region) -> MassDistribution:
    """1..3 cuboid items inside index ranges `region` (0..3: U1..U4, 4: the whole box), from (n,) uniforms.

    Items are placed independently (they may overlap); items beyond the voxel budget are dropped, last first.
    """
    ranges = jnp.asarray(_index_ranges(box))[region]  # (3, 2) [lo, hi) per axis
    lo, hi = ranges[:, 0], ranges[:, 1]
    u_count, u_items, u_mass = u[0], u[1 : 1 + 6 * _ITEM_MAX].reshape(_ITEM_MAX, 6), u[1 + 6 * _ITEM_MAX]
    # Number of items ~ U{1, 2, 3}.
    n = jnp.minimum(jnp.floor(u_count * _ITEM_MAX).astype(jnp.int32) + 1, _ITEM_MAX)
    # Item size per axis ~ U{1, 2} voxels (5-10 cm along x, 3.75-7.5 cm along y and z with the default
    # grid), capped at the range's extent; lower corner ~ U{lo, ..., hi - size} per axis (the item fits).
    extent = hi - lo
    size = jnp.minimum(jnp.floor(u_items[:, :3] * _ITEM_SIZE_MAX).astype(jnp.int32) + 1, _ITEM_SIZE_MAX)
    size = jnp.minimum(size, extent)
    start = lo + jnp.minimum(jnp.floor(u_items[:, 3:] * (extent - size + 1)).astype(jnp.int32), extent - size)
    idx = [jnp.arange(g) for g in box.grid]

    def item_occ(s, z):  # (3,), (3,) -> (nx, ny, nz) bool
        ax = [(a >= z[d]) & (a < z[d] + s[d]) for d, a in enumerate(idx)]
        return ax[0][:, None, None] & ax[1][None, :, None] & ax[2][None, None, :]

    items = jax.vmap(item_occ)(size, start) & (jnp.arange(_ITEM_MAX) < n)[:, None, None, None]
    unions = jnp.cumsum(items.astype(jnp.int32), axis=0) > 0  # (3, ...) union of the first k + 1 items
    counts = jnp.sum(unions, axis=(1, 2, 3))
    # The largest prefix of items within the budget (the first item alone is at most 8 voxels).
    k = jnp.sum(counts <= _ITEM_VOXEL_BUDGET) - 1
    occ = unions[k]
    # Total mass ~ U(mass_range) kg, shared equally by the occupied voxels.
    total_mass = _lerp(u_mass, *box.mass_range)
    return MassDistribution(occ.astype(jnp.float32), total_mass.astype(jnp.float32))


def sample_items_hazardous(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random hazardous box holding a few small items, all inside one outer quarter (paper §4.2).

    Random quantities (all independent, one ``jax.random.uniform`` call):
      * region ~ U{U1, U2, U3, U4};
      * number of items ~ U{1, 2, 3};
      * each item an axis-aligned cuboid of voxels, size per axis ~ U{1, 2} voxels (so 1..8 voxels each),
        its lower corner ~ U{...} over the positions where it fits inside the region (items may overlap);
      * total mass ~ U(box.mass_range), shared equally by the occupied voxels.
    The union holds 1..16 voxels: items beyond 16 occupied voxels are dropped, last first. Every occupied
    voxel lies inside the region, so `is_hazardous` is always true. Pure jnp, jittable, vmap over keys with
    ``jax.vmap(functools.partial(sample_items_hazardous, box=box))``.
    """
    u = jax.random.uniform(key, (_n_item_uniforms(),), jnp.float32)
    region = jnp.minimum(jnp.floor(u[-1] * 4).astype(jnp.int32), 3)
    return _items_from_uniforms(u[:-1], box, region)


def sample_items(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random box holding a few small items anywhere (safe or hazardous: a family for testing
    generalisation).

    Random quantities as in `sample_items_hazardous`, except that each item's lower corner ~ U{...} over
    the positions where it fits inside the whole box (no region is drawn). Hazardous (`is_hazardous`) only
    when the items happen to fall inside one outer quarter. Pure jnp, jittable.
    """
    u = jax.random.uniform(key, (_n_item_uniforms(),), jnp.float32)
    return _items_from_uniforms(u[:-1], box, 4)


# Slab and scatter samplers: two more families (issue 30). Slabs are walls and layers (a heavy plate or a row
# of books against one side); scatter is loose contents (each voxel of a random sub-box occupied by chance):
# not compact, unlike the gaussian blobs, items and slabs. The scatter family is HELD OUT: no estimator,
# decision rule or controller setting is trained or tuned on it; it exists to test generalisation.
FAMILIES = ("gaussian", "items", "slabs", "scatter")
_SCATTER_P_RANGE = (0.15, 0.6)  # probability that a voxel of the sub-box is occupied


def _box_mask(box: BoxConfig, start, size) -> jax.Array:
    """(nx, ny, nz) bool: the voxels [start, start + size) per axis."""
    ax = [(jnp.arange(g) >= start[d]) & (jnp.arange(g) < start[d] + size[d]) for d, g in enumerate(box.grid)]
    return ax[0][:, None, None] & ax[1][None, :, None] & ax[2][None, None, :]


def _slab_from_uniforms(u, box: BoxConfig, region) -> MassDistribution:
    """A slab inside index ranges `region` (0..3: U1..U4, 4: the whole box), from 5 uniforms: its thin axis
    ~ U{x, y, z}; thickness ~ U{1, 2, 3} voxels capped at the range's extent; position ~ U over where it fits;
    it spans the range's full extent along the other two axes; total mass ~ U(box.mass_range)."""
    ranges = jnp.asarray(_index_ranges(box))[region]
    lo, hi = ranges[:, 0], ranges[:, 1]
    extent = hi - lo
    axis = jnp.minimum(jnp.floor(u[0] * 3).astype(jnp.int32), 2)
    thick = jnp.minimum(jnp.floor(u[1] * 3).astype(jnp.int32) + 1, extent[axis])
    offset = jnp.minimum(jnp.floor(u[2] * (extent[axis] - thick + 1)).astype(jnp.int32), extent[axis] - thick)
    thin = jnp.arange(3) == axis
    start = jnp.where(thin, lo + offset, lo)
    size = jnp.where(thin, thick, extent)
    total_mass = _lerp(u[3], *box.mass_range)
    return MassDistribution(_box_mask(box, start, size).astype(jnp.float32), total_mass.astype(jnp.float32))


def sample_slabs(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random box holding one slab (a wall or a layer) anywhere: safe or hazardous (`_slab_from_uniforms`;
    a slab 1-2 voxels thick against an end or a side is hazardous). Pure jnp, jittable."""
    return _slab_from_uniforms(jax.random.uniform(key, (4,), jnp.float32), box, 4)


def sample_slabs_hazardous(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random hazardous box: one slab inside a random outer quarter U1..U4 (`_slab_from_uniforms`)."""
    u = jax.random.uniform(key, (5,), jnp.float32)
    region = jnp.minimum(jnp.floor(u[4] * 4).astype(jnp.int32), 3)
    return _slab_from_uniforms(u, box, region)


def _scatter_from_uniforms(key, box: BoxConfig, region) -> MassDistribution:
    """Loose contents inside index ranges `region`: a sub-box (per axis, size ~ U{1..extent}, position ~ U
    over where it fits) whose voxels are occupied independently with probability p ~ U(0.15, 0.6), one of
    them always (so the box is never empty); total mass ~ U(box.mass_range)."""
    k_u, k_vox, k_one = jax.random.split(key, 3)
    u = jax.random.uniform(k_u, (8,), jnp.float32)
    ranges = jnp.asarray(_index_ranges(box))[region]
    lo, hi = ranges[:, 0], ranges[:, 1]
    extent = hi - lo
    size = jnp.minimum(jnp.floor(u[:3] * extent).astype(jnp.int32) + 1, extent)
    start = lo + jnp.minimum(jnp.floor(u[3:6] * (extent - size + 1)).astype(jnp.int32), extent - size)
    inside = _box_mask(box, start, size)
    p = _lerp(u[6], *_SCATTER_P_RANGE)
    one = jax.random.randint(k_one, (3,), 0, size) + start
    forced = _box_mask(box, one, jnp.ones(3, jnp.int32))
    occ = inside & ((jax.random.uniform(k_vox, tuple(box.grid)) < p) | forced)
    return MassDistribution(occ.astype(jnp.float32), _lerp(u[7], *box.mass_range).astype(jnp.float32))


def sample_scatter(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random box of loose contents anywhere (`_scatter_from_uniforms`; safe or hazardous). Held out
    (see `FAMILIES`). Pure jnp, jittable."""
    return _scatter_from_uniforms(key, box, 4)


def sample_scatter_hazardous(key: jax.Array, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """A random hazardous box of loose contents inside a random outer quarter U1..U4. Held out."""
    k_region, k = jax.random.split(key)
    return _scatter_from_uniforms(k, box, jax.random.randint(k_region, (), 0, 4))


def sampler(family: str, hazardous: bool):
    """The sampler (key, box) -> MassDistribution of a family in `FAMILIES`: its hazardous form (all mass in
    one outer quarter) or its free form (safe or hazardous as it falls; for "gaussian", `sample`)."""
    table = {
        "gaussian": (sample, sample_hazardous),
        "items": (sample_items, sample_items_hazardous),
        "slabs": (sample_slabs, sample_slabs_hazardous),
        "scatter": (sample_scatter, sample_scatter_hazardous),
    }
    if family not in table:
        raise ValueError(f"unknown box family {family!r}; choose one of {FAMILIES}")
    return table[family][bool(hazardous)]


# ----------------------------------------------------------------------------------------------------------
# Named distributions (paper §4.1). Fixed parameters: box-frame metres; never derived from a key.


class _Named(NamedTuple):
    means: tuple  # G x (x, y, z) m, box frame
    stds: tuple  # G x (sx, sy, sz) m
    weights: tuple  # G peak heights
    threshold: float  # fraction of the maximum over the allowed voxels
    total_mass: float  # kg
    region: int | None = None  # restrict to U1..U4 (0..3), or None for the whole box


_NAMED: dict[str, _Named] = {
    # Two bumps: a large one low at +x / -y, a smaller one at -x / +y.
    "A": _Named(
        means=((0.08, -0.06, -0.03), (-0.08, 0.06, 0.0)),
        stds=((0.08, 0.06, 0.05), (0.05, 0.05, 0.04)),
        weights=(1.0, 0.8),
        threshold=0.4,
        total_mass=5.0,
    ),
    # A with the first mean moved by (+2, +1, 0) cm and the second by (+2, +1.5, 0) cm; 10 % heavier.
    "B": _Named(
        means=((0.10, -0.05, -0.03), (-0.06, 0.075, 0.0)),
        stds=((0.08, 0.06, 0.05), (0.05, 0.05, 0.04)),
        weights=(1.0, 0.8),
        threshold=0.4,
        total_mass=5.5,
    ),
    # Mass high up along the +y side, heaviest towards -x: the mirror image of A's main bump.
    "C": _Named(
        means=((-0.11, 0.07, 0.02), (0.07, 0.07, 0.03)),
        stds=((0.07, 0.05, 0.05), (0.05, 0.05, 0.04)),
        weights=(1.0, 0.7),
        threshold=0.35,
        total_mass=8.0,
    ),
    # One elongated bump along the +y side, cut to U4: all the mass rests on the right belt at yaw 0.
    "D": _Named(
        means=((-0.02, 0.12, -0.03),),
        stds=((0.12, 0.05, 0.05),),
        weights=(1.0,),
        threshold=0.3,
        total_mass=7.0,
        region=3,
    ),
}


def named(name: str, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """One of the fixed distributions 'A', 'B', 'C', 'D', 'uniform' (see the module docstring).

    The mixtures are evaluated on the given box's voxel centres in float64 numpy, so the result does not
    depend on JAX's PRNG or precision settings. Raises ValueError for an unknown name.
    """
    if name == "uniform":
        return MassDistribution(jnp.ones(box.grid, jnp.float32), jnp.asarray(5.0, jnp.float32))
    if name not in _NAMED:
        raise ValueError(f"unknown mass distribution {name!r}; valid names are {', '.join(NAMES)}")
    # Every voxel's density is >= 1e-4 x max away from the threshold (default and 12 x 12 x 6 grids), so
    # rounding differences between platforms cannot flip a voxel.
    return from_mixture(*_NAMED[name], box=box)


def from_mixture(means, stds, weights, threshold, total_mass, region=None, box: BoxConfig = DEFAULT.box):
    """A distribution from explicit mixture parameters, voxelised as `named` does (float64 numpy).

    Args:
      means, stds: (G, 3) m, box frame; weights: (G,) peak heights; threshold: a voxel is occupied when
        the mixture at its centre is >= threshold x the maximum over the allowed voxels; total_mass: kg;
      region: None (the whole box) or 0..3 to confine the mass to U1..U4.
    """
    c = _voxel_centres64(box)
    z = (c[..., None, :] - np.asarray(means, np.float64)) / np.asarray(stds, np.float64)
    rho = np.sum(np.asarray(weights, np.float64) * np.exp(-0.5 * np.sum(z * z, axis=-1)), axis=-1)
    allowed = np.ones(box.grid, bool) if region is None else _region_masks(box)[region]
    rho = np.where(allowed, rho, -1.0)
    occ = allowed & (rho >= threshold * rho.max())
    return MassDistribution(jnp.asarray(occ, jnp.float32), jnp.asarray(total_mass, jnp.float32))


def iou(occ_a, occ_b) -> jax.Array:
    """() Intersection over union of two occupancy grids (occupied: > 0.5); 1 if both are empty."""
    a, b = jnp.asarray(occ_a) > 0.5, jnp.asarray(occ_b) > 0.5
    union = jnp.sum(a | b)
    return jnp.where(union > 0, jnp.sum(a & b) / jnp.maximum(union, 1), 1.0)


# ----------------------------------------------------------------------------------------------------------
# Host-side checks and text.


def validate(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> MassDistribution:
    """Check one distribution on the host; return it unchanged or raise DistributionError naming the problem.

    Checks, in order: occupancy shape == box.grid, numeric, finite, every value 0 or 1, at least one occupied
    voxel ("no mass"), total_mass a finite scalar > 0 kg.
    """
    occ = np.asarray(dist.occupancy)
    mass = np.asarray(dist.total_mass)
    if occ.shape != tuple(box.grid):
        raise DistributionError(
            f"occupancy has shape {occ.shape} but the box grid needs shape {tuple(box.grid)}"
        )
    if not np.issubdtype(occ.dtype, np.number) and occ.dtype != np.bool_:
        raise DistributionError(f"occupancy must be numeric, got dtype {occ.dtype}")
    occ = occ.astype(np.float64)
    if not np.all(np.isfinite(occ)):
        raise DistributionError(f"occupancy contains NaN or inf ({np.sum(~np.isfinite(occ))} voxels)")
    bad = (occ != 0) & (occ != 1)
    if np.any(bad):
        raise DistributionError(
            f"occupancy must be 0 or 1 in every voxel; {np.sum(bad)} voxels are not (e.g. {occ[bad][0]!r})"
        )
    if not np.any(occ):
        raise DistributionError("no mass: no voxel is occupied")
    if mass.shape != ():
        raise DistributionError(f"total_mass must be a scalar, got shape {mass.shape}")
    if not np.issubdtype(mass.dtype, np.number):
        raise DistributionError(f"total_mass must be a number, got dtype {mass.dtype}")
    if not np.isfinite(mass) or mass <= 0:
        raise DistributionError(f"total_mass must be finite and > 0 kg, got {float(mass)!r}")
    return dist


def describe(dist: MassDistribution, box: BoxConfig = DEFAULT.box) -> str:
    """Two human-readable lines: total mass, centre of mass (cm, box frame), fill fraction, hazard region."""
    occ = np.asarray(dist.occupancy) > 0.5
    # Host-side numpy (float64), same formula as `voxel_masses`: no per-op JAX dispatch for a string.
    masses = float(dist.total_mass) * occ / max(int(occ.sum()), 1) + box.voxel_eps
    com_cm = 100 * np.tensordot(masses, _voxel_centres64(box), axes=3) / masses.sum()
    com_cm = np.round(com_cm, 1) + 0.0  # + 0.0 turns -0.0 into 0.0
    n, total = int(occ.sum()), occ.size
    region = int(hazard_region(dist, box))
    hazard = "not hazardous" if region < 0 else f"HAZARDOUS: all mass in {_REGION_TEXT[region]}"
    return (
        f"total mass {float(dist.total_mass):.2f} kg; centre of mass (x, y, z) = "
        f"({com_cm[0]:+.1f}, {com_cm[1]:+.1f}, {com_cm[2]:+.1f}) cm in the box frame\n"
        f"fill {n}/{total} voxels ({100 * n / total:.0f} %); {hazard}"
    )
