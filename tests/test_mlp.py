"""The pure-JAX MLP: shapes, parameter count, deterministic init, He scaling, and that it can learn."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from boxjax import mlp


def test_shapes_and_param_count():
    params = mlp.init(jax.random.key(0), (3, 5, 2))
    assert [(p["w"].shape, p["b"].shape) for p in params] == [((3, 5), (5,)), ((5, 2), (2,))]
    assert mlp.n_params(params) == 3 * 5 + 5 + 5 * 2 + 2
    assert mlp.sizes_of(params) == (3, 5, 2)
    assert mlp.apply(params, jnp.ones(3)).shape == (2,)
    batched = jax.vmap(mlp.apply, in_axes=(None, 0))(params, jnp.ones((7, 3)))
    assert batched.shape == (7, 2)
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree_util.tree_leaves(params))


def test_apply_is_for_one_example():
    params = mlp.init(jax.random.key(0), (3, 2))
    with pytest.raises(ValueError, match="ONE example"):
        mlp.apply(params, jnp.ones((4, 3)))


def test_last_layer_linear_unless_asked():
    params = mlp.init(jax.random.key(0), (2, 4))
    params[0]["b"] = -10.0 * jnp.ones(4)  # pre-activations all very negative
    x = jnp.zeros(2)
    np.testing.assert_allclose(mlp.apply(params, x, jax.nn.relu), -10.0)
    np.testing.assert_allclose(mlp.apply(params, x, jax.nn.relu, activate_last=True), 0.0)


def test_init_deterministic_by_key():
    a = mlp.init(jax.random.key(1), (4, 8, 3))
    b = mlp.init(jax.random.key(1), (4, 8, 3))
    c = mlp.init(jax.random.key(2), (4, 8, 3))
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert not np.array_equal(a[0]["w"], c[0]["w"])
    assert not np.array_equal(a[0]["w"], a[1]["w"][:4, :3])  # layers get distinct keys


def test_init_he_scale_and_zero_bias():
    params = mlp.init(jax.random.key(0), (1000, 1000, 1000))
    assert np.std(params[0]["w"]) == pytest.approx(np.sqrt(2 / 1000), rel=0.02)
    assert np.std(params[1]["w"]) == pytest.approx(np.sqrt(1 / 1000), rel=0.02)  # last layer: LeCun
    assert not np.any(params[0]["b"])


@pytest.mark.parametrize("sizes", [(3,), (), (3, 0, 2)])
def test_init_rejects_bad_sizes(sizes):
    with pytest.raises(ValueError):
        mlp.init(jax.random.key(0), sizes)


def test_tiny_mlp_learns_a_function():
    x = jnp.linspace(-1, 1, 128)[:, None]
    y = jnp.sin(3 * x)
    params = mlp.init(jax.random.key(0), (1, 32, 32, 1))
    opt = optax.adam(1e-2)

    def loss(p):
        pred = jax.vmap(mlp.apply, in_axes=(None, 0))(p, x)
        return jnp.mean((pred - y) ** 2)

    @jax.jit
    def fit(p):
        def step(carry, _):
            p, s = carry
            value, g = jax.value_and_grad(loss)(p)
            u, s = opt.update(g, s, p)
            return (optax.apply_updates(p, u), s), value

        (p, _), values = jax.lax.scan(step, (p, opt.init(p)), None, length=600)
        return p, values

    trained, _ = fit(params)
    assert float(loss(trained)) < float(loss(params)) / 10
    assert float(loss(trained)) < 1e-2


def test_fit_classifier_separates_a_linear_rule():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2048, 3)).astype(np.float32)
    y = x[:, 0] + 0.5 * x[:, 1] > 0
    net = mlp.fit_classifier(jax.random.PRNGKey(0), x, y, (16,), epochs=40, batch_size=64)
    acc = np.mean((np.asarray(mlp.logits(net, x)) > 0) == y)
    assert acc > 0.95
