"""The physics-prior predictor (paper §2.3): hand-computed cases, guards, gradients, batching."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import geometry, massdist, planning, prior
from boxjax.config import DEFAULT
from boxjax.planners import paper as planner
from boxjax.prior import force_map as calibrate
from boxjax.prior.force_map import ForceMap
from boxjax.sim import make_env

BOX, G = DEFAULT.box, DEFAULT.gripper
DT = G.control_dt
REST = jnp.array([-0.1, 0.1, 0.0, 0.0, 0.0])
# Compiled once per PriorParams (static) and shared by the tests: compiling dominates their run time.
batched = jax.jit(jax.vmap(prior.predict, in_axes=(None, None, None, 0)))
explain = jax.jit(prior.explain)


def one(model, window, belt_speed, action):
    return explain(model, window, belt_speed, action)[0]


def _const_map(f1=0.0, f2=0.0, f3=0.0, f4=0.0):
    """A force map that returns the same forces for every action value."""
    grid = jnp.asarray(calibrate.default_grid(G, 3))
    mean = jnp.tile(jnp.array([f1, f2, f3, f4])[:, None], (1, 3))
    return ForceMap(grid, mean, jnp.zeros_like(mean), jnp.ones((4, 3), jnp.int32))


def _linear_map():
    grid = jnp.asarray(calibrate.default_grid(G, 5))
    mean = grid * jnp.array([300.0, 300.0, 2000.0, 2000.0])[:, None]
    return ForceMap(grid, mean, jnp.zeros_like(mean), jnp.ones((4, 5), jnp.int32))


def _uniform():
    return massdist.voxel_masses(massdist.named("uniform", BOX), BOX)


def _heavy(i, j, k=0, m=2.0):
    return jnp.full(BOX.grid, BOX.voxel_eps).at[i, j, k].add(m)


def _moving_window(v=(0.02, -0.01), omega=0.3, s=REST):
    """Three states of a box moving with constant velocity and yaw rate."""
    k = jnp.arange(3.0)[:, None] - 2
    d = jnp.concatenate([jnp.zeros((3, 2)), k * DT * jnp.array([*v, omega])], axis=1)
    return s[None] + d


# ----------------------------------------------------------------------------------------------------------
# Hand-computed cases.


def test_heavy_voxel_mass_properties():
    model = prior.make_prior(_heavy(2, 1, 0), None, BOX, G)
    c = massdist.voxel_centres(BOX)[2, 1, 0]
    assert np.allclose(np.asarray(model.com), c, atol=2e-4)
    dx, dy, _ = BOX.voxel_size
    own = 2.0 * (dx**2 + dy**2) / 12
    assert float(model.izz) == pytest.approx(own, rel=0.2)  # plus the eps of the other 255 voxels
    assert float(model.column_mass[2, 1]) == pytest.approx(2.0 + 4 * BOX.voxel_eps)


@pytest.mark.parametrize("row, torque_sign", [(1, 0), (0, -1)])
def test_paper_single_heavy_voxel_under_f1(row, torque_sign):
    # One 2 kg voxel over belt 1 (rows 0..2 are S1 at yaw 0), F1 = 20 N along x on S1, box at rest.
    # Friction (eqs. 11-13) at rest opposes the frictionless displacement, mu g per kg of V1 / V2.
    masses = _heavy(3, row)
    model = prior.make_prior(masses, _const_map(f1=20.0), BOX, G, variant="paper")
    s_next, info = explain(model, planning.initial_window(REST), jnp.zeros(2), jnp.zeros(4))
    assert np.allclose(np.asarray(info["forces"]), [20.0, 0, 0, 0])
    m = float(jnp.sum(masses))
    # The heavy voxel's column dominates the friction: beta ~ -mu g (2 kg) / M along x.
    beta_x = float(info["beta"][0])
    assert beta_x == pytest.approx(-G.friction * G.gravity * 2.0 / m, rel=0.02)
    ax = 20.0 / m + beta_x
    # Centre of mass: r_c' = r_c + (F / M + beta) dt^2 / 2 (eq. 14 from rest; 0r''_c = 0).
    rc = s_next[2:4] + geometry.rot2(s_next[geometry.YAW]) @ model.com[:2] - model.com[:2]
    assert float(rc[0]) == pytest.approx(0.5 * ax * DT**2, rel=1e-3)
    assert abs(float(rc[1])) < 1e-4
    # Torque of F1 about the centre of mass: -(mean y of S1 - y_c) F1 (eq. 8). Row 1 is S1's centroid
    # row: ~0 (up to the eps masses); row 0 is outside it: negative.
    yaw = float(s_next[geometry.YAW])
    if torque_sign == 0:
        assert abs(yaw) < 0.01
    else:
        assert yaw < -0.1  # a 2 kg point-like mass has a tiny I_zz: a large turn in one step


def test_paper_symmetric_uniform_box_opposite_forces():
    # Uniform box, F1 = +F on S1 (y < 0), F2 = -F on S2 (y > 0): zero net force; torque
    # sum_S1 (-y) F / |S1| + sum_S2 (-y)(-F) / |S2| = F (mean y of S2 - mean y of S1) = 0.1875 F (> 0),
    # friction torque at rest -mu g sum_V m_col |r_col| (eq. 11 opposes the rotation).
    F = 40.0
    masses = _uniform()
    model = prior.make_prior(masses, _const_map(f1=F, f2=-F), BOX, G, variant="paper")
    s_next, info = explain(model, planning.initial_window(REST), jnp.zeros(2), jnp.zeros(4))
    s1, s2 = geometry.contact_masks(REST, BOX, G)
    yc = geometry.bottom_voxel_centres_xy(BOX)
    mean_y1 = float(np.sum(np.asarray(s1) * yc[..., 1]) / np.sum(np.asarray(s1)))
    mean_y2 = float(np.sum(np.asarray(s2) * yc[..., 1]) / np.sum(np.asarray(s2)))
    assert mean_y2 - mean_y1 == pytest.approx(0.1875)
    tau = F * (mean_y2 - mean_y1)
    col = np.asarray(jnp.sum(masses, axis=2))
    v = np.asarray(s1 + s2)
    tau_f = -G.friction * G.gravity * np.sum(v * col * np.linalg.norm(yc, axis=-1))
    izz = float(jnp.sum(masses)) * (0.4**2 + 0.3**2) / 12
    assert float(model.izz) == pytest.approx(izz, rel=1e-4)
    yaw = 0.5 * (tau + tau_f) / izz * DT**2
    assert yaw > 0
    assert float(s_next[geometry.YAW]) == pytest.approx(yaw, rel=1e-3)
    assert np.allclose(np.asarray(s_next[2:4]), 0.0, atol=1e-6)  # zero net force: no translation
    assert np.allclose(np.asarray(info["friction"]).sum(0), 0.0, atol=1e-4)


@pytest.mark.parametrize("contact", ["polygon", "voxels"])
def test_slip_symmetric_uniform_box_opposite_belts(contact):
    # Belts running at +-0.2 m/s under a box at rest: symmetric slip, zero net force, positive torque
    # (belt 1 at y < 0 pushes +x). Upper bound on the turn: the torque of full slip, mu (M g / 2) x the
    # load-weighted |y| of each patch (~0.1 m) x 2, over I_zz, for the whole step.
    model = prior.make_prior(_uniform(), None, BOX, G, contact=contact)
    speed = jnp.array([0.2, -0.2])
    s_next, info = explain(model, planning.initial_window(REST), speed, jnp.array([0.2, -0.2, 0, 0]))
    assert np.allclose(np.asarray(s_next[2:4]), 0.0, atol=1e-5)
    assert np.allclose(np.asarray(info["normal_load"]), 5.0 * G.gravity / 2, rtol=1e-3)
    f = np.asarray(info["forces"])
    assert f[0] > 0 > f[1] and f[0] == pytest.approx(-f[1], rel=1e-3)
    izz = 5.0 * (0.4**2 + 0.3**2) / 12
    upper = 0.5 * (G.friction * 5.0 * G.gravity * 0.1) / izz * DT**2
    yaw = float(s_next[geometry.YAW])
    assert 0.3 * upper < yaw < upper


@pytest.mark.parametrize("contact", ["polygon", "voxels"])
def test_slip_box_sticks_to_accelerating_belts(contact):
    # Both belts accelerate at 0.6 m/s^2 < mu g = 4.9 m/s^2: the box follows them without slipping
    # (heavy voxel anywhere, no rotation): x after one step = a dt^2 / 2 = 0.75 mm and the box ends at
    # the belt speed a dt = 0.03 m/s. (A box sliding at mu g would overshoot; one not dragged would stay.)
    a = G.belt_accel_limit
    for masses in (_uniform(), _heavy(6, 1, 2, m=4.0)):
        model = prior.make_prior(masses, None, BOX, G, contact=contact)
        s_next, info = explain(
            model, planning.initial_window(REST), jnp.zeros(2), jnp.array([0.2, 0.2, 0, 0])
        )
        assert float(s_next[geometry.X]) == pytest.approx(0.5 * a * DT**2, rel=0.03)
        assert float(info["com_velocity"][0]) == pytest.approx(a * DT, rel=0.03)
        assert abs(float(s_next[geometry.YAW])) < 2e-4
        assert abs(float(s_next[geometry.Y])) < 2e-5


def test_slip_box_moving_with_belts_keeps_moving():
    v = 0.1
    model = prior.make_prior(_uniform(), None, BOX, G)
    w = _moving_window(v=(v, 0.0), omega=0.0)
    s_next = one(model, w, jnp.array([v, v]), jnp.array([v, v, 0.0, 0.0]))
    assert np.allclose(np.asarray(s_next[2:]), [v * DT, 0.0, 0.0], atol=2e-5)


def test_slip_position_step_drags_box_sideways():
    # Belt 2 moves +1 cm: P2 follows, the box moves +y but less than the belt (belt 1 holds it back).
    model = prior.make_prior(_uniform(), None, BOX, G)
    s_next = one(model, planning.initial_window(REST), jnp.zeros(2), jnp.array([0.0, 0.0, 0.0, 0.01]))
    assert float(s_next[geometry.P2]) == pytest.approx(0.11)
    assert float(s_next[geometry.P1]) == pytest.approx(-0.1)
    assert 0.0 < float(s_next[geometry.Y]) < 0.01


def test_belt_positions_clipped_to_range():
    model = prior.make_prior(_uniform(), None, BOX, G)
    s = jnp.array([G.p1_range[0] + 0.002, G.p2_range[1] - 0.001, 0.0, 0.0, 0.0])
    s_next = one(model, planning.initial_window(s), jnp.zeros(2), jnp.array([0.0, 0.0, -0.01, 0.01]))
    assert np.allclose(np.asarray(s_next[:2]), [G.p1_range[0], G.p2_range[1]])


@pytest.mark.parametrize("cone", ["elliptic", "pyramidal"])
def test_friction_jacobian_matches_finite_differences(cone):
    key = jax.random.key(3)
    k1, k2, k3, k4 = jax.random.split(key, 4)
    u = jax.random.normal(k1, (3,)) * 0.1
    ub = jax.random.normal(k2, (2, 2)) * 0.1
    off = jax.random.normal(k3, (2, 12, 2)) * 0.1
    loads = jax.random.uniform(k4, (2, 12))

    ff = jax.jit(prior.friction_force, static_argnums=(4, 5, 6))  # one compile for all evaluations
    force, jac, per_belt, a_mm, b_mm = ff(u, ub, off, loads, 0.5, 1e-3, cone)
    h = 1e-3  # central differences (float32: truncation and round-off both well below the tolerance)
    auto = np.stack(
        [
            (
                np.asarray(ff(u + h * e, ub, off, loads, 0.5, 1e-3, cone)[0])
                - np.asarray(ff(u - h * e, ub, off, loads, 0.5, 1e-3, cone)[0])
            )
            / (2 * h)
            for e in jnp.eye(3)
        ],
        axis=1,
    )
    assert np.allclose(np.asarray(jac), auto, rtol=2e-2, atol=2e-2)
    assert np.allclose(np.asarray(per_belt.sum(0)), np.asarray(force[:2]), atol=1e-5)
    # The force is minus the gradient of the dissipation potential, and the majoriser touches it at u.
    grad = jax.grad(lambda uu: prior.dissipation(uu, ub, off, loads, 0.5, 1e-3, cone))(u)
    assert np.allclose(np.asarray(force), -np.asarray(grad), rtol=1e-4, atol=1e-4)
    assert np.allclose(np.asarray(a_mm @ u - b_mm), np.asarray(grad), rtol=1e-3, atol=1e-3)


def test_solve3_and_its_derivatives_are_linalg_solves():
    """The adjugate solve and its implicit derivatives (forward and reverse mode) against LAPACK's solve
    differentiated by JAX, in float64, on well- and ill-conditioned systems like the friction step's."""
    from boxjax.prior.contact import solve3

    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        for cond in (1.0, 1e3):
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            a = jnp.asarray(q @ np.diag([1.0, 0.5, 1.0 / cond]) @ q.T + 0.1 * rng.normal(size=(3, 3)) / cond)
            b = jnp.asarray(rng.normal(size=3))
            ref = lambda a, b: jnp.linalg.solve(a, b)  # noqa: E731
            np.testing.assert_allclose(solve3(a, b), ref(a, b), rtol=1e-9 * cond)
            for jac in (jax.jacrev, jax.jacfwd):
                for arg in (0, 1):
                    got = jac(solve3, argnums=arg)(a, b)
                    want = jac(ref, argnums=arg)(a, b)
                    np.testing.assert_allclose(got, want, rtol=1e-8 * cond, atol=1e-12 * cond)
        # Vmapped, as the friction step calls it, and through a scalar loss.
        a2 = jnp.stack([a, a.T])
        g = jax.grad(lambda a2: jnp.sum(jax.vmap(solve3)(a2, jnp.stack([b, b])) ** 2))(a2)
        want = jax.grad(lambda a2: jnp.sum(jnp.linalg.solve(a2, jnp.stack([b, b])[..., None]) ** 2))(a2)
        np.testing.assert_allclose(g, want, rtol=1e-6)


@pytest.mark.parametrize(
    "angle_deg, expect",
    [
        (0.0, (1.0, 0.0)),  # along an axis: full mu N, both laws
        (30.0, (1.0, 0.0)),  # pyramid: the diamond's vertex on the dominant axis, still mu N
        (45.0, (0.5, 0.5)),  # pyramid: on the diagonal only mu N / sqrt 2 (each component mu N / 2)
        (90.0, (0.0, 1.0)),
    ],
)
def test_pyramidal_friction_is_mujocos_diamond(angle_deg, expect):
    # One contact under a box at rest, belt sliding at 0.2 m/s in direction angle_deg: the friction on the
    # box (as a fraction of mu N) for MuJoCo's pyramidal cone, |f_x| + |f_y| <= mu N (module docstring).
    a = np.radians(angle_deg)
    ub = jnp.array([[0.2 * np.cos(a), 0.2 * np.sin(a)], [0.0, 0.0]])
    off, loads = jnp.zeros((2, 1, 2)), jnp.array([[10.0], [0.0]])
    mu_n = 0.5 * 10.0
    f_pyr = np.asarray(prior.friction_force(jnp.zeros(3), ub, off, loads, 0.5, 2e-3, "pyramidal")[0][:2])
    assert np.allclose(f_pyr / mu_n, expect, atol=0.02)
    f_ell = np.asarray(prior.friction_force(jnp.zeros(3), ub, off, loads, 0.5, 2e-3, "elliptic")[0][:2])
    assert np.allclose(f_ell / mu_n, [np.cos(a), np.sin(a)], atol=0.01)  # isotropic: along the slip


def test_contact_fractions_match_masks_at_yaw_zero():
    fr = np.asarray(prior.contact_fractions(REST, BOX, G))
    s1, s2 = (np.asarray(m) for m in geometry.contact_masks(REST, BOX, G))
    # Rows 0, 1 fully on belt 1; row 2 covers y in [-0.075, -0.0375], the belt ends at -0.05: 2/3.
    assert np.allclose(fr[0][:, :2], 1.0, atol=5e-3) and np.allclose(fr[0][:, 2], 2 / 3, atol=1e-3)
    assert np.allclose(fr[0][:, 3:], 0.0)
    assert np.array_equal(fr[0] > 0.5, s1 > 0) and np.array_equal(fr[1] > 0.5, s2 > 0)
    # Rotated: total area over a belt is about the belt area under the box (belt strip x box).
    s = REST.at[geometry.YAW].set(0.7)
    fr = np.asarray(prior.contact_fractions(s, BOX, G))
    assert np.all((fr >= 0) & (fr <= 1))


@pytest.mark.parametrize("name", ["C", "A", "uniform"])
def test_normal_loads_balance_weight_and_moments_without_tension(name):
    """Statics of the rigid box: the loads are >= 0, sum to M g and have no moment about the centre of mass
    (box C's centre of mass lies 7 cm towards belt 2, so part of belt 1's contact lifts off)."""
    model = prior.make_prior(massdist.voxel_masses(massdist.named(name, BOX), BOX), None, BOX, G)
    for s in (REST, REST.at[geometry.YAW].set(0.6).at[geometry.P1].set(-0.16)):
        c = prior.polygon_contacts(model, s)
        n = np.asarray(prior.normal_loads(model, c))
        assert np.all(n >= 0)
        np.testing.assert_allclose(n.sum(), float(model.mass) * G.gravity, rtol=1e-4)
        moment = (n[..., None] * np.asarray(c.offsets)).sum(axis=(0, 1))
        np.testing.assert_allclose(moment, 0.0, atol=2e-3 * float(model.mass))


def test_normal_loads_with_friction_moment_closed_form():
    """Friction F at the belt surface, h = com_z + half height below the centre of mass, must be balanced
    by the normal loads: sum N = M g and sum q N = -h F (box axes). Dragged towards -y the uniform box
    presses harder on its +y side (belt 2); the sum is still M g and no load is negative."""
    model = prior.make_prior(_uniform(), None, BOX, G)
    c = prior.polygon_contacts(model, REST)
    mg = float(model.mass) * G.gravity
    f = jnp.array([0.0, -0.2 * mg])
    n = np.asarray(prior.normal_loads(model, c, f))
    h = float(model.com[2]) + BOX.half_size[2]
    assert np.all(n >= 0)
    np.testing.assert_allclose(n.sum(), mg, rtol=1e-4)
    moment = (n[..., None] * np.asarray(c.offsets)).sum(axis=(0, 1))
    np.testing.assert_allclose(moment, -h * np.asarray(f), atol=2e-3 * float(model.mass))
    assert n[1].sum() > n[0].sum() + 0.5  # N: the +y belt (2) carries more
    np.testing.assert_allclose(
        prior.normal_loads(model, c, jnp.zeros(2)), prior.normal_loads(model, c), atol=1e-5
    )


def test_normal_loads_per_belt_match_mujoco_at_rest():
    """Reference nobody here wrote: MuJoCo's contact forces on box C resting on the belts (averaged over
    0.1 s after settling) split its weight 18.0 / 60.5 N between belt 1 and belt 2."""
    import mujoco

    from boxjax.sim import model as sim_model

    dist = massdist.named("C", BOX)
    m = sim_model.box_model(DEFAULT, dist)
    d = mujoco.MjData(m)
    d.qpos[:] = sim_model.initial_qpos(DEFAULT, m)
    d.ctrl[sim_model.CARRIAGE1_P : sim_model.CARRIAGE2_P + 1] = G.belt_y0
    mujoco.mj_step(m, d, nstep=100)
    belt2 = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "belt2")
    f6, sim = np.zeros(6), np.zeros(2)
    for _ in range(50):
        mujoco.mj_step(m, d)
        for i in range(d.ncon):
            mujoco.mj_contactForce(m, d, i, f6)
            sim[int(belt2 in (d.contact[i].geom1, d.contact[i].geom2))] += f6[0] / 50
    model = prior.make_prior(massdist.voxel_masses(dist, BOX), None, BOX, G)
    pred = np.asarray(prior.normal_loads(model, prior.polygon_contacts(model, REST)).sum(axis=1))
    np.testing.assert_allclose(pred, sim, atol=1.5)  # N, of 78.5 N


def test_stability_margin_hand_computed():
    """Uniform box at yaw 0 on belts at -+0.10 m: the support hull is the whole 0.40 x 0.30 footprint, the
    centre of mass is 0.15 m from its nearest (long) edge. Belt 1 moved clear of the box: the box rests on
    belt 2 alone (y in [0.05, 0.15]) and its centre of mass lies 0.05 m outside: it tips."""
    model = prior.make_prior(_uniform(), None, BOX, G)
    np.testing.assert_allclose(float(prior.stability_margin(model, REST)), 0.15, atol=1e-5)
    off = REST.at[geometry.P1].set(-0.26)
    np.testing.assert_allclose(float(prior.stability_margin(model, off)), -0.05, atol=1e-5)
    # Box C: centre of mass (-5.2, +6.8) cm from the box centre, so 0.15 - 0.068 from the +y edge.
    c = prior.make_prior(massdist.voxel_masses(massdist.named("C", BOX), BOX), None, BOX, G)
    np.testing.assert_allclose(float(prior.stability_margin(c, REST)), 0.15 - float(c.com[1]), atol=1e-5)
    # Turned, belts spread to their stops: two corner patches; the margin shrinks (here below 2 cm).
    spread = jnp.array([-0.20, 0.20, 0.0, 0.0, 0.41])
    assert float(prior.stability_margin(c, spread)) < 0.02


def test_the_exact_stability_margin_is_the_distance_to_the_support_hull():
    """Reference: scipy's convex hull (Qhull) of the contact vertices. margin="exact" is the centre of mass's
    distance to the hull's nearest edge when inside and negative when outside; "sampled" (32
    directions) is never below it and over-estimates it near an edge (by up to ~2 cm: the hull's edge
    normals fall between its directions)."""
    from scipy.spatial import ConvexHull

    from boxjax.sim import statics

    rng = np.random.default_rng(3)
    n = 300
    s = statics.random_states(rng, n, DEFAULT)
    masses = massdist.voxel_masses(massdist.sample_hazardous(jax.random.PRNGKey(5), BOX), BOX)
    exact = prior.make_prior(masses, None, BOX, G, prior.PriorParams(margin="exact"))
    sampled = prior.make_prior(masses, None, BOX, G, prior.PriorParams(margin="sampled"))
    m_exact = np.asarray(jax.jit(jax.vmap(prior.stability_margin, in_axes=(None, 0)))(exact, jnp.asarray(s)))
    m_sampled = np.asarray(
        jax.jit(jax.vmap(prior.stability_margin, in_axes=(None, 0)))(sampled, jnp.asarray(s))
    )
    contacts = jax.jit(jax.vmap(prior.polygon_contacts, in_axes=(None, 0)))(exact, jnp.asarray(s))
    inside = 0
    for k in range(n):
        q = np.asarray(contacts.offsets[k]).reshape(-1, 2)[np.asarray(contacts.weights[k]).reshape(-1) > 0]
        hull = ConvexHull(q.astype(np.float64))
        distance = float(np.min(-hull.equations[:, 2]))  # unit normals n, offsets b: n . x + b <= 0 inside
        if distance > 0:
            np.testing.assert_allclose(m_exact[k], distance, atol=2e-6)
            inside += 1
        else:
            assert m_exact[k] <= 1e-6
    assert inside > 100
    assert np.all(m_sampled >= m_exact - 1e-6)
    assert np.max(m_sampled - m_exact) > 0.005
    # "refined": between the two, within 2 mm of the exact margin and mostly on it
    refined = prior.make_prior(masses, None, BOX, G, prior.PriorParams(margin="refined"))
    m_refined = np.asarray(
        jax.jit(jax.vmap(prior.stability_margin, in_axes=(None, 0)))(refined, jnp.asarray(s))
    )
    assert np.all(m_refined >= m_exact - 1e-6) and np.all(m_refined <= m_sampled + 1e-6)
    assert np.max(m_refined - m_exact) < 0.002 and np.mean(m_refined - m_exact < 1e-4) > 0.95
    # no contact at all: -1 m, whichever the margin
    away = jnp.asarray(s[0]).at[geometry.X].set(0.9)
    for model in (sampled, refined, exact):
        assert float(prior.stability_margin(model, away)) == -1.0
    # finite gradients through every margin (the planner's barrier differentiates it)
    for model in (sampled, refined, exact):
        grad = jax.grad(lambda st, model=model: prior.stability_margin(model, st))(jnp.asarray(s[1]))
        assert np.all(np.isfinite(np.asarray(grad)))


def _clip(poly, inside, cross):
    """Sutherland-Hodgman: `poly` (n, 2) float64 clipped to one half-plane."""
    out = []
    for k in range(len(poly)):
        a, b = poly[k], poly[(k + 1) % len(poly)]
        if inside(b):
            if not inside(a):
                out.append(cross(a, b))
            out.append(b)
        elif inside(a):
            out.append(cross(a, b))
    return np.asarray(out, np.float64).reshape(-1, 2)


def _overlap_reference(s):
    """Each belt's overlap with the box footprint in float64 (box axes, from the geometric centre), by
    clipping the footprint to the belt's four half-planes: an implementation independent of the prior's."""
    hx, hy = BOX.half_size[0], BOX.half_size[1]
    c, sn = np.cos(float(s[geometry.YAW])), np.sin(float(s[geometry.YAW]))
    r = np.array([[c, -sn], [sn, c]])
    box = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]]) @ r.T + np.array(s[2:4], np.float64)
    out = []
    for p in (float(s[geometry.P1]), float(s[geometry.P2])):
        poly = box
        for axis, level, keep in ((1, p - G.belt_width / 2, 1), (1, p + G.belt_width / 2, -1),
                                  (0, -G.belt_length / 2, 1), (0, G.belt_length / 2, -1)):  # fmt: skip
            inside = lambda q, a=axis, lv=level, k=keep: k * (q[a] - lv) >= 0  # noqa: E731
            cross = lambda a_, b_, a=axis, lv=level: a_ + (lv - a_[a]) / (b_[a] - a_[a]) * (b_ - a_)  # noqa: E731
            poly = _clip(poly, inside, cross) if len(poly) else poly
        out.append((poly - np.array(s[2:4], np.float64)) @ r)
    return out


def _area(poly):
    if len(poly) < 3:
        return 0.0
    hull = poly[np.argsort(np.arctan2(*(poly - poly.mean(0)).T[::-1]))]
    x, y = hull.T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _outside(points, poly):
    """(n,) m: how far each point lies outside the convex polygon `poly` (0 inside), float64."""
    hull = poly[np.argsort(np.arctan2(*(poly - poly.mean(0)).T[::-1]))]  # counter-clockwise
    edge = np.roll(hull, -1, axis=0) - hull
    normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1)[:, None]
    keep = np.linalg.norm(edge, axis=1) > 1e-9
    return np.maximum(0.0, ((points[:, None, :] - hull[None]) * normal[None]).sum(-1)[:, keep].max(axis=1))


def test_the_contact_polygons_are_the_overlaps_even_where_a_box_edge_meets_a_belt_edge():
    """Adversarial: the box's long edges within micrometres of the belts' outer edges (where the box starts,
    belts at +-0.1 m: its 30 cm width spans both exactly), at tiny yaws. The prior's polygon and the float64
    overlap lie within 1 um of each other and their areas agree: a vertex lost there
    (both candidates refused, one by its distance to the line, the other by its position along the
    edge) took a box's exact stability margin from +44 to -34 mm at rest."""
    model = prior.make_prior(_uniform(), None, BOX, G)
    contacts = jax.jit(jax.vmap(prior.polygon_contacts, in_axes=(None, 0)))
    rng = np.random.default_rng(0)
    n = 400
    s = np.zeros((n, 5))
    s[:, geometry.P1] = -0.1 + rng.choice([0.0, 1.0], n) * rng.uniform(-5e-6, 5e-6, n)
    s[:, geometry.P2] = 0.1 + rng.uniform(-5e-6, 5e-6, n)
    s[:, geometry.X] = rng.uniform(-0.01, 0.01, n)
    s[:, geometry.Y] = rng.choice([0.0, 1.0], n) * rng.uniform(-5e-6, 5e-6, n)
    s[:, geometry.YAW] = rng.choice([0.0, 1.0], n) * rng.uniform(-1e-3, 1e-3, n)
    s[0] = [-0.1000002, 0.10001609, -0.003052581, 0.000077852, 0.000303268]  # the state that lost one
    c = contacts(model, jnp.asarray(s, jnp.float32))
    off, w = np.asarray(c.offsets, np.float64) + np.asarray(model.com[:2]), np.asarray(c.weights)
    for i in range(n):
        for b, ref in enumerate(_overlap_reference(s[i])):
            got = off[i, b][w[i, b] > 0]
            assert len(got) >= len(ref) >= 3 or len(ref) == 0, (i, b)
            # each polygon's vertices on or within 1 um of the other (a vertex on an edge nearly parallel
            # to a belt's edge is ill-placed along it in float32, not off it)
            assert max(_outside(ref, got).max(), _outside(got, ref).max()) < 1e-6, (i, b)
            assert _area(got) == pytest.approx(_area(ref), rel=1e-4, abs=1e-8), (i, b)


def test_polygon_contacts():
    model = prior.make_prior(_uniform(), None, BOX, G)
    polygon_contacts = jax.jit(prior.polygon_contacts)
    c = polygon_contacts(model, REST)
    # Yaw 0, belts at +-0.1 m (0.10 wide): each belt touches [-0.2, 0.2] x [+-0.05, +-0.15] at 4 corners.
    for i, sign in ((0, -1), (1, 1)):
        pts = np.asarray(c.offsets[i])[np.asarray(c.weights[i]) > 0]
        expect = {(x, sign * y) for x in (-0.2, 0.2) for y in (0.05, 0.15)}
        assert {(round(float(p[0]), 4), round(float(p[1]), 4)) for p in pts} == expect
    # Turned 0.6 rad: 4 vertices per belt, where the box's long edges cross the belt's edges.
    s = REST.at[geometry.YAW].set(0.6)
    c = polygon_contacts(model, s)
    assert np.asarray(c.weights).sum(axis=1).tolist() == [4.0, 4.0]
    world = np.asarray(geometry.box_to_world_xy(s, c.offsets + model.com[:2]))
    ys = world[..., 1][np.asarray(c.weights) > 0]
    assert np.allclose(np.sort(np.abs(ys)), [0.05] * 4 + [0.15] * 4, atol=1e-5)
    loads = jax.jit(prior.normal_loads)(model, c)
    assert float(jnp.sum(loads)) == pytest.approx(float(model.mass) * G.gravity, rel=1e-4)
    # Near a belt end: the belt's corners inside the footprint become vertices too.
    s = REST.at[geometry.X].set(G.belt_length / 2 - 0.1)
    c = polygon_contacts(model, s)
    xs = np.asarray(c.offsets[0, :, 0])[np.asarray(c.weights[0]) > 0] + float(s[geometry.X])
    assert np.allclose(np.sort(xs), [0.1 - 0.0, 0.1, G.belt_length / 2, G.belt_length / 2], atol=1e-5)
    # Beyond the belt ends: no contact.
    c = polygon_contacts(model, REST.at[geometry.X].set(0.9))
    assert float(jnp.sum(c.weights)) == 0


# ----------------------------------------------------------------------------------------------------------
# Guards, gradients, batching.


def _off_belt2():
    # Belt 2 at the edge of its range, box shifted left: S2 is empty, S1 is not.
    s = jnp.array([-0.1, G.p2_range[1], 0.0, -0.06, 0.0])
    s1, s2 = geometry.contact_masks(s, BOX, G)
    assert float(jnp.sum(s2)) == 0 and float(jnp.sum(s1)) > 0
    return s


SETUPS = {"slip": dict(), "slip-voxels": dict(contact="voxels"), "paper": dict(variant="paper")}


@pytest.mark.parametrize("setup", list(SETUPS))
def test_no_nan_and_finite_grads(setup):
    # Situations: S2 empty; box beyond the belt ends (no contact at all); at rest; moving. One compiled
    # gradient per setup, vmapped over the situations.
    windows = jnp.stack(
        [
            planning.initial_window(_off_belt2()),
            planning.initial_window(REST.at[geometry.X].set(0.9)),
            planning.initial_window(REST),
            _moving_window(),
        ]
    )
    speeds = jnp.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.05, -0.05]])
    fm = _linear_map()
    masses = massdist.voxel_masses(massdist.named("C", BOX), BOX)
    action = jnp.array([0.07, -0.07, 0.004, 0.0])

    out = np.stack(
        [
            np.asarray(one(prior.make_prior(masses, fm, BOX, G, **SETUPS[setup]), w, b, action))
            for w, b in zip(windows, speeds, strict=True)
        ]
    )
    assert np.all(np.isfinite(out))
    # Off the belts nothing touches the box: it keeps its (zero) velocity.
    assert np.allclose(out[1, 2:], np.asarray(windows[1, -1, 2:]), atol=1e-6)
    if setup == "slip-voxels":
        return  # same solver as "slip"; spare the compile of a third gradient

    def yaw(a, m, w, b):
        return prior.predict(prior.make_prior(m, fm, BOX, G, **SETUPS[setup]), w, b, a)[geometry.YAW]

    grad = jax.jit(jax.grad(yaw, argnums=(0, 1)))
    for w, b in zip(windows, speeds, strict=True):
        ga, gm = grad(action, masses, w, b)
        assert np.all(np.isfinite(np.asarray(ga))) and np.all(np.isfinite(np.asarray(gm)))
    # Moving (the last situation): the turn depends on the belt-1 command and on the masses.
    assert float(jnp.abs(ga[0])) > 0 and float(jnp.max(jnp.abs(gm))) > 0


@pytest.mark.parametrize("setup", ["slip", "paper"])
def test_vmap_over_action_set_equals_loop(setup):
    masses = massdist.voxel_masses(massdist.named("B", BOX), BOX)
    model = prior.make_prior(masses, _linear_map(), BOX, G, **SETUPS[setup])
    window = _moving_window()
    speed = jnp.array([0.05, -0.05])
    acts = planner.to_env_actions(planner.action_set(G), speed, G)
    assert acts.shape == (95, 4)
    got = np.asarray(batched(model, window, speed, acts))
    loop = np.stack([np.asarray(one(model, window, speed, a)) for a in acts])
    assert np.allclose(got, loop, atol=1e-6)
    assert len(np.unique(np.round(got, 7), axis=0)) > 50  # the actions do differ


def test_rollout_first_step_is_predict():
    model = prior.make_prior(_uniform(), None, BOX, G)
    w, b, a = _moving_window(), jnp.array([0.05, -0.05]), jnp.array([0.08, -0.08, 0.0, 0.0])
    traj = prior.rollout(model, w, b, a, 3)
    assert traj.shape == (3, 5)
    assert np.allclose(np.asarray(traj[0]), np.asarray(one(model, w, b, a)), atol=1e-6)
    assert np.allclose(np.asarray(planning.next_belt_speed(model, b, a)), [0.08, -0.08])


def test_check_window():
    w = np.tile(np.asarray(REST), (3, 1))
    assert planning.check_window(w).shape == (3, 5)
    with pytest.raises(ValueError, match="at least 3"):
        planning.check_window(w[:2])
    with pytest.raises(ValueError, match=r"shape \(W, 5\)"):
        planning.check_window(w[:, :4])
    bad = w.copy()
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match="row 1 yaw"):
        planning.check_window(bad)
    with pytest.raises(ValueError, match="belt_speed"):
        planning.check_window(w, belt_speed=[0.0, np.inf])
    with pytest.raises(ValueError, match="action"):
        planning.check_window(w, action=[0.0, 0.0, 0.0])


def test_make_prior_rejects_bad_setup():
    with pytest.raises(ValueError, match="force map"):
        prior.make_prior(_uniform(), None, BOX, G, variant="paper")
    with pytest.raises(ValueError, match="variant"):
        prior.make_prior(_uniform(), None, BOX, G, variant="nope")
    with pytest.raises(ValueError, match="shape"):
        prior.make_prior(jnp.ones((4, 4, 4)), None, BOX, G)
    with pytest.raises(ValueError, match="columns"):
        prior.make_prior(_uniform(), None, BOX, G, normal="columns")
    with pytest.raises(ValueError, match="friction cone"):
        prior.make_prior(_uniform(), None, BOX, G, cone="round")


# ----------------------------------------------------------------------------------------------------------
# Against the simulator.


def test_prior_beats_constant_velocity_on_boxes_starting_to_spin():
    # Boxes uniform, A, B, C at rest; the belts start up in opposite directions (increments of up to
    # 0.03 m/s per step, the most the acceleration limit allows), so the box starts to turn (and, off
    # centre, to slide). The first two transitions of each start: constant velocity predicts no motion at
    # the first and only the first step's mean motion at the second; the prior predicts the belts' pull.
    # Measured: median position error prior 0.13 mm vs 0.36 mm, yaw 0.027 vs 0.10 deg; it fails for a
    # prior that ignores the action (0.34 mm, 0.085 deg), swaps the belts, has a tenth of the friction
    # (0.29 mm), or uses isotropic friction instead of the simulator's pyramidal cone (0.19 mm).
    env = make_env(DEFAULT, "native")
    masses, windows, speeds, actions, truth = [], [], [], [], []
    for dv in ((0.03, -0.03), (0.03, -0.015), (-0.015, 0.03), (-0.03, 0.03)):
        for name in ("uniform", "A", "B", "C"):
            dist = massdist.named(name, BOX)
            state = env.reset(jax.random.PRNGKey(0), dist)
            hist = [np.asarray(state.s)] * 3
            for _ in range(2):
                speed = np.asarray(state.belt_speed)
                action = np.array([speed[0] + dv[0], speed[1] + dv[1], 0.0, 0.0])
                state = env.step(state, action)
                masses.append(np.asarray(massdist.voxel_masses(dist, BOX)))
                windows.append(np.stack(hist[-3:]))
                speeds.append(speed)
                actions.append(action)
                truth.append(np.asarray(state.s))
                hist.append(np.asarray(state.s))
    windows, truth = np.stack(windows), np.stack(truth)
    assert np.median(np.abs(truth[:, geometry.YAW])) > 1e-3  # the boxes do turn (rad)
    predict = jax.jit(jax.vmap(lambda m, w, b, a: prior.predict(prior.make_prior(m, None, BOX, G), w, b, a)))
    pred = np.asarray(
        predict(*(jnp.asarray(np.stack(x), jnp.float32) for x in (masses, windows, speeds, actions)))
    )
    # Constant velocity from the last step (as in benchmarks/prediction_error.py), and from the prior's
    # own second-order velocity estimate.
    const_vel = windows[:, -1] + (windows[:, -1] - windows[:, -2])
    const_vel2 = windows[:, -1] + (3 * windows[:, -1] - 4 * windows[:, -2] + windows[:, -3]) / 2

    def errors(p):
        pos = np.linalg.norm(p[:, 2:4] - truth[:, 2:4], axis=1)
        return np.median(pos), np.median(np.abs(p[:, geometry.YAW] - truth[:, geometry.YAW]))

    pos_prior, yaw_prior = errors(pred)
    for baseline in (const_vel, const_vel2):
        pos_cv, yaw_cv = errors(baseline)
        assert pos_prior < 0.5 * pos_cv, (pos_prior, pos_cv)
        assert yaw_prior < 0.5 * yaw_cv, (yaw_prior, yaw_cv)


def test_unrolled_step_is_the_looped_step_without_its_loops():
    """`PriorParams.unroll` (default) writes the step's substep and solver loops out as straight-line code:
    the compiled step has no `while` loop left (on a GPU each iteration reads its condition back to the
    host), and it predicts what the looped step predicts. Not bit for bit: XLA fuses the two programs
    differently, and the solver's choice between its Newton and majorise-minimise candidates
    (`jnp.where` on their objectives) may flip on a round-off tie, so a few micrometres is the tolerance
    over a 10-step rollout of random actions."""
    rng = np.random.default_rng(3)
    window = jnp.asarray(
        np.tile([-0.10, 0.10, 0.0, 0.0, 0.0], (3, 1)) + rng.normal(0, 1e-3, (3, 5)), jnp.float32
    )
    belt = jnp.array([0.05, -0.05], jnp.float32)
    actions = jnp.asarray(rng.uniform(-1, 1, (10, 4)) * [0.2, 0.2, 0.01, 0.01], jnp.float32)
    step = jax.jit(prior.predict)  # one program per setting: the model is an argument (its params static)
    roll = jax.jit(lambda m, a: m.rollout_sequence(window, belt, a))
    for name in ("A", "B", "C"):
        masses = massdist.voxel_masses(massdist.named(name), DEFAULT.box)
        looped, unrolled = (prior.make_prior(masses, unroll=u) for u in (False, True))
        if name == "A":
            hlo = [step.lower(m, window, belt, actions[0]).compile().as_text() for m in (looped, unrolled)]
            assert " while(" in hlo[0] and " while(" not in hlo[1]
        np.testing.assert_allclose(
            np.asarray(roll(unrolled, actions)), np.asarray(roll(looped, actions)), atol=2e-5
        )


def test_rollout_from_a_given_start_velocity():
    """`rollout_sequence(velocity=u)`: the window's own finite-difference velocity reproduces the default
    rollout; a box already spinning at +1 rad/s ends further round than one at rest; and the variants that
    re-derive every step's velocity from the window refuse a start velocity."""
    window = jnp.asarray(np.tile([-0.10, 0.10, 0.0, 0.0, 0.0], (3, 1)), jnp.float32)  # at rest
    belt = jnp.zeros(2, jnp.float32)
    actions = jnp.zeros((5, 4), jnp.float32)
    masses = massdist.voxel_masses(massdist.named("uniform"), DEFAULT.box)
    model = prior.make_prior(masses)
    base = prior.rollout_sequence(model, window, belt, actions)
    same = prior.rollout_sequence(model, window, belt, actions, velocity=jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(same), np.asarray(base), atol=1e-7)
    spun = prior.rollout_sequence(model, window, belt, actions, velocity=jnp.array([0.0, 0.0, 1.0]))
    assert float(spun[0, 4]) > 0.01 and float(spun[-1, 4]) >= float(spun[0, 4])  # friction slows it
    assert abs(float(base[-1, 4])) < 1e-6
    with pytest.raises(ValueError, match="start velocity"):
        prior.rollout_sequence(
            prior.make_prior(masses, carry_velocity=False), window, belt, actions, velocity=jnp.zeros(3)
        )
