"""The physics-prior predictor (paper §2.3, eqs. 4-14): the next planar state for ONE action.

Everything is pure jnp on one action; the planner batches actions with
``jax.vmap(predict, in_axes=(None, None, None, 0))``. Gradients w.r.t. the action and the voxel masses
are finite (every division is guarded). Conveyor frame, SI units (see config.py).

Two variants (``PriorParams.variant``), sharing the paper's structure -- voxel masses give the centre of
mass and I_zz; forces on S1 / S2 act on the voxels there; torque from voxel positions relative to the
centre of mass; angular acceleration tau / I_zz (planar); second-order Taylor step for position and yaw
(eq. 14):

``"paper"`` -- the paper as written.
  * r''_c = 0r''_c + F / M + beta (eq. 5): 0r''_c (the acceleration before the action) and the velocities
    come from finite differences of the last three observed states (`calibrate.window_kinematics`);
  * F = F1 + F2 + F3 + F4 from the calibrated force map (`calibrate.forces`) at the action values
    (dv_i = setpoint - belt speed, dp_i), applied evenly over S_i (delta F = F_i / |S_i|, eq. 9; a force on
    an empty S_i is dropped: nothing transmits it). S_i are the observed contact masks at time t;
  * torque tau = sum over S_i of r'_Q x delta F (eq. 8); omega' = 0omega' + tau / I_zz (the angular
    analogue of 0r''_c, from the window, is added; the paper writes omega' = I^-1 tau);
  * frictions (eqs. 11-13) over V1, V2 (voxel columns above S1, S2): direction eta_Q from the frictionless
    prediction (eq. 10), orthogonal to the voxel's current velocity, magnitude mu_k g dM_Q per voxel,
    beta = F_f / M and the matching torque / I_zz added to the angular acceleration;
  * one Taylor step over control_dt.

``"slip"`` (default) -- the same quantities computed from the contact physics instead of a lookup.
  The paper's force map sends a speed command to a constant force, but a belt acts on the box only
  through kinetic friction on the slip between the belt surface and the box: a box already moving with
  the belt feels no force however fast the belt runs, and a position step drags only as long as the box
  lags the carriage. So here, for each contact element Q of the box on belt i (the paper's S_i),
      delta F_Q = mu_k N_Q (u_belt_i - rdot_Q) / |u_belt_i - rdot_Q|      (Coulomb, regularised)
  (the isotropic form; with the simulator's pyramidal friction cone, the diamond law below: ``cone``)
  where u_belt_i = (belt surface speed, carriage sideways speed) during the step, given the action: the
  belt speed ramps linearly to its setpoint at <= belt_accel_limit (as the simulator's belt servo does),
  the carriage follows a critically damped step of natural frequency `carriage_omega` to P_i + dp_i.
  The paper's F1..F4 are the x / y sums of these forces over S1 / S2 (reported by `explain`), the paper's
  beta is part of them, and 0r''_c is not added (the friction is the only horizontal force, so adding the
  observed acceleration would count it twice). Differences from the paper, and why:
    * contact elements (``contact``): "polygon" (default) the vertices of each belt's contact polygon
      (the box footprint clipped to the belt strip): a rigid box on a flat belt bears on the corners of
      the overlap, and so does MuJoCo's box-box contact. Where the load sits along the box decides how
      much the sideways sliding of the box's ends resists the turn: with the load spread evenly over
      the bottom voxels ("voxels", area-weighted; the paper's S_i) the predicted steady turn rate for
      belts at +-0.2 m/s is ~1.15 rad/s against ~0.68 rad/s in the simulator, with the polygon ~0.62
      (isotropic friction) or ~0.71 (pyramidal, the default with the simulator's cone; uniform box).
      Measured against the simulator (1223 transitions of random restricted actions on boxes uniform,
      A, B, C), median one-step yaw error for position actions 0.15 deg (polygon) vs 0.56 deg (voxels);
    * normal loads N_Q (``normal``): "pressure" (default) a rigid box on an elastic belt surface: a
      linear pressure over the contact elements, sum M g, zero moment about the centre of mass, no
      tension (statically consistent; every kilogram presses on some belt). "columns" is the paper's V_i
      (voxels only): each contact voxel carries the weight of its own column, and mass between the belts
      carries nothing;
    * voxel contacts use area fractions: each bottom voxel's footprint (rotated with the box) overlaps
      belt i by a fraction in [0, 1] (exact along y for the rotated rectangle's projection; x and y
      treated as independent) instead of the hard 0/1 masks of `geometry.contact_masks`;
    * the step is split into `n_substeps` backward-Euler substeps, each a second-order Taylor step in
      position and yaw. One explicit step of 0.05 s with kinetic friction mu g = 4.9 m/s^2 would predict
      velocity changes of 0.25 m/s for a slip of a few mm/s (the box would overshoot the belt speed).
      The implicit velocity solves a small convex problem (see `_explain_slip`), so sticking is
      captured (a box on belts accelerating below mu g follows them) without chatter;
    * contact elements and loads are evaluated once, at time t (as the paper's observed S_i), and move
      rigidly with the box within the step;
    * the friction law follows the contact's friction cone (``cone``, default: the gripper's
      `GripperConfig.contact_cone`). With MuJoCo's pyramidal cone (the simulator's default) a contact
      transmits |f_x| + |f_y| <= mu N in the conveyor axes (a diamond, not a disk), so a sliding contact
      pushes along the axis of its larger slip component with the full mu N, and only with mu N / sqrt 2
      along a diagonal. Measured in the simulator (580k contact samples): the friction saturates at
      |f_x| + |f_y| = mu N for slips above ~5 mm/s and points along the dominant axis for slip
      directions up to ~40 degrees from it. The isotropic (elliptic) law is then wrong where it matters
      most: in a turn the box's ends slide diagonally, so the elliptic prior over-predicts the friction
      that resists the turn. For belts at +-0.2 m/s from rest, 30 steps open loop: the simulator turns
      A and B by 0.91 / 0.97 rad (drifting 4-5 cm); the pyramidal prior by 0.93 / 0.99 rad, the elliptic
      one by only 0.12 / 0.25 rad while predicting a 21-24 cm slide along the belts. One-step errors
      (benchmarks/prediction_error.py, 20000 transitions, median): position 0.33 -> 0.30 mm, yaw 0.053
      -> 0.037 deg (constant velocity: 0.53 mm, 0.062 deg); on spinning boxes yaw 0.101 -> 0.065 deg
      (constant velocity 0.094 deg).
  Ignored (both variants): the load shift from friction acting below the centre of mass, the box's
  rocking on its contact points (the simulator's box-belt contacts carry the load on 1-2 points per belt
  that move between corners from one 2 ms physics step to the next; the load-weighted centre of each
  belt's patch, averaged over a step, differs from the rigid-pressure model by ~4 cm along x, median;
  this decides the turn a position step causes, so for position actions the predicted yaw change beyond
  constant velocity correlates only ~0.3 with the simulator's, where the translation correlates ~0.7),
  the residual of the carriage's previous move, and belt-speed tracking error (measured negligible:
  feeding the simulator's own belt and carriage trajectories changes the one-step errors by < 0.01 mm).
  The "paper" variant also ignores the cone's anisotropy.

Velocities and the yaw are continuous (not wrapped) in the predicted state: yaw_next = yaw_t + delta.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import calibrate, geometry
from boxjax.calibrate import ForceMap, cross2, perp, rot2
from boxjax.config import BoxConfig, GripperConfig
from boxjax.massdist import mass_properties_from_masses

MIN_WINDOW = 3  # states s_{t-2}, s_{t-1}, s_t: second-order velocities and the pre-action acceleration
VARIANTS = ("slip", "paper")
NORMALS = ("pressure", "columns")
CONTACTS = ("voxels", "polygon")
CONES = ("gripper", "elliptic", "pyramidal")
_TINY = 1e-12
_MIN_WIDTH = 1e-3  # m, smallest projected footprint width (keeps the overlap formula well conditioned)
_BOX, _GRIPPER = BoxConfig(), GripperConfig()
_MAX_VERTICES = 8  # vertices of the intersection of two rectangles, at most
_NO_TENSION_ITERATIONS = 4  # active-set passes of `normal_loads` (a box on 2 belts settles in 1-2)


@dataclasses.dataclass(frozen=True)
class PriorParams:
    """Static (hashable) settings of the predictor; changing one recompiles.

    variant: "slip" (default) or "paper" (see module docstring).
    n_substeps: implicit (backward Euler) substeps per control step ("slip" only).
    n_iterations: solver iterations per substep ("slip"; see `_explain_slip`).
    slip_eps: m/s, regularisation of the friction direction slip / sqrt(|slip|^2 + eps^2) ("slip").
    contact: "voxels" or "polygon", where the belts touch the box ("slip"; see module docstring).
    normal: "pressure" or "columns", the normal-load model ("slip"; "columns" needs contact="voxels").
    carriage_omega: rad/s, natural frequency of the critically damped carriage step response ("slip");
      math.inf means constant sideways speed dp / control_dt over the step. The default matches the
      simulator's servo (kp 5e4 N/m, kv 1e3 N s/m on 5 kg: 100 rad/s, 96 % of the step done in 0.05 s).
    cone: the friction law at each contact element ("slip"): "elliptic" isotropic Coulomb, "pyramidal"
      MuJoCo's pyramidal cone (|f_x| + |f_y| <= mu N, see `dissipation`), or "gripper" (default) the
      cone the gripper is simulated with (GripperConfig.contact_cone).
    load_transfer: the normal loads include the moment of the belt friction about the centre of mass
      ("slip" with normal="pressure"; `normal_loads`), updated every substep from the previous one's
      friction (the first from the observed acceleration, M a). False: loads from gravity alone.
    carry_velocity: multi-step rollouts carry the predicted end-of-step velocity ("slip";
      `rollout_sequence`). False: every step re-derives it from the window's finite differences.
    """

    variant: str = "slip"
    n_substeps: int = 2
    n_iterations: int = 2
    slip_eps: float = 2e-3
    contact: str = "polygon"
    normal: str = "pressure"
    carriage_omega: float = 100.0
    cone: str = "gripper"
    load_transfer: bool = True
    carry_velocity: bool = True

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown prior variant {self.variant!r}; choose one of {VARIANTS}")
        if self.normal not in NORMALS:
            raise ValueError(f"unknown normal-load model {self.normal!r}; choose one of {NORMALS}")
        if self.contact not in CONTACTS:
            raise ValueError(f"unknown contact model {self.contact!r}; choose one of {CONTACTS}")
        if self.cone not in CONES:
            raise ValueError(f"unknown friction cone {self.cone!r}; choose one of {CONES}")
        if self.contact == "polygon" and self.normal == "columns":
            raise ValueError("normal='columns' (the paper's V_i) needs contact='voxels'")
        if self.n_substeps < 1 or self.n_iterations < 1 or self.slip_eps <= 0 or not self.carriage_omega > 0:
            raise ValueError("need n_substeps >= 1, n_iterations >= 1, slip_eps > 0 and carriage_omega > 0")


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["masses", "force_map", "mass", "com", "izz", "column_mass", "offsets"],
    meta_fields=["box", "gripper", "params"],
)
@dataclasses.dataclass(frozen=True)
class PriorModel:
    """Everything the predictor needs for one box (a pytree; box, gripper and params are static).

    masses: (nx, ny, nz) kg voxel masses (estimated or true).
    force_map: calibrate.ForceMap (used by the "paper" variant; may be None for "slip").
    mass: () kg total; com: (3,) m centre of mass (box frame); izz: () kg m^2 inertia about the vertical
      axis through the centre of mass (voxels as solid cuboids, massdist.mass_properties_from_masses).
    column_mass: (nx, ny) kg, mass of each vertical voxel column (the paper's V_i are sets of columns).
    offsets: (nx, ny, 2) m, box-frame planar positions of the columns (= bottom voxels) relative to the
      centre of mass.
    """

    masses: jax.Array
    force_map: ForceMap | None
    mass: jax.Array
    com: jax.Array
    izz: jax.Array
    column_mass: jax.Array
    offsets: jax.Array
    box: BoxConfig
    gripper: GripperConfig
    params: PriorParams

    # The model slot of the planners (`planning.Model`).
    def rollout_sequence(self, window, belt_speed, actions) -> jax.Array:
        """(H, 5) predicted states for the action sequence (H, 4); see module-level `rollout_sequence`."""
        return rollout_sequence(self, window, belt_speed, actions)

    def stability_margin(self, s) -> jax.Array:
        """() m, the centre of mass's distance inside the support polygon; see `stability_margin`."""
        return stability_margin(self, s)


def make_prior(
    masses,
    force_map: ForceMap | None = None,
    box: BoxConfig = _BOX,
    gripper: GripperConfig = _GRIPPER,
    params: PriorParams | None = None,
    **param_overrides,
) -> PriorModel:
    """Precompute the per-episode quantities of the predictor (pure jnp; differentiable w.r.t. masses).

    Args:
      masses: (nx, ny, nz) kg voxel masses, box frame (massdist.voxel_masses of a distribution).
      force_map: required for the "paper" variant.
      params: PriorParams, or keyword overrides of its fields (variant="paper", n_substeps=10, ...).
    """
    params = params or PriorParams()
    if param_overrides:
        params = dataclasses.replace(params, **param_overrides)
    if params.variant == "paper" and force_map is None:
        raise ValueError("the 'paper' prior variant needs a force map (calibrate.ForceMap)")
    masses = jnp.asarray(masses, jnp.float32)
    if masses.shape != tuple(box.grid):
        raise ValueError(f"masses must have the box grid's shape {tuple(box.grid)}, got {masses.shape}")
    props = mass_properties_from_masses(masses, box)
    return PriorModel(
        masses=masses,
        force_map=force_map,
        mass=props.mass,
        com=props.com,
        izz=props.inertia[2, 2],
        column_mass=jnp.sum(masses, axis=2),
        offsets=calibrate.bottom_offsets_box(props.com, box),
        box=box,
        gripper=gripper,
        params=params,
    )


# ----------------------------------------------------------------------------------------------------------
# Host-side input checks.


def check_window(window, belt_speed=None, action=None, min_window: int = MIN_WINDOW) -> np.ndarray:
    """Validate predictor inputs on the host; returns the window as a float32 array.

    Raises:
      ValueError: window not of shape (W, 5), W < min_window (MIN_WINDOW = 3 states at control_dt
        spacing are needed), non-finite values (naming the rows and state components), or a belt_speed
        not (2,) / an action not (4,) / either non-finite.
    """
    w = np.asarray(window, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 5:
        raise ValueError(
            f"window must have shape (W, 5) = planar states {geometry.STATE_NAMES} over time, got {w.shape}"
        )
    if w.shape[0] < min_window:
        raise ValueError(
            f"window has {w.shape[0]} states; the predictor needs at least {min_window} "
            f"(s_(t-2), s_(t-1), s_t at control_dt spacing). At the start of an episode, repeat the "
            "initial state (the box is at rest)."
        )
    bad = ~np.isfinite(w)
    if np.any(bad):
        rows, cols = np.nonzero(bad)
        names = geometry.STATE_NAMES
        where = ", ".join(f"row {r} {names[c]}" for r, c in zip(rows[:5], cols[:5], strict=True))
        raise ValueError(f"window contains NaN or inf ({int(bad.sum())} values: {where})")
    for name, x, n in (("belt_speed", belt_speed, 2), ("action", action, 4)):
        if x is None:
            continue
        a = np.asarray(x, dtype=np.float64)
        if a.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf: {a.tolist()}")
    return w.astype(np.float32)


def initial_window(s0, length: int = MIN_WINDOW) -> jax.Array:
    """(length, 5) window for the first step of an episode: the initial state repeated (box at rest)."""
    return jnp.tile(jnp.asarray(s0, jnp.float32)[None], (length, 1))


# ----------------------------------------------------------------------------------------------------------
# Small pure helpers.


def _solve3(a, b):
    """x with a x = b for a (3, 3) by the adjugate (elementwise: cheap under vmap); det guarded."""
    r0, r1, r2 = a[0], a[1], a[2]
    c0, c1, c2 = jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)
    det = jnp.dot(r0, c0)
    det = jnp.where(jnp.abs(det) > _TINY, det, jnp.where(det < 0, -_TINY, _TINY))
    return (c0 * b[0] + c1 * b[1] + c2 * b[2]) / det


def _sum_uniform_cdf(t, a, b):
    """CDF at t of U(-a/2, a/2) + U(-b/2, b/2) (a trapezoid): the fraction of a rectangle's area whose
    projection on an axis lies below t, for projected widths a, b (a rotated rectangle dx x dy projects
    with a = |sin| dx, b = |cos| dy on y). Widths are floored at 1 mm."""
    a = jnp.maximum(a, _MIN_WIDTH)
    b = jnp.maximum(b, _MIN_WIDTH)
    s = 0.5 * (a + b)
    d = 0.5 * jnp.abs(a - b)
    t = jnp.clip(t, -s, s)  # keeps magnitudes small: no float32 cancellation far from the support
    r2 = lambda u: jnp.square(jnp.maximum(u, 0.0))  # noqa: E731
    return jnp.clip((r2(t + s) - r2(t + d) - r2(t - d) + r2(t - s)) / (2 * a * b), 0.0, 1.0)


def contact_fractions(s, box: BoxConfig, gripper: GripperConfig) -> jax.Array:
    """(2, nx, ny) fraction in [0, 1] of each bottom voxel's footprint resting on belt 1 / belt 2.

    A soft version of `geometry.contact_masks` (same index layout): the voxel's rotated footprint is
    projected on y (exact trapezoid overlap with the belt strip |y - P_i| <= width / 2) and on x (overlap
    with |x| <= length / 2); the area fraction is the product of the two.
    """
    dx, dy, _ = box.voxel_size
    centres = geometry.box_to_world_xy(s, jnp.asarray(geometry.bottom_voxel_centres_xy(box)))
    c, sn = jnp.abs(jnp.cos(s[geometry.YAW])), jnp.abs(jnp.sin(s[geometry.YAW]))
    half_l, half_w = gripper.belt_length / 2, gripper.belt_width / 2
    fx = _sum_uniform_cdf(half_l - centres[..., 0], c * dx, sn * dy) - _sum_uniform_cdf(
        -half_l - centres[..., 0], c * dx, sn * dy
    )

    def over_belt(p):
        lo, hi = p - half_w - centres[..., 1], p + half_w - centres[..., 1]
        return _sum_uniform_cdf(hi, sn * dx, c * dy) - _sum_uniform_cdf(lo, sn * dx, c * dy)

    return jnp.stack([fx * over_belt(s[geometry.P1]), fx * over_belt(s[geometry.P2])])


class Contacts(NamedTuple):
    """Contact elements between the belts and the box at one instant ("slip" variant).

    offsets: (2, E, 2) m, planar positions relative to the centre of mass, box-frame axes, of the E
      elements of belt 1 and belt 2 (rigidly attached to the box for the duration of a step).
    weights: (2, E) >= 0: how much of each element touches its belt (area fraction for voxels, 0 or 1 for
      polygon vertices); an element with weight 0 carries no load.
    """

    offsets: jax.Array
    weights: jax.Array


def voxel_contacts(model: PriorModel, s) -> Contacts:
    """The bottom voxels, weighted by their footprint's overlap with each belt (`contact_fractions`)."""
    fr = contact_fractions(s, model.box, model.gripper).reshape(2, -1)
    off = jnp.broadcast_to(model.offsets.reshape(1, -1, 2), (2, fr.shape[1], 2))
    return Contacts(off, fr)


def polygon_contacts(model: PriorModel, s) -> Contacts:
    """The vertices of each belt's contact polygon: box footprint intersected with the belt's top face.

    A rigid box resting on a flat belt touches it, in the rigid limit, at the vertices of the overlap
    polygon (this is also what MuJoCo's box-box collision reports). For two rectangles the vertices are
    among: the footprint's 4 corners inside the belt, the belt's 4 corners strictly inside the footprint,
    and the crossings of the footprint's 4 edges with the belt's 4 edge lines (strictly inside the
    footprint edge, within the belt edge), so a vertex on an edge is counted once: 24 candidates per belt,
    the valid ones with weight 1, compacted to the 8 slots a rectangle-rectangle intersection can need.
    """
    hx, hy, _ = model.box.half_size
    corners_box = jnp.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]], jnp.float32)
    c = geometry.box_to_world_xy(s, corners_box)  # (4, 2) footprint corners, world
    d = jnp.roll(c, -1, axis=0) - c  # edges c_k -> c_{k+1}
    rot_t = rot2(s[geometry.YAW]).T  # world -> box axes
    half_w, half_l = model.gripper.belt_width / 2, model.gripper.belt_length / 2
    tol = 1e-7

    def belt(p):
        lo, hi = p - half_w, p + half_w
        in_x = (c[:, 0] >= -half_l - tol) & (c[:, 0] <= half_l + tol)
        in_b = in_x & (c[:, 1] >= lo - tol) & (c[:, 1] <= hi + tol)
        cb = jnp.array([[-half_l, lo], [half_l, lo], [half_l, hi], [-half_l, hi]], jnp.float32)
        cb_box = (cb - s[geometry.X : geometry.Y + 1]) @ rot_t.T
        in_a = (jnp.abs(cb_box[:, 0]) < hx - 1e-6) & (jnp.abs(cb_box[:, 1]) < hy - 1e-6)
        # Footprint edges against the belt's lines y = lo, y = hi (|x| <= L/2) and x = -+L/2 (lo <= y <= hi).
        level = jnp.array([lo, hi, -half_l, half_l])
        axis = jnp.array([1, 1, 0, 0])
        start = c[None, :, :]  # (1, 4, 2)
        dd = d[None, :, :]
        # (4 lines, 4 edges):
        num = level[:, None] - jnp.where(axis[:, None] == 1, start[..., 1], start[..., 0])
        den = jnp.where(axis[:, None] == 1, dd[..., 1], dd[..., 0])
        ok = jnp.abs(den) > 1e-9
        t = num / jnp.where(ok, den, 1.0)
        pts = start + jnp.clip(t, 0.0, 1.0)[..., None] * dd  # (4, 4, 2)
        other = jnp.where(axis[:, None] == 1, pts[..., 0], pts[..., 1])
        other_lo = jnp.where(axis == 1, -half_l, lo)[:, None] - tol
        other_hi = jnp.where(axis == 1, half_l, hi)[:, None] + tol
        valid = ok & (t > 1e-5) & (t < 1 - 1e-5) & (other >= other_lo) & (other <= other_hi)
        points = jnp.concatenate([c, cb, pts.reshape(-1, 2)])  # (24, 2)
        weights = jnp.concatenate([in_b, in_a, valid.reshape(-1)]).astype(jnp.float32)
        # The intersection of two rectangles has at most 8 vertices: keep 8 slots (the valid ones
        # first), so the friction sums run over 8 elements per belt instead of 24.
        _, keep = jax.lax.top_k(weights, _MAX_VERTICES)
        return points[keep], weights[keep]

    pts1, w1 = belt(s[geometry.P1])
    pts2, w2 = belt(s[geometry.P2])
    world = jnp.stack([pts1, pts2])  # (2, 24, 2)
    box_xy = (world - s[geometry.X : geometry.Y + 1]) @ rot_t.T  # R^T (p - r_geom), as row vectors
    return Contacts(box_xy - model.com[:2], jnp.stack([w1, w2]).astype(jnp.float32))


def stability_margin(model: PriorModel, s, n_directions: int = 32) -> jax.Array:
    """() m: how far the centre of mass lies inside the support polygon (negative: outside, the box tips).

    The support polygon is the convex hull of both belts' contact polygons (`polygon_contacts`); a rigid
    box at rest stays up while the vertical through its centre of mass meets it (the static tipping
    criterion). The signed distance to the hull's boundary is min over unit directions n of the hull's
    support function max_q n . q (q: contact vertices relative to the centre of mass), evaluated on
    `n_directions` evenly spaced directions: exact on the hull's edge normals, so the sampled value
    over-estimates the distance by at most R (1 - cos(pi / n_directions)) (< 1 mm for a 0.25 m reach and
    32 directions). No contact at all: -1 m.

    Why the planner needs it: with both belts spread out to their stops, a turned box rests on two small
    corner patches at opposite ends of a diagonal; a box whose centre of mass lies off that diagonal
    tips into the gap between the belts (measured in the simulator: box C at yaw 0.4 rad, belts at
    +-0.20 m, margin 3 mm, tipped). The planar prior cannot see this; the margin can.
    """
    c = polygon_contacts(model, jnp.asarray(s, jnp.float32))
    ang = jnp.arange(n_directions, dtype=jnp.float32) * (2 * math.pi / n_directions)
    dirs = jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=-1)  # (D, 2), box axes (the hull rotates with it)
    proj = c.offsets.reshape(-1, 2) @ dirs.T  # (2E, D)
    proj = jnp.where(c.weights.reshape(-1, 1) > 0, proj, -1.0)
    return jnp.min(jnp.max(proj, axis=0))


def normal_loads(model: PriorModel, contacts: Contacts, friction=None) -> jax.Array:
    """(2, E) N, normal force on each contact element from belt 1 / belt 2.

    friction: (2,) N, the total belt friction on the box in box axes (None: zero). Friction acts at the
    belt surface, h = com_z + half height below the centre of mass, so it tilts the box's load: the
    moment balance about the centre of mass becomes sum q N = -h F (a box dragged towards -y presses
    harder on its +y side). Without it, a carriage pulled out from under a box is predicted to drag the
    box along; measured in the simulator (box with the centre of mass 7.5 cm over belt 1 and 5.6 cm above
    its centre, belt 1 moved 8 cm outwards): the box moved 1.6 cm, the load-blind prior predicted 7.7.

    "pressure": p(q) = a + b q_x + c q_y over the weighted contact elements (q relative to the centre of
    mass), with sum = M g and zero moment about the centre of mass (a rigid box on an elastic belt
    surface), without tension: elements where the pressure would be negative lift off and the rest is
    solved again (active-set passes); if the centre of mass lies outside the support (no solution), the
    negative values are clipped and the total renormalised to M g. Against MuJoCo, box C at rest: 17.8 /
    60.7 N on belt 1 / belt 2, simulator 18.0 / 60.5 N. "columns": g x column mass x area fraction (the
    paper's V_i; voxel contacts only). No contact at all: all zero.
    """
    g = model.gripper.gravity
    w = contacts.weights
    if model.params.normal == "columns":
        return g * model.column_mass.reshape(1, -1) * w
    q = contacts.offsets  # (2, E, 2); frame-independent: the moments vanish in any frame
    phi = jnp.concatenate([jnp.ones_like(w)[..., None], q], axis=-1)  # (2, E, 3)
    mg = model.mass * g
    if friction is None:
        rhs = jnp.stack([mg, 0.0 * mg, 0.0 * mg])
    else:
        h = model.com[2] + model.box.half_size[2]
        rhs = jnp.concatenate([mg[None], -h * friction])

    def solve(active):
        """The linear pressure over the active elements with sum M g and zero moment."""
        wa = w * active
        a = jnp.einsum("be,bek,bel->kl", wa, phi, phi)
        # Ridge: a contact set on one line is degenerate. (dtype: stays float32 under jax_enable_x64.)
        a = a + (1e-6 * a[0, 0] + _TINY) * jnp.eye(3, dtype=a.dtype)
        return _solve3(a, rhs)

    # No tension (a box does not stick to its belts): where the linear pressure comes out negative the
    # element lifts off, and the pressure is solved again over the elements still pressing (active-set
    # iterations, as for a rigid footing on an elastic foundation). Merely clipping the negative values
    # breaks the moment balance: box C at rest (centre of mass 7 cm towards belt 2) was left with 0.19 N m
    # of moment about its centre of mass and 18.5 N on belt 1 (now 17.8 N, MuJoCo 18.0 N).
    coef = solve(jnp.ones_like(w))
    for _ in range(_NO_TENSION_ITERATIONS):
        coef = solve((phi @ coef > 0).astype(w.dtype))
    n = w * jnp.maximum(phi @ coef, 0.0)
    tot = jnp.sum(n)
    ok = tot > 1e-9
    return jnp.where(ok, n * (mg / jnp.where(ok, tot, 1.0)), 0.0)


def _belt_profiles(model: PriorModel, s_t, belt_speed, action):
    """Belt surface velocities over the step, and the next belt positions.

    Returns (vx(tau) callable -> (2,), carriage displacement y(tau) callable -> (2,), P_next (2,)).
    """
    gr = model.gripper
    dt = gr.control_dt
    sp = jnp.clip(action[:2], -gr.belt_speed_limit, gr.belt_speed_limit)
    acc = jnp.clip((sp - belt_speed) / dt, -gr.belt_accel_limit, gr.belt_accel_limit)
    dp = jnp.clip(action[2:], -gr.max_position_step, gr.max_position_step)
    p = s_t[:2]
    lo = jnp.array([gr.p1_range[0], gr.p2_range[0]], s_t.dtype)  # keeps float32 under jax_enable_x64
    hi = jnp.array([gr.p1_range[1], gr.p2_range[1]], s_t.dtype)
    p_next = jnp.clip(p + dp, lo, hi)
    d = p_next - p
    w = model.params.carriage_omega

    def vx(tau):
        return belt_speed + acc * tau

    def y(tau):
        if math.isinf(w):
            return d * (tau / dt)
        return d * (1.0 - (1.0 + w * tau) * jnp.exp(-w * tau))

    return vx, y, p_next


def _geom_state(model: PriorModel, p_next, rc, theta):
    """(5,) planar state from the centre of mass position and yaw."""
    r_geom = rc - rot2(theta) @ model.com[:2]
    return jnp.concatenate([p_next, r_geom, theta[None]])


# ----------------------------------------------------------------------------------------------------------
# The two variants.


def _slip(u, belt_velocity, off):
    """(..., 2, E, 2) slip of each belt under each contact element: u_belt_i - (v + omega perp(o)),
    for body velocities u (..., 3) and element offsets off (2, E, 2) (conveyor axes)."""
    u = u[..., None, None, :]
    vq = u[..., :2] + u[..., 2:3] * perp(off)
    return belt_velocity[:, None, :] - vq


_DIAG = 1.0 / math.sqrt(2.0)  # the pyramid's diagonal directions e1 = (1, 1) / sqrt 2, e2 = (1, -1) / sqrt 2


def _diag(v):
    """(..., 2) components of planar vectors v along the diagonals e1, e2 (Q v, Q = Q^T = Q^-1)."""
    return jnp.stack([_DIAG * (v[..., 0] + v[..., 1]), _DIAG * (v[..., 0] - v[..., 1])], axis=-1)


def dissipation(u, belt_velocity, off, loads, mu: float, eps: float, cone: str = "elliptic"):
    """(...) the friction's convex potential (W) for body velocities u (..., 3), whose negative gradient
    w.r.t. u is the generalised friction force, summed over the contact elements:

    "elliptic": mu N sqrt(|s|^2 + eps^2), isotropic regularised Coulomb on the slip s;
    "pyramidal": (mu N / sqrt 2) (sqrt((s . e1)^2 + eps^2) + sqrt((s . e2)^2 + eps^2)) with the diagonals
    e1 = (1, 1) / sqrt 2, e2 = (1, -1) / sqrt 2. MuJoCo's pyramidal cone (condim 3: edges n +- mu t1,
    n +- mu t2; the contact frame's tangents are the conveyor's y and x axes for the flat belt contacts)
    lets a contact transmit |f_x| + |f_y| <= mu N, a diamond. A sliding contact dissipates the most it can,
    sup over the diamond of f . s = mu N max(|s_x|, |s_y|) = (mu N / sqrt 2) (|s . e1| + |s . e2|): two 1-D
    Coulomb frictions of coefficient mu / sqrt 2 along the diagonals, regularised like the isotropic law.
    The force is then mu N along the axis of the larger slip component (the diamond's vertex), and
    mu N / sqrt 2 along a diagonal slip.
    """
    s = _slip(u, belt_velocity, off)
    if cone == "elliptic":
        per = jnp.sqrt(jnp.sum(s * s, -1) + eps * eps)
    else:
        z = _diag(s)
        per = _DIAG * jnp.sum(jnp.sqrt(z * z + eps * eps), -1)
    return jnp.sum(mu * loads * per, axis=(-2, -1))


def friction_force(u, belt_velocity, off, loads, mu: float, eps: float, cone: str = "elliptic"):
    """Belt friction on the box ("slip" variant): generalised force, its Jacobian, per-belt forces, and
    the quadratic majoriser of `dissipation` at u.

    Per contact element Q on belt i: slip s = u_belt_i - (v + omega perp(o_Q)) = u_belt_i - G u with
    G = [I2 | perp(o_Q)]; force f = W s = -d dissipation / d s with W a 2 x 2 weight; D = d f / d s; the
    generalised force is sum G^T f and its Jacobian -sum G^T D G = -sum [[D, D p], [p^T D, p^T D p]]
    with p = perp(o_Q) (analytic: cheaper than jacfwd under vmap, and tested against it). Majoriser
    (IRLS): every term of `dissipation` is a concave function of a square, so dissipation(u') <= const +
    sum (u_belt - G u')^T W (u_belt - G u') / 2 with W frozen at u, i.e. the quadratic u'^T A u' / 2 -
    b^T u' with A = sum G^T W G, b = sum G^T W u_belt = force + A u.
      "elliptic": W = w I, w = mu N / sqrt(|s|^2 + eps^2); D = w I - w s s^T / (|s|^2 + eps^2).
      "pyramidal": W and D are diagonal along e1, e2: with z_j = s . e_j, w_j = (mu N / sqrt 2) /
      sqrt(z_j^2 + eps^2) and d_j = w_j eps^2 / (z_j^2 + eps^2), W = Q diag(w) Q, D = Q diag(d) Q (Q the
      reflection onto the diagonals, Q = Q^T = Q^-1), so the sums run in the diagonal axes (with
      p' = Q p) and are turned back once.

    Args:
      u: (3,) body velocity (vx, vy, omega) of the centre of mass (m/s, rad/s).
      belt_velocity: (2, 2) surface velocity (x, y) of belt 1 and belt 2 (m/s).
      off: (2, E, 2) m, contact element positions relative to the centre of mass (conveyor axes).
      loads: (2, E) N, normal force of belt 1 / belt 2 on each element.
      mu: friction coefficient; eps: m/s regularisation; cone: "elliptic" or "pyramidal" (`dissipation`).
    Returns:
      (force (3,) = (Fx N, Fy N, tau N m), jac (3, 3) d force / d u, per_belt (2, 2) N, A (3, 3), b (3,)).
    """
    p = perp(off)  # (2, E, 2)
    if cone == "elliptic":
        slip = _slip(u, belt_velocity, off)  # (2, E, 2)
        sx, sy = slip[..., 0], slip[..., 1]
        r = jax.lax.rsqrt(sx * sx + sy * sy + eps * eps)  # (2, E)
        w = mu * loads * r
        r3 = w * r * r
        px, py = p[..., 0], p[..., 1]
        dxx, dyy, dxy = w - r3 * sx * sx, w - r3 * sy * sy, -r3 * sx * sy
        dpx, dpy = dxx * px + dxy * py, dxy * px + dyy * py
        fx, fy = w * sx, w * sy
        # One reduction over the contacts for every sum (much faster on CPU than a dozen small ones).
        terms = [fx, fy, px * fx + py * fy]  # force, torque (p . f = o x f)
        terms += [dxx, dyy, dxy, dpx, dpy, px * dpx + py * dpy]  # friction Jacobian blocks
        terms += [w, w * px, w * py, w * (px * px + py * py)]  # majoriser
        per = jnp.sum(jnp.stack(terms, axis=-1), axis=1)  # (2 belts, 13)
        t = jnp.sum(per, axis=0)
        force = t[0:3]
        sxx, syy, sxy, spx, spy, spp = t[3], t[4], t[5], t[6], t[7], t[8]
        jac = -jnp.array([[sxx, sxy, spx], [sxy, syy, spy], [spx, spy, spp]])
        wt, wpx, wpy, wpp = t[9], t[10], t[11], t[12]
        a_mm = jnp.array([[wt, 0.0, wpx], [0.0, wt, wpy], [wpx, wpy, wpp]])
        per_belt = per[:, 0:2]
    else:
        # Everything in the diagonal axes: z = Q s = Q u_belt - Q v - omega p', p' = Q p.
        pd = _diag(p)  # (2, E, 2)
        z = _diag(belt_velocity)[:, None, :] - _diag(u[:2]) - u[2] * pd
        q = jax.lax.rsqrt(z * z + eps * eps)  # (2, E, 2)
        w = (_DIAG * mu) * loads[..., None] * q
        dd = w * (eps * eps) * q * q
        f = w * z
        dp, wp = dd * pd, w * pd
        terms = [f, jnp.sum(pd * f, -1, keepdims=True)]  # force (diagonal axes), torque
        terms += [dd, dp, jnp.sum(dp * pd, -1, keepdims=True)]  # friction Jacobian blocks
        terms += [w, wp, jnp.sum(wp * pd, -1, keepdims=True)]  # majoriser
        per = jnp.sum(jnp.concatenate(terms, axis=-1), axis=1)  # (2 belts, 13)
        t = jnp.sum(per, axis=0)

        def back(s1, s2, s1p, s2p, spp):
            """G^T Q diag(s) Q G sums from their diagonal-axes parts: the 3 x 3 block matrix."""
            h = 0.5 * (s1 + s2)
            k = 0.5 * (s1 - s2)
            cx, cy = _DIAG * (s1p + s2p), _DIAG * (s1p - s2p)
            return jnp.array([[h, k, cx], [k, h, cy], [cx, cy, spp]])

        force = jnp.stack([_DIAG * (t[0] + t[1]), _DIAG * (t[0] - t[1]), t[2]])
        jac = -back(*(t[3:8]))
        a_mm = back(*(t[8:13]))
        per_belt = _diag(per[:, 0:2])
    b_mm = force + a_mm @ u  # = sum G^T W u_belt, since force = sum G^T W (u_belt - G u)
    return force, jac, per_belt, a_mm, b_mm


def _explain_slip(model: PriorModel, window, belt_speed, action, velocity=None, friction=None):
    gr, prm = model.gripper, model.params
    dt = gr.control_dt
    h = dt / prm.n_substeps
    mu, eps = gr.friction, prm.slip_eps
    cone = gr.contact_cone if prm.cone == "gripper" else prm.cone
    s_t = window[-1]
    kin = calibrate.window_kinematics(window, model.com[:2], dt)
    contacts = polygon_contacts(model, s_t) if prm.contact == "polygon" else voxel_contacts(model, s_t)
    static_loads = normal_loads(model, contacts)  # (2, E) N, from gravity alone
    transfer = prm.load_transfer and prm.normal == "pressure"
    vx, y, p_next = _belt_profiles(model, s_t, belt_speed, action)
    mdiag = jnp.stack([model.mass, model.mass, model.izz])
    mmat = jnp.diag(mdiag)

    def implicit_velocity(u0, ub, off, loads):
        """Backward Euler for the velocity: u' = argmin (u' - u0)^T M (u' - u0) / 2 + h dissipation(u'),
        a smooth strongly convex problem in 3 unknowns. Each iteration takes the better (lower objective)
        of a Newton step (exact where the friction is in its linear, near-sticking regime; overshoots
        where the friction saturates) and an IRLS majorise-minimise step (never increases the objective,
        so it cannot overshoot into chatter; slow where the friction saturates)."""

        def objectives(uu):  # (k, 3) candidate velocities -> (k,) objective values
            du = uu - u0
            return 0.5 * jnp.sum(du * mdiag * du, -1) + h * dissipation(uu, ub, off, loads, mu, eps, cone)

        def iterate(uc, _):
            force, jac, fb, a_mm, b_mm = friction_force(uc, ub, off, loads, mu, eps, cone)
            u_newton = uc - _solve3(mmat - h * jac, mdiag * (uc - u0) - h * force)
            u_mm = _solve3(mmat + h * a_mm, mdiag * u0 + h * b_mm)
            cand = jnp.stack([u_newton, u_mm])
            phi = objectives(cand)
            return jnp.where(phi[0] < phi[1], u_newton, u_mm), fb

        u1, fbs = jax.lax.scan(iterate, u0, None, length=prm.n_iterations)
        return u1, fbs[-1]

    def substep(carry, k):
        rc, th, u, f_prev = carry
        # The friction of the previous substep (conveyor axes) tilts this substep's loads.
        loads = normal_loads(model, contacts, f_prev @ rot2(th)) if transfer else static_loads
        tau0, tau1 = k * h, (k + 1) * h
        # Belt speed at the END of the substep (backward Euler: with the trapezoidal position update a
        # box sticking to a ramping belt follows it exactly); carriage speed averaged over the substep
        # (its fast step is mostly slipped through, so the belt's displacement is what matters).
        ub = jnp.stack([vx(tau1), (y(tau1) - y(tau0)) / h], axis=-1)  # (2 belts, 2)
        off = contacts.offsets @ rot2(th).T  # (2, E, 2) conveyor axes
        u_new, fb = implicit_velocity(u, ub, off, loads)
        mean_u = 0.5 * (u + u_new)  # second-order Taylor step (eq. 14) per substep: u h + (du / h) h^2 / 2
        return (rc + h * mean_u[:2], th + h * mean_u[2], u_new, jnp.sum(fb, axis=0)), (fb, loads)

    u0 = jnp.concatenate([kin.v, kin.omega[None]]) if velocity is None else velocity
    ks = jnp.arange(prm.n_substeps, dtype=u0.dtype)
    # The belts' friction is the only horizontal force on the box: M a from the window, unless known.
    f0 = model.mass * kin.a0 if friction is None else friction
    (rc, th, u, f_end), (fbs, loads_k) = jax.lax.scan(substep, (kin.rc, kin.theta, u0, f0), ks)
    loads = jnp.mean(loads_k, axis=0)
    fb = jnp.mean(fbs, axis=0)  # (2 belts, 2): mean friction on S1, S2 over the step
    info = {
        "forces": jnp.stack([fb[0, 0], fb[1, 0], fb[0, 1], fb[1, 1]]),  # F1, F2 (x), F3, F4 (y), N
        "normal_load": jnp.sum(loads, axis=1),  # (2,) N on belt 1, belt 2
        "contact_area": jnp.sum(contacts.weights, axis=1),  # (2,) voxel footprints (soft |S_i|) or vertices
        "com_velocity": u[:2],
        "omega": u[2],
        "velocity": u,  # (3,) (vx, vy, omega) at the end of the step: `rollout_sequence` carries it
        "friction": f_end,  # (2,) N, total belt friction of the last substep (conveyor axes)
    }
    return _geom_state(model, p_next, rc, th), info


def _explain_paper(model: PriorModel, window, belt_speed, action):
    gr = model.gripper
    dt = gr.control_dt
    s_t = window[-1]
    kin = calibrate.window_kinematics(window, model.com[:2], dt)
    off = model.offsets @ rot2(kin.theta).T  # (nx, ny, 2) r'_Q, conveyor axes
    s1, s2 = geometry.contact_masks(s_t, model.box, gr)
    n1, n2 = jnp.sum(s1), jnp.sum(s2)
    f = calibrate.forces(model.force_map, calibrate.action_values(action, belt_speed, gr))
    fv1 = jnp.stack([f[0], f[2]]) * (n1 > 0)  # F1 (x) and F3 (y) on S1; dropped when S1 is empty
    fv2 = jnp.stack([f[1], f[3]]) * (n2 > 0)
    df1 = fv1 / jnp.maximum(n1, 1.0)  # eq. 9: F_i / |S_i| per voxel
    df2 = fv2 / jnp.maximum(n2, 1.0)
    tau = jnp.sum(s1 * cross2(off, df1)) + jnp.sum(s2 * cross2(off, df2))  # eq. 8
    a = kin.a0 + (fv1 + fv2) / model.mass  # eq. 5 without beta
    alpha = kin.alpha0 + tau / model.izz  # eq. 6
    # Frictionless displacement of every column over the step (eqs. 4, 10), then the friction (11-13).
    vq = kin.v + kin.omega * perp(off)
    aq = a + alpha * perp(off) - kin.omega**2 * off
    disp = vq * dt + 0.5 * aq * dt**2
    ff1, ff2, tau_f = calibrate.paper_friction(
        off, model.column_mass, s1, s2, kin.v, kin.omega, disp, gr.friction, gr.gravity
    )
    a = a + (ff1 + ff2) / model.mass  # + beta
    alpha = alpha + tau_f / model.izz
    rc = kin.rc + kin.v * dt + 0.5 * a * dt**2  # eq. 14
    th = kin.theta + kin.omega * dt + 0.5 * alpha * dt**2
    _, _, p_next = _belt_profiles(model, s_t, belt_speed, action)
    info = {
        "forces": jnp.stack([fv1[0], fv2[0], fv1[1], fv2[1]]),
        "friction": jnp.stack([ff1, ff2]),  # (2 belts, 2) N, eqs. 11-13
        "beta": (ff1 + ff2) / model.mass,
        "contact_area": jnp.stack([n1, n2]),
        "com_velocity": kin.v + a * dt,
        "omega": kin.omega + alpha * dt,
    }
    return _geom_state(model, p_next, rc, th), info


def explain(model: PriorModel, window, belt_speed, action, velocity=None, friction=None):
    """`predict` plus the physical quantities behind it (for explanations and checks).

    Returns (s_next (5,), info dict): 'forces' (4,) N = (F1, F2, F3, F4) (paper §2.3; for "slip" the mean
    friction on S1 / S2 over the step), 'contact_area' (2,) |S1|, |S2| in voxel footprints,
    'com_velocity' (2,) m/s and 'omega' rad/s at the end of the step; "slip" adds 'normal_load' (2,) N,
    "paper" adds 'friction' (2, 2) N (eqs. 11-13 on V1, V2) and 'beta' (2,) m/s^2.

    velocity, friction ("slip" only): the centre of mass's (vx, vy, omega) at t and the belt friction
    (2,) N at t, when known (from the previous predicted step: `rollout_sequence`); None: from the window.
    """
    window = jnp.asarray(window, jnp.float32)
    belt_speed = jnp.asarray(belt_speed, jnp.float32)
    action = jnp.asarray(action, jnp.float32)
    if model.params.variant == "paper":
        return _explain_paper(model, window, belt_speed, action)
    return _explain_slip(model, window, belt_speed, action, velocity, friction)


def predict(model: PriorModel, window, belt_speed, action) -> jax.Array:
    """The planar state after one control step with `action` (pure jnp; vmap over actions).

    Args:
      model: PriorModel (from `make_prior`).
      window: (W, 5) planar states s_{t-W+1..t} at control_dt spacing, W >= MIN_WINDOW (only the last
        three are used). Check it on the host with `check_window`.
      belt_speed: (2,) m/s, actual belt surface speeds at time t.
      action: (4,) (v1, v2, dp1, dp2): belt-speed setpoints (m/s) and position increments (m), clipped
        to the gripper's limits as the simulator does.
    Returns:
      (5,) s_{t+1} = (P1, P2, x, y, yaw); P_i next = clip(P_i + dp_i) to its range.
    """
    return explain(model, window, belt_speed, action)[0]


def next_belt_speed(model: PriorModel, belt_speed, action) -> jax.Array:
    """(2,) m/s belt speeds after one step: the setpoint, or as close as belt_accel_limit allows."""
    gr = model.gripper
    sp = jnp.clip(action[:2], -gr.belt_speed_limit, gr.belt_speed_limit)
    dv = gr.belt_accel_limit * gr.control_dt
    return belt_speed + jnp.clip(sp - belt_speed, -dv, dv)


def rollout_sequence(model: PriorModel, window, belt_speed, actions) -> jax.Array:
    """(H, 5) predicted states for the action sequence `actions` (H, 4). Each step feeds the predicted
    state back through the window, and the belt speeds follow the setpoints at <= belt_accel_limit
    (`next_belt_speed`). The first step takes its velocities from the window's finite differences, as
    `predict` does; with the "slip" variant and `carry_velocity` (default) every later step starts from the
    velocity (and belt friction) the previous predicted step ended with. Finite differences give a step's
    MEAN velocity, which is not the velocity it ends with when the motion inside the step is a pulse: a
    carriage step drags the box during its fast 20-30 ms move and the box then slides to rest on the
    stopped belt. Re-deriving the velocity from positions turns each pulse's mean into momentum the box
    does not have, and the drag ratchets up step after step (box with the centre of mass 7.5 cm over
    belt 1, belt 1 pulled 8 cm outwards: 6.9 cm of predicted drag, 1.6 cm in the simulator)."""
    window = jnp.asarray(window, jnp.float32)[-MIN_WINDOW:]
    belt_speed = jnp.asarray(belt_speed, jnp.float32)
    actions = jnp.asarray(actions, jnp.float32)
    if model.params.variant != "slip" or not model.params.carry_velocity:

        def step(carry, a):
            w, b = carry
            s = predict(model, w, b, a)
            return (jnp.concatenate([w[1:], s[None]]), next_belt_speed(model, b, a)), s

        _, states = jax.lax.scan(step, (window, belt_speed), actions)
        return states

    def step_carried(carry, a):
        w, b, u, f = carry
        s, info = _explain_slip(model, w, b, a, u, f)
        w = jnp.concatenate([w[1:], s[None]])
        return (w, next_belt_speed(model, b, a), info["velocity"], info["friction"]), s

    kin = calibrate.window_kinematics(window, model.com[:2], model.gripper.control_dt)
    u0 = jnp.concatenate([kin.v, kin.omega[None]])
    _, states = jax.lax.scan(step_carried, (window, belt_speed, u0, model.mass * kin.a0), actions)
    return states


def rollout(model: PriorModel, window, belt_speed, action, horizon: int, brake_steps: int = 0) -> jax.Array:
    """(horizon + brake_steps, 5) predicted states when `action` is held for `horizon` steps (setpoints
    held; position increments repeated), then the belts are braked for `brake_steps` steps (setpoints 0,
    no position change: they slow down at belt_accel_limit); see `rollout_sequence`."""
    action = jnp.asarray(action, jnp.float32)
    held = jnp.broadcast_to(action, (horizon, 4))
    return rollout_sequence(model, window, belt_speed, jnp.concatenate([held, jnp.zeros((brake_steps, 4))]))
