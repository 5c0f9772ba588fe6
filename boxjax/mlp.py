"""A pure-JAX multilayer perceptron (no Flax): params are a plain pytree, `apply` acts on ONE example.

Params are a list of layers, each a dict {"w": (in, out), "b": (out,)} of float32 arrays. Batches are
handled from outside with `jax.vmap(apply, in_axes=(None, 0))`.

Initialisation (He / Kaiming normal, fan-in): w ~ N(0, 2 / fan_in), b = 0. The factor 2 keeps the
activation variance roughly constant through ReLU / GELU layers (He et al. 2015). The last layer, which
has no activation, is scaled by `last_scale` (default 1 / sqrt(2), i.e. LeCun's 1 / fan_in variance),
so initial outputs are O(1) rather than inflated by the ReLU gain.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

Params = list  # list[dict[str, jax.Array]]


def init(key: jax.Array, sizes: Sequence[int], last_scale: float = 1 / np.sqrt(2.0)) -> Params:
    """He-normal weights and zero biases for layer widths `sizes` = (in, hidden..., out).

    Args:
      key: PRNG key, split once per layer.
      sizes: at least two ints >= 1; `len(sizes) - 1` dense layers.
      last_scale: multiplies the last layer's weights (see module docstring).
    Returns:
      list of {"w": (sizes[i], sizes[i + 1]) float32, "b": (sizes[i + 1],) float32}.
    """
    sizes = [int(s) for s in sizes]
    if len(sizes) < 2 or min(sizes) < 1:
        raise ValueError(f"need at least two layer sizes, all >= 1; got {sizes}")
    layer_keys = jax.random.split(key, len(sizes) - 1)
    params = []
    for i, (k, n_in, n_out) in enumerate(zip(layer_keys, sizes[:-1], sizes[1:], strict=True)):
        scale = np.sqrt(2.0 / n_in) * (last_scale if i == len(sizes) - 2 else 1.0)
        w = scale * jax.random.normal(k, (n_in, n_out), jnp.float32)
        params.append({"w": w, "b": jnp.zeros((n_out,), jnp.float32)})
    return params


def apply(
    params: Params,
    x: jax.Array,
    activation: Callable[[jax.Array], jax.Array] = jax.nn.gelu,
    activate_last: bool = False,
) -> jax.Array:
    """Forward pass for ONE example.

    Args:
      params: from `init`.
      x: (in,) input.
      activation: applied after every hidden layer (and after the last one if `activate_last`).
      activate_last: True for a trunk whose output feeds further layers.
    Returns:
      (out,) output, linear unless `activate_last`.
    """
    if x.ndim != 1:
        raise ValueError(f"apply takes ONE example of shape (in,), got {x.shape}; vmap for batches")
    h = x
    for i, layer in enumerate(params):
        h = h @ layer["w"] + layer["b"]
        if activate_last or i < len(params) - 1:
            h = activation(h)
    return h


def n_params(params) -> int:
    """Total number of scalars in any params pytree."""
    return int(sum(np.size(leaf) for leaf in jax.tree_util.tree_leaves(params)))


def sizes_of(params: Params) -> tuple[int, ...]:
    """Layer widths (in, hidden..., out) of an MLP built by `init`."""
    return (int(params[0]["w"].shape[0]), *(int(layer["w"].shape[1]) for layer in params))


def fit_classifier(
    key: jax.Array,
    x,
    y,
    hidden: Sequence[int] = (128, 128),
    *,
    epochs: int = 15,
    batch_size: int = 512,
    optimizer: optax.GradientTransformation | None = None,
    seed: int = 0,
) -> Params:
    """A binary classifier (x (N, F) -> one logit) trained by sigmoid cross-entropy on labels y (N,),
    minibatches shuffled by numpy's generator `seed` (a partial last batch is dropped), Adam(1e-3) unless
    `optimizer` is given; returns its params (`logits` scores a batch)."""
    x, y = jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32)
    net = init(key, (x.shape[1], *hidden, 1))
    opt = optax.adam(1e-3) if optimizer is None else optimizer
    state = opt.init(net)

    def loss(net, xb, yb):
        return jnp.mean(optax.sigmoid_binary_cross_entropy(logits(net, xb), yb))

    @jax.jit
    def step(net, state, idx):
        g = jax.grad(loss)(net, x[idx], y[idx])
        u, state = opt.update(g, state, net)
        return optax.apply_updates(net, u), state

    rng = np.random.default_rng(seed)
    for _ in range(epochs):
        perm = rng.permutation(x.shape[0])
        for i in range(0, len(perm) - batch_size + 1, batch_size):
            net, state = step(net, state, jnp.asarray(perm[i : i + batch_size]))
    return net


def logits(params: Params, x) -> jax.Array:
    """(N,) the first output of a batch x (N, in)."""
    return jax.vmap(lambda v: apply(params, v)[0])(jnp.asarray(x, jnp.float32))
