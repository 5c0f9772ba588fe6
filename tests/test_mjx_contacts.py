"""MJX's box-belt contacts as the overlap polygon (`boxjax.sim.mjx_contacts`), against native MuJoCo's
collider and closed-form geometry, and the MJX backend's choice of collider
(`GripperConfig.mjx_box_contacts`)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from boxjax import massdist
from boxjax.cli import main
from boxjax.config import DEFAULT, ConfigError
from boxjax.estimator import explore
from boxjax.sim import core, model, native
from boxjax.sim.mjx_contacts import NCON, box_box_contacts, box_contacts, native_box_box

CFG = DEFAULT
M = model.box_model(CFG, massdist.named("C", CFG.box))
IDX = model.ids(M)
B = IDX.box_qpos
BOX_GEOM = M.geom("box").id
assert [M.geom(f"belt{i + 1}").id for i in (0, 1)] == [0, 1]  # `_ours(d, belt)` indexes the belts 0, 1


def _quat(roll, pitch, yaw):
    """(w, x, y, z), MuJoCo's order, of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, cp, cy = np.cos(np.array([roll, pitch, yaw]) / 2)
    sr, sp, sy = np.sin(np.array([roll, pitch, yaw]) / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def _pose(roll=0.0, pitch=0.0, yaw=0.0, dz=0.0, dy=0.0):
    d = mujoco.MjData(M)
    q = model.initial_qpos(CFG, M).copy()
    q[B + 3 : B + 7] = _quat(roll, pitch, yaw)
    q[B + 1] += dy
    q[B + 2] += dz
    d.qpos[:] = q
    mujoco.mj_forward(M, d)
    return d


def _ours(d, belt):
    dist, pos, frame = box_box_contacts(
        *(
            jnp.asarray(x)
            for x in (
                d.geom_xpos[belt],
                d.geom_xmat[belt].reshape(3, 3),
                M.geom_size[belt],
                d.geom_xpos[BOX_GEOM],
                d.geom_xmat[BOX_GEOM].reshape(3, 3),
                M.geom_size[BOX_GEOM],
            )
        )
    )
    dist, pos, frame = np.asarray(dist), np.asarray(pos), np.asarray(frame)
    assert dist.shape == (NCON,) and pos.shape == (NCON, 3) and frame.shape == (NCON, 3, 3)
    on = dist < 0
    return dist[on], pos[on], frame[on]


# Poses where native MuJoCo's collider reports the whole overlap polygon: resting and pressed in at several
# yaws (4, 5 and 4 vertices per belt), rolled about the belts' axis, pitched, and rolled while overhanging a
# belt's outer edge by 2 mm at 3 degrees of yaw.
POSES = [
    dict(dz=-5e-4),
    dict(yaw=0.3, dz=-5e-4, dy=0.01),
    dict(yaw=0.8, dz=-5e-4, dy=0.01),
    dict(roll=2e-4, dz=-2e-6),
    dict(pitch=2e-4, dz=-2e-6),
    dict(roll=2e-4, yaw=0.05, dz=-2e-6, dy=0.002),
]


@pytest.mark.parametrize("pose", POSES, ids=[str(p) for p in POSES])
def test_contacts_are_native_mujocos_where_it_reports_the_whole_polygon(pose):
    """MuJoCo's own box-box collider is the reference: the same vertices, depths (float32 here: 0.05 um)
    and normal, and the contact point midway between the surfaces as native MuJoCo puts it."""
    d = _pose(**pose)
    for belt in (0, 1):
        native = [c for c in d.contact[: d.ncon] if belt in c.geom and c.dist < 0]
        dist, pos, frame = _ours(d, belt)
        assert len(dist) == len(native), (belt, len(dist), len(native))
        for c in native:
            j = int(np.argmin(np.linalg.norm(pos - c.pos, axis=1)))
            np.testing.assert_allclose(pos[j], c.pos, atol=2e-6)
            assert abs(dist[j] - c.dist) < 5e-8
            np.testing.assert_allclose(frame[j][0], c.frame[:3], atol=1e-3)  # normal, belt towards box


def test_depths_of_a_pitched_box_follow_the_tilted_face():
    """Closed form: a box pitched by a about y and pressed in by h at its lowest end has depth
    h - (x_end - x) sin(a) under each vertex (x along the box), at the box's ends x = +-L/2 here."""
    a, h = 1e-4, 5e-5  # the high end still pressed in: h > L sin(a)
    half_l, half_h = CFG.box.half_size[0], CFG.box.half_size[2]
    # lowest end at x = +L/2 (positive pitch tips +x down); its bottom edge sits h below the belts' top
    rise = half_l * np.sin(a) + half_h * (np.cos(a) - 1)  # how far the +x bottom edge drops on tilting
    d = _pose(pitch=a, dz=-(h - rise))
    for belt in (0, 1):
        dist, pos, _ = _ours(d, belt)
        assert len(dist) == 4  # the box's two ends over the belt, both edges of the belt
        x_box = pos[:, 0] - d.qpos[B]
        expected = h - (half_l - x_box / np.cos(a)) * np.sin(a)
        np.testing.assert_allclose(-dist, expected, atol=2e-7)
        assert np.ptp(x_box) > 2 * half_l - 1e-3


def test_a_line_contact_has_one_contact_per_end_not_repeated_points():
    """A box rolled onto the outer edge of one belt touches it along a line: two contacts, one at each end
    of the line, each as deep as the edge (MJX's own collider gives four, three of them at one end), and
    none on the lifted belt."""
    r, h = 2e-3, 5e-5  # +roll about x lowers the -y side (belt 1); the edge at y = -W/2 pressed in by h
    half_w, half_h = CFG.box.half_size[1], CFG.box.half_size[2]
    drop = half_w * np.sin(r) - half_h * (1 - np.cos(r))
    d = _pose(roll=r, dz=drop - h)
    d1, p1, _ = _ours(d, 0)
    assert len(_ours(d, 1)[0]) == 0
    assert len(d1) == 2
    np.testing.assert_allclose(-d1, h, atol=2e-7)
    np.testing.assert_allclose(
        np.sort(p1[:, 0] - d.qpos[B]), [-CFG.box.half_size[0], CFG.box.half_size[0]], atol=1e-5
    )
    np.testing.assert_allclose(p1[:, 1], -half_w * np.cos(r) + half_h * np.sin(r), atol=1e-6)  # the edge


def _inner_edge_line(pitch):
    """The box rolled by 2e-4 rad (its +y side up) and pressed 5 um into belt 2's inner edge (y = +5 cm),
    along which it touches belt 2; pitched by `pitch`, one end of that line is deeper than the other."""
    r = 2e-4
    return _pose(roll=r, pitch=pitch, dz=-(0.05 * np.sin(r) + 5e-6))


def test_native_mujoco_collapses_a_pitched_line_contact_to_one_point():
    """What the docs say of native MuJoCo's collider (docs/results/simulation.md#colliders): the box lying
    on belt 2's inner edge gets both ends of the line as contacts, until it pitches by 2e-5 rad (8 um of
    depth between the ends): then an edge-cross axis wins and one contact remains. The polygon keeps both,
    at their depths."""
    for pitch, n_native in ((0.0, 2), (2e-5, 1), (-2e-5, 1)):
        d = _inner_edge_line(pitch)
        native = [c for c in d.contact[: d.ncon] if 1 in c.geom and c.dist < 0]
        dist, pos, _ = _ours(d, 1)
        assert len(native) == n_native, (pitch, len(native))
        assert len(dist) == 2 and np.ptp(pos[:, 0]) > 0.39
        np.testing.assert_allclose(np.ptp(dist), abs(pitch) * np.ptp(pos[:, 0]), atol=2e-7)


@pytest.mark.slow  # MJX's own collider is not the default (suite time)
def test_mjx_own_collider_repeats_a_point_of_a_line_contact():
    """Why the polygon exists: MJX's box-box collider fills its 4 slots by repeating the vertices of a line
    contact, so one end carries a multiple of the other's load."""
    from boxjax.sim.mjx_backend import _mjx  # noqa: PLC0415 (MJX is slow to import)

    mjx = _mjx()
    d = _inner_edge_line(2e-5)
    mx = mjx.put_model(M, impl="jax")
    dx = jax.jit(mjx.forward)(mx, mjx.make_data(mx).replace(qpos=jnp.asarray(d.qpos, jnp.float32)))
    con = dx._impl.contact
    on = (np.asarray(con.dist) < 0) & (np.asarray(con.geom)[:, 0] == 1)
    pts = np.round(np.asarray(con.pos)[on, :2], 4)
    assert len(pts) == 4 and len(np.unique(pts, axis=0)) == 2  # four contacts at two points


def _compare_native_rules(d, m, box_geom, belt_geom, kinds):
    """native_box_box (float64) against native MuJoCo's contacts of one box-belt pair at state d: the same
    number of contacts, positions to 1e-9 m, depths to 1e-12 m, normals to 1e-12; records the kind of the
    winning axis (native's normal exactly along the belt's z, along a box axis, or an edge-cross axis)."""
    nat = [c for c in d.contact[: d.ncon] if set(c.geom) == {box_geom, belt_geom}]
    g1, g2 = nat[0].geom if nat else (box_geom, belt_geom)
    mats = d.geom_xmat.reshape(-1, 3, 3)
    dist, pos, frame = (
        np.asarray(x)
        for x in _NATIVE_RULES(
            d.geom_xpos[g1], mats[g1], m.geom_size[g1], d.geom_xpos[g2], mats[g2], m.geom_size[g2]
        )
    )
    on = dist <= 0
    assert on.sum() == len(nat), (on.sum(), len(nat))
    for c in nat:
        j = int(np.argmin(np.linalg.norm(pos[on] - c.pos, axis=1)))
        np.testing.assert_allclose(pos[on][j], c.pos, atol=1e-9)
        assert abs(dist[on][j] - c.dist) < 1e-12
        np.testing.assert_allclose(frame[0, 0], c.frame[:3], atol=1e-12)
    if nat:
        n = nat[0].frame[:3]
        box_axis = np.max(np.abs(mats[box_geom].T @ n)) > 1 - 1e-12
        kinds["belt face" if n[0] == n[1] == 0 else "box face" if box_axis else "edge"] += 1


_NATIVE_RULES = jax.jit(native_box_box)


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def test_native_rules_are_native_mujocos_along_an_exploration(x64):
    """`native_box_box` is native MuJoCo's collider (mjc_BoxBox), rule for rule: along a random box's
    exploration, every box-belt pair's contacts agree to rounding, including the single edge-cross
    contacts native reports for a box lying nearly flat on a belt (which the polygon does not)."""
    m = model.box_model(CFG, massdist.sample(jax.random.PRNGKey(5), CFG.box))
    idx, d = model.ids(m), mujoco.MjData(m)
    d.qpos[:] = model.initial_qpos(CFG, m)
    p = np.asarray(CFG.gripper.belt_y0)
    d.ctrl[model.CARRIAGE1_P], d.ctrl[model.CARRIAGE2_P] = p
    box_geom, belts = m.geom("box").id, (m.geom("belt1").id, m.geom("belt2").id)
    kinds = {"belt face": 0, "box face": 0, "edge": 0}
    for a in np.asarray(explore.exploration_actions(CFG)):
        ctrl, p = core.command(CFG, a, d.act[[model.BELT1_V, model.BELT2_V]], p)[:2]
        d.ctrl[:], p = np.asarray(ctrl), np.asarray(p)
        for k in range(CFG.gripper.n_substeps):
            mujoco.mj_step(m, d)  # d.contact and d.geom_xpos: both of the state before the step
            for belt in belts if k % 5 == 0 else ():  # every fifth physics step (suite time)
                _compare_native_rules(d, m, box_geom, belt, kinds)
        native.recentre_belts(idx, d.qpos)
    assert min(kinds.values()) >= 10, kinds  # each of native's paths was compared


def test_native_rules_at_random_orientations(x64):
    """Adversarial: the box in 60 random orientations, its lowest corner pressed 1 mm below the belts' top
    at random places over them (corners, edges and faces on the belts, edge-edge crossings)."""
    rng = np.random.default_rng(0)
    d = mujoco.MjData(M)
    box_geom, belts = M.geom("box").id, (M.geom("belt1").id, M.geom("belt2").id)
    corners = np.array(np.meshgrid(*([-1, 1],) * 3)).reshape(3, -1).T * CFG.box.half_size
    kinds = {"belt face": 0, "box face": 0, "edge": 0}
    for _ in range(60):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, q)
        low = np.min(corners @ mat.reshape(3, 3).T[:, 2])
        qpos = model.initial_qpos(CFG, M).copy()
        qpos[B : B + 3] = [rng.uniform(-0.3, 0.3), rng.uniform(-0.15, 0.15), -low - 1e-3]
        qpos[B + 3 : B + 7] = q
        d.qpos[:] = qpos
        mujoco.mj_forward(M, d)
        for belt in belts:
            _compare_native_rules(d, M, box_geom, belt, kinds)
    assert kinds["edge"] >= 3 and kinds["belt face"] >= 3, kinds  # (box faces: along the exploration)


def test_far_apart_boxes_have_no_contact():
    d = _pose(dz=0.05)
    for belt in (0, 1):
        assert len(_ours(d, belt)[0]) == 0


def test_the_config_chooses_the_collider_and_names_bad_values(capsys, tmp_path):
    with pytest.raises(ConfigError, match="mjx_box_contacts must be one of"):
        dataclasses.replace(CFG.gripper, mjx_box_contacts="voxels")
    with pytest.raises(ValueError, match="MJX box contacts must be one of"):
        with box_contacts("voxels"):
            pass
    toml = tmp_path / "c.toml"
    toml.write_text('[gripper]\nmjx_box_contacts = "polygon"\n')
    assert main(["simulate", "--config", str(toml), "--steps", "1"]) == 2
    assert "it does nothing here" in capsys.readouterr().err


@pytest.mark.parametrize("kind", [pytest.param("polygon", marks=pytest.mark.slow), "native"])
def test_mjx_with_these_contacts_accelerates_the_box_as_native_mujoco(kind):
    """One MJX forward (float32) at a state where the colliders agree: the box's accelerations within 1 %
    of native MuJoCo's; the contact arrays hold 8 slots per belt."""
    from boxjax.sim.mjx_backend import _mjx  # noqa: PLC0415 (MJX is slow to import)

    mjx = _mjx()
    d = _pose(yaw=0.3, dz=-2e-4, dy=0.01)
    mx = mjx.put_model(M, impl="jax")
    with box_contacts(kind):
        dx = mjx.make_data(mx).replace(
            qpos=jnp.asarray(d.qpos, jnp.float32), ctrl=jnp.asarray(d.ctrl, jnp.float32)
        )
        dx = jax.jit(mjx.forward)(mx, dx)  # traced inside the block: with `kind`
    assert dx._impl.contact.dist.shape == (2 * NCON,)
    box_dofs = slice(M.nv - 6, M.nv)
    np.testing.assert_allclose(np.asarray(dx.qacc)[box_dofs], d.qacc[box_dofs], rtol=1e-2, atol=1e-2)
