"""Voxel mass distributions: mass properties against MuJoCo, principal axes, the hazard test (paper §4.2),
the samplers, gradients, validation and the named distributions A-D."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from boxjax import massdist as md
from boxjax.config import BoxConfig
from boxjax.massdist import DistributionError, MassDistribution

BOX = BoxConfig()
# Tolerances of the float64 comparison with MuJoCo's compiler (which works in double).
MASS_RTOL = 1e-9
COM_TOL = 1e-6  # relative to the box length
INERTIA_RTOL = 1e-6  # relative to the tensor's Frobenius norm
# The default float32 path against the float64 one.
F32_RTOL = 1e-5


# Jitted once per module (a new partial per test would recompile every time); one batch size for all.
N_KEYS = 1024
_SAMPLE = jax.jit(jax.vmap(functools.partial(md.sample, box=BOX)))
_SAMPLE_HAZARDOUS = jax.jit(jax.vmap(functools.partial(md.sample_hazardous, box=BOX)))
_SAMPLE_MIXED = jax.jit(jax.vmap(lambda key, p: md.sample_mixed(key, BOX, p), in_axes=(0, None)))
_HAZARD_REGION = jax.jit(jax.vmap(functools.partial(md.hazard_region, box=BOX)))
_PROPS = jax.jit(functools.partial(md.mass_properties, box=BOX))


def _keys(seed, n=N_KEYS):
    return jax.random.split(jax.random.key(seed), n)


@pytest.fixture
def x64():
    """Enable float64 in JAX for one test, then restore the previous setting.

    jax 0.10 provides ``jax.enable_x64`` as a context manager (the older ``jax.experimental.enable_x64`` is
    gone); it saves and restores the flag itself.
    """
    with jax.enable_x64(True):
        yield


def _occ(indices, box=BOX):
    """Occupancy (float32) with the given (i, j, k) voxels set."""
    occ = np.zeros(box.grid, np.float32)
    for idx in indices:
        occ[idx] = 1.0
    return occ


@functools.cache
def _test_distributions():
    """20 distributions: random, hazardous, uniform, named, and a single voxel in a corner."""
    # The module's jitted samplers (eager per-key sampling compiles every primitive separately: slow).
    rand = _SAMPLE(_keys(42))
    haz = _SAMPLE_HAZARDOUS(_keys(43))
    dists = [jax.tree.map(lambda x, i=i: x[i], rand) for i in range(10)]
    dists += [jax.tree.map(lambda x, i=i: x[i], haz) for i in range(4)]
    dists += [md.named(n, BOX) for n in md.NAMES]
    dists.append(MassDistribution(jnp.asarray(_occ([(7, 0, 3)])), jnp.asarray(2.0, jnp.float32)))
    assert len(dists) == 20
    return dists


def _mujoco_body(masses: np.ndarray, box: BoxConfig) -> mujoco.MjModel:
    """One free body made of one box geom per voxel, each with its own mass; MuJoCo computes the inertia."""
    centres = md._voxel_centres64(box).reshape(-1, 3)
    half = [v / 2 for v in box.voxel_size]
    geoms = "\n".join(
        f'<geom type="box" size="{half[0]!r} {half[1]!r} {half[2]!r}" '
        f'pos="{c[0]!r} {c[1]!r} {c[2]!r}" mass="{m!r}"/>'
        for c, m in zip(centres.tolist(), masses.reshape(-1).tolist(), strict=True)
    )
    xml = f"""
    <mujoco>
      <compiler inertiafromgeom="true"/>
      <worldbody><body name="box"><freejoint/>{geoms}</body></worldbody>
    </mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def _mujoco_inertia(model: mujoco.MjModel, body: int) -> np.ndarray:
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.body_iquat[body])
    rot = rot.reshape(3, 3)
    return rot @ np.diag(model.body_inertia[body]) @ rot.T


# ----------------------------------------------------------------------------------------------------------
# Mass properties.


def test_mass_properties_match_mujoco():
    """Our mass, COM and full inertia tensor equal MuJoCo's for the same voxels as box geoms (float64)."""
    dists = _test_distributions()  # sampled in float32, outside x64 (jit caches are per x64 setting)
    with jax.enable_x64(True):
        _compare_with_mujoco(dists)


def _compare_with_mujoco(dists):
    props64 = jax.jit(functools.partial(md.mass_properties_from_masses, box=BOX))
    for dist in dists:
        dist64 = MassDistribution(
            jnp.asarray(dist.occupancy, jnp.float64), jnp.asarray(dist.total_mass, jnp.float64)
        )
        masses = np.asarray(md.voxel_masses(dist64, BOX))
        assert masses.dtype == np.float64
        ours = props64(jnp.asarray(masses))
        assert ours.inertia.dtype == jnp.float64

        model = _mujoco_body(masses, BOX)
        body = model.body("box").id
        np.testing.assert_allclose(float(ours.mass), model.body_mass[body], rtol=MASS_RTOL)
        np.testing.assert_allclose(float(ours.mass), float(dist.total_mass) + BOX.n_voxels * BOX.voxel_eps)
        com_err = np.max(np.abs(np.asarray(ours.com) - model.body_ipos[body])) / BOX.size[0]
        assert com_err <= COM_TOL, com_err
        ref = _mujoco_inertia(model, body)
        inertia_err = np.linalg.norm(np.asarray(ours.inertia) - ref) / np.linalg.norm(ref)
        assert inertia_err <= INERTIA_RTOL, inertia_err


def test_float32_path_close_to_float64():
    """The default float32 computation agrees with numpy float64 reference maths to ~1e-5."""
    for dist in _test_distributions()[::3]:
        ours = _PROPS(dist)
        masses = (
            np.asarray(dist.occupancy, np.float64) * float(dist.total_mass) / float(np.sum(dist.occupancy))
            + BOX.voxel_eps
        )
        model = _mujoco_body(masses, BOX)
        ref = _mujoco_inertia(model, 1)
        np.testing.assert_allclose(float(ours.mass), model.body_mass[1], rtol=F32_RTOL)
        assert np.max(np.abs(np.asarray(ours.com) - model.body_ipos[1])) / BOX.size[0] <= F32_RTOL
        assert np.linalg.norm(np.asarray(ours.inertia) - ref) / np.linalg.norm(ref) <= F32_RTOL


def test_single_voxel_inertia_is_a_solid_cuboid():
    """One occupied voxel (eps 0): COM at its centre, inertia m (b^2 + c^2) / 12 etc. about it."""
    box = BoxConfig(voxel_eps=0.0)
    dist = MassDistribution(jnp.asarray(_occ([(2, 5, 1)], box)), jnp.asarray(3.0))
    props = jax.jit(functools.partial(md.mass_properties, box=box))(dist)
    np.testing.assert_allclose(props.com, md.voxel_centres(box)[2, 5, 1], atol=1e-7)
    a, b, c = box.voxel_size
    expected = 3.0 / 12 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(props.inertia, expected, rtol=1e-5, atol=1e-12)


def test_voxel_centres_layout():
    c = md.voxel_centres(BOX)
    assert c.shape == (*BOX.grid, 3) and c.dtype == np.float32
    dx, dy, dz = BOX.voxel_size
    hx, hy, hz = BOX.half_size
    np.testing.assert_allclose(c[0, 0, 0], [-hx + dx / 2, -hy + dy / 2, -hz + dz / 2], atol=1e-7)
    np.testing.assert_allclose(c[-1, -1, -1], [hx - dx / 2, hy - dy / 2, hz - dz / 2], atol=1e-7)
    np.testing.assert_allclose(c.mean(axis=(0, 1, 2)), 0.0, atol=1e-7)


def test_voxel_masses_share_total_mass():
    dist = md.named("A", BOX)
    m = np.asarray(md.voxel_masses(dist, BOX))
    occ = np.asarray(dist.occupancy) > 0
    np.testing.assert_allclose(m[~occ], BOX.voxel_eps)
    np.testing.assert_allclose(m[occ], 5.0 / occ.sum() + BOX.voxel_eps, rtol=1e-6)


# ----------------------------------------------------------------------------------------------------------
# Principal axes.


def _check_principal_axes(inertia):
    diag, quat = md.principal_axes(inertia)
    assert diag.dtype == np.float64 and quat.shape == (4,)
    np.testing.assert_allclose(np.linalg.norm(quat), 1.0, atol=1e-12)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)  # MuJoCo's own (w, x, y, z) convention
    rot = rot.reshape(3, 3)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    scale = np.linalg.norm(inertia)
    np.testing.assert_allclose(rot @ np.diag(diag) @ rot.T, inertia, atol=1e-10 * scale)


def test_principal_axes_round_trip():
    for dist in _test_distributions():
        _check_principal_axes(np.asarray(_PROPS(dist).inertia, np.float64))
    rng = np.random.default_rng(0)
    for _ in range(50):
        a = rng.normal(size=(3, 3))
        _check_principal_axes(a @ a.T + 0.1 * np.eye(3))
    # Degenerate spectra: already diagonal, and fully isotropic.
    _check_principal_axes(np.diag([3.0, 1.0, 2.0]))
    _check_principal_axes(2.0 * np.eye(3))


def test_principal_axes_rejects_bad_input():
    with pytest.raises(ValueError, match="finite"):
        md.principal_axes(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="shape"):
        md.principal_axes(np.eye(2))


# ----------------------------------------------------------------------------------------------------------
# Hazard (paper §4.2).


@pytest.mark.parametrize("region", range(4))
def test_full_quarter_slab_is_hazardous(region):
    occ = _slab(BOX, region).astype(np.float32)
    dist = MassDistribution(jnp.asarray(occ), jnp.asarray(4.0))
    assert int(md.hazard_region(dist, BOX)) == region
    assert bool(md.is_hazardous(dist, BOX))


def test_default_grid_slabs_are_the_outer_two_voxel_columns_and_rows():
    masks = [_slab(BOX, r) for r in range(4)]
    i = np.arange(8)[:, None, None] * np.ones(BOX.grid, int)
    j = np.arange(8)[None, :, None] * np.ones(BOX.grid, int)
    np.testing.assert_array_equal(masks[0], i <= 1)
    np.testing.assert_array_equal(masks[1], i >= 6)
    np.testing.assert_array_equal(masks[2], j <= 1)
    np.testing.assert_array_equal(masks[3], j >= 6)


@pytest.mark.parametrize(
    ("inside", "outside", "region"),
    [
        ([(0, 3, 0), (1, 4, 3)], (2, 4, 0), 0),  # U1 plus a voxel in the next column
        ([(7, 3, 0), (6, 4, 3)], (5, 4, 0), 1),  # U2
        ([(3, 0, 0), (4, 1, 2)], (4, 2, 2), 2),  # U3
        ([(3, 7, 0), (4, 6, 2)], (4, 5, 2), 3),  # U4
    ],
)
def test_one_voxel_outside_the_slab_is_not_hazardous(inside, outside, region):
    slab = MassDistribution(jnp.asarray(_occ(inside)), jnp.asarray(1.0))
    assert int(md.hazard_region(slab, BOX)) == region
    spilled = MassDistribution(jnp.asarray(_occ([*inside, outside])), jnp.asarray(1.0))
    assert int(md.hazard_region(spilled, BOX)) == -1
    assert not bool(md.is_hazardous(spilled, BOX))


def test_eps_mass_does_not_count_and_empty_is_not_hazardous():
    # All the (eps) mass is everywhere, but occupancy says U1 only.
    dist = MassDistribution(jnp.asarray(_occ([(0, 4, 1)])), jnp.asarray(1.0))
    assert int(md.hazard_region(dist, BOX)) == 0
    empty = MassDistribution(jnp.zeros(BOX.grid), jnp.asarray(1.0))
    assert int(md.hazard_region(empty, BOX)) == -1


def test_named_hazard():
    for name in ("A", "B", "C", "uniform"):
        assert not bool(md.is_hazardous(md.named(name, BOX), BOX)), name
    assert int(md.hazard_region(md.named("D", BOX), BOX)) == 3  # U4: over one belt at yaw 0


GRIDS = [(4, 4, 1), (8, 8, 4), (12, 8, 3), (16, 12, 2)]


def _slab(box, region):
    """(nx, ny, nz) bool voxels of U1..U4 from the paper's definition, independently of massdist's masks.

    A voxel belongs to a quarter slab when its centre does (the slabs fall on voxel faces).
    """
    c = md.voxel_centres(box)
    length, width, _ = box.size
    return [
        c[..., 0] < -length / 4,  # U1: [0, l/4] in the paper's [0, l] coordinates
        c[..., 0] > length / 4,  # U2: [3l/4, l]
        c[..., 1] < -width / 4,  # U3: [0, w/4]
        c[..., 1] > width / 4,  # U4: [3w/4, w]
    ][region]


@st.composite
def _slab_occupancy(draw):
    grid = draw(st.sampled_from(GRIDS))
    box = BoxConfig(grid=grid)
    region = draw(st.integers(0, 3))
    mask = _slab(box, region)
    bits = draw(hnp.arrays(np.bool_, grid))
    seed_voxel = draw(st.sampled_from(np.argwhere(mask).tolist()))
    occ = bits & mask
    occ[tuple(seed_voxel)] = True  # at least one voxel occupied
    return box, region, occ


@settings(max_examples=60, deadline=None)
@given(_slab_occupancy())
def test_random_occupancy_in_a_quarter_slab_is_hazardous(case):
    box, _, occ = case
    dist = MassDistribution(jnp.asarray(occ, jnp.float32), jnp.asarray(1.0))
    region = int(md.hazard_region(dist, box))
    assert region >= 0
    # The reported region (the lowest whose slab holds everything; corners lie in two) contains every voxel.
    assert not np.any(occ & ~_slab(box, region))


@settings(max_examples=40, deadline=None)
@given(_slab_occupancy(), st.data())
def test_adding_a_central_voxel_breaks_the_hazard(case, data):
    box, _, occ = case
    # A voxel in none of U1..U4: the middle half along both length and width.
    central = ~(_slab(box, 0) | _slab(box, 1) | _slab(box, 2) | _slab(box, 3))
    voxel = data.draw(st.sampled_from(np.argwhere(central).tolist()))
    occ = occ.copy()
    occ[tuple(voxel)] = True
    dist = MassDistribution(jnp.asarray(occ, jnp.float32), jnp.asarray(1.0))
    assert int(md.hazard_region(dist, box)) == -1


# ----------------------------------------------------------------------------------------------------------
# Samplers.


@pytest.mark.parametrize("box", [BOX, BoxConfig(grid=(4, 8, 2), mass_range=(2.0, 3.0))])
def test_sample_vmaps_and_is_valid(box):
    keys = _keys(0, 64)
    dists = jax.vmap(functools.partial(md.sample, box=box))(keys)  # eager vmap: no compile of the whole
    occ = np.asarray(dists.occupancy)
    mass = np.asarray(dists.total_mass)
    assert occ.shape == (64, *box.grid) and occ.dtype == np.float32 and mass.shape == (64,)
    assert set(np.unique(occ)) <= {0.0, 1.0}
    assert np.all(occ.reshape(64, -1).sum(1) >= 1)
    lo, hi = box.mass_range
    assert np.all((mass >= lo) & (mass <= hi))
    for b in range(0, 64, 8):
        md.validate(MassDistribution(occ[b], mass[b]), box)
    # Deterministic for a key, and different keys give different boxes.
    again = md.sample(keys[5], box)
    np.testing.assert_array_equal(again.occupancy, occ[5])
    np.testing.assert_allclose(again.total_mass, mass[5])
    assert len({o.tobytes() for o in occ}) >= 60
    assert len(np.unique(mass)) == 64


def test_sample_statistics():
    """Fill fractions vary widely and only a few samples are hazardous (module docstring: ~4 %)."""
    dists = _SAMPLE(_keys(3))
    fill = np.asarray(dists.occupancy).reshape(N_KEYS, -1).mean(1)
    assert fill.min() > 0 and fill.min() < 0.03 and fill.max() > 0.8 and 0.12 < np.median(fill) < 0.3
    hazardous = np.mean(np.asarray(_HAZARD_REGION(dists)) >= 0)
    assert 0.01 < hazardous < 0.1


def test_sample_hazardous_is_always_hazardous():
    dists = _SAMPLE_HAZARDOUS(_keys(1))
    regions = np.asarray(_HAZARD_REGION(dists))
    assert np.all(regions >= 0)
    assert set(regions.tolist()) == {0, 1, 2, 3}
    assert np.all(np.asarray(dists.occupancy).reshape(N_KEYS, -1).sum(1) >= 1)
    lo, hi = BOX.mass_range
    assert np.all((np.asarray(dists.total_mass) >= lo) & (np.asarray(dists.total_mass) <= hi))


def test_sample_mixed_hazard_proportion():
    natural = float(np.mean(np.asarray(_HAZARD_REGION(_SAMPLE(_keys(7)))) >= 0))
    for p in (0.0, 0.25, 1.0):
        rate = float(np.mean(np.asarray(_HAZARD_REGION(_SAMPLE_MIXED(_keys(11), p))) >= 0))
        expected = p + (1 - p) * natural
        sigma = np.sqrt(expected * (1 - expected) / N_KEYS) + 1e-3
        assert abs(rate - expected) < 5 * sigma, (p, rate, expected)


def test_sample_rejects_zero_gaussians():
    with pytest.raises(ValueError, match="max_gaussians"):
        md.sample(jax.random.key(0), BOX, max_gaussians=0)


# ----------------------------------------------------------------------------------------------------------
# Gradients.


def test_grad_of_mass_properties_is_finite():
    def scalar(masses):
        p = md.mass_properties_from_masses(masses, BOX)
        return p.inertia[2, 2] + jnp.sum(p.com**2) + p.mass

    masses = md.voxel_masses(md.named("A", BOX), BOX)
    g = jax.jit(jax.grad(scalar))(masses)
    assert g.shape == BOX.grid and np.all(np.isfinite(g)) and np.any(g != 0)

    # Through voxel_masses too, w.r.t. a soft occupancy and the total mass (what a predictor would do).
    def from_dist(occ, total):
        return md.mass_properties(MassDistribution(occ, total), BOX).inertia[2, 2]

    soft = jnp.full(BOX.grid, 0.3)
    g_occ, g_m = jax.jit(jax.grad(from_dist, argnums=(0, 1)))(soft, jnp.asarray(5.0))
    assert np.all(np.isfinite(g_occ)) and np.isfinite(g_m)


def test_grad_matches_finite_differences(x64):
    masses = jnp.asarray(np.asarray(md.voxel_masses(md.named("C", BOX), BOX)), jnp.float64)

    @jax.jit
    def izz(m):
        return md.mass_properties_from_masses(m, BOX).inertia[2, 2]

    g = np.asarray(jax.grad(izz)(masses))
    h = 1e-6
    for idx in [(0, 0, 0), (3, 4, 1), (7, 2, 3)]:
        e = jnp.zeros(BOX.grid, jnp.float64).at[idx].set(h)
        fd = (float(izz(masses + e)) - float(izz(masses - e))) / (2 * h)
        np.testing.assert_allclose(g[idx], fd, rtol=1e-6, atol=1e-12)


# ----------------------------------------------------------------------------------------------------------
# Validation and description.


def _good():
    return md.named("A", BOX)


@pytest.mark.parametrize(
    ("occ", "mass", "match"),
    [
        (np.ones((8, 8, 3), np.float32), 5.0, r"shape \(8, 8, 3\).*\(8, 8, 4\)"),
        (np.where(np.arange(256).reshape(8, 8, 4) == 3, np.nan, 1.0), 5.0, "NaN or inf"),
        (np.where(np.arange(256).reshape(8, 8, 4) == 3, np.inf, 1.0), 5.0, "NaN or inf"),
        (np.full((8, 8, 4), 0.5, np.float32), 5.0, "0 or 1"),
        (np.zeros((8, 8, 4), np.float32), 5.0, "no mass"),
        (np.ones((8, 8, 4), np.float32), float("nan"), "total_mass"),
        (np.ones((8, 8, 4), np.float32), float("inf"), "total_mass"),
        (np.ones((8, 8, 4), np.float32), 0.0, "total_mass"),
        (np.ones((8, 8, 4), np.float32), -1.0, "total_mass"),
        (np.ones((8, 8, 4), np.float32), np.ones(2), "scalar"),
        (np.ones((8, 8, 4), np.float32), "5 kg", "number"),
    ],
)
def test_validate_names_the_problem(occ, mass, match):
    with pytest.raises(DistributionError, match=match):
        md.validate(MassDistribution(occ, mass), BOX)


def test_validate_accepts_good_distributions():
    for name in md.NAMES:
        d = md.named(name, BOX)
        assert md.validate(d, BOX) is d
    # A bool occupancy is fine too (host-side check only).
    md.validate(MassDistribution(np.asarray(_good().occupancy) > 0, 5.0), BOX)


def test_describe():
    text_a = md.describe(md.named("A", BOX), BOX)
    text_d = md.describe(md.named("D", BOX), BOX)
    assert "5.00 kg" in text_a and "cm" in text_a and "not hazardous" in text_a and "48/256" in text_a
    assert "HAZARDOUS" in text_d and "U4" in text_d
    assert text_a.count("\n") <= 1


# ----------------------------------------------------------------------------------------------------------
# Named distributions.


def test_named_unknown_lists_the_valid_names():
    with pytest.raises(ValueError, match="A, B, C, D, uniform"):
        md.named("E", BOX)


def test_named_similarity():
    a = md.named("A", BOX).occupancy
    assert float(md.iou(md.named("B", BOX).occupancy, a)) > 0.6
    assert float(md.iou(md.named("C", BOX).occupancy, a)) < 0.2
    assert float(md.iou(md.named("D", BOX).occupancy, a)) < 0.2
    assert float(md.iou(a, a)) == 1.0


# The documented centres of mass (cm) and voxel counts: the named distributions must never change silently.
NAMED_DOC = {
    "A": ((4.3, -3.3, -1.6), 48, 5.0),
    "B": ((6.2, -2.5, -1.8), 52, 5.5),
    "C": ((-5.2, 6.8, 2.2), 51, 8.0),
    "D": ((-2.1, 11.3, -2.2), 39, 7.0),
    "uniform": ((0.0, 0.0, 0.0), 256, 5.0),
}


@pytest.mark.parametrize("name", md.NAMES)
def test_named_match_their_docstring(name):
    com_cm, count, mass = NAMED_DOC[name]
    d = md.named(name, BOX)
    assert int(np.sum(d.occupancy)) == count
    assert float(d.total_mass) == mass
    lo, hi = BOX.mass_range
    assert lo <= mass <= hi
    np.testing.assert_allclose(100 * np.asarray(_PROPS(d).com), com_cm, atol=0.051)
    assert f"{com_cm[0]:+.1f}" in md.__doc__ or name == "uniform"


def test_named_on_another_grid():
    box = BoxConfig(grid=(12, 12, 6))
    for name in md.NAMES:
        d = md.validate(md.named(name, box), box)
        assert d.occupancy.shape == box.grid
    assert bool(md.is_hazardous(md.named("D", box), box))
    assert not bool(md.is_hazardous(md.named("A", box), box))


# ----------------------------------------------------------------------------------------------------------
# Plot (smoke test of boxjax.viz.plots' voxel figure).


def test_plot_mass_distributions_writes_png(tmp_path):
    from boxjax.viz import plots

    path = tmp_path / "sub" / "named.png"
    out = plots.plot_mass_distributions({"A": md.named("A", BOX), "D": md.named("D", BOX)}, BOX, path)
    assert out == str(path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in path.parent.iterdir()] == ["named.png"]  # no temporary file left behind
