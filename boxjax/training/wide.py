"""Wider training boxes for the estimators (issue 30): gaussian mixtures, items and slabs, never scatter.

`sample_wide(key, n, cfg)` draws n boxes, each from one family chosen by `WIDE_SHARES`: the gaussian
mixtures H was trained on (`massdist.sample_mixed`, 25 % drawn hazardous), and the items and slabs families
in their free and their hazardous forms. The scatter family (`massdist.sample_scatter`) is held out of every
training and tuning decision: it is the family the estimators are tested on without having seen it.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from boxjax import massdist
from boxjax.config import DEFAULT, Config

HELD_OUT = "scatter"
# (family, hazardous form?, share): shares sum to 1.
WIDE_SHARES = (
    ("gaussian", None, 0.4),  # sample_mixed, p_hazardous 0.25
    ("items", False, 0.15),
    ("items", True, 0.15),
    ("slabs", False, 0.15),
    ("slabs", True, 0.15),
)


@functools.cache
def _drawer(family: str, hazardous, box):
    """The jitted, key-vmapped sampler of one family form (built once: a new jit per call re-traces)."""
    if hazardous is None:
        fn = functools.partial(massdist.sample_mixed, box=box, p_hazardous=0.25)
    else:
        fn = functools.partial(massdist.sampler(family, hazardous), box=box)
    return jax.jit(jax.vmap(fn))


def _draw(family: str, hazardous, keys, box) -> massdist.MassDistribution:
    return _drawer(family, hazardous, box)(keys)


def sample_wide(
    key: jax.Array, n: int, cfg: Config = DEFAULT
) -> tuple[massdist.MassDistribution, np.ndarray]:
    """n boxes of the wide training mixture, shuffled; and (n,) int: the index into `WIDE_SHARES` of each."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    counts = np.floor(np.array([s for *_, s in WIDE_SHARES]) * n).astype(int)
    counts[0] += n - counts.sum()
    k_draw, k_perm = jax.random.split(key)
    parts, source = [], []
    for i, ((family, hazardous, _), c) in enumerate(zip(WIDE_SHARES, counts, strict=True)):
        if c:
            parts.append(
                _draw(family, hazardous, jax.random.split(jax.random.fold_in(k_draw, i), c), cfg.box)
            )
            source.append(np.full(c, i))
    order = np.asarray(jax.random.permutation(k_perm, n))
    dists = jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a])[order], *parts)
    return massdist.MassDistribution(*dists), np.concatenate(source)[order]


def sample_family(key: jax.Array, n: int, family: str, hazardous: bool, cfg: Config = DEFAULT):
    """n boxes of one family in `massdist.FAMILIES` (its hazardous or free form), numpy arrays."""
    d = _draw(family, hazardous, jax.random.split(key, n), cfg.box)
    return massdist.MassDistribution(np.asarray(d.occupancy), np.asarray(d.total_mass, np.float32))


__all__ = ["HELD_OUT", "WIDE_SHARES", "sample_family", "sample_wide"]
