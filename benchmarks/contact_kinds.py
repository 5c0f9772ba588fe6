"""How native MuJoCo's box-box collider touches the box to the belts along explorations: at every physics
step of `--boxes` random boxes' explorations (`massdist.sample`, `--seed`), for each belt, which axis won
native's separating-axis test (a face of the belt, a face of the box, or an edge-cross axis: one contact)
and how many contacts native reports against the overlap polygon's penetrating vertices
(`boxjax.sim.mjx_contacts.box_box_contacts`, float64). The count behind docs/results/simulation.md#colliders:
the belt-steps where native has fewer contacts than the polygon, by the kind of native's contact.

Prints ONE JSON object (the last line).
Run: python benchmarks/contact_kinds.py [--boxes 3] [--seed 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # the polygon in native's precision (a script, not the library)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit_to, machine  # noqa: E402

from boxjax import massdist  # noqa: E402
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.estimator import explore  # noqa: E402
from boxjax.sim import core, mjx_contacts, model, native  # noqa: E402


def kind_of(normal: np.ndarray, box_mat: np.ndarray) -> str:
    """The winning axis of native's test from its contact normal (the belts never tilt)."""
    if normal[0] == 0 and normal[1] == 0:
        return "belt_face"
    if np.max(np.abs(box_mat.T @ normal)) > 1 - 1e-12:
        return "box_face"
    return "edge"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--boxes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if args.boxes < 1:
        ap.error("--boxes must be >= 1")
    cfg = DEFAULT
    polygon = jax.jit(mjx_contacts.box_box_contacts)
    actions = np.asarray(explore.exploration_actions(cfg))
    counts: collections.Counter = collections.Counter()
    t0 = time.perf_counter()
    steps = 0
    for key in jax.random.split(jax.random.PRNGKey(args.seed), args.boxes):
        m = model.box_model(cfg, massdist.sample(key, cfg.box))
        idx, d = model.ids(m), mujoco.MjData(m)
        d.qpos[:] = model.initial_qpos(cfg, m)
        p = np.asarray(cfg.gripper.belt_y0)
        d.ctrl[model.CARRIAGE1_P], d.ctrl[model.CARRIAGE2_P] = p
        box = m.geom("box").id
        for a in actions:
            ctrl, p = core.command(cfg, a, d.act[[model.BELT1_V, model.BELT2_V]], p)[:2]
            d.ctrl[:], p = np.asarray(ctrl), np.asarray(p)
            for _ in range(cfg.gripper.n_substeps):
                mujoco.mj_step(m, d)  # d.contact and d.geom_xpos: both of the state before the step
                steps += 1
                mats = d.geom_xmat.reshape(-1, 3, 3)
                for belt in (m.geom("belt1").id, m.geom("belt2").id):
                    nat = [c for c in d.contact[: d.ncon] if set(c.geom) == {box, belt}]
                    dist = np.asarray(
                        polygon(d.geom_xpos[box], mats[box], m.geom_size[box], d.geom_xpos[belt], mats[belt],
                                m.geom_size[belt])[0]
                    )  # fmt: skip
                    n_poly = int(np.sum(dist <= 0))
                    kind = kind_of(nat[0].frame[:3], mats[box]) if nat else "none"
                    rel = "same" if len(nat) == n_poly else ("fewer" if len(nat) < n_poly else "more")
                    counts[f"{kind}:{rel}"] += 1
            native.recentre_belts(idx, d.qpos)
    emit_to(
        {
            "benchmark": "contact_kinds",
            "boxes": args.boxes,
            "seed": args.seed,
            **machine(),
            "physics_steps": steps,
            "belt_steps": 2 * steps,
            "native_kind_vs_polygon": dict(sorted(counts.items())),
            "wall_s": time.perf_counter() - t0,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
