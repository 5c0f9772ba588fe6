"""The belts' friction on the box in the "slip" prior (`boxjax.prior.predictor`): the slip of each contact
element,
the friction's convex potential (`dissipation`) for the elliptic and pyramidal cones, and its force,
Jacobian and majoriser (`friction_force`) for the implicit velocity solve.

Pure jnp; split out of prior.py, which re-exports `dissipation` and `friction_force`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from boxjax.geometry import perp


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
