"""The moments estimator on held-out explorations: coverage of its stated uncertainty, its errors beside H's,
and the hazard decisions (H's rule, the moments' Bayes rule, either) per box family (issue 30).

Box sets (each simulated with the fixed exploration by `--make`, cached as .npz under --data):
  wide:           the training mixture (`training.wide.sample_wide`), a seed no training used: the
                  development set the moments rule's threshold is chosen on (false aborts <= --budget);
  gaussian_free:  `massdist.sample` (label-safe ones are the safe boxes `boxjax evaluate` turns);
  scatter_free:   loose contents anywhere (the HELD-OUT family: nothing was trained or tuned on it);
  <family>_haz:   the hazardous form of gaussian, items, slabs, scatter.

    python scripts/moments_hazards.py --make                 # simulate the sets (about 3 min)
    python scripts/moments_hazards.py --out benchmarks/results_moments_hazards.json   # the shipped model
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist, mlp
from boxjax.config import DEFAULT
from boxjax.estimator import hazard
from boxjax.estimator import moments as M
from boxjax.estimator.shipped import SHIPPED_MOMENTS, default_estimator
from boxjax.fileio import atomic_path
from boxjax.training import dataset, wide

SETS = {  # name: (family or "wide", hazardous form, boxes, seed)
    "wide": ("wide", None, 2000, 102),
    "gaussian_free": ("gaussian", False, 1500, 108),
    "scatter_free": ("scatter", False, 1000, 103),
    "gaussian_haz": ("gaussian", True, 300, 106),
    "items_haz": ("items", True, 300, 105),
    "slabs_haz": ("slabs", True, 300, 107),
    "scatter_haz": ("scatter", True, 300, 104),
}
LIBRARY_SEED, LIBRARY_BOXES = 7, 100_000


def make(data_dir: str) -> None:
    os.makedirs(data_dir, exist_ok=True)
    for name, (family, haz, n, seed) in SETS.items():
        path = os.path.join(data_dir, f"{name}.npz")
        if os.path.exists(path):
            continue
        key = jax.random.PRNGKey(seed)
        d = wide.sample_wide(key, n)[0] if family == "wide" else wide.sample_family(key, n, family, haz)
        t = time.time()
        data = dataset.simulate(DEFAULT, d, progress=False, chunk=1000)
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(tmp, **data)
        print(f"{name}: {n} boxes simulated in {time.time() - t:.0f} s", flush=True)


def _rate(x) -> float:
    return round(float(np.mean(x)), 4) if np.size(x) else None


def assess(model: M.MomentsModel, h_model, library: M.Library, sets: dict, budget: float) -> dict:
    box = DEFAULT.box
    est, post, truth, h_haz, h_com = {}, {}, {}, {}, {}
    for name, data in sets.items():
        traj, final = jnp.asarray(data["traj"]), jnp.asarray(data["final"])
        est[name] = jax.tree.map(np.asarray, M.predict_batch(model, traj, final))
        post[name] = jax.tree.map(np.asarray, M.hazard_posterior_batch(M.Moments(*est[name]), library))
        dists = massdist.MassDistribution(jnp.asarray(data["occupancy"]), jnp.asarray(data["total_mass"]))
        truth[name] = M.true_moments_batch(dists, box)
        ev = hazard.evidence_batch(h_model, traj, final)
        h_haz[name] = np.asarray(hazard.decide_batch(h_model, ev, "physics")["hazardous"], bool)
        h_com[name] = np.asarray(ev.com)

    out = {"coverage": {}, "median_abs_error": {}}
    for name in ("wide", "scatter_free"):
        out["coverage"][name] = M.coverage(M.Moments(*est[name]), truth[name])
        err = np.abs(est[name].mean - truth[name])
        out["median_abs_error"][name] = {q: float(np.median(err[:, i])) for i, q in enumerate(M.QUANTITIES)}
        out["median_stated_std"] = out.get("median_stated_std", {})
        out["median_stated_std"][name] = {
            q: float(np.median(est[name].std[:, i])) for i, q in enumerate(M.QUANTITIES)
        }
        out["median_abs_error"][name + "_H_com"] = {
            q: float(np.median(np.abs(h_com[name][:, i] - truth[name][:, 1 + i])))
            for i, q in enumerate(("com_x", "com_y", "com_z"))
        }

    # The moments rule's threshold: the lowest at which the development set's safe boxes are refused at
    # most `budget` of the time.
    dev = post["wide"].hazardous[~np.asarray(sets["wide"]["hazardous"], bool)]
    tau = float(np.quantile(dev, 1 - budget, method="higher")) + 1e-6
    out["threshold"] = {"tau": tau, "chosen_on": "wide (development set)", "false_abort_budget": budget}
    rules = {
        "H (physics or head, shipped)": lambda n: h_haz[n],
        "moments": lambda n: post[n].hazardous >= tau,
        "H or moments": lambda n: h_haz[n] | (post[n].hazardous >= tau),
    }
    table = {}
    for rule, decide in rules.items():
        row = {}
        for name, data in sets.items():
            d, haz = decide(name), np.asarray(data["hazardous"], bool)
            if name.endswith("_haz"):
                row[f"{name} refused"] = _rate(d)
            else:
                row[f"{name} safe aborted"] = _rate(d[~haz])
                row[f"{name} hazardous refused"] = _rate(d[haz])
        table[rule] = row
    out["rules"] = table
    out["n_eff_median"] = {n: float(np.median(p.n_eff)) for n, p in post.items()}
    out["ceiling_exact_moments"] = ceiling(library, truth, sets, budget)
    return out


CEILING_INPUTS = {  # what a classifier is given EXACTLY (QUANTITIES' indices)
    "planar (centre of mass, radius of gyration I_zz)": (1, 2, 3, 7),
    "full (centre of mass, spreads along x, y, z)": (1, 2, 3, 4, 5, 6),
}


def ceiling(library: M.Library, truth: dict, sets: dict, budget: float, seed: int = 0) -> dict:
    """What any estimator could reach: an MLP classifier given the EXACT moments (no exploration), trained
    on the library (the training families), its threshold chosen on the development set's safe boxes."""
    out = {}
    lib_x, lib_y = np.asarray(library.q), np.asarray(library.region) >= 0
    for name, cols in CEILING_INPUTS.items():
        cols = list(cols)
        mu, sd = lib_x[:, cols].mean(0), lib_x[:, cols].std(0)
        net = mlp.fit_classifier(jax.random.PRNGKey(seed), (lib_x[:, cols] - mu) / sd, lib_y, seed=seed)
        score = {n: np.asarray(mlp.logits(net, (t[:, cols] - mu) / sd)) for n, t in truth.items()}
        dev_safe = score["wide"][~np.asarray(sets["wide"]["hazardous"], bool)]
        thr = float(np.quantile(dev_safe, 1 - budget, method="higher"))
        row = {}
        for n, data in sets.items():
            haz = np.asarray(data["hazardous"], bool)
            if n.endswith("_haz"):
                row[f"{n} refused"] = _rate(score[n] > thr)
            else:
                row[f"{n} safe aborted"] = _rate(score[n][~haz] > thr)
        out[name] = row
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="runs/moments_sets", help="folder of the simulated sets")
    ap.add_argument("--make", action="store_true", help="simulate the missing sets first")
    ap.add_argument("--moments", help="the moments checkpoint (default: shipped)")
    ap.add_argument("--budget", type=float, default=0.01, help="false aborts allowed on the development set")
    ap.add_argument("--out", help="write the JSON here")
    args = ap.parse_args(argv)
    if args.make:
        make(args.data)
    path = args.moments or str(SHIPPED_MOMENTS)
    model, _ = M.load(path, DEFAULT.box)
    lib_d, _ = wide.sample_wide(jax.random.PRNGKey(LIBRARY_SEED), LIBRARY_BOXES)
    library = M.make_library(
        massdist.MassDistribution(jnp.asarray(lib_d.occupancy), jnp.asarray(lib_d.total_mass)), DEFAULT.box
    )
    sets = {n: dict(np.load(os.path.join(args.data, f"{n}.npz"))) for n in SETS}
    res = {"moments": path, "library": {"seed": LIBRARY_SEED, "boxes": LIBRARY_BOXES}}
    res.update(assess(model, default_estimator(), library, sets, args.budget))
    text = json.dumps(res, indent=1)
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as f:
            f.write(text + "\n")
    print(text)
    return res


if __name__ == "__main__":
    main()
