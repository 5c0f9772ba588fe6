"""A box placed at rest on the belts in MuJoCo: does it stay up? The simulator's side of the static tipping
criterion that the physics prior (`prior.stability_margin`) and the monitor's tipping watch rely on.

`hold(cfg, m, s)` places the box flat and at rest at the planar state s (P1, P2, x, y, yaw), the
carriages at P1 / P2 and the belts at rest, then holds the gripper still for `seconds` and returns the
largest tilt the box reached and `contact_hull_margin`, the distance of its centre of mass inside the
convex hull of the contacts MuJoCo generated between the box and the belts at the placement (the support
MuJoCo actually gives it, against the prior's overlap polygons). scripts/tip_calibration.py measures both
against the prior's margins (docs/results/faults.md, "The static criterion against MuJoCo").
"""

from __future__ import annotations

import math
from typing import NamedTuple

import mujoco
import numpy as np

from boxjax import geometry
from boxjax.config import Config
from boxjax.sim import model


class Held(NamedTuple):
    peak_tilt: float  # rad, the largest tilt of the box while held (its z axis from the vertical)
    hull_margin: float  # m, the centre of mass inside MuJoCo's contact hull at the placement (< 0: outside)
    n_contacts: int  # box-belt contacts MuJoCo generated at the placement


def random_states(rng: np.random.Generator, n: int, cfg: Config) -> np.ndarray:
    """(n, 5) float32 planar states (P1, P2, x, y, yaw) a turn passes through: the carriages anywhere in
    their ranges, the box within 4 cm (y) of the belts' middle and 5 cm (x) of the gripper's centre,
    yaw in [0, pi / 2]."""
    g = cfg.gripper
    s = np.stack(
        [
            rng.uniform(*g.p1_range, n),
            rng.uniform(*g.p2_range, n),
            rng.uniform(-0.05, 0.05, n),
            rng.uniform(-0.04, 0.04, n),
            rng.uniform(0.0, math.pi / 2, n),
        ],
        axis=1,
    )
    s[:, geometry.Y] += 0.5 * (s[:, geometry.P1] + s[:, geometry.P2])
    return s.astype(np.float32)


def place_at_rest(cfg: Config, m: mujoco.MjModel, s, sink: float = 3e-4) -> tuple[mujoco.MjData, np.ndarray]:
    """(data, ctrl): the box flat at the planar state s (P1, P2, x, y, yaw), `sink` m into the belts (so
    that its contacts exist), every velocity and the belt drives at rest, the carriages at P1 / P2; ctrl
    holds it so (belt accelerations 0, carriage targets P1 / P2)."""
    s = np.asarray(s, np.float64)
    idx = model.ids(m)
    d = mujoco.MjData(m)
    d.qpos[:] = model.initial_qpos(cfg, m)
    b = idx.box_qpos
    yaw = s[geometry.YAW]
    d.qpos[b : b + 7] = [
        s[geometry.X],
        s[geometry.Y],
        cfg.box.half_size[2] - sink,
        math.cos(yaw / 2),
        0.0,
        0.0,
        math.sin(yaw / 2),
    ]
    d.qpos[idx.carriage_qpos[0]], d.qpos[idx.carriage_qpos[1]] = s[geometry.P1], s[geometry.P2]
    d.qvel[:] = 0.0
    d.act[:] = 0.0
    mujoco.mj_forward(m, d)
    ctrl = np.zeros(m.nu)
    ctrl[model.CARRIAGE1_P], ctrl[model.CARRIAGE2_P] = s[geometry.P1], s[geometry.P2]
    return d, ctrl


def contact_hull_margin(m: mujoco.MjModel, d: mujoco.MjData) -> tuple[float, int]:
    """(margin m, contacts): how far the box's centre of mass lies (in the horizontal plane) inside the
    convex hull of its contacts in `d` (negative: outside; -inf: no contact), measured as the prior's
    exact margin is (`PriorParams(margin="exact")`): the min over the normals of every pair of contact
    points of the hull's support function, the edges' among them."""
    box = m.body("box").id
    bodies = m.geom_bodyid
    pts = [
        c.pos[:2] for c in (d.contact[k] for k in range(d.ncon)) if box in (bodies[c.geom1], bodies[c.geom2])
    ]
    if not pts:
        return -math.inf, 0
    q = np.asarray(pts) - d.xipos[box][:2]
    edge = (q[None, :, :] - q[:, None, :]).reshape(-1, 2)
    edge = edge[np.einsum("ij,ij->i", edge, edge) > 1e-12]
    if len(edge) == 0:  # one point (or coincident ones): no area
        return -float(np.linalg.norm(q[0])), len(pts)
    normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1, keepdims=True)
    return float(np.min(np.max(q @ normal.T, axis=0))), len(pts)


def hold(cfg: Config, m: mujoco.MjModel, s, seconds: float = 2.0) -> Held:
    """The box placed at rest at s (`place_at_rest`), the gripper held still for `seconds`."""
    d, ctrl = place_at_rest(cfg, m, s)
    hull, n = contact_hull_margin(m, d)
    box = model.ids(m).box_body
    quats = []
    for _ in range(round(seconds / cfg.gripper.control_dt)):
        d.ctrl[:] = ctrl
        mujoco.mj_step(m, d, nstep=cfg.gripper.n_substeps)
        quats.append(d.xquat[box].copy())
    peak = float(np.max(np.asarray(geometry.tilt_from_quat(np.asarray(quats))), initial=0.0))
    return Held(peak, hull, n)
