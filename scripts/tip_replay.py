"""A tipped episode of a written evaluation, replayed from its recorded actions: the box's tilt in MuJoCo
and the physics prior's stability margin on the TRUE box (how far the centre of mass lies inside the
support polygon of both belts' contacts, `prior.stability_margin`, what `MonitorConfig.tip_stop` watches)
over its last control steps (docs/results/faults.md, "Tipping").

    python scripts/planner_study.py --boxes 100 --seed 0 --fault obs_noise_mm=3 --fault obs_noise_deg=1.5 \\
        --out ev/
    python scripts/tip_replay.py ev/ [INDEX ...] [--last 12]     # default: every tipped box of ev/

Prints one JSON line per step: the step, the tilt (degrees, after the step's action), the margin (mm, of the
state the action was sent at: the controller's prior setting, `PriorParams.margin`, and the exact one), the
carriages P1 / P2 and the box's x, y (mm) and yaw (degrees), the action. An episode with a mass shift first
gets a line with its step, the centre of mass it left (mm) and whether the motion told it (the prior's
one-step prediction errors with the box before and after the shift, before and after its step:
`shift_evidence`); the exact margin follows the slid masses from that step on, the controller's prior keeps
the box it was given.
"""

from __future__ import annotations

import argparse
import json
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry, massdist, planning, prior
from boxjax.config import DEFAULT
from boxjax.control import batch, true_stability_margins
from boxjax.control.models import planning_model
from boxjax.control.world import World
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
    # the episode's mass shift, drawn from its key as the replay's world drew it: the true margin
    # follows the slid masses from its step on (the controller's prior keeps the box it was given)
    shift = World(cfg, faults, ctrl.pose_filter, key, truth).shift
    if shift is not None:
        shift.done = shift.step < len(actions)
    true_margins = true_stability_margins(cfg, truth, s, shift)
    rows = []
    if shift is not None:
        com = np.round(1e3 * shift.com[:2], 1).tolist()
        rows.append(
            {"mass_shift_step": shift.step, "com_after_mm": com, **shift_evidence(cfg, truth, shift, res)}
        )
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


def shift_evidence(cfg, truth, shift, res) -> dict:
    """Whether the motion told the shift: the prior's one-step prediction errors along the replayed states
    (the actions applied, the measured belt speeds), with the box before the shift and with the box after
    it, before and after its step (median position error in mm, yaw in degrees)."""
    s, b, a = (np.asarray(x, np.float32) for x in (res.trace.s, res.trace.belt_speed, res.trace.actions))
    t = np.arange(planning.MIN_WINDOW - 1, len(a))
    windows = np.stack([s[i - planning.MIN_WINDOW + 1 : i + 1] for i in t])
    out = {}
    for name, masses in (("before", massdist.voxel_masses(truth, cfg.box)), ("after", shift.masses)):
        model = prior.make_prior(jnp.asarray(masses, jnp.float32), None, cfg.box, cfg.gripper)
        p = np.asarray(jax.jit(jax.vmap(partial(prior.predict, model)))(windows, b[t], a[t]))
        e = p - s[t + 1]
        pos, yaw = 1e3 * np.hypot(e[:, geometry.X], e[:, geometry.Y]), np.degrees(np.abs(e[:, geometry.YAW]))
        for when, sel in (("pre", t < shift.step), ("post", t >= shift.step)):
            if sel.any():
                out[f"{name}_model_{when}_shift_mm_deg"] = [
                    round(float(np.median(pos[sel])), 2),
                    round(float(np.median(yaw[sel])), 3),
                ]
    return out


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
