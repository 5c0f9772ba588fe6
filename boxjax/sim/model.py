"""The MuJoCo model of the two-belt gripper, and applying a box's mass distribution to it.

One MJCF serves both backends (docs/design.md#simulation):
- each belt is a flat box geom on an x-slide joint driven by a velocity servo; the slab is re-centred to
  x = 0 after every control step, so a finite slab emulates an endless belt surface;
- each belt rides on a carriage on a y-slide joint under a position servo (the belt position P_i);
- the box is a free body with one box geom; its mass, centre of mass and inertia come from a voxel mass
  distribution (`massdist`), written into the model and followed by `mj_setConst` so that MuJoCo's
  derived constants (subtree mass, inverse weights, mean inertia) match the new box.

Belt speed limit and acceleration limit are enforced by MuJoCo itself: the belt actuator is an integrator
(`dyntype="integrator"`) whose activation is the belt's commanded surface speed, clamped to the speed limit
(`actrange`), and whose control is the commanded acceleration, clamped to the acceleration limit
(`ctrlrange`). The force is a stiff velocity servo kv * (act - qvel).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import NamedTuple

import mujoco
import numpy as np

from boxjax import massdist
from boxjax.config import Config

# Servo gains. The belt drive is stiff enough that the heaviest box (10 kg, mu 0.5: ~50 N of friction)
# changes the belt speed by < 0.25 % of its limit; the carriage servo holds its position within ~1 mm
# under the same load and settles well inside one 0.05 s control step.
BELT_ARMATURE = 50.0  # kg, reflected inertia of the belt drive
BELT_KV = 2.0e4  # N s/m
CARRIAGE_MASS = 5.0  # kg
CARRIAGE_KP = 5.0e4  # N/m (natural frequency 100 rad/s with the carriage mass)
CARRIAGE_KV = 1.0e3  # N s/m (critically damped)

# Actuator order (ctrl / act layout).
BELT1_V, BELT2_V, CARRIAGE1_P, CARRIAGE2_P = range(4)


def mjcf(cfg: Config) -> str:
    """The gripper and a placeholder box as an MJCF string (SI units)."""
    g, b = cfg.gripper, cfg.box
    hl, hw, hh = b.half_size
    bl, bw, bt = g.belt_length / 2, g.belt_width / 2, g.belt_thickness / 2
    vmax, amax = g.belt_speed_limit, g.belt_accel_limit
    carriages = []
    for i, rng in enumerate((g.p1_range, g.p2_range), start=1):
        carriages.append(f"""
    <body name="carriage{i}" pos="0 0 {-bt}">
      <joint name="carriage{i}_y" type="slide" axis="0 1 0" range="{rng[0]} {rng[1]}" ref="0"/>
      <inertial pos="0 0 0" mass="{CARRIAGE_MASS}" diaginertia="0.1 0.1 0.1"/>
      <body name="belt{i}">
        <joint name="belt{i}_x" type="slide" axis="1 0 0" armature="{BELT_ARMATURE}"/>
        <geom name="belt{i}" type="box" size="{bl} {bw} {bt}" mass="1" contype="0" conaffinity="1"
              rgba="{0.2 + 0.5 * (i == 1)} 0.3 {0.2 + 0.5 * (i == 2)} 1"/>
      </body>
    </body>""")
    actuators = []
    for i in (1, 2):
        actuators.append(
            f'<general name="belt{i}_v" joint="belt{i}_x" dyntype="integrator" gaintype="fixed" '
            f'gainprm="{BELT_KV}" biastype="affine" biasprm="0 0 {-BELT_KV}" ctrlrange="{-amax} {amax}" '
            f'actlimited="true" actrange="{-vmax} {vmax}"/>'
        )
    for i, rng in ((1, g.p1_range), (2, g.p2_range)):
        actuators.append(
            f'<position name="carriage{i}_p" joint="carriage{i}_y" kp="{CARRIAGE_KP}" kv="{CARRIAGE_KV}" '
            f'ctrlrange="{rng[0]} {rng[1]}"/>'
        )
    # The box touches only the belts, through explicit pairs: they can carry a friction reference
    # (solreffriction, used by MuJoCo with the elliptic cone only) that geoms cannot.
    mu = g.friction
    srf = f' solreffriction="{g.friction_timeconst} 1"' if g.friction_timeconst > 0 else ""
    pairs = "".join(
        f'\n    <pair geom1="box" geom2="belt{i}" condim="3" friction="{mu} {mu} 0.005 0.0001 0.0001"{srf}/>'
        for i in (1, 2)
    )
    # The placeholder box inertial is deliberately off-centre and rotated: a box compiled with its centre
    # of mass at the geometric centre gets body_sameframe = 1, and native MuJoCo then silently ignores a
    # later change of body_ipos / body_iquat (docs/design.md#simulation-pitfalls). Every real box overwrites
    # these values.
    return f"""<mujoco model="boxjax_gripper">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{g.timestep}" integrator="implicitfast" gravity="0 0 {-g.gravity}"
          cone="{g.contact_cone}"/>
  <default>
    <geom friction="{g.friction} 0.005 0.0001" condim="3"/>
  </default>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>{"".join(carriages)}
    <body name="box" pos="0 0 {hh}">
      <freejoint name="box"/>
      <inertial pos="0.01 0.01 0.005" quat="0.9 0.1 0.1 0.1" mass="1" diaginertia="0.01 0.02 0.03"/>
      <geom name="box" type="box" size="{hl} {hw} {hh}" contype="0" conaffinity="0" rgba="0.8 0.6 0.3 1"/>
    </body>
  </worldbody>
  <contact>{pairs}
  </contact>
  <actuator>
    {chr(10).join("    " + a for a in actuators).strip()}
  </actuator>
</mujoco>
"""


class Ids(NamedTuple):
    """Indices looked up once by name (Brax / Playground convention)."""

    box_body: int
    box_qpos: int  # start of the box free joint in qpos (x, y, z, qw, qx, qy, qz)
    box_dof: int  # start of the box free joint in qvel
    belt_qpos: tuple[int, int]  # belt x-slides
    belt_dof: tuple[int, int]
    carriage_qpos: tuple[int, int]  # carriage y-slides (qpos = P_i)
    carriage_dof: tuple[int, int]


def ids(m: mujoco.MjModel) -> Ids:
    jnt = lambda name: m.joint(name)  # noqa: E731
    return Ids(
        box_body=m.body("box").id,
        box_qpos=int(jnt("box").qposadr[0]),
        box_dof=int(jnt("box").dofadr[0]),
        belt_qpos=tuple(int(jnt(f"belt{i}_x").qposadr[0]) for i in (1, 2)),
        belt_dof=tuple(int(jnt(f"belt{i}_x").dofadr[0]) for i in (1, 2)),
        carriage_qpos=tuple(int(jnt(f"carriage{i}_y").qposadr[0]) for i in (1, 2)),
        carriage_dof=tuple(int(jnt(f"carriage{i}_y").dofadr[0]) for i in (1, 2)),
    )


@lru_cache(maxsize=8)
def template(cfg: Config) -> mujoco.MjModel:
    """The compiled gripper model with the placeholder box (cached per config; do not mutate)."""
    return mujoco.MjModel.from_xml_string(mjcf(cfg))


def initial_qpos(cfg: Config, m: mujoco.MjModel) -> np.ndarray:
    """Box resting centred on the belts, yaw 0; belts at their nominal centre-lines."""
    idx = ids(m)
    q = m.qpos0.copy()
    q[idx.box_qpos : idx.box_qpos + 7] = [0, 0, cfg.box.half_size[2], 1, 0, 0, 0]
    for k, p in zip(idx.carriage_qpos, cfg.gripper.belt_y0, strict=True):
        q[k] = p
    for k in idx.belt_qpos:
        q[k] = 0.0
    return q


# Model fields that depend on the box (found by compiling different boxes and comparing every field; see
# tests/test_sim.py::test_box_fields_cover_everything_that_changes). MJX does not recompute derived
# constants, so all of them travel per world.
BOX_FIELDS = (
    "body_mass",
    "body_ipos",
    "body_iquat",
    "body_inertia",
    "body_subtreemass",
    "body_invweight0",
    "dof_invweight0",
)
STAT_FIELDS = ("meaninertia",)


def box_model(cfg: Config, dist: massdist.MassDistribution) -> mujoco.MjModel:
    """A native model copy whose box carries the mass distribution `dist` (derived constants recomputed).

    Raises:
      massdist.DistributionError: if `dist` is not a valid distribution for `cfg.box`.
    """
    dist = massdist.validate(dist, cfg.box)
    props = massdist.mass_properties(dist, cfg.box)
    diag, quat = massdist.principal_axes(np.asarray(props.inertia, dtype=np.float64))
    m = _copy(template(cfg))
    b = ids(m).box_body
    m.body_mass[b] = float(props.mass)
    m.body_ipos[b] = np.asarray(props.com, dtype=np.float64)
    m.body_iquat[b] = quat
    m.body_inertia[b] = diag
    m.body_sameframe[b] = 0  # never let MuJoCo skip the inertial frame (see mjcf())
    mujoco.mj_setConst(m, mujoco.MjData(m))
    if not np.allclose(m.body_ipos[b], np.asarray(props.com), atol=1e-7):  # the pitfall, checked
        raise RuntimeError("MuJoCo did not take the box's centre of mass; body_sameframe pitfall")
    return m


def box_params(m: mujoco.MjModel) -> dict[str, np.ndarray]:
    """The per-box model fields of a native model (see BOX_FIELDS), as float32 arrays for MJX."""
    out = {f: np.array(getattr(m, f), dtype=np.float32) for f in BOX_FIELDS}
    out.update({f"stat.{f}": np.array(getattr(m.stat, f), dtype=np.float32) for f in STAT_FIELDS})
    return out


def _copy(m: mujoco.MjModel) -> mujoco.MjModel:
    import copy

    return copy.copy(m)


def describe_model(cfg: Config) -> dict:
    """Plain-data summary of the simulated hardware (for the README and `--json`)."""
    return {
        "gripper": dataclasses.asdict(cfg.gripper),
        "n_substeps": cfg.gripper.n_substeps,
        "belt_kv": BELT_KV,
        "belt_armature": BELT_ARMATURE,
        "carriage_kp": CARRIAGE_KP,
        "carriage_kv": CARRIAGE_KV,
    }
