"""Planar geometry shared by the simulator, the task rules and the planner (pure jnp).

The planar state is the paper's 5-d vector s = (P1, P2, x, y, yaw): the y positions of the left and right
belt centre-lines, and the planar pose of the box's geometric centre in the conveyor frame (m, m, m, m,
rad). All functions here act on ONE state; vmap them for batches.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from boxjax.config import BoxConfig, GripperConfig

# Indices into the 5-d planar state.
P1, P2, X, Y, YAW = range(5)
STATE_NAMES = ("P1", "P2", "x", "y", "yaw")


def wrap_angle(a):
    """Wrap radians to [-pi, pi)."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


def yaw_from_quat(q):
    """Yaw (rotation about z, rad) of a unit quaternion q = (w, x, y, z)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def tilt_from_quat(q):
    """Angle (rad) between the box's z axis and the world z axis, for a unit quaternion (w, x, y, z)."""
    x, y = q[..., 1], q[..., 2]
    cos_tilt = 1 - 2 * (x * x + y * y)  # world-z component of the rotated z axis
    return jnp.arccos(jnp.clip(cos_tilt, -1.0, 1.0))


def bottom_voxel_centres_xy(box: BoxConfig) -> np.ndarray:
    """(nx, ny, 2) box-frame x, y of the bottom-layer voxel centres (m)."""
    nx, ny, _ = box.grid
    dx, dy, _ = box.voxel_size
    hx, hy, _ = box.half_size
    cx = -hx + (np.arange(nx) + 0.5) * dx
    cy = -hy + (np.arange(ny) + 0.5) * dy
    return np.stack(np.meshgrid(cx, cy, indexing="ij"), axis=-1).astype(np.float32)


def box_to_world_xy(s, pts_xy):
    """Map box-frame planar points (..., 2) to the conveyor frame for the planar state s (5,)."""
    c, si = jnp.cos(s[YAW]), jnp.sin(s[YAW])
    px, py = pts_xy[..., 0], pts_xy[..., 1]
    return jnp.stack([s[X] + c * px - si * py, s[Y] + si * px + c * py], axis=-1)


def contact_masks(s, box: BoxConfig, gripper: GripperConfig):
    """The paper's S1, S2 (eq. 2): bottom-layer voxels resting on the left / right belt.

    A bottom voxel belongs to S_i when its centre lies over belt i's surface (|y - P_i| <= width / 2 and
    |x| <= length / 2). This is computed from the pose and belt positions alone, as the robot's vision
    would, so the planner can predict it for future states too.

    Args:
      s: (5,) planar state (P1, P2, x, y, yaw).
    Returns:
      (S1, S2): two (nx, ny) float32 masks in {0, 1}; index [i, j] is the voxel at box-frame column i
      (along the box length) and row j (along its width) of the bottom layer (k = 0).
    """
    w = box_to_world_xy(s, jnp.asarray(bottom_voxel_centres_xy(box)))
    on_x = jnp.abs(w[..., 0]) <= gripper.belt_length / 2
    half = gripper.belt_width / 2
    s1 = (jnp.abs(w[..., 1] - s[P1]) <= half) & on_x
    s2 = (jnp.abs(w[..., 1] - s[P2]) <= half) & on_x
    return s1.astype(jnp.float32), s2.astype(jnp.float32)


def balance_offset(s):
    """y_geom - (P1 + P2) / 2 (m), signed: where the box's geometric centre is from midway between belts
    (index arithmetic only: numpy in, numpy out, so the host-side monitor pays no dispatch for it)."""
    return s[Y] - 0.5 * (s[P1] + s[P2])


def balance_error(s):
    """|y_geom - (P1 + P2) / 2| (m): how far the box's geometric centre is from midway between belts."""
    return jnp.abs(balance_offset(s))


def rot2(theta) -> jax.Array:
    """(2, 2) planar rotation matrix."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.array([[c, -s], [s, c]])


def perp(r) -> jax.Array:
    """z x r for planar vectors r (..., 2): (-r_y, r_x). omega * perp(r) is the velocity of a point at r."""
    return jnp.stack([-r[..., 1], r[..., 0]], axis=-1)


def cross2(r, f) -> jax.Array:
    """z component of r x f for planar vectors (..., 2)."""
    return r[..., 0] * f[..., 1] - r[..., 1] * f[..., 0]
