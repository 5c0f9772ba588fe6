"""Hazard recall and false aborts of H's hazard decisions (issue 11 item 4), exploration + H only.

Boxes (one seed; every family from its own key):
  * gaussian: `massdist.sample_hazardous` (the hazardous family H was trained on);
  * items: `massdist.sample_items_hazardous` (1-3 small items, 1-16 voxels, inside one outer quarter; H never
    saw such boxes);
  * safe: `massdist.sample` with the hazardous draws rejected (paper §4.3's label-safe boxes);
  * items_any (optional, --items-any N): `massdist.sample_items`, small items anywhere (hazardous or not):
    recall on its hazardous boxes, false aborts on its label-safe ones.
Each box runs the fixed 45-step exploration open loop (`dataset.simulate`, native MuJoCo on all threads);
H's ensemble gives its evidence (`boxjax.estimator.hazard.evidence_batch`) and each rule decides: "head" (H's
hazard
head alone, its calibrated threshold), "physics_only" and "physics" (physics or head; the controller's
default). Diagnostics in physical terms: H's centre-of-mass error on each family against the depth of the
true centre of mass inside its region, and what a rule on the TRUE centre of mass (or its first two moments
along the quarter's axis) would abort. `--ceiling-boxes N` also fits a classifier on the EXACT centre of
mass and inertia tensor (`moment_ceiling`, no simulation): what the rigid body's physics can decide at all.

  .venv/bin/python scripts/hazard_recall.py --seed 0 --hazardous 100 --safe 300 \
      [--items-any 300] [--weights FILE ...] [--ceiling-boxes 40000]

Prints one JSON object (last line).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import estimator as E
from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.estimator import hazard
from boxjax.estimator.shipped import check_exploration, default_estimator
from boxjax.training import dataset as ds


def _draw(sampler, key, n, box):
    return jax.jit(jax.vmap(functools.partial(sampler, box=box)))(jax.random.split(key, n))


def _safe(key, n, box):
    """n label-safe `massdist.sample` draws (hazardous ones rejected), in vmapped rounds."""
    parts, got, i = [], 0, 0
    while got < n:
        d = _draw(massdist.sample, jax.random.fold_in(key, i), 2 * n, box)
        keep = ~np.asarray(jax.vmap(massdist.is_hazardous, in_axes=(0, None))(d, box))
        parts.append(jax.tree.map(lambda a, keep=keep: np.asarray(a)[keep], d))
        got += int(keep.sum())
        i += 1
    return jax.tree.map(lambda *a: np.concatenate(a)[:n], *parts)


def _rate(x) -> float | None:
    x = np.asarray(x, bool)
    return float(x.mean()) if x.size else None


def _pct(x, qs=(50, 95, 100)) -> dict:
    x = np.asarray(x, np.float64)
    return {f"p{q}": round(float(np.percentile(x, q)), 2) for q in qs} if x.size else {}


def _operating_points(score, family, haz) -> dict:
    """For a score where higher = more hazardous (the head's probability, the physics margin): the recall
    reached at the threshold that aborts at most 2 % of the safe boxes, and the safe boxes a threshold
    low enough to refuse EVERY hazardous box of a family would abort (oracle thresholds, for information)."""
    safe = score[family == "safe"]
    out = {}
    if safe.size:
        thr = float(np.quantile(safe, 0.98, method="higher"))
        out["threshold_at_2pct_false_aborts"] = round(thr, 4)
        for f in ("gaussian", "items"):
            m = family == f
            if m.any():
                out[f"{f}_recall_at_2pct_false_aborts"] = _rate(score[m] > thr)
                out[f"false_abort_rate_to_refuse_every_{f}"] = _rate(safe >= score[m].min())
    return out


def _moments_fit_a_quarter(truth, box) -> np.ndarray:
    """(B,) bool: the TRUE centre of mass and inertia along a quarter's axis are consistent with all the
    mass inside that quarter. A mass distribution on [lo, hi] with mean mu and variance s^2 exists iff
    s^2 <= (hi - mu)(mu - lo) (Bhatia-Davis); the variance comes from the inertia tensor,
    sum m x^2 = tr(I) / 2 - I_xx (voxels as solid cuboids, so the support is the quarter itself). Every
    hazardous box passes. A rule that sees only these two moments per axis, exactly, and never misses a
    hazardous box must refuse every box that passes; the rest of the tensor (and the voxel grid) can rule
    out some of them, so the share of safe boxes passing is an upper bound for a rule on the exact tensor."""
    props = jax.vmap(lambda d: massdist.mass_properties(d, box))(truth)
    mass, com, inertia = (np.asarray(a, np.float64) for a in props)
    second = (
        np.trace(inertia, axis1=1, axis2=2)[:, None] / 2 - np.diagonal(inertia, axis1=1, axis2=2)
    ) / mass[:, None]
    hx, hy, _ = box.half_size
    lx, ly, _ = box.size
    fits = []
    for axis, lo, hi in (
        (0, -hx, -hx + lx / 4),
        (0, hx - lx / 4, hx),
        (1, -hy, -hy + ly / 4),
        (1, hy - ly / 4, hy),
    ):
        mu, var = com[:, axis], second[:, axis]
        fits.append((mu >= lo) & (mu <= hi) & (var <= (hi - mu) * (mu - lo) + 1e-9))
    return np.any(fits, axis=0)


def moment_ceiling(seed: int, n_train: int, n_test: int, cfg, epochs: int = 40) -> dict:
    """What the EXACT centre of mass and inertia can decide: an MLP (9 -> 256 x 3 -> 1, AdamW, BCE) from
    the centre of mass and the inertia tensor per unit mass (no voxels) to the paper's label, trained on
    fresh draws of every family (n_train `sample`, n_train / 4 each of `sample_hazardous`,
    `sample_items_hazardous`, `sample_items`) and tested on n_test more. No simulation: this is the
    information the simulated box carries (a rigid body), not what H extracts from 45 steps of it."""
    import optax

    from boxjax import mlp

    box = cfg.box

    def feats(d):
        p = jax.vmap(lambda x: massdist.mass_properties(x, box))(d)
        per_mass = p.inertia / p.mass[:, None, None]
        iu = jnp.triu_indices(3)
        x = jnp.concatenate([p.com / 0.1, per_mass[:, iu[0], iu[1]] / 0.003], axis=1)
        return np.asarray(x), np.asarray(jax.vmap(massdist.is_hazardous, in_axes=(0, None))(d, box))

    def draw_all(key, n):
        k = jax.random.split(key, 4)
        samplers = (
            massdist.sample,
            massdist.sample_hazardous,
            massdist.sample_items_hazardous,
            massdist.sample_items,
        )
        names = ("sample", "gaussian", "items", "items_any")
        sizes = (n, n // 4, n // 4, n // 4)
        parts = [feats(_draw(f, kk, m, box)) for f, kk, m in zip(samplers, k, sizes, strict=True)]
        xs, ys = [p[0] for p in parts], [p[1] for p in parts]
        fam = np.concatenate([[nm] * m for nm, m in zip(names, sizes, strict=True)])
        return np.concatenate(xs), np.concatenate(ys), fam

    key_tr, key_te, key_init = jax.random.split(jax.random.fold_in(jax.random.key(seed), 99), 3)
    x_tr, y_tr, _ = draw_all(key_tr, n_train)
    x_te, y_te, fam = draw_all(key_te, n_test)
    t0 = time.perf_counter()
    net = mlp.fit_classifier(
        key_init,
        x_tr,
        y_tr,
        (256, 256, 256),
        epochs=epochs,
        batch_size=256,
        optimizer=optax.adamw(1e-3),
        seed=seed,
    )
    score = np.asarray(jax.vmap(lambda v: mlp.apply(net, v)[0])(jnp.asarray(x_te)))
    safe = score[(fam == "sample") & ~y_te]
    thr = float(np.quantile(safe, 0.98, method="higher"))
    out = {
        "train_boxes": int(len(x_tr)),
        "test_safe_boxes": int(safe.size),
        "train_s": round(time.perf_counter() - t0, 1),
    }
    for f in ("gaussian", "items"):
        m = fam == f
        out[f"{f}_recall_at_2pct_false_aborts"] = _rate(score[m] > thr)
        out[f"false_abort_rate_to_refuse_every_{f}"] = _rate(safe >= score[m].min())
    m = fam == "items_any"
    out["items_any_recall_at_that_threshold"] = _rate(score[m & y_te] > thr)
    out["items_any_false_abort_rate_at_that_threshold"] = _rate(score[m & ~y_te] > thr)
    return out


def assess_estimator(model, data, family, truth, cfg, show_misses: int = 3) -> dict:
    """Rules, physical diagnostics and a few explained misses of one estimator on simulated boxes."""
    box = cfg.box
    ev = jax.tree.map(
        np.asarray, hazard.evidence_batch(model, jnp.asarray(data["traj"]), jnp.asarray(data["final"]))
    )
    true_com = np.asarray(jax.vmap(lambda d: massdist.mass_properties(d, box).com)(truth))
    true_region = np.asarray(jax.vmap(massdist.hazard_region, in_axes=(0, None))(truth, box))
    haz = np.asarray(data["hazardous"], bool)
    fams = list(dict.fromkeys(family.tolist()))

    decisions = {r: hazard.decide_batch(model, ev, r) for r in hazard.HAZARD_RULES}
    rules = {}
    for r, dec in decisions.items():
        h = dec["hazardous"]
        row = {}
        for f in fams:
            m = family == f
            if f == "safe":
                row["safe_false_aborts"] = int(h[m].sum())
                row["safe_false_abort_rate"] = _rate(h[m])
            elif f == "items_any":
                row["items_any_recall"] = _rate(h[m & haz])
                row["items_any_false_abort_rate"] = _rate(h[m & ~haz])
            else:
                row[f"{f}_refused"] = int(h[m].sum())
                row[f"{f}_recall"] = _rate(h[m])
        rules[r] = row
    operating = {
        "head_probability": _operating_points(np.asarray(ev.head), family, haz),
        "physics_margin": _operating_points(decisions["physics"]["margin"], family, haz),
    }

    # Physical diagnostics: centre-of-mass error (cm) and the true centre of mass's depth inside its region.
    ax, sg = np.array([0, 0, 1, 1]), np.array([-1.0, 1.0, -1.0, 1.0])
    quarter = np.array([box.size[a] / 4 for a in ax])
    true_depth = sg * true_com[:, ax] - quarter  # (B, 4) m
    com_err = 100 * np.linalg.norm(ev.com - true_com, axis=1)
    diag = {}
    for f in fams:
        m = family == f
        row = {"com_error_cm": _pct(com_err[m])}
        hm = m & haz
        if hm.any():
            i = np.where(hm)[0]
            r = true_region[i]
            row["true_com_depth_in_region_cm"] = _pct(100 * true_depth[i, r], (0, 5, 50))
            row["est_com_depth_in_region_cm"] = _pct(100 * ev.depth[i, r], (0, 5, 50))
            row["com_error_along_region_axis_cm"] = _pct(100 * np.abs(ev.depth[i, r] - true_depth[i, r]))
            row["est_mass_fraction_in_region"] = {
                f"p{q}": round(float(np.percentile(ev.fraction[i, r], q)), 3) for q in (0, 5, 50)
            }
        if f == "safe":
            row["est_max_mass_fraction_in_a_region"] = {
                f"p{q}": round(float(np.percentile(ev.fraction[m].max(1), q)), 3) for q in (50, 95, 98, 100)
            }
            # What a rule on the TRUE centre of mass that refuses every hazardous box would abort:
            row["true_com_in_a_quarter_rate"] = _rate((true_depth[m] >= 0).any(1))
            row["true_moments_consistent_with_a_quarter_rate"] = _rate(_moments_fit_a_quarter(truth, box)[m])
            hz_idx = np.where(haz & np.isin(family, ("gaussian", "items")))[0]
            if hz_idx.size:
                min_haz = float(np.min(true_depth[hz_idx, true_region[hz_idx]]))
                row["shallowest_hazardous_true_depth_cm"] = round(100 * min_haz, 2)
                row["true_com_as_deep_as_shallowest_hazardous_rate"] = _rate(
                    (true_depth[m] >= min_haz).any(1)
                )
        diag[f] = row

    misses = {}
    for f in ("gaussian", "items"):
        idx = np.where((family == f) & ~decisions["physics"]["hazardous"])[0][:show_misses]
        texts = []
        for j in idx:
            one = jax.tree.map(lambda a, j=j: a[j], ev)
            true = massdist.MassDistribution(truth.occupancy[j], truth.total_mass[j])
            text = hazard.explain(model, one, hazard.decide(model, one))
            texts.append(text + " Truth: " + massdist.describe(true, box).replace("\n", "; "))
        misses[f] = texts
    return {
        "hazard_threshold": model.hazard_threshold,
        "physics_rule": dataclasses.asdict(hazard.DEFAULT_RULE),
        "rules": rules,
        "operating_points": operating,
        "diagnostics": diag,
        "missed_by_physics_rule": misses,
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hazardous", type=int, default=100, help="hazardous boxes of EACH family")
    ap.add_argument("--safe", type=int, default=300, help="label-safe boxes")
    ap.add_argument("--items-any", type=int, default=0, help="boxes of massdist.sample_items (any label)")
    ap.add_argument(
        "--weights",
        nargs="*",
        default=[],
        help="estimator checkpoints, all on the same boxes (default: shipped H)",
    )
    ap.add_argument("--show-misses", type=int, default=3, help="explanations of this many missed boxes")
    ap.add_argument(
        "--ceiling-boxes", type=int, default=0, help="also fit the exact-moment classifier on this many boxes"
    )
    args = ap.parse_args(argv)
    cfg = DEFAULT
    box = cfg.box
    t0 = time.perf_counter()
    models = {}
    for path in args.weights or [None]:
        if path is None:
            models["boxjax/data/estimator.npz"] = default_estimator(cfg)
        else:
            models[path] = E.load(path, expected_box_config=box)
            check_exploration(models[path], cfg, path)

    key_g, key_i, key_s, key_a = jax.random.split(jax.random.key(args.seed), 4)
    fams = {
        "gaussian": _draw(massdist.sample_hazardous, key_g, args.hazardous, box),
        "items": _draw(massdist.sample_items_hazardous, key_i, args.hazardous, box),
        "safe": _safe(key_s, args.safe, box),
    }
    if args.items_any:
        fams["items_any"] = _draw(massdist.sample_items, key_a, args.items_any, box)
    family = np.concatenate([[f] * int(np.shape(d.total_mass)[0]) for f, d in fams.items()])
    dists = jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a]), *fams.values())
    t1 = time.perf_counter()
    data = ds.simulate(cfg, dists, progress=False, chunk=500)
    sim_s = time.perf_counter() - t1
    truth = massdist.MassDistribution(jnp.asarray(data["occupancy"]), jnp.asarray(data["total_mass"]))
    # Boxes whose balance error passed the 4 cm limit during the exploration itself (an episode fails there).
    lost = np.asarray(data["max_balance_error"]) > cfg.task.balance_limit
    haz = np.asarray(data["hazardous"], bool)
    result = {
        "seed": args.seed,
        "boxes": {f: int((family == f).sum()) for f in fams},
        "items_any_hazardous": int((haz & (family == "items_any")).sum()),
        "explore_balance_exceeded": {f: int(lost[family == f].sum()) for f in fams},
        "estimators": {
            name: assess_estimator(m, data, family, truth, cfg, args.show_misses)
            for name, m in models.items()
        },
        "simulate_s": round(sim_s, 1),
        **(
            {
                "exact_moment_ceiling": moment_ceiling(
                    args.seed, args.ceiling_boxes, args.ceiling_boxes // 5, cfg
                )
            }
            if args.ceiling_boxes
            else {}
        ),
        "total_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
