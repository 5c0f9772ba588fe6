"""The exploration's expected information under the prior (`boxjax.estimator.design`): the Jacobians against
finite differences, closed-form cases (no motion: no information), the search's constraints."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import massdist, planning
from boxjax.config import DEFAULT
from boxjax.estimator import design, explore
from boxjax.prior import predictor


@pytest.fixture(scope="module")
def boxes():
    masses = jnp.stack([massdist.voxel_masses(massdist.named(n)) for n in ("A", "B", "C", "uniform")])
    models = jax.vmap(lambda m: predictor.make_prior(m))(masses)
    theta = jax.vmap(design.theta_of)(masses)
    return masses, models, theta


def _one(models, i):
    return jax.tree.map(lambda a: a[i], models)


def test_theta_round_trip_keeps_the_prior(boxes):
    masses, models, theta = boxes
    m = _one(models, 0)
    back = design.with_theta(m, theta[0])
    np.testing.assert_allclose(back.com, m.com, atol=1e-7)
    np.testing.assert_allclose(back.izz, m.izz, rtol=1e-5)
    np.testing.assert_allclose(back.offsets, m.offsets, atol=1e-7)
    p = massdist.mass_properties(massdist.named("A"))
    np.testing.assert_allclose(theta[0, :3], p.com, atol=1e-6)
    np.testing.assert_allclose(np.exp(theta[0, 3]), p.inertia[2, 2] / p.mass, rtol=1e-5)


def test_jacobian_matches_finite_differences(boxes):
    """The per-step Jacobian behind the Fisher information, against central differences of the prior's
    one-step prediction in theta (a turning step of box A, from the shipped sequence's rollout)."""
    _, models, theta = boxes
    m = _one(models, 0)
    actions = design.actions_of(explore.VECTORS)
    states = jax.jit(m.rollout_sequence)(
        planning.initial_window(design.initial_state()), jnp.zeros(2), actions
    )
    w, b, a = states[4:7], jnp.array([0.09, -0.09]), actions[7]

    @jax.jit
    def f(th):
        return predictor.predict(design.with_theta(m, th), w, b, a)[2:]

    jac = np.asarray(jax.jit(jax.jacfwd(f))(theta[0]))
    for i, h in enumerate((1e-3, 1e-3, 1e-3, 1e-2)):
        e = np.zeros(4, np.float32)
        e[i] = h
        fd = (np.asarray(f(theta[0] + e)) - np.asarray(f(theta[0] - e))) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=0.1, atol=2e-3 * np.abs(jac).max())


@pytest.fixture(scope="module")
def three(boxes):
    """The shipped sequence, its turns alone (no probes), and no motion: gains, posterior stds, worst balance
    errors on the named boxes (one compile of `design.evaluate` for 3 sequences, shared with the search)."""
    _, models, theta = boxes
    c0 = jnp.cov(theta.T) + 1e-6 * jnp.eye(4)
    full = jnp.asarray(explore.VECTORS, jnp.float32)
    seqs = jnp.stack([full, full.at[4:12].set(0.0), jnp.zeros((15, 4))])
    return c0, design.evaluate(DEFAULT, models, seqs, c0)


@pytest.mark.slow  # with the next: 15 s compiling `design.evaluate`; the gain's closed form and Jacobian stay
def test_no_motion_reveals_nothing(boxes, three):
    """Belts at rest and carriages still: the pose does not depend on where the mass sits, so the Fisher
    information is zero, the gain 0 nats and the posterior the prior (closed form)."""
    c0, (g, std, worst) = three
    assert abs(float(g[2])) < 1e-5
    np.testing.assert_allclose(std[2], jnp.broadcast_to(jnp.sqrt(jnp.diag(c0)), std[2].shape), rtol=1e-4)
    assert float(jnp.max(worst[2])) < 1e-6


def test_gain_is_the_gaussian_information_gain():
    """0.5 log det(I + C0^1/2 F C0^1/2) and the posterior std against the textbook forms."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 4))
    f = a @ a.T
    b = rng.normal(size=(4, 4))
    c0 = b @ b.T + 0.1 * np.eye(4)
    eig, std = design.gain(jnp.asarray(f, jnp.float32), jnp.asarray(c0, jnp.float32))
    post = np.linalg.inv(np.linalg.inv(c0) + f)
    want = 0.5 * (np.linalg.slogdet(c0)[1] - np.linalg.slogdet(post)[1])
    np.testing.assert_allclose(float(eig), want, rtol=1e-3)
    np.testing.assert_allclose(std, np.sqrt(np.diag(post)), rtol=1e-3)


@pytest.mark.slow  # shares the fixture above
def test_more_turning_shows_more(three):
    """The shipped sequence reveals something (gain > 0), and its turn and probes show more than its turns
    alone."""
    _, (g, _, _) = three
    assert float(g[0]) > float(g[1]) > 0


def test_sequence_keeps_the_rules():
    free = 3.0 * jax.random.normal(jax.random.key(0), (200, 14, 4))
    vecs = np.asarray(jax.vmap(design.sequence)(free))
    v, dp = vecs[..., :2], vecs[..., 2:]
    prev = np.concatenate([np.zeros((200, 1, 2)), v[:, :-1]], 1)
    assert np.all(np.abs(v - prev) <= design.DV_MAX + 1e-6)  # no setpoint the 0.6 m/s^2 ramp would clip
    assert np.all(np.abs(v) <= design.V_MAX + 1e-6)
    assert np.all(v[:, -1] == 0)  # the belts end at rest
    assert np.all(np.abs(dp[:, :-1]) <= design.DP_MAX + 1e-7)
    assert np.all(np.abs(dp[:, -1]) <= DEFAULT.gripper.max_position_step + 1e-7)
    undone = np.abs(np.asarray(jax.vmap(design.undone_error)(vecs)))
    ok = np.abs(3 * dp[:, :-1].sum(1)) <= 3 * DEFAULT.gripper.max_position_step
    assert np.all(undone[ok] < 1e-6)  # within reach of the last vector, every move is undone
    np.testing.assert_allclose(design.sequence(design.free_of(explore.VECTORS)), explore.VECTORS, atol=2e-4)


@pytest.mark.slow  # 12 s, mostly compiling the one-sequence evaluation
def test_search_never_returns_worse_than_its_start(boxes, three):
    _, models, _ = boxes
    c0, _ = three
    found = design.search(jax.random.key(1), models, c0, population=3, elites=2, iterations=2)
    g0, _, w0 = design.evaluate(DEFAULT, models, jnp.asarray(explore.VECTORS, jnp.float32)[None], c0)
    assert found.gain >= float(g0[0]) - 1e-4
    assert found.balance_p95 <= float(np.percentile(np.asarray(w0[0]), 95)) + 1e-6
    assert found.vectors.shape == (15, 4) and len(found.history) == 2 and found.guard_trips == -1
    np.testing.assert_allclose(design.undone_error(found.vectors), 0.0, atol=1e-4)


def test_guard_judged_is_the_guards_judgement():
    """The offline guard judgement equals what `explore.Guarded` judges, step by step (no sensor noise)."""
    rng = np.random.default_rng(3)
    h = np.cumsum(rng.normal(0, 0.004, size=(5, 46)), axis=1)
    judged = design.guard_judged(h, lead=3)
    for row, want in zip(h, judged, strict=True):
        g = explore.Guarded(DEFAULT, 0.875, lead=3)
        s = np.zeros(5)
        got = []
        for b in row:
            s[3] = b  # the box's y with the belts at -0.1 / +0.1: the offset is y
            s[0], s[1] = -0.1, 0.1
            got.append(g._judge(s, abs(b)))
        np.testing.assert_allclose(want, got, atol=1e-12)


def test_simulated_offsets_are_the_explorations():
    """The batched simulation of several sequences gives each box the balance error its own rollout gives
    (`explore.describe_effect`), and no motion none."""
    names = ("uniform", "A", "C")
    dists = [massdist.named(n) for n in names]
    batch = massdist.MassDistribution(
        np.stack([np.asarray(d.occupancy) for d in dists]), np.array([float(d.total_mass) for d in dists])
    )
    off = design.simulated_offsets(DEFAULT, batch, np.stack([explore.VECTORS, np.zeros((15, 4))]))
    assert off.shape == (2, 3, 46)
    effect = explore.describe_effect(DEFAULT, names)
    np.testing.assert_allclose(
        100 * np.abs(off[0]).max(1), [effect[n]["max_balance_error_cm"] for n in names], atol=0.01
    )
    np.testing.assert_allclose(off[1], 0.0, atol=1e-4)
