"""Box-belt contacts for MJX (`GripperConfig.mjx_box_contacts`): native MuJoCo's rules, or the overlap
polygon of the touching faces.

Three colliders find where the box touches a belt, and they differ where it matters for turning a box:

- native MuJoCo's (`mjc_BoxBox`, MuJoCo 4.0): a separating-axis test over the 15 axes (6 face normals, 9
  edge-cross directions). When a face axis wins, the incident face clipped by the reference face: every
  penetrating vertex of the overlap polygon. When an edge-cross axis wins, ONE contact at the midpoint of the
  two supporting edges' closest points. A box lying nearly flat on a belt at micrometres of penetration
  often makes an edge-cross axis a few micro-radians from the face normal win (along it the boxes overlap
  less than along the face normal, by more than 5 % of the face depth), so native reports a single
  contact on 36 % of the box-belt steps in contact along explorations, on 25 % where two or more polygon
  vertices penetrate (benchmarks/contact_kinds.py, docs/results/simulation.md#colliders).
- MJX's own (`mujoco.mjx._src.collision_convex.box_box`): 4 of the polygon's vertices, some repeated when
  fewer penetrate (a line contact's 4 contacts at its 2 ends, 3 and 1), and at sub-micrometre penetration
  of nearly parallel faces sometimes none.
- the polygon (`box_box_contacts`): every vertex of the overlap polygon, whichever axis wins.

`native_box_box` ports native's rules to fixed shapes (8 slots; native's float32 or float64 tolerances
by the inputs' dtype): in float64 it gives native's contacts to 1e-9 m along explorations and at random
orientations (tests/test_mjx_contacts.py). It is the one that makes MJX simulate what native MuJoCo
simulates, on which the physics prior and H were fitted.

`box_box_contacts` is the face-face clip with every vertex, for fixed shapes: the reference face is
the face of either box with the largest separating distance along its normal; the incident face is the
other box's face most opposed to it; the contacts are the vertices of the two faces' overlap projected on
the reference plane (incident corners inside the reference face, reference corners inside the incident
face, crossings of their edges, boundaries included: 24 candidates, the distinct ones compacted into 8
slots), each at its depth below the reference plane, placed midway between the surfaces, with the
reference face's normal. A vertex enters and leaves the set at zero depth, so the loads change without
jumps, on the polygon the physics prior's `polygon_contacts` assumes. Edge-edge contacts of two boxes at a
large angle are not modelled (a box lying on a belt meets it face on).

`box_contacts(kind)` installs one of them for the MJX programs traced inside the `with` block only (`MjxEnv`
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


# Native MuJoCo's rounding scales (engine_collision_box.c, by precision) and rules, for `native_box_box`.
_NATIVE_EPS = {  # dtype: (SEPEPS, PAREPS, SGNEPS)
    jnp.dtype(jnp.float32): (1e-6, 1e-7, 1e-5),
    jnp.dtype(jnp.float64): (1e-13, 1e-16, 1e-9),
}
_EDGEBIAS = 1e-6  # relative penalty on an edge axis against the best face axis
_MINVAL = 1e-15  # mjMINVAL


def native_box_box(pos1, mat1, size1, pos2, mat2, size2):
    """`box_box_contacts`' outputs under native MuJoCo's rules (`mjc_BoxBox`, MuJoCo 4.0: separating-axis
    test over the 15 axes, face axes preferred on near-ties, an edge axis within ~8 degrees of the best face
    axis replaced by it unless it beats the face by more than 5 % of the face depth): when an edge axis wins,
    ONE contact at the midpoint of the two supporting edges' closest points, along that axis; otherwise the
    face clip (the same polygon as `box_box_contacts`, the reference face chosen as native chooses it).

    For nearly parallel faces at shallow penetration the winning axis is often an edge-cross axis a few
    micro-radians from the face normal, so a box lying on a belt gets a single contact on about a third
    of the belt-steps of an exploration (docs/results/simulation.md#colliders): this is the collider that
    makes MJX simulate what native MuJoCo simulates."""
    sepeps, pareps, sgneps = _NATIVE_EPS[jnp.result_type(pos1, mat1, size1)]
    rot = mat1.T @ mat2  # box 2's axes in box 1's frame (columns)
    rotabs = jnp.abs(rot)
    pos21 = mat1.T @ (pos2 - pos1)
    pos12 = mat2.T @ (pos1 - pos2)
    septol = sepeps * (jnp.sum(size1) + jnp.sum(size2))  # the pair's margin is 0
    # Face axes: box 1's three, then box 2's (the first maximum wins, as native's strict >).
    sep_faces = jnp.concatenate(
        [jnp.abs(pos21) - size1 - rotabs @ size2, jnp.abs(pos12) - size2 - rotabs.T @ size1]
    )
    code_face = jnp.argmax(sep_faces)
    sep_face = sep_faces[code_face]
    separated = jnp.any(sep_faces > septol)
    # Edge axes e_i x (box 2's axis j), in box 1's frame, in native's order.
    sep_best, code = sep_face, jnp.asarray(-1)
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            ax1, ax2 = -rot[i2, j], rot[i1, j]
            norm2 = ax1 * ax1 + ax2 * ax2
            ok = norm2 >= pareps
            inv = 1.0 / jnp.sqrt(jnp.where(ok, norm2, 1.0))
            ax1, ax2 = ax1 * inv, ax2 * inv
            r1 = size1[i1] * jnp.abs(ax1) + size1[i2] * jnp.abs(ax2)
            a21 = ax1 * rot[i1, j1] + ax2 * rot[i2, j1]
            a22 = ax1 * rot[i1, j2] + ax2 * rot[i2, j2]
            r2 = size2[j1] * jnp.abs(a21) + size2[j2] * jnp.abs(a22)
            sep = jnp.abs(ax1 * pos21[i1] + ax2 * pos21[i2]) - r1 - r2
            separated = separated | (ok & (sep > septol))
            better = ok & (sep - _EDGEBIAS * jnp.abs(sep) > sep_best) & (sep > sep_face)
            sep_best = jnp.where(better, sep, sep_best)
            code = jnp.where(better, 6 + 3 * i + j, code)
    # The edge axis of `code` (unit, box 1's frame); a near-parallel edge that separates little more
    # than the best face gives way to it.
    ei, ej = jnp.maximum(code - 6, 0) // 3, jnp.maximum(code - 6, 0) % 3
    col = rot[:, ej]
    axis = jnp.cross(jnp.eye(3, dtype=rot.dtype)[ei], col)  # (0, -rot[i2, j], rot[i1, j]) rolled to i
    axis = axis / jnp.maximum(jnp.linalg.norm(axis), _MINVAL)
    face_dir = jnp.where(code_face < 3, jnp.eye(3, dtype=rot.dtype)[code_face % 3], rot[:, code_face % 3])
    face_dot = jnp.abs(axis @ face_dir)
    give_way = (face_dot > 0.99) & (sep_best < sep_face + 0.05 * jnp.abs(sep_face) + _MINVAL)
    edge = (code >= 6) & ~give_way
    e_dist, e_pos, e_normal = _edge_contact(pos1, mat1, size1, size2, rot, pos21, ei, ej, axis, sgneps)
    separated = separated | (edge & (e_dist > septol))
    # Face clip against native's reference face (box 1's on a face tie).
    ref2 = code_face >= 3
    a = code_face % 3
    sgn = jnp.where(jnp.where(ref2, pos12[a], pos21[a]) >= 0, 1.0, -1.0)  # side of the incident box
    pick = lambda u, v: jnp.where(ref2, v, u)  # noqa: E731 (v when box 2 holds the reference face)
    f_dist, f_pos, n = _polygon_contacts(
        pick(pos1, pos2), pick(mat1, mat2), pick(size1, size2), a, sgn,
        pick(pos2, pos1), pick(mat2, mat1), pick(size2, size1),
    )  # fmt: skip
    f_normal = jnp.where(ref2, -n, n)
    slot0 = jnp.arange(NCON) == 0
    dist = jnp.where(edge, jnp.where(slot0, e_dist, _NONE), f_dist)
    dist = jnp.where(separated, _NONE, dist)
    pos = jnp.where(edge, jnp.broadcast_to(e_pos, (NCON, 3)), f_pos)
    frame = _frame(jnp.where(edge, e_normal, f_normal))
    return dist, pos, jnp.broadcast_to(frame, (NCON, 3, 3))


def _edge_contact(pos1, mat1, size1, size2, rot, pos21, i, j, axis, sgneps):
    """Native's edge-edge contact for edge axis (i, j): dist, world position and normal (box 1 -> 2) at
    the midpoint of the closest points of the two supporting edges; an axis component below `sgneps` makes
    its corner ambiguous, and both are tried (the closest pair kept, native's order on ties)."""
    eye = jnp.eye(3, dtype=rot.dtype)
    axis = jnp.where(axis @ pos21 < 0, -axis, axis)  # from box 1 towards box 2
    a2 = rot.T @ axis  # the axis in box 2's frame
    i1, i2 = (i + 1) % 3, (i + 2) % 3
    j1, j2 = (j + 1) % 3, (j + 2) % 3
    amb1 = jnp.where(jnp.abs(axis[i1]) < sgneps, i1, jnp.where(jnp.abs(axis[i2]) < sgneps, i2, -1))
    amb2 = jnp.where(jnp.abs(a2[j1]) < sgneps, j1, jnp.where(jnp.abs(a2[j2]) < sgneps, j2, -1))
    d2 = rot[:, j]
    b = d2[i]  # d1 . d2, d1 = e_i
    denom = 1 - b * b
    c1_base = jnp.where(axis >= 0, size1, -size1) * (1 - eye[i])  # corner of box 1's edge (component i: 0)
    cc_base = jnp.where(a2 >= 0, -size2, size2) * (1 - eye[j])  # box 2's, along -axis, in its frame
    best = None
    for v1 in (0, 1):
        for v2 in (0, 1):
            c1 = jnp.where((v1 == 1) & (jnp.arange(3) == amb1), -c1_base, c1_base)
            cc = jnp.where((v2 == 1) & (jnp.arange(3) == amb2), -cc_base, cc_base)
            c2 = rot @ cc + pos21
            e = c2 - c1
            d1e, d2e = e[i], d2 @ e
            s = jnp.where(denom < _MINVAL, 0.0, (d1e - b * d2e) / jnp.where(denom < _MINVAL, 1.0, denom))
            s = jnp.clip(s, -size1[i], size1[i])
            t = jnp.clip(b * s - d2e, -size2[j], size2[j])
            s = jnp.clip(d1e + b * t, -size1[i], size1[i])
            p1 = c1 + s * eye[i]
            p2 = c2 + t * d2
            gap2 = jnp.sum(jnp.square(p2 - p1))
            tried = ((v1 == 0) | (amb1 >= 0)) & ((v2 == 0) | (amb2 >= 0))
            if best is None:
                best = (gap2, p1, p2)
            else:
                take = tried & (gap2 < best[0])
                best = tuple(jnp.where(take, new, old) for new, old in zip((gap2, p1, p2), best, strict=True))
    _, w1, w2 = best
    dist = (w2 - w1) @ axis
    mid = 0.5 * (w1 + w2)
    return dist, mat1 @ mid + pos1, mat1 @ axis


def _frame(n):
    """MuJoCo's contact frame for normal n (rows: normal, two tangents), as mju_makeFrame / MJX."""
    from mujoco.mjx._src import math as mjx_math  # noqa: PLC0415 (MJX is imported on first use)

    return mjx_math.make_frame(n)


def _collider(contacts):
    """An MJX collision function (model, data, function key, (P, 2) geom pairs) -> dist (P*8,),
    pos (P*8, 3), frame (P*8, 3, 3), pair-major, from a per-pair `contacts` function."""

    def collide(m, d, key, geom):
        g1, g2 = geom.T
        mats = d.geom_xmat.reshape(-1, 3, 3)
        dist, pos, frame = jax.vmap(contacts)(
            d.geom_xpos[g1], mats[g1], m.geom_size[g1], d.geom_xpos[g2], mats[g2], m.geom_size[g2]
        )
        return dist.reshape(-1), pos.reshape(-1, 3), frame.reshape(-1, 3, 3)

    collide.ncon = NCON
    return collide


_COLLIDERS = {"polygon": _collider(box_box_contacts), "native": _collider(native_box_box)}


@contextlib.contextmanager
def box_contacts(kind: str = "polygon"):
    """Within the block, MJX programs traced (and `mjx.make_data` called) collide box pairs with `kind`:
    "polygon" (`box_box_contacts`, 8 slots per pair), "native" (`native_box_box`, 8 slots) or "mjx" (MJX's
    own collider, unchanged)."""
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
    table[k] = _COLLIDERS[kind]
    try:
        yield
    finally:
        table[k] = old
