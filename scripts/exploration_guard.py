"""The exploration guard on box families: boxes lost while exploring, refused by the guard, per rule.

The guard (`explore.Guarded`) watches the balance error during the fixed 45-step exploration; past its
threshold the belts stop, the carriages re-centre for 20 steps and the box is refused. Boxes with their
mass at one end swing their geometric centre sideways by ~1 cm per step during the first turn and cross
the 4 cm limit within a step of any fixed threshold: the guard's `lead` extrapolates the balance error
along its trend. Each rule runs the exploration closed loop (the guard acts on what it sees), box by box
with the native simulator; a box is "lost" when it crosses the limit, leaves the belts or tips.

    python scripts/exploration_guard.py --out benchmarks/results_exploration_guard.json

Development boxes: seeds 301-307, no evaluation seed (0-2) and no held-out set of scripts/moments_hazards.py.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

from boxjax import massdist
from boxjax.config import DEFAULT as cfg
from boxjax.estimator import explore
from boxjax.fileio import atomic_path
from boxjax.sim import make_env
from boxjax.training import wide

SETS = {  # name: (family, hazardous form, boxes, seed)
    "gaussian_free": ("gaussian", False, 600, 301),
    "items_free": ("items", False, 300, 302),
    "slabs_free": ("slabs", False, 300, 303),
    "gaussian_haz": ("gaussian", True, 150, 304),
    "items_haz": ("items", True, 150, 305),
    "slabs_haz": ("slabs", True, 150, 306),
    "scatter_haz": ("scatter", True, 150, 307),
}
RULES = {  # name: (guard fraction of the limit or None, lead steps)
    "none (paper)": (None, 0),
    "3.5 cm (default before)": (0.875, 0),
    "3.5 cm, lead 2": (0.875, 2),
    "3.5 cm, lead 3": (0.875, 3),
    "3.5 cm, lead 4": (0.875, 4),
    "3.0 cm": (0.75, 0),
}


def explore_one(env, dist, guard: float | None, lead: int, noise_m: float = 0.0, seed: int = 0):
    """(lost, refused by the guard, worst true balance error m) of one box's guarded exploration. The guard
    sees the planar state with gaussian noise of std `noise_m` on x and y (a camera's pose noise; the
    carriages' positions are the drives' own, exact)."""
    state = env.reset(jax.random.PRNGKey(0), dist)
    g = explore.Guarded(cfg, guard, lead=lead)
    rng = np.random.default_rng(seed)
    worst = float(state.balance_error)
    while not bool(state.done):
        seen = np.asarray(state.s, np.float64).copy()
        seen[2:4] += noise_m * rng.standard_normal(2)
        a = g.next(seen, abs(seen[3] - 0.5 * (seen[0] + seen[1])))
        if a is None:
            break
        state = env.step(state, a)
        worst = max(worst, float(state.balance_error))
    return bool(state.done), g.tripped, worst


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every set's box count")
    ap.add_argument("--rules", nargs="*", default=list(RULES), help="rule names (default: all)")
    ap.add_argument("--sets", nargs="*", default=list(SETS), help="set names (default: all)")
    ap.add_argument("--noise-mm", type=float, default=0.0, help="pose noise the guard sees (std, mm)")
    ap.add_argument("--out", help="write the JSON here")
    args = ap.parse_args(argv)
    env = make_env(cfg)
    res = {"sets": {}, "rules": {}, "noise_mm": args.noise_mm}
    t0 = time.time()
    for name in args.sets:
        family, haz, n, seed = SETS[name]
        n = max(1, int(n * args.scale))
        d = wide.sample_family(jax.random.PRNGKey(seed), n, family, haz)
        labels = np.asarray(jax.vmap(lambda x: massdist.is_hazardous(x, cfg.box))(d)).astype(bool)
        res["sets"][name] = {"family": family, "hazardous_form": haz, "boxes": n, "seed": seed}
        for rule in args.rules:
            guard, lead = RULES[rule]
            out = [
                explore_one(env, jax.tree.map(lambda a, j=j: a[j], d), guard, lead, args.noise_mm / 1000, j)
                for j in range(n)
            ]
            lost = np.array([o[0] for o in out])
            refused = np.array([o[1] for o in out]) & ~lost
            row = res["rules"].setdefault(rule, {})
            row[name] = {
                "lost": int(lost.sum()),
                "refused_by_guard": int(refused.sum()),
                "safe_boxes": int((~labels).sum()),
                "safe_refused": int((refused & ~labels).sum()),
                "safe_lost": int((lost & ~labels).sum()),
                "hazardous_lost": int((lost & labels).sum()),
            }
            print(f"{time.time() - t0:6.0f} s  {name:14s} {rule:24s} {row[name]}", flush=True)
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as f:
            json.dump(res, f, indent=1)
            f.write("\n")
    return res


if __name__ == "__main__":
    main()
