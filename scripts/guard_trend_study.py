"""What the exploration guard could have seen coming: the fixed exploration recorded unguarded, step by step,
in a world with faults, and guard rules judged on the records offline.

Until a guard first trips, a guarded exploration IS the unguarded one (same box, key, sensor draws), so the
step at which any rule would first trip is exact from one unguarded record; what the stop after it saves
is not (a closed-loop run measures that, `scripts/guard_stop_study.py`). Per box the record holds the true
signed balance offset, the one the controller sees (the filter's present estimate), the filter's velocity
of the box's y relative to the belts' midline and its std, and the step the box was lost (crossed the
balance limit, tipped or left the belts). A rule is scored by the boxes it trips on too late (lost within
`--react` steps of its trip, or never tripped) and the safe boxes it trips on (refusals).

    python scripts/guard_trend_study.py record --families gaussian items slabs scatter --seeds 5 6 9 10 \
        --hazardous 300 --safe 300 --world realistic --out FILE.npz
    python scripts/guard_trend_study.py judge FILE.npz [FILE.npz ...]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax
import numpy as np

from boxjax import geometry
from boxjax.config import DEFAULT as cfg
from boxjax.control import ControllerConfig
from boxjax.control.episode import env_for
from boxjax.control.world import World
from boxjax.estimator import explore
from boxjax.experiments import fault_table
from boxjax.experiments.evaluation import HAZARD_FAMILIES, make_boxes
from boxjax.sim.faults import Faults
from boxjax.training.estimator import write_json

WORLDS = {name: fault_table.row(row).faults for name, row in (
    ("none", "none"), ("noise", "noise 3 mm / 1.5 deg"), ("realistic", "realistic")
)}  # fmt: skip
COLUMNS = ("true", "seen", "v_rel", "v_std", "y_std")  # m, m, m/s, m/s, m


def record_box(
    truth, key, faults: Faults, ctrl: ControllerConfig, first_turn_scale: float = 1.0
) -> tuple[np.ndarray, int]:
    """(K+1, 5) the COLUMNS at every step of the unguarded exploration (the fixed sequence and its rest),
    and the step at which the box was lost (-1: not lost). `first_turn_scale` scales the belt speeds of the
    first turn (the first three vectors), a what-if: the shipped H reads only the sequence as it is."""
    key_reset, _ = jax.random.split(key)
    env = env_for(cfg, "native")
    state = env.reset(key_reset, truth)
    world = World(cfg, faults, ctrl.pose_filter, key, truth)
    world.prepare(state.model)
    guard = explore.Guarded(cfg, None, settle=world.exploration_delay)
    guard.actions = guard.actions.copy()
    guard.actions[: 3 * explore.HOLD, :2] *= first_turn_scale
    rows, lost, t = [], -1, 0
    p_prev = None
    s_seen, _ = world.observe(state.s, state.belt_speed)
    while True:
        s_true = np.asarray(state.s, np.float64)
        p_mid = 0.5 * (s_seen[geometry.P1] + s_seen[geometry.P2])
        v_mid = 0.0 if p_prev is None else (p_mid - p_prev) / cfg.gripper.control_dt
        p_prev = p_mid
        flt = world.filter
        v_y, v_std = (0.0, 0.0) if flt is None else (float(flt.velocity()[1]), math.sqrt(flt.P[1, 1, 1]))
        y_std = 0.0 if flt is None else flt.y_std()
        rows.append(
            [geometry.balance_offset(s_true), geometry.balance_offset(s_seen), v_y - v_mid, v_std, y_std]
        )
        if bool(state.done):
            lost = t
            break
        a = guard.next(s_seen, abs(geometry.balance_offset(s_seen)))
        if a is None:
            break
        world.before_step(t, state.model, env.ids.box_body)
        state = env.step(state, world.send(np.asarray(a, np.float64)))
        s_seen, _ = world.observe(state.s, state.belt_speed)
        t += 1
    return np.asarray(rows, np.float32), lost


def record(args) -> None:
    faults, ctrl = WORLDS[args.world], ControllerConfig()
    recs, lost, hazardous, names = [], [], [], []
    t0 = time.time()
    for family, seed in zip(args.families, args.seeds, strict=True):
        boxes = make_boxes(cfg, args.safe, args.hazardous, seed, family)
        for j in range(len(boxes.keys)):
            key = jax.random.wrap_key_data(boxes.keys[j])
            r, k = record_box(boxes.dist(j), key, faults, ctrl, args.first_turn_scale)
            recs.append(r)
            lost.append(k)
            hazardous.append(bool(boxes.hazardous[j]))
            names.append(f"{family}:{seed}:{j}")
        print(
            f"{time.time() - t0:6.0f} s  {family} seed {seed}: lost {sum(x >= 0 for x in lost)}", flush=True
        )
    n = max(len(r) for r in recs)
    pad = np.full((len(recs), n, len(COLUMNS)), np.nan, np.float32)
    for i, r in enumerate(recs):
        pad[i, : len(r)] = r
    np.savez_compressed(
        args.out,
        rows=pad,
        lost=np.asarray(lost),
        hazardous=np.asarray(hazardous),
        names=np.asarray(names),
        world=args.world,
        first_turn_scale=args.first_turn_scale,
    )


def trip_frames(seen, lead, noise, threshold):
    """First step the present rule (`explore.judged_balance` on the seen offsets) trips, per box (-1:
    never)."""
    b = np.abs(seen)
    h = np.stack([np.roll(seen, 2, 1), np.roll(seen, 1, 1), seen], -1)
    judged = explore.judged_balance(h, b, lead, noise)
    judged[:, :2] = b[:, :2]
    return first(judged > threshold)


def trip_filter(seen, v_rel, v_std, lead, z, threshold, dt):
    """First step a rule on the filter's velocity trips: the seen offset plus `lead` steps of its velocity
    away from the midline beyond z of its std."""
    side = np.where(seen >= 0, 1.0, -1.0)
    away = np.maximum(side * v_rel - z * v_std, 0.0) * dt
    return first(np.abs(seen) + lead * away > threshold)


def first(mask) -> np.ndarray:
    mask = np.nan_to_num(mask, nan=0).astype(bool)
    return np.where(mask.any(1), mask.argmax(1), -1)


def score(trip, lost, hazardous, react) -> dict:
    late = (lost >= 0) & ((trip < 0) | (trip > lost - react))
    return {
        "hazardous_lost_unguarded": int(((lost >= 0) & hazardous).sum()),
        "hazardous_late": int((late & hazardous).sum()),
        "hazardous_never_tripped_lost": int(((lost >= 0) & (trip < 0) & hazardous).sum()),
        "safe_tripped": int(((trip >= 0) & ~hazardous).sum()),
        "safe_lost_unguarded": int(((lost >= 0) & ~hazardous).sum()),
    }


def judge(args) -> None:
    dt = cfg.gripper.control_dt
    out = {"react": args.react, "files": []}
    for path in args.files:
        d = np.load(path)
        rows, lost, haz = d["rows"], d["lost"], d["hazardous"]
        seen, v_rel, v_std = rows[..., 1], rows[..., 2], rows[..., 3]
        noise = 3e-3 if str(d["world"]) != "none" else 0.0
        thr = 0.875 * cfg.task.balance_limit
        print(f"# {path}: {len(lost)} boxes ({int(haz.sum())} hazardous), world {d['world']}")
        cands = {"frames lead 3 (default)": trip_frames(seen, 3, noise, thr)}
        for a in args.allowance_mm:
            cands[f"frames lead 3 allowance {a} mm"] = trip_frames(
                seen, 3, a * 1e-3 / (2 * math.sqrt(2)), thr
            )
        for lead in args.leads:
            for z in args.z:
                for t in args.thresholds_cm:
                    cands[f"filter lead {lead} z {z} thr {t}"] = trip_filter(
                        seen, v_rel, v_std, lead, z, t / 100, dt
                    )
        fams = sorted({str(n).split(":")[0] for n in d["names"]})
        entry = {
            "file": path,
            "world": str(d["world"]),
            "families": fams,
            "boxes": int(len(lost)),
            "rules": [],
        }
        for name, trip in cands.items():
            row = {"rule": name, **score(trip, lost, haz, args.react)}
            entry["rules"].append(row)
            print(json.dumps(row))
        haz_lost = lost[haz & (lost >= 0)]
        entry["hazardous_lost_by_step"] = {"10": int((haz_lost <= 10).sum()), "all": int(len(haz_lost))}
        out["files"].append(entry)
    if args.out:
        write_json(args.out, out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--families", nargs="+", default=["gaussian"], choices=HAZARD_FAMILIES)
    r.add_argument("--seeds", nargs="+", type=int, default=[5])
    r.add_argument("--hazardous", type=int, default=300)
    r.add_argument("--safe", type=int, default=0)
    r.add_argument("--world", default="realistic", choices=tuple(WORLDS))
    r.add_argument("--out", required=True)
    r.add_argument(
        "--first-turn-scale", type=float, default=1.0, help="what-if: scale the first turn's belt speeds"
    )
    j = sub.add_parser("judge")
    j.add_argument("files", nargs="+")
    j.add_argument("--react", type=int, default=3, help="steps a trip must come before the loss")
    j.add_argument("--leads", nargs="+", type=int, default=[3])
    j.add_argument("--z", nargs="+", type=float, default=[0.0, 1.0, 2.0])
    j.add_argument("--thresholds-cm", nargs="+", type=float, default=[3.5])
    j.add_argument("--allowance-mm", nargs="+", type=float, default=[])
    j.add_argument("--out", help="write the scores as JSON here")
    args = ap.parse_args(argv)
    record(args) if args.cmd == "record" else judge(args)


if __name__ == "__main__":
    main()
