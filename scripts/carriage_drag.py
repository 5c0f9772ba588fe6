"""How far a carriage moved under a box at rest drags the box: MuJoCo against the physics prior.

The runtime safety monitor's stop either holds the carriages or moves them under the box's centre
(`MonitorConfig.backup`); with one carriage at its stop, re-centring moves the other alone, and the box
rests on that belt too. Whether that gains on the box depends on how much of the carriage's travel the
box follows. For each box: settle at rest, move one carriage 5 x 1 cm outward (then, from a fresh reset,
inward), and compare the box's sideways move in the simulator with the prior's prediction from the same
start (docs/results/faults.md).

    python scripts/carriage_drag.py --boxes 20 --out benchmarks/results_carriage_drag.json
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning
from boxjax.config import DEFAULT as CFG
from boxjax.control.episode import env_for
from boxjax.experiments.evaluation import sample_safe
from boxjax.fileio import atomic_path
from boxjax.prior import make_prior

STEPS = 5


def drag(box: massdist.MassDistribution, carriage: int, sign: float) -> dict:
    """One move: the carriage's travel and the box's sideways move, simulated and predicted (m)."""
    env = env_for(CFG, "native")
    state = env.reset(jax.random.PRNGKey(0), box)
    for _ in range(5):
        state = env.step(state, np.zeros(4))
    s0 = np.asarray(state.s, np.float64)
    move = np.zeros(4)
    move[2 + carriage] = sign * CFG.gripper.max_position_step
    for _ in range(STEPS):
        state = env.step(state, move)
    s1 = np.asarray(state.s, np.float64)
    prior = make_prior(massdist.voxel_masses(box, CFG.box))
    seq = jnp.tile(jnp.asarray(move, jnp.float32), (STEPS, 1))
    pred = prior.rollout_sequence(planning.initial_window(jnp.asarray(s0, jnp.float32)), jnp.zeros(2), seq)
    travel = s1[carriage] - s0[carriage]
    return {
        "travel_m": float(travel),
        "sim_dy_m": float(s1[geometry.Y] - s0[geometry.Y]),
        "prior_dy_m": float(pred[-1, geometry.Y]) - float(s0[geometry.Y]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=20, help="random safe boxes besides the named ones")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    boxes = {name: massdist.named(name, CFG.box) for name in ("uniform", "A", "B", "C", "D")}
    for j, b in enumerate(sample_safe(jax.random.PRNGKey(args.seed), args.boxes, CFG)):
        boxes[f"random {j}"] = b
    rows = []
    for name, box in boxes.items():
        for carriage, label in ((geometry.P1, "belt 1"), (geometry.P2, "belt 2")):
            for sign, way in ((1.0, "+y"), (-1.0, "-y")):
                r = drag(box, carriage, sign)
                rows.append({"box": name, "carriage": label, "direction": way, **r})
                print(json.dumps(rows[-1]), flush=True)
    sim = np.array([r["sim_dy_m"] / r["travel_m"] for r in rows])
    pred = np.array([r["prior_dy_m"] / r["travel_m"] for r in rows])
    summary = {
        "moves": len(rows),
        "sim_fraction_dragged": {"median": float(np.median(sim)), "max": float(sim.max())},
        "prior_fraction_dragged": {"median": float(np.median(pred)), "max": float(pred.max())},
        "prior_minus_sim_fraction": {
            "median": float(np.median(pred - sim)),
            "rms": float(np.sqrt(np.mean((pred - sim) ** 2))),
        },
    }
    print(json.dumps(summary, indent=1))
    if args.out:
        with atomic_path(args.out) as tmp:
            with open(tmp, "w") as f:
                json.dump({"steps": STEPS, "summary": summary, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
