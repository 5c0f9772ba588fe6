"""A tipped episode of a written evaluation, replayed from its recorded actions: the box's tilt in MuJoCo
and the physics prior's stability margin on the TRUE box (how far the centre of mass lies inside the
support polygon of both belts' contacts, `prior.stability_margin`, what `MonitorConfig.tip_stop` watches)
over its last control steps (docs/results/faults.md, "Tipping").

    python scripts/planner_study.py --boxes 100 --seed 0 --fault obs_noise_mm=3 --fault obs_noise_deg=1.5 \\
        --out ev/
    python scripts/tip_replay.py ev/ [INDEX ...] [--last 12]     # default: every tipped box of ev/

Prints one JSON line per step: the step, the tilt (degrees, after the step's action), the margin (mm, of the
state the action was sent at: the controller's prior setting, `PriorParams.margin`, and the exact one), the
carriages P1 / P2 and the box's x, y (mm) and yaw (degrees), the action.
"""

from __future__ import annotations

import argparse
import json
import math

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, prior
from boxjax.config import DEFAULT
from boxjax.control import batch
from boxjax.control.models import planning_model
from boxjax.experiments import evaluation as experiments
from boxjax.sim import native


def replay(out_dir: str, index: int, last: int) -> list[dict]:
    """The last `last` steps of box `index`'s episode (see the module docstring)."""
    cfg = DEFAULT
    boxes, summary = experiments.load_boxes(out_dir)
    recorded = experiments.load_actions(out_dir)
    actions = np.asarray(recorded[index], np.float64).reshape(-1, 4)
    ctrl = experiments.controller_from_settings(summary)
    faults = experiments.faults_from_settings(summary)
    truth, key = boxes.dist(index), jax.random.wrap_key_data(boxes.keys[index])
    tilts, step = [], native.NativeBatch.step

    def recording(self, *args, **kwargs):
        out = step(self, *args, **kwargs)
        tilts.append(float(geometry.tilt_from_quat(np.asarray(self.datas[0].xquat[self.ids.box_body]))))
        return out

    native.NativeBatch.step = recording
    try:
        res = batch.replay_episode(cfg, truth, key, actions, ctrl=ctrl, faults=faults)
    finally:
        native.NativeBatch.step = step
    s = np.asarray(res.trace.s, np.float32)
    model = planning_model(cfg, ctrl, truth)
    margins = np.asarray(jax.jit(jax.vmap(model.stability_margin))(jnp.asarray(s)))
    exact = prior.make_prior(
        massdist.voxel_masses(truth, cfg.box), None, cfg.box, cfg.gripper, prior.PriorParams(margin="exact")
    )
    true_margins = np.asarray(jax.jit(jax.vmap(exact.stability_margin))(jnp.asarray(s)))
    rows = []
    for t in range(max(0, len(actions) - last), len(actions)):
        rows.append(
            {
                "step": t,
                "tilt_deg": round(math.degrees(tilts[t]), 1),
                "margin_mm": round(1e3 * float(margins[t]), 1),
                "exact_margin_mm": round(1e3 * float(true_margins[t]), 1),
                "p_mm": [round(1e3 * float(v)) for v in s[t, [geometry.P1, geometry.P2]]],
                "xy_mm": [round(1e3 * float(v)) for v in s[t, [geometry.X, geometry.Y]]],
                "yaw_deg": round(math.degrees(float(s[t, geometry.YAW])), 1),
                "action": np.round(actions[t], 3).tolist(),
            }
        )
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="an evaluation written with --out (with recorded actions)")
    ap.add_argument("index", type=int, nargs="*", help="the boxes' rows (default: every tipped one)")
    ap.add_argument("--last", type=int, default=12, help="control steps before the end to show")
    args = ap.parse_args(argv)
    ev = json.load(open(f"{args.dir}/evaluation.json"))
    if experiments.load_actions(args.dir) is None:
        ap.error(f"{args.dir} has no recorded actions")
    n = len(ev["rows"])
    if any(not 0 <= i < n for i in args.index):
        ap.error(f"an index is outside the evaluation's {n} boxes")
    if args.last < 1:
        ap.error("--last must be >= 1")
    indices = args.index or [r["index"] for r in ev["rows"] if r["outcome"] == "tipped"]
    out = {}
    for i in indices:
        print(json.dumps({"box": i, "outcome": ev["rows"][i]["outcome"]}))
        out[i] = replay(args.dir, i, args.last)
        for row in out[i]:
            print(json.dumps(row))
    return out


if __name__ == "__main__":
    main()
