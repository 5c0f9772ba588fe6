"""The physics prior's static tipping criterion against MuJoCo (docs/results/faults.md, "The static criterion
against MuJoCo").

Random boxes (half `massdist.sample`, half `massdist.sample_hazardous`, whose mass sits off-centre) are placed
flat and at rest on the belts at random planar states whose rigid margin (`prior.stability_margin` on the
TRUE box: how far the centre of mass lies inside the exact overlap polygons of box and belts) is near the
edge, held still for 2 s (`sim.statics.hold`); a box tips when its tilt passes 10 degrees. Per margin bin:
how many tipped, by the prior's margin and by the margin inside the hull of the contacts MuJoCo generated.

    python scripts/tip_calibration.py --boxes 80 --seed 1 --out benchmarks/results_tip_calibration.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import massdist
from boxjax.config import DEFAULT
from boxjax.fileio import atomic_path
from boxjax.prior import PriorParams, make_prior, stability_margin
from boxjax.sim import model, statics

BINS_MM = (-4, -2, 0, 2, 4, 6, 8, 10, 12, 15, 20)
TIPPED = math.radians(10.0)


def binned(margins_mm, tipped) -> list[dict]:
    out = []
    for lo, hi in zip(BINS_MM[:-1], BINS_MM[1:], strict=True):
        sel = (margins_mm >= lo) & (margins_mm < hi)
        out.append({"margin_mm": [lo, hi], "placed": int(sel.sum()), "tipped": int(tipped[sel].sum())})
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--boxes", type=int, default=80)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--per-box", type=int, default=30, help="placements per box")
    ap.add_argument("--out", help="write the summary JSON here")
    args = ap.parse_args(argv)
    if args.boxes < 1 or args.per_box < 1:
        ap.error("--boxes and --per-box must be >= 1")
    cfg = DEFAULT
    rng = np.random.default_rng(args.seed)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.boxes)
    margin = jax.jit(jax.vmap(stability_margin, in_axes=(None, 0)))
    rows, t0 = [], time.perf_counter()
    for i in range(args.boxes):
        truth = (massdist.sample_hazardous if i % 2 else massdist.sample)(keys[i], cfg.box)
        masses = massdist.voxel_masses(truth, cfg.box)
        prior = make_prior(masses, None, cfg.box, cfg.gripper)
        exact = dataclasses.replace(prior, params=PriorParams(margin="exact"))
        m = model.box_model(cfg, truth)
        s = statics.random_states(rng, 20 * args.per_box, cfg)
        rigid = np.asarray(margin(prior, jnp.asarray(s)))
        true = np.asarray(margin(exact, jnp.asarray(s)))
        for k in np.flatnonzero((rigid > -0.004) & (rigid < 0.02))[: args.per_box]:
            held = statics.hold(cfg, m, s[k])
            rows.append(
                (
                    i,
                    float(rigid[k]),
                    held.hull_margin,
                    held.n_contacts,
                    held.peak_tilt > TIPPED,
                    float(true[k]),
                )
            )
        print(
            f"box {i + 1}/{args.boxes}: {len(rows)} placements, {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
        )
    rigid_mm = 1e3 * np.array([r[1] for r in rows])
    hull_mm = 1e3 * np.array([r[2] for r in rows])
    exact_mm = 1e3 * np.array([r[5] for r in rows])
    tipped = np.array([r[4] for r in rows])
    gap = hull_mm - exact_mm
    out = {
        "command": "python scripts/tip_calibration.py "
        + " ".join(argv if argv is not None else sys.argv[1:]),
        "boxes": args.boxes,
        "seed": args.seed,
        "placements": len(rows),
        "held_s": 2.0,
        "tipped_deg": 10.0,
        "by_prior_margin": binned(rigid_mm, tipped),
        "by_exact_margin": binned(exact_mm, tipped),
        "by_mujoco_contact_hull": binned(hull_mm, tipped),
        "sampled_minus_exact_mm": {
            q: round(float(np.percentile(rigid_mm - exact_mm, p)), 2)
            for q, p in (("median", 50), ("p90", 90), ("p99", 99), ("max", 100))
        },
        "hull_minus_exact_mm": {
            q: round(float(np.percentile(gap, p)), 2)
            for q, p in (("p10", 10), ("median", 50), ("p90", 90), ("max", 100))
        },
        "contacts_per_placement": np.bincount([r[3] for r in rows]).tolist(),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    text = json.dumps(out, indent=1)
    print(text)
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as f:
            f.write(text + "\n")
    return out


if __name__ == "__main__":
    main()
