"""The action -> force mapping of paper §2.4 ("Mapping controls to forces"): data structure, fitting,
force recovery from observed transitions, and storage.

The paper maps each of the four action components to one force on the box:

  component 0 (belt 1 speed)    -> F1, along the conveyor x axis, applied to S1 (left belt, y < 0)
  component 1 (belt 2 speed)    -> F2, along x, applied to S2 (right belt, y > 0)
  component 2 (belt 1 position) -> F3, along the conveyor y axis, applied to S1
  component 3 (belt 2 position) -> F4, along y, applied to S2

and builds it offline from "disjoint" calibration transitions (only one component active per step) on a
box of uniform mass: the force of a transition is F(a) = M * delta(acc_c) - F_f1 - F_f2, the change of
the centre of mass acceleration the action caused, minus the frictions of eqs. 11-13 (`recover_forces`).
Each action value is then mapped to the mean force observed for it (`fit_force_map`); the spread is
kept too (the paper leaves its use to future work).

Action-value convention (the x axis of the map). The paper's actions are increments: dv moves a belt
surface faster or slower, dp moves a belt sideways. Our simulator takes belt-speed SETPOINTS, so the
value of a velocity component is the increment it commands: dv_i = clip(v_i, +-limit) - belt_speed_i
(m/s, setpoint minus the belt's actual speed before the step; the belt follows at <= belt_accel_limit).
The value of a position component is the (clipped) increment dp_i in m. `action_values` computes these
from an environment action, and both the calibration and the prior use it, so they agree.

The calibration itself (simulated episodes -> transitions -> forces -> map) is
`boxjax.training.calibration.calibrate_by_simulation`, the `boxjax calibrate` command. A map made with the
default configuration ships in boxjax/data/calibration.npz: `default_force_map(cfg)`.

Host-side functions (numpy): `fit_force_map`, `save`, `load`, `default_force_map`. Pure jnp (jit/vmap/grad
safe): `forces`, `action_values`, `window_kinematics`, `paper_friction`, `recover_forces`, `component_force`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry
from boxjax.config import BoxConfig, Config, GripperConfig
from boxjax.config_io import MISSING, field_mismatches
from boxjax.fileio import atomic_path, read_npz
from boxjax.massdist import mass_properties_from_masses

FORMAT_VERSION = 1
N_COMPONENTS = 4
FORCE_NAMES = ("F1", "F2", "F3", "F4")
# Config fields a force map depends on: a calibration made with different values is rejected by `load`.
CALIBRATION_FIELDS = (
    "gripper.friction",
    "gripper.control_dt",
    "gripper.gravity",
    "gripper.belt_speed_limit",
    "gripper.belt_accel_limit",
    "gripper.max_position_step",
    "gripper.belt_width",
    "box.size",
)
_TINY = 1e-12
SHIPPED_CALIBRATION = Path(__file__).parent.parent / "data" / "calibration.npz"


class CalibrationError(ValueError):
    """A calibration file is corrupt, of an unknown format, or was made for another configuration."""


class ForceMap(NamedTuple):
    """Action value -> force on the box, per action component (a pytree of arrays; paper §2.4).

    grid: (4, K) action values per component, strictly increasing along K. Components 0, 1: belt-speed
      increments dv_i (m/s); components 2, 3: position increments dp_i (m) (see module docstring).
    mean: (4, K) N, mean force for each grid value: F1, F2 along the conveyor x axis on S1 / S2, F3, F4
      along the conveyor y axis on S1 / S2.
    std: (4, K) N, standard deviation of the observed forces in each bin.
    count: (4, K) number of samples in each bin (0 where the bin was filled by interpolation).
    """

    grid: jax.Array
    mean: jax.Array
    std: jax.Array
    count: jax.Array


def forces(fm: ForceMap, values) -> jax.Array:
    """(4,) N: (F1, F2, F3, F4) for the action values (4,) (see `action_values`), by linear
    interpolation on each component's grid; constant beyond the ends of the grid. Differentiable in
    `values` (piecewise linear)."""
    return jax.vmap(jnp.interp)(jnp.asarray(values, fm.mean.dtype), fm.grid, fm.mean)


def action_values(action, belt_speed, gripper: GripperConfig) -> jax.Array:
    """(4,) the force map's input for an environment action.

    Args:
      action: (4,) (v1, v2, dp1, dp2): belt-speed setpoints (m/s) and position increments (m).
      belt_speed: (2,) actual belt surface speeds before the step (m/s).
    Returns:
      (dv1, dv2, dp1, dp2): setpoint minus belt speed (m/s, setpoints clipped to the speed limit) and the
      position increments clipped to max_position_step (m).
    """
    action = jnp.asarray(action)
    v = jnp.clip(action[:2], -gripper.belt_speed_limit, gripper.belt_speed_limit)
    dp = jnp.clip(action[2:], -gripper.max_position_step, gripper.max_position_step)
    return jnp.concatenate([v - belt_speed, dp])


def component_force(force_xy, component) -> jax.Array:
    """The scalar force of one component from a planar force (2,) N: x for components 0, 1 (F1, F2),
    y for 2, 3 (F3, F4)."""
    return jnp.where(jnp.asarray(component) < 2, force_xy[0], force_xy[1])


# ----------------------------------------------------------------------------------------------------------
# Fitting (host-side).


def fit_force_map(component, action_value, force, grid) -> ForceMap:
    """Bin calibration samples into a ForceMap (host-side numpy).

    Each sample goes to the bin of the grid value NEAREST to its action value, within its own component
    (values beyond the grid go to the end bins). A bin's mean and std (population std, 0 for one sample)
    are those of its samples. Empty bins take the mean and std linearly interpolated between the nearest
    non-empty bins of the same component, and the end value beyond the last non-empty bin (np.interp);
    their count stays 0 so they are recognisable.

    Args:
      component: (n,) int in 0..3, the active action component of each sample.
      action_value: (n,) the sample's action value (see `action_values`).
      force: (n,) N, the recovered force component (see `recover_forces`, `component_force`).
      grid: (4, K) action values per component, each strictly increasing, or (K,) shared by all four.
    Raises:
      ValueError: mismatched shapes, non-finite samples, a component outside 0..3, a grid that is not
        strictly increasing, or a component without any sample.
    """
    comp = np.asarray(component)
    val = np.asarray(action_value, dtype=np.float64)
    f = np.asarray(force, dtype=np.float64)
    g = np.asarray(grid, dtype=np.float64)
    if comp.ndim != 1 or val.shape != comp.shape or f.shape != comp.shape:
        raise ValueError(
            f"component, action_value, force must be 1-D of equal length, got shapes {comp.shape}, "
            f"{val.shape}, {f.shape}"
        )
    if g.ndim == 1:
        g = np.broadcast_to(g, (N_COMPONENTS, g.shape[0]))
    if g.ndim != 2 or g.shape[0] != N_COMPONENTS or g.shape[1] < 2:
        raise ValueError(f"grid must have shape (4, K) or (K,) with K >= 2, got {np.shape(grid)}")
    if not np.all(np.isfinite(g)) or np.any(np.diff(g, axis=1) <= 0):
        raise ValueError("grid values must be finite and strictly increasing along each component")
    if not (np.all(np.isfinite(val)) and np.all(np.isfinite(f))):
        raise ValueError("action_value and force must be finite")
    if comp.size and (not np.issubdtype(comp.dtype, np.integer) or comp.min() < 0 or comp.max() > 3):
        raise ValueError(f"component must be integers in 0..3, got {np.unique(comp)[:8]}")
    K = g.shape[1]
    mean = np.zeros((N_COMPONENTS, K))
    std = np.zeros((N_COMPONENTS, K))
    count = np.zeros((N_COMPONENTS, K), dtype=np.int32)
    for c in range(N_COMPONENTS):  # four components, host side; not a hot path
        sel = comp == c
        if not np.any(sel):
            raise ValueError(f"no calibration sample for component {c} ({FORCE_NAMES[c]})")
        v, y = val[sel], f[sel]
        b = np.argmin(np.abs(v[:, None] - g[c][None, :]), axis=1)
        cnt = np.bincount(b, minlength=K)
        s1 = np.bincount(b, weights=y, minlength=K)
        s2 = np.bincount(b, weights=y * y, minlength=K)
        full = cnt > 0
        m = np.where(full, s1 / np.maximum(cnt, 1), 0.0)
        var = np.where(full, s2 / np.maximum(cnt, 1) - m * m, 0.0)
        sd = np.sqrt(np.maximum(var, 0.0))
        mean[c] = np.interp(g[c], g[c][full], m[full])
        std[c] = np.interp(g[c], g[c][full], sd[full])
        count[c] = cnt
    return ForceMap(
        grid=jnp.asarray(g, jnp.float32),
        mean=jnp.asarray(mean, jnp.float32),
        std=jnp.asarray(std, jnp.float32),
        count=jnp.asarray(count),
    )


def default_grid(gripper: GripperConfig, k: int = 9) -> np.ndarray:
    """(4, k) a symmetric grid: dv in [-a dt, +a dt] (the most the belt can change in one control step)
    for components 0, 1, and dp in [-max_position_step, +max_position_step] for components 2, 3."""
    dv = gripper.belt_accel_limit * gripper.control_dt
    gv = np.linspace(-dv, dv, k)
    gp = np.linspace(-gripper.max_position_step, gripper.max_position_step, k)
    return np.stack([gv, gv, gp, gp]).astype(np.float32)


# ----------------------------------------------------------------------------------------------------------
# Kinematics from a window of planar states, and the paper's friction (eqs. 11-13). Pure jnp.


class Kinematics(NamedTuple):
    """Planar rigid-body kinematics of the centre of mass at the last state of a window (conveyor frame).

    rc (2,) m; v (2,) m/s; a0 (2,) m/s^2 (the acceleration before the next action, paper eq. 5's
    0_r''_c); theta () rad (the box yaw); omega () rad/s; alpha0 () rad/s^2.
    """

    rc: jax.Array
    v: jax.Array
    a0: jax.Array
    theta: jax.Array
    omega: jax.Array
    alpha0: jax.Array


def window_kinematics(window, com_xy, dt: float) -> Kinematics:
    """Centre-of-mass kinematics at the last of the last three planar states of `window`.

    The centre of mass is at r_c = r_geom + R(yaw) com_xy (paper §2.3: its offset from the observed
    geometric centre is known from the mass distribution). Velocities are second-order backward
    differences, v = (3 r_t - 4 r_{t-1} + r_{t-2}) / (2 dt) (exact under constant acceleration; the
    paper's first-order (r_t - r_{t-1}) / dt lags by half a step), accelerations second differences.
    Yaw differences are wrapped, so a window across +-pi is continuous.

    Args:
      window: (W, 5) planar states s_{t-W+1..t} at spacing dt, W >= 3.
      com_xy: (2,) m, centre of mass in the box frame.
    """
    w = window[-3:]
    th2 = w[2, 4]
    th1 = th2 - geometry.wrap_angle(w[2, 4] - w[1, 4])
    th0 = th1 - geometry.wrap_angle(w[1, 4] - w[0, 4])
    ths = jnp.stack([th0, th1, th2])
    rc = w[:, 2:4] + jax.vmap(lambda t: geometry.rot2(t) @ com_xy)(ths)
    v = (3 * rc[2] - 4 * rc[1] + rc[0]) / (2 * dt)
    a0 = (rc[2] - 2 * rc[1] + rc[0]) / dt**2
    omega = (3 * th2 - 4 * th1 + th0) / (2 * dt)
    alpha0 = (th2 - 2 * th1 + th0) / dt**2
    return Kinematics(rc=rc[2], v=v, a0=a0, theta=th2, omega=omega, alpha0=alpha0)


def paper_friction(offsets, column_mass, s1, s2, v, omega, disp, mu: float, g: float):
    """Frictions of paper eqs. 11-13 over V1 and V2 (the voxel columns above S1 and S2).

    For each column Q (all its voxels share the planar position), the friction direction is eq. 11,
    eta_Q = -dr_Q - proj(-dr_Q, -v_Q): the part of the voxel's displacement over the step that is
    orthogonal to its current velocity, reversed (the friction along the current velocity is already in
    the observed acceleration). eta_Q is normalised to a unit vector (eq. 11 gives a direction), faded
    to 0 where that orthogonal part is below 0.1 % of the displacement (along the velocity, or zero).
    Each voxel of the column contributes
    eta_Q mu_k g dM_Q (eq. 13).

    Args:
      offsets: (nx, ny, 2) m, planar positions of the columns relative to the centre of mass (conveyor
        frame axes).
      column_mass: (nx, ny) kg, mass of each voxel column.
      s1, s2: (nx, ny) {0, 1} contact masks; V_i are the columns with S_i = 1.
      v: (2,) m/s centre-of-mass velocity; omega: () rad/s.
      disp: (nx, ny, 2) m, displacement of each column over the step (predicted or observed).
    Returns:
      (f1, f2, tau): (2,) N frictions on V1 and V2, and () N m their torque about the centre of mass.
    """
    vq = v + omega * geometry.perp(offsets)
    proj = jnp.sum(disp * vq, -1, keepdims=True) / (jnp.sum(vq * vq, -1, keepdims=True) + _TINY) * vq
    orth = -(disp - proj)
    # Unit direction, faded out when the orthogonal part is below 0.1 % of the displacement: there the
    # direction is float32 round-off (a displacement along the velocity has no eq. 11 friction).
    scale2 = 1e-6 * jnp.sum(disp * disp, -1, keepdims=True) + 1e-18
    eta = orth * jax.lax.rsqrt(jnp.sum(orth * orth, -1, keepdims=True) + scale2)
    df = mu * g * column_mass[..., None] * eta  # (nx, ny, 2)
    f1 = jnp.sum(s1[..., None] * df, axis=(0, 1))
    f2 = jnp.sum(s2[..., None] * df, axis=(0, 1))
    tau = jnp.sum((s1 + s2) * geometry.cross2(offsets, df))
    return f1, f2, tau


def bottom_offsets_box(com, box: BoxConfig) -> jax.Array:
    """(nx, ny, 2) m: planar box-frame positions of the voxel columns relative to the centre of mass."""
    return jnp.asarray(geometry.bottom_voxel_centres_xy(box)) - com[:2]


def recover_forces(states, masses, box: BoxConfig, gripper: GripperConfig):
    """The paper's F(a) = M delta(acc_c) - F_f1 - F_f2 (§2.4) from one transition window.

    delta(acc_c) is the change of the centre-of-mass acceleration caused by the action applied between
    s_t and s_{t+1}: the mean acceleration over that step, 2 (r_{t+1} - r_t - v_t dt) / dt^2, minus the
    acceleration before it, a0 (from s_{t-2}, s_{t-1}, s_t; see `window_kinematics`). The frictions are
    those of eqs. 11-13 (`paper_friction`) with the OBSERVED column displacements over the step and the
    contact masks at s_t.

    Args:
      states: (4, 5) planar states s_{t-2}, s_{t-1}, s_t, s_{t+1} at spacing control_dt; the action was
        applied between s_t and s_{t+1}.
      masses: (nx, ny, nz) kg voxel masses of the calibration box (paper: uniform).
    Returns:
      (force (2,) N, conveyor frame x and y; a dict with 'm_delta_acc' (2,), 'friction1' (2,),
      'friction2' (2,)). Pick the component's scalar with `component_force`.
    """
    dt = gripper.control_dt
    props = mass_properties_from_masses(masses, box)
    com_xy = props.com[:2]
    kin = window_kinematics(states[:3], com_xy, dt)
    s_t, s_n = states[2], states[3]
    th_n = kin.theta + geometry.wrap_angle(s_n[4] - s_t[4])
    rc_n = s_n[2:4] + geometry.rot2(th_n) @ com_xy
    a_step = 2 * (rc_n - kin.rc - kin.v * dt) / dt**2
    m_dacc = props.mass * (a_step - kin.a0)
    off_box = bottom_offsets_box(props.com, box)
    off_t = off_box @ geometry.rot2(kin.theta).T
    off_n = off_box @ geometry.rot2(th_n).T
    disp = (rc_n - kin.rc) + (off_n - off_t)
    s1, s2 = geometry.contact_masks(s_t, box, gripper)
    f1, f2, _ = paper_friction(
        off_t, jnp.sum(masses, axis=2), s1, s2, kin.v, kin.omega, disp, gripper.friction, gripper.gravity
    )
    force = m_dacc - f1 - f2
    return force, {"m_delta_acc": m_dacc, "friction1": f1, "friction2": f2}


# ----------------------------------------------------------------------------------------------------------
# Storage: .npz without pickle, atomic write, format version and configuration.


def save(path, fm: ForceMap, config: Config, meta: dict | None = None) -> None:
    """Write a force map to `path` (.npz, no pickle) atomically: a temporary file in the same folder,
    then os.replace, so a reader never sees a half-written file.

    Stored: format_version, the four ForceMap arrays, the full configuration (JSON) the calibration was
    made with, and `meta` (any JSON-serialisable dict: seeds, number of transitions, ...).
    """
    path = os.fspath(path)
    arrays = {k: np.asarray(v) for k, v in fm._asdict().items()}
    for k in ("grid", "mean", "std"):
        if arrays[k].ndim != 2 or arrays[k].shape[0] != N_COMPONENTS:
            raise ValueError(f"ForceMap.{k} must have shape (4, K), got {arrays[k].shape}")
    payload = dict(
        format_version=np.asarray(FORMAT_VERSION, np.int64),
        config_json=np.asarray(json.dumps(dataclasses.asdict(config), sort_keys=True)),
        meta_json=np.asarray(json.dumps(meta or {}, sort_keys=True)),
        **arrays,
    )
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, **payload)


def load(path, expected_config: Config) -> tuple[ForceMap, dict]:
    """Read a force map written by `save`; returns (ForceMap, meta).

    Raises:
      CalibrationError: the file is missing, not a valid .npz, of another format version, has missing /
        malformed / non-finite arrays, or was made with a configuration that differs from
        `expected_config` in any of CALIBRATION_FIELDS (the message names each field, stored vs expected).
    """
    path = os.fspath(path)
    data = read_npz(path, CalibrationError, "calibration")
    required = ("format_version", "config_json", "meta_json", *ForceMap._fields)
    missing = [k for k in required if k not in data]
    if missing:
        raise CalibrationError(f"calibration file {path!r} is corrupt: missing entries {missing}")
    try:
        version = int(data["format_version"])
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"calibration file {path!r}: unreadable format_version") from e
    if version != FORMAT_VERSION:
        raise CalibrationError(
            f"calibration file {path!r} has format version {version}; "
            f"this code reads version {FORMAT_VERSION}"
        )
    try:
        stored = json.loads(str(data["config_json"]))
        meta = json.loads(str(data["meta_json"]))
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"calibration file {path!r} is corrupt: unreadable config or meta JSON") from e
    diffs = [
        f"{name}: missing in the file (expected {want!r})"
        if have is MISSING
        else f"{name}: file has {have!r}, expected {want!r}"
        for name, have, want in field_mismatches(
            stored, dataclasses.asdict(expected_config), CALIBRATION_FIELDS
        )
    ]
    if diffs:
        raise CalibrationError(
            f"calibration file {path!r} was made for another configuration: " + "; ".join(diffs)
        )
    grid, mean, std, count = (np.asarray(data[k]) for k in ForceMap._fields)
    shape = grid.shape
    if len(shape) != 2 or shape[0] != N_COMPONENTS or shape[1] < 2:
        raise CalibrationError(
            f"calibration file {path!r} is corrupt: grid has shape {shape}, need (4, K>=2)"
        )
    for name, arr in (("mean", mean), ("std", std), ("count", count)):
        if arr.shape != shape:
            raise CalibrationError(
                f"calibration file {path!r} is corrupt: {name} has shape {arr.shape}, grid {shape}"
            )
    for name, arr in (("grid", grid), ("mean", mean), ("std", std)):
        if not np.issubdtype(arr.dtype, np.floating) or not np.all(np.isfinite(arr)):
            raise CalibrationError(f"calibration file {path!r} is corrupt: {name} is not finite floats")
    if np.any(np.diff(grid, axis=1) <= 0):
        raise CalibrationError(f"calibration file {path!r} is corrupt: grid is not strictly increasing")
    fm = ForceMap(
        grid=jnp.asarray(grid, jnp.float32),
        mean=jnp.asarray(mean, jnp.float32),
        std=jnp.asarray(std, jnp.float32),
        count=jnp.asarray(count.astype(np.int32)),
    )
    return fm, meta


@functools.lru_cache(maxsize=4)
def _load_default(path: str, cfg: Config) -> ForceMap:
    try:
        return load(path, cfg)[0]
    except CalibrationError as e:
        raise CalibrationError(
            f"the shipped calibration cannot be used: {e}. Make one for this configuration with "
            "`boxjax calibrate --out FILE` (boxjax.training.calibration.calibrate_by_simulation) and pass "
            "its force map explicitly"
        ) from e


def default_force_map(cfg: Config) -> ForceMap:
    """The shipped force map (boxjax/data/calibration.npz, made by `boxjax calibrate` with the default
    configuration; the command is in its meta), loaded once per config and checked against `cfg`.

    Raises:
      CalibrationError: the file is missing or corrupt, or `cfg` differs from the calibration's
        configuration in any of CALIBRATION_FIELDS (friction, control_dt, belt limits, box size, ...).
    """
    return _load_default(str(SHIPPED_CALIBRATION), cfg)
