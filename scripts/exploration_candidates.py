"""Compare exploration sequences: what a net can recover from each, and how safe each is while exploring.

For every candidate (15 vectors (v1, v2, dp1, dp2), each held 3 steps, like
`boxjax.estimator.explore.VECTORS`) this
simulates the same random boxes (`boxjax.training.dataset`, seeds 100 / 101: --boxes training and 1000 test
boxes,
25 % drawn hazardous), then

  * safety: the share of non-hazardous / hazardous test boxes whose balance error crosses the 4 cm limit
    during the exploration (the episode would end there), and the 95th percentile for non-hazardous boxes;
  * information: an ensemble of 2 MLPs (900 -> 512 x 3 -> 5, AdamW, early stopping on 10 % of the training
    boxes) regresses log mass, centre of mass (x, y, z) and log I_zz from H's features
    (`boxjax.estimator.features`); the median absolute errors on the test boxes. These are the rigid-body
    quantities through which the mass distribution reaches the simulation (`scripts/estimator_ceiling.py`).

Usage: python scripts/exploration_candidates.py [--boxes 8000] [--only NAME ...] [--out FILE.json]
(about 100 s per candidate with 8000 boxes on the 2-core CPU). Prints one JSON line per candidate.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from boxjax import estimator as E
from boxjax import massdist, mlp
from boxjax.config import DEFAULT
from boxjax.estimator import explore
from boxjax.training import dataset
from boxjax.training.estimator import write_json

_TURN = [[+0.09, -0.09, 0, 0], [+0.12, -0.12, 0, 0]]
_PROBES = [
    [+0.09, 0, 0, 0],
    [0, +0.09, 0, 0],
    [0, 0, +0.007, 0],
    [0, 0, -0.007, 0],
    [0, 0, 0, -0.007],
    [0, 0, 0, +0.007],
]
_SQUEEZE = [[0, 0, +0.007, -0.007], [0, 0, -0.007, +0.007]]
_SHIFT = [[0, 0, +0.004, +0.004], [0, 0, -0.004, -0.004]]
_PREVIOUS = (
    _TURN
    + [[+0.09, -0.09, +0.004, +0.004], [+0.09, -0.09, -0.004, -0.004], [0, 0, 0, 0]]
    + _PROBES
    + _SQUEEZE
    + _SHIFT
)

CANDIDATES = {
    # The sequence shipped before 2026-11-30: turn while shifting, probes at the final yaw, a squeeze.
    "previous": _PREVIOUS,
    "longer_turn": _TURN
    + [[+0.12, -0.12, +0.004, +0.004], [+0.12, -0.12, -0.004, -0.004], [+0.03, -0.03, 0, 0]]
    + _PROBES
    + _SQUEEZE
    + _SHIFT,
    "oscillate": [
        [+0.09, -0.09, 0, 0],
        [+0.09, -0.09, 0, 0],
        [0, 0, 0, 0],
        [-0.09, +0.09, 0, 0],
        [-0.09, +0.09, 0, 0],
        [0, 0, 0, 0],
        [+0.09, -0.09, 0, 0],
        [0, 0, 0, 0],
    ]
    + _PROBES
    + _SQUEEZE[:1],
    "turn_probe_squeeze_return": _TURN
    + [[+0.09, -0.09, 0, 0], [0, 0, 0, 0]]
    + _PROBES
    + _SQUEEZE
    + [[-0.09, +0.09, 0, 0], [-0.12, +0.12, 0, 0], [-0.03, +0.03, 0, 0]],
    "previous_without_squeeze": _PREVIOUS[:11] + [[-0.09, +0.09, 0, 0], [0, 0, 0, 0]] + _SHIFT,
    # boxjax.estimator.explore.VECTORS since 2026-11-30: turn, probe at the turned yaw, turn back, end at
    # rest.
    "turn_probe_return": explore.VECTORS.tolist(),
}


@contextlib.contextmanager
def exploration(vectors):
    """Run `boxjax.estimator.explore` with another sequence inside the block (the module reads VECTORS per
    call)."""
    saved = explore.VECTORS
    explore.VECTORS = np.asarray(vectors, np.float64)
    try:
        yield
    finally:
        explore.VECTORS = saved


_batched_features = jax.jit(jax.vmap(E.features))
_batched_properties = jax.jit(jax.vmap(lambda d: massdist.mass_properties(d, DEFAULT.box)))


def _features(d) -> np.ndarray:
    n = len(d["traj"])
    return np.concatenate(
        [
            np.asarray(_batched_features(d["traj"][i : i + 4000], d["final"][i : i + 4000]))
            for i in range(0, n, 4000)
        ]
    )


def _targets(d) -> np.ndarray:
    p = _batched_properties(
        massdist.MassDistribution(jnp.asarray(d["occupancy"]), jnp.asarray(d["total_mass"]))
    )
    return np.concatenate(
        [
            np.log(np.asarray(p.mass))[:, None],
            np.asarray(p.com),
            np.log(np.asarray(p.inertia[:, 2, 2]))[:, None],
        ],
        1,
    )


def _fit(key: int, x, y, xv, yv, epochs: int = 150, batch: int = 128, patience: int = 20):
    """One MLP regressor, MSE, AdamW with a cosine schedule; the parameters with the best validation loss."""
    params = mlp.init(jax.random.key(key), (x.shape[1], 512, 512, 512, y.shape[1]))
    steps = epochs * (len(x) // batch)
    opt = optax.chain(
        optax.clip_by_global_norm(1.0),
        optax.adamw(optax.cosine_decay_schedule(1e-3, steps), weight_decay=1e-4),
    )
    state = opt.init(params)

    def loss(p, xb, yb):
        return jnp.mean((jax.vmap(lambda v: mlp.apply(p, v, jax.nn.gelu))(xb) - yb) ** 2)

    @jax.jit
    def epoch(p, s, k):
        order = jax.random.permutation(k, len(x))[: (len(x) // batch) * batch].reshape(-1, batch)

        def body(carry, idx):
            p, s = carry
            g = jax.grad(loss)(p, x[idx], y[idx])
            upd, s = opt.update(g, s, p)
            return (optax.apply_updates(p, upd), s), None

        return jax.lax.scan(body, (p, s), order)[0]

    val_loss = jax.jit(loss)
    k = jax.random.key(key + 99)
    best, best_params, since = np.inf, params, 0
    for _ in range(epochs):
        k, kk = jax.random.split(k)
        params, state = epoch(params, state, kk)
        v = float(val_loss(params, xv, yv))
        best, best_params, since = (v, params, 0) if v < best else (best, best_params, since + 1)
        if since >= patience:
            break
    return lambda xq: np.asarray(jax.vmap(lambda v: mlp.apply(best_params, v, jax.nn.gelu))(xq))


def evaluate(name: str, vectors, n_boxes: int, net_seeds=(0,)) -> list[dict]:
    """One row per net seed (the nets of seed k are initialised and shuffled with 2k, 2k + 1), all on the
    same simulated boxes."""
    t0 = time.perf_counter()
    with exploration(vectors):
        train = dataset.generate(jax.random.key(100), n_boxes, DEFAULT, progress=False)
        test = dataset.generate(jax.random.key(101), 1000, DEFAULT, progress=False)
    gen_s = time.perf_counter() - t0
    bal, haz = test["max_balance_error"], test["hazardous"]
    x, y, xt, yt = _features(train), _targets(train), _features(test), _targets(test)
    order = np.random.default_rng(0).permutation(len(x))
    iv, it = order[: len(x) // 10], order[len(x) // 10 :]
    mu, sd = x[it].mean(0), x[it].std(0) + 1e-9
    ym, ys = y[it].mean(0), y[it].std(0)

    def scale(a):
        return jnp.asarray((a - mu) / sd, jnp.float32)

    yn = jnp.asarray((y - ym) / ys, jnp.float32)
    rows = []
    for seed in net_seeds:
        t1 = time.perf_counter()
        nets = [_fit(2 * seed + m, scale(x[it]), yn[it], scale(x[iv]), yn[iv]) for m in range(2)]
        err = np.abs(np.mean([f(scale(xt)) for f in nets], 0) * ys + ym - yt)
        rows.append(
            {
                "name": name,
                "net_seed": seed,
                "vectors": [list(map(float, v)) for v in vectors],
                "boxes": n_boxes,
                "safe_over_4cm": float(np.mean(bal[~haz] > 0.04)),
                "hazardous_over_4cm": float(np.mean(bal[haz] > 0.04)),
                "safe_balance_p95_cm": float(100 * np.percentile(bal[~haz], 95)),
                "com_error_cm_median_xyz": [round(float(v), 3) for v in 100 * np.median(err[:, 1:4], 0)],
                "log_mass_error_median": float(np.median(err[:, 0])),
                "log_izz_error_median": float(np.median(err[:, 4])),
                "simulate_s": gen_s,
                "fit_s": time.perf_counter() - t1,
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--boxes", type=int, default=8000, help="training boxes per candidate")
    ap.add_argument("--only", nargs="+", choices=list(CANDIDATES), help="evaluate only these")
    ap.add_argument("--out", help="also write all results to this JSON file (atomically)")
    args = ap.parse_args()
    if args.boxes < 100:
        ap.error("need --boxes >= 100")
    results = []
    for name in args.only or list(CANDIDATES):
        vectors = np.asarray(CANDIDATES[name], np.float64)
        if vectors.shape != (explore.N_VECTORS, 4):
            sys.exit(f"candidate {name}: need {explore.N_VECTORS} vectors of 4, got {vectors.shape}")
        results += evaluate(name, vectors, args.boxes)
        print(json.dumps(results[-1]), flush=True)
    if args.out:
        write_json(args.out, {"command": " ".join(sys.argv), "results": results})


if __name__ == "__main__":
    main()
