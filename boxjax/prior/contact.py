"""Where the belts touch the box, and how hard: the contact geometry and normal loads of the "slip"
prior (`boxjax.prior.predictor`), and the static tipping margin the planners' barrier uses.

Pure jnp on one state; `model` is a `prior.PriorModel` (only its box, gripper, params, com, offsets and
column_mass are read). Split out of prior.py; `prior` re-exports every public name.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from boxjax import geometry
from boxjax.config import BoxConfig, GripperConfig
from boxjax.geometry import rot2

_TINY = 1e-12
_MIN_WIDTH = 1e-3  # m, smallest projected footprint width (keeps the overlap formula well conditioned)
_MAX_VERTICES = 8  # vertices of the intersection of two rectangles, at most
_NO_TENSION_ITERATIONS = 4  # active-set passes of `normal_loads` (a box on 2 belts settles in 1-2)


def _adjugate(a):
    """The columns c0, c1, c2 of a's adjugate (a^-1 = [c0 c1 c2] / det) and det, guarded away from 0."""
    r0, r1, r2 = a[0], a[1], a[2]
    c0, c1, c2 = jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)
    det = jnp.dot(r0, c0)
    return c0, c1, c2, jnp.where(jnp.abs(det) > _TINY, det, jnp.where(det < 0, -_TINY, _TINY))


@jax.custom_jvp
def solve3(a, b):
    """x with a x = b for a (3, 3) by the adjugate (elementwise: cheap under vmap); det guarded.

    Differentiated implicitly, x' = a^-1 (b' - a' x), with the adjugate the value already formed (reverse
    mode transposes it: b's cotangent l = a^-T g, a's -l x^T), instead of through the cross products: the
    planner's gradient steps run it thousands of times per call (benchmarks/planner.py --structure-only).
    Where det is guarded (a singular a) this is the derivative of the guarded inverse's solve."""
    return _apply_inverse(*_adjugate(a), b)


def _apply_inverse(c0, c1, c2, det, v):
    """a^-1 v from a's adjugate columns and det (`_adjugate`)."""
    return (c0 * v[0] + c1 * v[1] + c2 * v[2]) / det


@solve3.defjvp
def _solve3_jvp(primals, tangents):
    a, b = primals
    da, db = tangents
    adj = _adjugate(a)
    x = _apply_inverse(*adj, b)
    return x, _apply_inverse(*adj, db - da @ x)


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


def voxel_contacts(model, s) -> Contacts:
    """The bottom voxels, weighted by their footprint's overlap with each belt (`contact_fractions`)."""
    fr = contact_fractions(s, model.box, model.gripper).reshape(2, -1)
    off = jnp.broadcast_to(model.offsets.reshape(1, -1, 2), (2, fr.shape[1], 2))
    return Contacts(off, fr)


def polygon_contacts(model, s) -> Contacts:
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
        # The belt's edge lines y = lo, y = hi (|x| <= L/2) and x = -+L/2 (lo <= y <= hi), each with the
        # side the belt is on: a footprint corner is inside a line's half-plane within `tol`, inside the
        # belt when inside all four, and an edge of the footprint crosses a line exactly where its two
        # corners are on different sides by that same test (where its corner is within `tol` outside the
        # line, the crossing is that corner again). One test for both, so a corner within micrometres of a
        # belt edge is one vertex or the other, never neither (two tests, a distance to the line for the
        # corner and a position along the edge for the crossing, once both refused a corner 1 um outside:
        # tests/test_prior.py). The belt's side of each line: keep * (q - level) >= 0.
        level = jnp.array([lo, hi, -half_l, half_l])
        axis = jnp.array([1, 1, 0, 0])
        keep = jnp.array([1.0, -1.0, 1.0, -1.0], jnp.float32)
        coord = jnp.where(axis[:, None] == 1, c[None, :, 1], c[None, :, 0])  # (4 lines, 4 corners)
        inside = keep[:, None] * (coord - level[:, None]) >= -tol
        in_b = jnp.all(inside, axis=0)
        cb = jnp.array([[-half_l, lo], [half_l, lo], [half_l, hi], [-half_l, hi]], jnp.float32)
        cb_box = (cb - s[geometry.X : geometry.Y + 1]) @ rot_t.T
        in_a = (jnp.abs(cb_box[:, 0]) < hx - 1e-6) & (jnp.abs(cb_box[:, 1]) < hy - 1e-6)
        start = c[None, :, :]  # (1, 4, 2)
        dd = d[None, :, :]
        # (4 lines, 4 edges c_k -> c_{k+1}):
        crosses = inside != jnp.roll(inside, -1, axis=1)
        num = level[:, None] - coord
        den = jnp.where(axis[:, None] == 1, dd[..., 1], dd[..., 0])
        ok = jnp.abs(den) > 1e-12
        t = num / jnp.where(ok, den, 1.0)
        pts = start + jnp.clip(t, 0.0, 1.0)[..., None] * dd  # (4, 4, 2)
        other = jnp.where(axis[:, None] == 1, pts[..., 0], pts[..., 1])
        other_lo = jnp.where(axis == 1, -half_l, lo)[:, None] - tol
        other_hi = jnp.where(axis == 1, half_l, hi)[:, None] + tol
        valid = crosses & ok & (other >= other_lo) & (other <= other_hi)
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


def stability_margin(model, s, n_directions: int = 32) -> jax.Array:
    """() m: how far the centre of mass lies inside the support polygon (negative: outside, the box tips).

    The support polygon is the convex hull of both belts' contact polygons (`polygon_contacts`); a rigid
    box at rest stays up while the vertical through its centre of mass meets it (the static tipping
    criterion; in MuJoCo it holds to 2 mm of the exact margin: tests/test_statics.py). The signed distance
    to the hull's boundary is the min over unit directions n of the hull's support function max_q n . q
    (q: contact vertices relative to the centre of mass): any direction gives at least the distance, the
    hull's edge normals give it exactly. `model.params.margin` chooses the directions:

    * "sampled" (the default until 2026-12-07; the planner's barrier was chosen with it):
      `n_directions` evenly spaced ones. They miss the edge normals, so near an edge the value
      over-estimates the distance: by 4.5 mm median, 10 mm at the 90th percentile and up to 18 mm over
      placements of random boxes within 2 cm of tipping (scripts/tip_calibration.py).
    * "refined" (the default, with the monitor's `tip_stop` 0.8 cm): 2 x `n_directions` evenly spaced ones,
      and the normal of the chord between the support vertices of every two neighbouring ones: where one hull
      edge lies between them, the chord is that edge, and the value exact. Over random boxes and states within
      5 cm of tipping it was exact to 0.1 mm in 99.3 % of them, at most 1.9 mm over; the default planner's
      step 1.2x the sampled one's (1.4x for 16 boxes vmapped, benchmarks/planner.py --margin-only).
    * "exact": the normals of every pair of contact vertices (every edge's among them): the distance
      itself, the reference the others are checked against; the planner's step 1.4x (2.6x for 16 boxes).

    No contact at all: -1 m.

    Why the planner needs it: with both belts spread out to their stops, a turned box rests on two small
    corner patches at opposite ends of a diagonal; a box whose centre of mass lies off that diagonal
    tips into the gap between the belts (measured in the simulator: box C at yaw 0.4 rad, belts at
    +-0.20 m, margin 3 mm, tipped). The planar prior cannot see this; the margin can.
    """
    c = polygon_contacts(model, jnp.asarray(s, jnp.float32))
    q = c.offsets.reshape(-1, 2)  # (2E, 2), box axes (the hull rotates with the box)
    valid = c.weights.reshape(-1) > 0
    ang = jnp.arange(n_directions, dtype=jnp.float32) * (2 * math.pi / n_directions)
    if model.params.margin == "refined":
        ang = jnp.arange(2 * n_directions, dtype=jnp.float32) * (math.pi / n_directions)
    dirs = jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=-1)  # (D, 2), counter-clockwise
    proj = jnp.where(valid[:, None], q @ dirs.T, -1.0)  # (V, D)
    margin = jnp.min(jnp.max(proj, axis=0))
    if model.params.margin == "refined":
        support = q[jnp.argmax(proj, axis=0)]  # (D, 2) the support vertex of each direction
        chord = jnp.roll(support, -1, axis=0) - support  # to the next direction's, counter-clockwise
        margin = jnp.minimum(
            margin, _support_min(q, valid, *_unit_normals(chord, jnp.ones(len(chord), bool)))
        )
    if model.params.margin == "exact":  # the sampled directions too: no contact, or no area, stays <= 0
        edge = (q[None, :, :] - q[:, None, :]).reshape(-1, 2)  # every pair of vertices
        use = (valid[:, None] & valid[None, :]).reshape(-1)
        margin = jnp.minimum(margin, _support_min(q, valid, *_unit_normals(edge, use)))
    return margin


def _unit_normals(edge, use):
    """(normals (N, 2), use (N,)): the outward unit normals of the edges (N, 2) of a counter-clockwise
    hull, (e_y, -e_x) / |e|, and which to use (`use` and not degenerate; no 0 / 0, nor in the gradient)."""
    use = use & (jnp.sum(edge * edge, axis=-1) > 1e-12)
    edge = jnp.where(use[:, None], edge, jnp.array([1.0, 0.0], jnp.float32))
    normal = jnp.stack([edge[:, 1], -edge[:, 0]], axis=-1)
    return normal / jnp.linalg.norm(normal, axis=-1, keepdims=True), use


def _support_min(q, valid, dirs, use) -> jax.Array:
    """min over the directions `dirs` (D, 2) that `use` (D,) of the support function of the points q
    (V, 2) that are `valid` (V,): -1 where no point is."""
    proj = jnp.where(valid[:, None], q @ dirs.T, -1.0)  # (V, D)
    return jnp.min(jnp.where(use, jnp.max(proj, axis=0), jnp.inf))


def normal_loads(model, contacts: Contacts, friction=None) -> jax.Array:
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
        return solve3(a, rhs)

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
