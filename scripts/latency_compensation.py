"""How well the controller knows the balance error under observation latency: the pose filter's own
constant-velocity extrapolation against the model's prediction through the actions sent
(`planning.compensate`), on no-fault episodes of random boxes (docs/results/faults.md).

    python scripts/latency_compensation.py --boxes 8
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning
from boxjax.config import DEFAULT as CFG
from boxjax.control import episode
from boxjax.control.config import ControllerConfig
from boxjax.control.models import planning_model
from boxjax.control.state_estimate import FilterConfig
from boxjax.control.world import World
from boxjax.sim.faults import Faults


def _stats(errors) -> dict:
    e = np.abs(np.asarray(errors))
    return {"rms_mm": 1e3 * float(np.sqrt(np.mean(e**2))), "p99_mm": 1e3 * float(np.quantile(e, 0.99))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--boxes", type=int, default=8)
    p.add_argument("--latencies", type=int, nargs="+", default=[1, 2, 4])
    args = p.parse_args()
    compensate = jax.jit(planning.compensate)
    cv = {d: [] for d in args.latencies}
    model = {d: [] for d in args.latencies}
    for seed in range(args.boxes):
        truth = massdist.sample(jax.random.PRNGKey(seed), CFG.box)
        if bool(massdist.is_hazardous(truth, CFG.box)):
            continue
        res = episode.run_episode(CFG, truth, jax.random.PRNGKey(100 + seed))
        s, b = res.trace.s.astype(np.float32), res.trace.belt_speed.astype(np.float32)
        a = res.trace.actions.astype(np.float32)
        prior = planning_model(CFG, ControllerConfig(), truth, None, {})
        for d in args.latencies:
            # the filter alone: it extrapolates its velocity over the latency (perfect camera, late)
            world = World(
                CFG, Faults(obs_latency=d), FilterConfig(compensation="constant_velocity", enabled=True),
                jax.random.PRNGKey(seed), truth,
            )  # fmt: skip
            for t in range(len(s)):
                seen, _ = world.observe(s[t], b[t])
                if t >= 50:
                    cv[d].append(float(geometry.balance_error(seen) - geometry.balance_error(s[t])))
            # the model through the actions applied since the (late) observation
            for t in range(50, len(a)):
                w = jnp.asarray(s[t - d - 2 : t - d + 1])
                wc, _ = compensate(prior, w, jnp.asarray(b[t - d]), jnp.asarray(a[t - d : t]))
                model[d].append(float(geometry.balance_error(wc[-1]) - geometry.balance_error(s[t])))
    out = {
        "boxes": args.boxes,
        "constant_velocity": {d: _stats(cv[d]) for d in args.latencies},
        "model": {d: _stats(model[d]) for d in args.latencies},
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
