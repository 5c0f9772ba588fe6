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

Modules: this one holds the settings (`PriorParams`), the per-box model (`make_prior`), the step of
either variant and the rollouts; where the belts touch the box and how hard (contact elements, normal
loads, the tipping margin) is `prior.contact`, the friction law `prior.friction`. Their public names are
re-exported here.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from boxjax import geometry, planning
from boxjax.config import BoxConfig, GripperConfig
from boxjax.geometry import cross2, perp, rot2
from boxjax.massdist import mass_properties_from_masses
from boxjax.prior import force_map as calibrate
from boxjax.prior.contact import (
    normal_loads,
    polygon_contacts,
    solve3,
    stability_margin,
    voxel_contacts,
)
from boxjax.prior.force_map import ForceMap
from boxjax.prior.friction import dissipation, friction_force

VARIANTS = ("slip", "paper")
NORMALS = ("pressure", "columns")
CONTACTS = ("voxels", "polygon")
CONES = ("gripper", "elliptic", "pyramidal")
MARGINS = ("sampled", "exact", "refined")
_BOX, _GRIPPER = BoxConfig(), GripperConfig()


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
    unroll: the step's loops over its substeps and solver iterations are unrolled into straight-line code
      ("slip"): the same arithmetic in fewer, larger operations, and no loop whose condition a GPU reads
      back to the host every iteration. The default planner's call then runs 2.3x fewer operations and
      6.6x fewer loop iterations (43.7 k / 140 against 102 k / 922; 40.2 k since the two candidates'
      solves are batched); on a 2-core CPU it is 5-9 % faster, compiles in up to 50 % more time
      (`benchmarks/planner.py --structure-only`), and turned as many boxes (284 / 300 both, oracle,
      seeds 0-2). False: `lax.scan` loops (the prior before 2026-12-06).
    margin: the static tipping margin (`stability_margin`): "sampled" (default) the support function on
      32 directions, which over-estimates the distance near an edge (p90 10 mm, up to 18 mm); "refined"
      64 directions and their support chords (exact to 0.1 mm in 99 % of states, at most 2 mm over);
      "exact" the distance itself (docs/results/faults.md, "The static criterion against MuJoCo").
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
    unroll: bool = True
    # The stability margin's directions (`contact.stability_margin`): "refined" since 2026-12-07 (with the
    # monitor's tip_stop 0.8 cm, over 2,200 paired episodes against "sampled" with 1.5 cm: turned 1,987 vs
    # 1,981, lost 3 vs 6, boxes kept 1.3 mm further from tipping; docs/results/faults.md).
    margin: str = "refined"

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown prior variant {self.variant!r}; choose one of {VARIANTS}")
        if self.normal not in NORMALS:
            raise ValueError(f"unknown normal-load model {self.normal!r}; choose one of {NORMALS}")
        if self.contact not in CONTACTS:
            raise ValueError(f"unknown contact model {self.contact!r}; choose one of {CONTACTS}")
        if self.margin not in MARGINS:
            raise ValueError(f"unknown stability margin {self.margin!r}; choose one of {MARGINS}")
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

    def planar_com(self) -> jax.Array:
        """(2,) m, the centre of mass in the box frame (x, y)."""
        return self.com[:2]


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


# ----------------------------------------------------------------------------------------------------------
# The step's belt motion.


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
            # Both candidates' 3 x 3 systems in one vmapped solve: half the operations of two solves.
            lhs = jnp.stack([mmat - h * jac, mmat + h * a_mm])
            rhs = jnp.stack([mdiag * (uc - u0) - h * force, mdiag * u0 + h * b_mm])
            sol = jax.vmap(solve3)(lhs, rhs)
            u_newton, u_mm = uc - sol[0], sol[1]
            cand = jnp.stack([u_newton, u_mm])
            phi = objectives(cand)
            return jnp.where(phi[0] < phi[1], u_newton, u_mm), fb

        u1, fbs = jax.lax.scan(iterate, u0, None, length=prm.n_iterations, unroll=prm.unroll)
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
    (rc, th, u, f_end), (fbs, loads_k) = jax.lax.scan(
        substep, (kin.rc, kin.theta, u0, f0), ks, unroll=prm.unroll
    )
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
      window: (W, 5) planar states s_{t-W+1..t} at control_dt spacing, W >= planning.MIN_WINDOW (only the last
        three are used). Check it on the host with `planning.check_window`.
      belt_speed: (2,) m/s, actual belt surface speeds at time t.
      action: (4,) (v1, v2, dp1, dp2): belt-speed setpoints (m/s) and position increments (m), clipped
        to the gripper's limits as the simulator does.
    Returns:
      (5,) s_{t+1} = (P1, P2, x, y, yaw); P_i next = clip(P_i + dp_i) to its range.
    """
    return explain(model, window, belt_speed, action)[0]


def rollout_sequence(
    model: PriorModel, window, belt_speed, actions, correction=None, velocity=None
) -> jax.Array:
    """(H, 5) predicted states for the action sequence `actions` (H, 4). Each step feeds the predicted
    state back through the window, and the belt speeds follow the setpoints at <= belt_accel_limit
    (`planning.next_belt_speed`). The first step takes its velocities from the window's finite differences, as
    `predict` does; with the "slip" variant and `carry_velocity` (default) every later step starts from the
    velocity (and belt friction) the previous predicted step ended with. Finite differences give a step's
    MEAN velocity, which is not the velocity it ends with when the motion inside the step is a pulse: a
    carriage step drags the box during its fast 20-30 ms move and the box then slides to rest on the
    stopped belt. Re-deriving the velocity from positions turns each pulse's mean into momentum the box
    does not have, and the drag ratchets up step after step (box with the centre of mass 7.5 cm over
    belt 1, belt 1 pulled 8 cm outwards: 6.9 cm of predicted drag, 1.6 cm in the simulator).

    correction ("slip" with `carry_velocity` only): None, or a pure function
    `correction(w, b, a, u, s, info) -> (s', velocity')` applied after every predicted step (window w,
    belt speed b, action a and start velocity u of the step, the prior's next state s and its `explain`
    info, whose "velocity" the next step starts from): how a learned residual (`boxjax.prior.residual`)
    corrects the prior in place.

    velocity ("slip" with `carry_velocity` only): None, or the centre of mass's (vx, vy, omega) at t when
    known better than the window's finite differences (conveyor axes, m/s and rad/s); the first step
    starts from it."""
    window = jnp.asarray(window, jnp.float32)[-planning.MIN_WINDOW :]
    belt_speed = jnp.asarray(belt_speed, jnp.float32)
    actions = jnp.asarray(actions, jnp.float32)
    if model.params.variant != "slip" or not model.params.carry_velocity:
        if correction is not None or velocity is not None:
            raise ValueError(
                "a correction of the prior or a start velocity needs the 'slip' variant with carry_velocity"
            )

        def step(carry, a):
            w, b = carry
            s = predict(model, w, b, a)
            return (jnp.concatenate([w[1:], s[None]]), planning.next_belt_speed(model, b, a)), s

        _, states = jax.lax.scan(step, (window, belt_speed), actions)
        return states

    def step_carried(carry, a):
        w, b, u, f = carry
        s, info = _explain_slip(model, w, b, a, u, f)
        u_next = info["velocity"]
        if correction is not None:
            s, u_next = correction(w, b, a, u, s, info)
        w = jnp.concatenate([w[1:], s[None]])
        return (w, planning.next_belt_speed(model, b, a), u_next, info["friction"]), s

    kin = calibrate.window_kinematics(window, model.com[:2], model.gripper.control_dt)
    u0 = jnp.concatenate([kin.v, kin.omega[None]]) if velocity is None else jnp.asarray(velocity, jnp.float32)
    _, states = jax.lax.scan(step_carried, (window, belt_speed, u0, model.mass * kin.a0), actions)
    return states


def rollout(model: PriorModel, window, belt_speed, action, horizon: int, brake_steps: int = 0) -> jax.Array:
    """(horizon + brake_steps, 5) predicted states when `action` is held for `horizon` steps (setpoints
    held; position increments repeated), then the belts are braked for `brake_steps` steps (setpoints 0,
    no position change: they slow down at belt_accel_limit); see `rollout_sequence`."""
    action = jnp.asarray(action, jnp.float32)
    held = jnp.broadcast_to(action, (horizon, 4))
    return rollout_sequence(model, window, belt_speed, jnp.concatenate([held, jnp.zeros((brake_steps, 4))]))
