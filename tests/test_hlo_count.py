"""The operation counter of the benchmarks (benchmarks/_hlo.py), checked on programs whose loops are known."""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
from _hlo import dynamic_ops  # noqa: E402


def _nested(outer: int, inner: int, unroll: bool = False):
    def f(x):
        def body(c, _):
            def step(d, _):
                return jnp.sin(d) * 2 + jnp.cumsum(d), None  # cumsum: not fused into the elementwise chain

            d, _ = jax.lax.scan(step, c, None, length=inner, unroll=unroll)
            return jnp.cos(d) + jnp.cumsum(d), None

        y, _ = jax.lax.scan(body, x, None, length=outer)
        return y

    return dynamic_ops(jax.jit(f).lower(jnp.ones(3)).compile().as_text())


def test_loop_iterations_and_operations_multiply_through_nested_loops():
    base = _nested(4, 3)
    assert base["while_iterations"] == 4 + 4 * 3  # the outer loop's 4 and the inner loop's 3 in each
    deeper = _nested(4, 6)
    assert deeper["while_iterations"] == 4 + 4 * 6
    # The inner body's operations run 4 x 3 more times per call: the count grows with the trip counts while
    # the program's text does not.
    assert deeper["ops"] > base["ops"] and deeper["static_ops"] == base["static_ops"]
    assert _nested(8, 3)["ops"] > base["ops"]


def test_an_unrolled_inner_loop_leaves_only_the_outer_one():
    unrolled = _nested(4, 3, unroll=True)
    assert unrolled["while_iterations"] == 4
    assert unrolled["static_ops"] > _nested(4, 3)["static_ops"]  # the body written out three times


def test_operations_are_split_by_the_function_they_come_from():
    from _hlo import by_source

    def inner_work(d):
        return jnp.sin(d) * 2 + jnp.cumsum(d)

    def f(x):
        def body(c, _):
            return inner_work(c), None

        y, _ = jax.lax.scan(body, x, None, length=5)
        return jnp.cumsum(y)

    text = jax.jit(f).lower(jnp.ones(3)).compile().as_text()
    split = by_source(text, package="tests")
    assert sum(split.values()) == dynamic_ops(text)["ops"]
    # the loop body's operations run 5 times and come from inner_work (its innermost frame in the package)
    assert (
        split[
            "test_hlo_count.py:test_operations_are_split_by_the_function_they_come_from.<locals>.inner_work"
        ]
        >= 5
    )
