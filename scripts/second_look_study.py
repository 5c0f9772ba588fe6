"""Would a second look cut the learned H's false aborts under a noisy, late sensor? Each box explores twice
in a row (the guarded fixed sequence and its rest, then again from where the first left it), H reads each
exploration, and a box refused after the first look is asked again: a refusal that stands only when both
looks refuse (the rule that a second look would make). Exploration and decisions only, in the realistic world
(docs/results/faults.md, "A second look"; benchmarks/results_second_look.json).

    python scripts/second_look_study.py --safe 300 --hazardous 100 --seed 4000 --out FILE
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from boxjax import geometry
from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig
from boxjax.control.episode import env_for, guarded_exploration
from boxjax.control.world import World
from boxjax.estimator.belief import learned_estimator
from boxjax.experiments import fault_table
from boxjax.experiments.evaluation import make_boxes
from boxjax.sim.faults import Faults
from boxjax.training.estimator import write_json

REALISTIC = fault_table.row("realistic").faults


def explore_twice(truth, key, estimate, ctrl: ControllerConfig, faults: Faults) -> dict:
    """One box's two looks: per look H's decision, or where the box was lost or the guard tripped."""
    env = env_for(cfg, "native")
    key_reset, _ = jax.random.split(key)
    state = env.reset(key_reset, truth)
    world = World(cfg, faults, ctrl.pose_filter, key, truth)
    world.prepare(state.model)
    s_seen, _ = world.observe(state.s, state.belt_speed)
    res: dict = {"looks": []}
    t = 0
    for look in range(2):
        guard = guarded_exploration(cfg, ctrl, world, ctrl.explore_guard)
        first_frame, sent = len(world.frames) - 1, []
        while not bool(state.done):
            a = guard.next(s_seen, geometry.balance_error(s_seen))
            if a is None:
                break
            world.before_step(t, state.model, env.ids.box_body)
            state = env.step(state, world.send(np.asarray(a, np.float64)))
            t += 1
            sent.append(np.asarray(a, np.float64))
            s_seen, _ = world.observe(state.s, state.belt_speed)
        if bool(state.done):
            res["lost_in_look"] = look
            break
        if guard.tripped:
            res["guard_in_look"] = look
            break
        frames = world.frames  # this look's frames only: its first is the state its first action met
        world.frames = frames[first_frame:]
        try:
            e = estimate(world.for_estimator({"actions": np.stack(sent)}, len(guard.actions)))
        finally:
            world.frames = frames
        res["looks"].append({"hazardous": bool(e["hazardous"]), "hazard_prob": float(e["hazard_prob"])})
        if not e["hazardous"]:
            break  # a box the first look turns is not looked at again
    return res


def summarise(rows: list[dict]) -> dict:
    out = {}
    for label, hz in (("safe", False), ("hazardous", True)):
        rs = [r for r in rows if r["hazardous"] == hz]
        first = [r for r in rs if r["looks"] and r["looks"][0]["hazardous"]]
        out[label] = {
            "boxes": len(rs),
            "first_look_refuses": len(first),
            "guard_in_first_look": sum(r.get("guard_in_look") == 0 for r in rs),
            "lost_in_first_look": sum(r.get("lost_in_look") == 0 for r in rs),
            "second_look_refuses_too": sum(len(r["looks"]) > 1 and r["looks"][1]["hazardous"] for r in first),
            "second_look_turns": sum(len(r["looks"]) > 1 and not r["looks"][1]["hazardous"] for r in first),
            "guard_in_second_look": sum(r.get("guard_in_look") == 1 for r in first),
            "lost_in_second_look": sum(r.get("lost_in_look") == 1 for r in first),
        }
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--safe", type=int, default=300)
    ap.add_argument("--hazardous", type=int, default=100)
    ap.add_argument("--seed", type=int, default=4000)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    ctrl, estimate = ControllerConfig(), learned_estimator(cfg)
    boxes = make_boxes(cfg, args.safe, args.hazardous, args.seed)
    rows, t0 = [], time.time()
    for j in range(len(boxes.keys)):
        r = explore_twice(boxes.dist(j), jax.random.wrap_key_data(boxes.keys[j]), estimate, ctrl, REALISTIC)
        rows.append({"index": j, "hazardous": bool(boxes.hazardous[j]), **r})
        if j % 50 == 0:
            print(f"{time.time() - t0:6.0f} s  box {j}", flush=True)
    res = {"seed": args.seed, "world": "realistic", "summary": summarise(rows), "rows": rows}
    print(res["summary"])
    if args.out:
        write_json(args.out, res)
    return res


if __name__ == "__main__":
    main()
