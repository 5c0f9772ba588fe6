"""The default planner's call with `prior.contact.solve3` differentiated two ways, in one run: through the
adjugate's cross products (JAX's autodiff of the formula, as before 2026-12-07) and implicitly (the
`custom_jvp`, x' = a^-1 (b' - a' x) from the adjugate the value already formed; the default).

For each, one call (one box) and 16 calls vmapped (the width of a batched evaluation's call): compile
time, the operations and loop iterations one call runs (`_hlo.dynamic_ops`, on a GPU each operation is a
kernel launch) and the latency, the two variants' calls interleaved (median), and whether the two plans
agree (the forward pass is the same; the gradient steps' round-off is not). Prints ONE JSON line.

    python benchmarks/solve3_derivative.py [--calls 100] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _hlo import dynamic_ops  # noqa: E402
from _util import emit_to, machine  # noqa: E402

from boxjax import massdist, prior  # noqa: E402
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.planners import sampling as sp  # noqa: E402
from boxjax.prior import contact, predictor  # noqa: E402

IMPLICIT = contact.solve3


def adjugate_autodiff(a, b):
    """`solve3` without its custom derivative: JAX differentiates the adjugate formula itself."""
    c0, c1, c2, det = contact._adjugate(a)
    return (c0 * b[0] + c1 * b[1] + c2 * b[2]) / det


def _use(solve) -> None:
    """Every caller of `solve3` (the normal loads and the friction step) traces `solve` from now on."""
    contact.solve3 = predictor.solve3 = solve


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=100, help="timed calls per variant (interleaved)")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    cfg = DEFAULT
    masses = massdist.voxel_masses(massdist.named("A", cfg.box), cfg.box)
    s = jnp.array([-0.11, 0.12, 0.01, -0.005, 0.4])  # a box part-way through a turn (as planner.py)
    step = jnp.array([0, 0, 1e-3, 5e-4, 0.02])
    window = jnp.stack([s - 2 * step, s - step, s])
    speed, target = jnp.array([0.12, -0.1]), jnp.float32(np.pi / 2)
    opts = sp.SamplingOptions()
    model = prior.make_prior(masses)
    nominal = sp.initial_nominal(cfg, opts, speed)

    calls, out = {}, {}
    for name, solve in (("adjugate_autodiff", adjugate_autodiff), ("implicit", IMPLICIT)):
        _use(solve)  # traced now, at the compiles below
        jax.clear_caches()  # nothing traced with the other variant is reused

        def plan(k, m, n):  # a new function per variant: jit's cache knows functions, not the patch
            return sp.plan(k, m, window, speed, target, n, cfg, opts)

        for width in (1, 16):
            fn = jax.jit(plan) if width == 1 else jax.jit(jax.vmap(plan, in_axes=(0, None, None)))
            keys = jax.random.key(0) if width == 1 else jax.random.split(jax.random.key(0), width)
            t0 = time.perf_counter()
            compiled = fn.lower(keys, model, nominal).compile()
            compile_s = time.perf_counter() - t0
            first = jax.tree.leaves(jax.block_until_ready(compiled(keys, model, nominal)))[0]
            calls[(name, width)] = (compiled, keys, np.asarray(first))
            out[f"{name}_x{width}"] = {"compile_s": compile_s, **dynamic_ops(compiled.as_text())}
    _use(IMPLICIT)
    times = {k: [] for k in calls}
    for _ in range(args.calls):
        for k, (compiled, keys, _) in calls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(keys, model, nominal))
            times[k].append(time.perf_counter() - t0)
    for (name, width), t in times.items():
        out[f"{name}_x{width}"]["median_ms"] = 1e3 * float(np.median(t))
    for width in (1, 16):
        a, b = calls[("adjugate_autodiff", width)][2], calls[("implicit", width)][2]
        out[f"plans_max_difference_x{width}"] = float(np.max(np.abs(a - b)))
    result = {
        "benchmark": "solve3_derivative",
        "calls": args.calls,
        **out,
        "ops_ratio_x1": out["implicit_x1"]["ops"] / out["adjugate_autodiff_x1"]["ops"],
        "load_avg_1m": os.getloadavg()[0],
        **machine(),
        "command": "python benchmarks/solve3_derivative.py " + " ".join(argv or sys.argv[1:]),
    }
    emit_to(result, args.out)
    return result


if __name__ == "__main__":
    main()
