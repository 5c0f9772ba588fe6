"""Design the exploration for information (`boxjax.estimator.design`), then measure in the simulator what it
reveals beside the shipped sequence.

  # explore.DESIGNED (about 12 min on the 2-core CPU):
  python scripts/exploration_design.py search --design-boxes 32 --sim-boxes 160 --screen 24 \
      --population 48 --elites 6 --iterations 14 --std 0.2 --out runs/design/search_guard.json
  # what it reveals in the simulator (about 6 min per sequence; --no-shipped skips the shipped one's row):
  python scripts/exploration_design.py validate --design runs/design/search_guard.json --boxes 8000 \
      --out runs/design/validate_guard.json

`search`: the cross-entropy method over 15-vector sequences (the shipped shape and rules) on --design-boxes
boxes of the wide training mixture (`boxjax.training.wide`; the held-out scatter family is never used),
maximising the prior's expected information gain about (com_x, com_y, com_z, log(I_zz / M)). Safety: with
--sim-boxes N, N label-safe boxes of the mixture are simulated for the --screen most informative candidates
of each iteration, and a candidate must keep the 95th percentile of their worst balance error and the
number judged past the exploration guard no worse than the shipped sequence's; without, the prior's
predicted 95th percentile (optimistic: docs/results/estimator-and-hazards.md#designed-exploration). It also
scores the candidates of `scripts/exploration_candidates.py` on the same boxes, so the prior's ranking can
be checked against the simulator's measurements of them.

`validate`: for the shipped sequence and each design, the protocol of `scripts/exploration_candidates.py`
(the same simulated boxes for all, a regressor of log mass, centre of mass and log I_zz trained on the
explorations' features per --net-seeds, its median errors on 1000 test boxes; the share of boxes pushed
past the 4 cm limit while exploring). Results: benchmarks/results_exploration_design.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.estimator import design, explore
from boxjax.prior import predictor
from boxjax.training import wide
from boxjax.training.estimator import write_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
import exploration_candidates as candidates  # noqa: E402


def _models(key, n):
    dists, _ = wide.sample_wide(key, n, DEFAULT)
    masses = jax.vmap(lambda o, m: massdist.voxel_masses(massdist.MassDistribution(o, m)))(
        jnp.asarray(dists.occupancy), jnp.asarray(dists.total_mass)
    )
    return jax.vmap(lambda m: predictor.make_prior(m))(masses), jax.vmap(design.theta_of)(masses)


def _score(models, vectors, c0) -> dict:
    g, std, worst = design.evaluate(DEFAULT, models, jnp.asarray(vectors, jnp.float32)[None], c0)
    return {
        "gain_nats": round(float(g[0]), 3),
        "posterior_std_median": dict(
            zip(design.THETA, [round(float(v), 4) for v in np.median(np.asarray(std[0]), 0)], strict=True)
        ),
        "predicted_balance_p95_cm": round(float(100 * np.percentile(np.asarray(worst[0]), 95)), 2),
    }


def search(args) -> None:
    t0 = time.perf_counter()
    _, theta = _models(jax.random.key(args.seed + 1), 2000)
    c0 = jnp.cov(np.asarray(theta).T)  # the population's belief about theta before any exploration
    models, _ = _models(jax.random.key(args.seed), args.design_boxes)
    sim_boxes = None
    if args.sim_boxes:  # label-safe boxes of the wide mixture, for the simulated safety constraint
        dists, _ = wide.sample_wide(jax.random.key(args.seed + 3), 2 * args.sim_boxes, DEFAULT)
        safe = ~np.asarray(jax.vmap(massdist.is_hazardous)(dists))
        idx = np.flatnonzero(safe)[: args.sim_boxes]
        sim_boxes = massdist.MassDistribution(dists.occupancy[idx], dists.total_mass[idx])

    def progress(it, best):
        print(
            f"iteration {it}: best gain {best.gain:.3f} nats (p95 balance {100 * best.balance_p95:.2f} cm, "
            f"guard trips {best.guard_trips}; {best.history[-1]['feasible']} feasible)",
            flush=True,
        )

    found = design.search(
        jax.random.key(args.seed + 2),
        models,
        c0,
        population=args.population,
        elites=args.elites,
        iterations=args.iterations,
        sim_boxes=sim_boxes,
        screen=args.screen,
        std=args.std,
        progress=progress,
    )
    scores = {name: _score(models, np.asarray(v), c0) for name, v in candidates.CANDIDATES.items()}
    scores["designed"] = _score(models, found.vectors, c0)
    out = {
        "command": " ".join(sys.argv),
        "design_boxes": args.design_boxes,
        "prior_std": dict(zip(design.THETA, np.sqrt(np.diag(np.asarray(c0))).round(4).tolist(), strict=True)),
        "vectors": np.round(found.vectors, 5).tolist(),
        "history": found.history,
        "scores": scores,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(scores), flush=True)
    write_json(args.out, out)


def validate(args) -> None:
    designs = {Path(f).stem: json.loads(Path(f).read_text()) for f in args.design}
    sequences = {k: np.asarray(d["vectors"]) for k, d in designs.items()}
    if not args.no_shipped:
        sequences = {"shipped": explore.VECTORS} | sequences
    rows = []
    for name, vectors in sequences.items():
        for row in candidates.evaluate(name, vectors, args.boxes, net_seeds=args.net_seeds):
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "vectors"}), flush=True)
    write_json(args.out, {"command": " ".join(sys.argv), "designs": designs, "results": rows})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("search")
    s.add_argument("--design-boxes", type=int, default=32)
    s.add_argument("--population", type=int, default=48)
    s.add_argument("--elites", type=int, default=6)
    s.add_argument("--iterations", type=int, default=10)
    s.add_argument("--seed", type=int, default=40)
    s.add_argument(
        "--sim-boxes",
        type=int,
        default=0,
        help="label-safe boxes whose SIMULATED worst balance error constrains the search (0: the prior's)",
    )
    s.add_argument("--out", required=True)
    s.add_argument("--std", type=float, default=0.6, help="initial sampling std of the free variables")
    s.add_argument(
        "--screen", type=int, help="simulate only this many most informative candidates per iteration"
    )
    v = sub.add_parser("validate")
    v.add_argument("--design", nargs="+", required=True, help="JSON files `search` wrote")
    v.add_argument("--boxes", type=int, default=8000)
    v.add_argument("--net-seeds", type=int, nargs="+", default=[0, 1])
    v.add_argument("--no-shipped", action="store_true", help="skip the shipped sequence's row")
    v.add_argument("--out", required=True)
    args = ap.parse_args()
    search(args) if args.what == "search" else validate(args)


if __name__ == "__main__":
    main()
