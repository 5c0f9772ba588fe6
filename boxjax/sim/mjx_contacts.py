"""Box-belt contacts for MJX as the overlap polygon of the touching faces (`GripperConfig.mjx_box_contacts`).

MJX's own box-box collider (`mujoco.mjx._src.collision_convex.box_box`, MuJoCo 4.0) keeps 4 of the overlap
polygon's vertices and, when fewer than 4 penetrate, repeats some: a box resting on a belt along a line
gets its 4 contacts at the line's 2 ends (3 and 1 in a state of the exploration, where that end carries
three times the load and the friction).
At sub-micrometre penetration of nearly parallel faces (a hopping box landing) it can also report no
contact where there is one. Native MuJoCo's collider drops vertices of its own: a box resting on a belt's
edge along a line gets one contact instead of two as soon as the box pitches by 2e-5 rad
(tests/test_mjx_contacts.py), and along the exploration of 3 random boxes it reported 3,607 contacts, 3,606
of them among the polygon's 4,447 penetrating vertices (docs/results/simulation.md#colliders).

`box_box_contacts` below is the face-face clip with every vertex, for fixed shapes: the reference face is
the face of either box with the largest separating distance along its normal; the incident face is the
other box's face most opposed to it; the contacts are the vertices of the two faces' overlap projected on
the reference plane (incident corners inside the reference face, reference corners inside the incident
face, crossings of their edges, boundaries included: 24 candidates, the distinct ones compacted into 8
slots), each at its depth below the reference plane, placed midway between the surfaces, with the
reference face's normal. A vertex enters and leaves the set at zero depth, so the loads change without
jumps, on the polygon the physics prior's `polygon_contacts` assumes. Edge-edge contacts of two boxes at a
large angle are not modelled (a box lying on a belt meets it face on; MJX's own collider reduces edge
contacts to one point too).

`box_contacts("polygon")` installs it for the MJX programs traced inside the `with` block only (`MjxEnv`
traces its programs there), so other MJX models in the same process keep MJX's collider.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp

from boxjax.config import MJX_BOX_CONTACTS

NCON = 8  # a convex quadrilateral clipped by a rectangle has at most 8 vertices
_NONE = 1.0  # dist of an empty slot (MJX's convention: inactive, > 0)
# m: a vertex this close to a face's edge counts as on it, and candidates this close together are one
# vertex. Above float32 rounding at the belts' scale (0.4 m x 6e-8), far below any physical length here.
_TOL = 1e-7


def _sep_along_faces(pos_a, mat_a, size_a, pos_b, mat_b, size_b):
    """(6,) separating distance of box b from box a along each of a's outward face normals (+x, +y, +z,
    -x, -y, -z of a's axes): b's lowest extent along the normal minus a's face offset. Negative: overlap."""
    normals = jnp.concatenate([mat_a.T, -mat_a.T])
    radius = jnp.abs(normals @ mat_b) @ size_b  # b's support radius along n: sum_j size_b[j] |n . b_j|
    return normals @ (pos_b - pos_a) - radius - jnp.concatenate([size_a, size_a])


def _face(mat, size, axis, sign):
    """Centre offset, in-plane unit axes (u, v) and half sizes of the face of a box with outward normal
    sign * mat[:, axis]."""
    ia, ib = (axis + 1) % 3, (axis + 2) % 3
    centre = sign * size[axis] * mat[:, axis]
    return centre, mat[:, ia], mat[:, ib], size[ia], size[ib]


def _inside_quad(q, quad):
    """(P,) bool: points q (P, 2) inside the convex quadrilateral `quad` (4, 2) or within _TOL of its
    boundary, either winding."""
    e = jnp.roll(quad, -1, axis=0) - quad  # (4, 2)
    rel = q[:, None, :] - quad[None]  # (P, 4, 2)
    # signed distance of q from each edge's line, times the edge's length
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]  # (P, 4)
    tol = _TOL * jnp.linalg.norm(e, axis=1)[None]
    return jnp.all(cross >= -tol, axis=1) | jnp.all(cross <= tol, axis=1)


def _polygon_contacts(ref_pos, ref_mat, ref_size, ref_axis, ref_sign, inc_pos, inc_mat, inc_size):
    """Contacts of the incident box against one reference face: dist (8,), pos (8, 3), normal (3,) from
    the reference box towards the incident one."""
    fc, u, v, hu, hv = _face(ref_mat, ref_size, ref_axis, ref_sign)
    fc = ref_pos + fc
    n = ref_sign * ref_mat[:, ref_axis]
    # The incident face: the incident box's face whose outward normal is most opposed to n.
    dots = n @ inc_mat  # (3,)
    ia = jnp.argmax(jnp.abs(dots))
    isign = -jnp.sign(dots[ia])
    isign = jnp.where(isign == 0, 1.0, isign)
    ic, iu, iv, ihu, ihv = _face(inc_mat, inc_size, ia, isign)
    ic = inc_pos + ic
    n_inc = isign * inc_mat[:, ia]
    signs = jnp.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    inc_corners = ic + (signs[:, :1] * ihu) * iu + (signs[:, 1:] * ihv) * iv  # (4, 3), a cycle
    # 2-D coordinates in the reference face (origin at its centre, axes u, v).
    inc2 = jnp.stack([(inc_corners - fc) @ u, (inc_corners - fc) @ v], axis=1)  # (4, 2)
    ref2 = signs * jnp.array([hu, hv])  # (4, 2), a cycle

    def in_ref(q):
        return (jnp.abs(q[:, 0]) <= hu + _TOL) & (jnp.abs(q[:, 1]) <= hv + _TOL)

    # Candidates: incident corners in the reference face, reference corners in the incident face, and the
    # crossings of the incident face's 4 edges with the reference face's 4 edge lines.
    a, e = inc2, jnp.roll(inc2, -1, axis=0) - inc2  # edges a_k -> a_k+1
    level = jnp.array([hu, -hu, hv, -hv])
    axis = jnp.array([0, 0, 1, 1])
    num = level[:, None] - jnp.where(axis[:, None] == 0, a[None, :, 0], a[None, :, 1])  # (4 lines, 4 edges)
    den = jnp.where(axis[:, None] == 0, e[None, :, 0], e[None, :, 1])
    ok = jnp.abs(den) > _TOL  # an edge along the line has no single crossing (its ends are corners)
    t = num / jnp.where(ok, den, 1.0)
    cross = a[None] + jnp.clip(t, 0.0, 1.0)[..., None] * e[None]  # (4, 4, 2)
    other = jnp.where(axis[:, None] == 0, cross[..., 1], cross[..., 0])
    other_half = jnp.where(axis == 0, hv, hu)[:, None]
    cross_ok = ok & (t >= 0.0) & (t <= 1.0) & (jnp.abs(other) <= other_half + _TOL)
    q = jnp.concatenate([inc2, ref2, cross.reshape(-1, 2)])  # (24, 2)
    valid = jnp.concatenate([in_ref(inc2), _inside_quad(ref2, inc2), cross_ok.reshape(-1)])
    # Depth: the incident face's plane over the reference plane, h(q) along n (negative: penetrating).
    nn = jnp.dot(n_inc, n)  # <= -1/sqrt(3): the incident face is the most opposed one
    h = -(jnp.dot(n_inc, fc - ic) + q[:, 0] * jnp.dot(n_inc, u) + q[:, 1] * jnp.dot(n_inc, v)) / nn
    # One vertex once: drop a candidate that lies on an earlier valid one.
    d2 = jnp.sum(jnp.square(q[:, None] - q[None]), axis=-1)
    earlier = jnp.tril(jnp.ones((q.shape[0],) * 2, bool), -1)
    dup = jnp.any(earlier & (d2 < _TOL**2) & valid[None, :], axis=1)
    keep = valid & ~dup
    # Compact: the kept vertices first (deepest first), into NCON slots.
    score = jnp.where(keep, 1.0 + jnp.tanh(-h), -1.0 - jnp.arange(q.shape[0]) * 1e-3)
    _, idx = jax.lax.top_k(score, NCON)
    qk, hk, kk = q[idx], h[idx], keep[idx]
    pos = fc + qk[:, :1] * u + qk[:, 1:] * v + (0.5 * hk)[:, None] * n
    dist = jnp.where(kk, hk, _NONE)
    return dist, pos, n


def box_box_contacts(pos1, mat1, size1, pos2, mat2, size2):
    """dist (8,), pos (8, 3), frame (8, 3, 3) of two boxes (centres, rotation matrices, half sizes): the
    overlap polygon's vertices of the reference face and the face most opposed to it, the normal pointing
    from box 1 to box 2 (MuJoCo's convention). Slots without a contact have dist 1."""
    s12 = _sep_along_faces(pos1, mat1, size1, pos2, mat2, size2)
    s21 = _sep_along_faces(pos2, mat2, size2, pos1, mat1, size1)
    i1, i2 = jnp.argmax(s12), jnp.argmax(s21)
    # Nearly parallel faces separate by nearly the same distance either way; prefer box 1's face unless
    # box 2's separates clearly more (a tie flips nothing physical: the overlap polygon is the same).
    use2 = s21[i2] > s12[i1] + 1e-6
    i = jnp.where(use2, i2, i1)
    pick = lambda a, b: jnp.where(use2, b, a)  # noqa: E731 (b when box 2 holds the reference face)
    dist, pos, n = _polygon_contacts(
        pick(pos1, pos2), pick(mat1, mat2), pick(size1, size2), i % 3, jnp.where(i < 3, 1.0, -1.0),
        pick(pos2, pos1), pick(mat2, mat1), pick(size2, size1),
    )  # fmt: skip
    normal = jnp.where(use2, -n, n)  # from box 1 towards box 2
    frame = _frame(normal)
    return dist, pos, jnp.broadcast_to(frame, (NCON, 3, 3))


def _frame(n):
    """MuJoCo's contact frame for normal n (rows: normal, two tangents), as mju_makeFrame / MJX."""
    from mujoco.mjx._src import math as mjx_math  # noqa: PLC0415 (MJX is imported on first use)

    return mjx_math.make_frame(n)


def _collide(m, d, key, geom):
    """MJX collision-function signature: (model, data, function key, (P, 2) geom pairs) -> dist (P*8,),
    pos (P*8, 3), frame (P*8, 3, 3), pair-major."""
    g1, g2 = geom.T
    mats = d.geom_xmat.reshape(-1, 3, 3)
    dist, pos, frame = jax.vmap(box_box_contacts)(
        d.geom_xpos[g1], mats[g1], m.geom_size[g1], d.geom_xpos[g2], mats[g2], m.geom_size[g2]
    )
    return dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3)


_collide.ncon = NCON


@contextlib.contextmanager
def box_contacts(kind: str = "polygon"):
    """Within the block, MJX programs traced (and `mjx.make_data` called) collide box pairs with `kind`:
    "polygon" (`box_box_contacts`, 8 slots per pair) or "mjx" (MJX's own collider, unchanged)."""
    if kind not in MJX_BOX_CONTACTS:
        raise ValueError(f"MJX box contacts must be one of {MJX_BOX_CONTACTS}, got {kind!r}")
    if kind == "mjx":
        yield
        return
    from mujoco.mjx._src import collision_driver  # noqa: PLC0415 (MJX is imported on first use)
    from mujoco.mjx._src.types import GeomType  # noqa: PLC0415

    table = collision_driver._COLLISION_FUNC
    k = (GeomType.BOX, GeomType.BOX)
    if k not in table:
        raise RuntimeError(
            "this MJX has no box-box entry in mujoco.mjx._src.collision_driver._COLLISION_FUNC: "
            "boxjax's box contacts cannot be installed (set gripper.mjx_box_contacts = 'mjx')"
        )
    old = table[k]
    table[k] = _collide
    try:
        yield
    finally:
        table[k] = old
