"""How the runtime safety monitor's threshold trades needless stops against late ones.

docs/results/faults.md reports it.

The monitor runs in shadow mode (`MonitorConfig(shadow=True)`: it checks every action and logs its
prediction, the controller acts as if it were off) on random safe development boxes (seeds from 1000, never
the fault table's) under several fault rows. For every setting (stop_at, k_sigma) the log tells, per
episode, the first step at which it would have stopped; against the TRUE balance trace that gives:

* crossings: episodes whose true balance error passed the limit, and the lead (control steps) between the
  first alarm and the crossing (an alarm after the crossing, or none, is an unnoticed crossing);
* needless alarms: episodes the controller turned without ever crossing in which it would have stopped.

    python scripts/monitor_study.py --boxes 60 --out benchmarks/results_monitor_study.json
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

from boxjax.config import DEFAULT as CFG
from boxjax.control import batch
from boxjax.control.config import ControllerConfig
from boxjax.control.monitor import MonitorConfig
from boxjax.experiments.evaluation import sample_safe
from boxjax.fileio import atomic_path
from boxjax.sim.faults import Faults

ROWS = {
    "none": Faults(),
    "realistic": Faults(obs_noise_mm=3, obs_noise_deg=1.5, obs_latency=2, drop_rate=0.05, friction=0.4),
    "noise_10mm": Faults(obs_noise_mm=10, obs_noise_deg=5),
    "latency_4": Faults(obs_latency=4),
    "friction_0.35": Faults(friction=0.35),
    "mass_shift_1kg": Faults(mass_shift_kg=1.0),
}
STOP_AT = (0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)
K_SIGMA = (0.0, 1.0, 2.0)
DELAY_STD = (0.0, 0.0018)  # m per sqrt(step): the prediction's error over the delay (MonitorConfig.delay_std)
# a miss of the prediction over the delay beyond this many of its expected std replaces that std
# (MonitorConfig.miss_sigmas; 0: off)
MISS_SIGMAS = (0.0, 2.0, 3.0, 4.0)
# the delay's own multiplier (MonitorConfig.k_delay; None: k_sigma's)
K_DELAY = (None, 2.0)
# the carriages' drag over the delay: std per metre of carriage travel in flight (MonitorConfig.drag_std)
DRAG_STD = (0.0, 0.1, 0.2, 0.3)


def run_row(faults: Faults, n: int, seed: int) -> list[dict]:
    """Shadow-monitored episodes: per box the log (t, go, stop, sigma) and the true balance trace."""
    truths = sample_safe(jax.random.PRNGKey(seed), n, CFG)
    keys = [jax.random.fold_in(jax.random.PRNGKey(seed + 1), j) for j in range(n)]
    logs: dict[int, list] = {}
    result = batch._result

    def keep(cfg, truth, sim, b, rec, *a, **k):  # the monitor's log of box b, before it is dropped
        logs[b] = [] if rec.monitor is None else rec.monitor.log
        return result(cfg, truth, sim, b, rec, *a, **k)

    batch._result = keep
    try:
        ctrl = ControllerConfig(monitor=MonitorConfig(shadow=True))
        res = batch.run_episodes(CFG, truths, keys, ctrl=ctrl, faults=faults)
    finally:
        batch._result = result
    return [
        {
            "outcome": "success" if r.summary["success"] else str(r.summary["failed_reason"] or "aborted"),
            "log": logs.get(j, []),
            "balance": np.asarray(r.trace.balance_error).tolist(),
        }
        for j, r in enumerate(res)
    ]


def _margin(sig: float, miss: float, delay_var: float, k: float, k_delay: float, miss_sigmas: float) -> float:
    """The monitor's margin on the predicted balance error (`Monitor.decide`, the gripper not at rest)."""
    if miss_sigmas > 0 and miss > miss_sigmas * np.sqrt(delay_var + 2 * sig**2):
        delay_var = max(delay_var, miss**2)
    return float(np.sqrt((k * sig) ** 2 + k_delay**2 * delay_var))


def analyse(
    episodes: list[dict],
    stop_at: float,
    k: float,
    delay_std: float = 0.0,
    delay: int = 0,
    window: int = 10,
    miss_sigmas: float = 0.0,
    k_delay: float | None = None,
    drag_std: float = 0.0,
) -> dict:
    """The alarms a setting would raise, against each episode's true balance trace: a crossing is noticed
    when an alarm came within `window` steps before the action that led to it (the stop's horizon; an
    older alarm would have been followed by a resume); `lead` is how long before. In episodes turned
    without crossing, every alarm onset (a step that alarms after one that did not) is a needless stop.
    Logs of before the miss was recorded (4 columns) count as no miss, before the carriage travel in
    flight (5 columns) as none."""
    limit = CFG.task.balance_limit
    leads, unnoticed, onsets, needless, turned = [], 0, 0, 0, 0
    dvar = delay * delay_std**2
    kd = k if k_delay is None else k_delay
    for ep in episodes:
        alarm = {
            row[0]: row[1]
            + _margin(
                row[3],
                row[4] if len(row) > 4 else 0.0,
                dvar + drag_std**2 * (row[5] if len(row) > 5 else 0.0),
                k,
                kd,
                miss_sigmas,
            )
            >= stop_at * limit
            for row in ep["log"]
        }
        over = np.flatnonzero(np.asarray(ep["balance"]) > limit)
        if over.size:
            t_cross = int(over[0]) - 1  # the action that led to it
            near = [t for t in range(t_cross - window, t_cross + 1) if alarm.get(t)]
            if near:
                leads.append(int(t_cross - near[0]))
            else:
                unnoticed += 1
        elif ep["outcome"] == "success":
            turned += 1
            steps = sorted(alarm)
            n = int(sum(alarm[t] and not alarm.get(t - 1, False) for t in steps))
            onsets += n
            needless += n > 0
    return {
        "stop_at": stop_at,
        "k_sigma": k,
        "delay_std": delay_std,
        "miss_sigmas": miss_sigmas,
        "k_delay": k_delay,
        "drag_std": drag_std,
        "crossings": int(len(leads) + unnoticed),
        "unnoticed": unnoticed,
        "lead_steps_min": min(leads) if leads else None,
        "lead_steps_median": float(np.median(leads)) if leads else None,
        "turned": turned,
        "turned_with_needless_stops": int(needless),
        "needless_stops_per_turned": onsets / turned if turned else None,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--boxes", type=int, default=60)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--rows", nargs="*", default=list(ROWS), choices=list(ROWS))
    p.add_argument("--out", default="benchmarks/results_monitor_study.json")
    p.add_argument("--raw", help="also write every episode's log and balance trace here (JSON)")
    p.add_argument("--from-raw", help="analyse the episodes of an earlier --raw file instead of running them")
    args = p.parse_args()
    batch.use_host_devices()
    out = {"boxes": args.boxes, "seed": args.seed, "rows": {}}
    raw = {}
    earlier = None
    if args.from_raw:
        with open(args.from_raw) as f:
            earlier = json.load(f)
    for name in args.rows:
        t0 = time.perf_counter()
        eps = earlier[name] if earlier is not None else run_row(ROWS[name], args.boxes, args.seed)
        delay = ROWS[name].obs_latency + ROWS[name].action_latency  # what the controller predicts over
        table = [
            analyse(eps, a, k, ds, delay, miss_sigmas=ms, k_delay=kd, drag_std=dr)
            for ds in DELAY_STD
            for k in K_SIGMA
            for a in STOP_AT
            for ms in (MISS_SIGMAS if ds > 0 else (0.0,))
            for kd in (K_DELAY if ds > 0 else (None,))
            for dr in (DRAG_STD if ds > 0 and ms == 0 and delay > 0 else (0.0,))
        ]
        wall = time.perf_counter() - t0
        raw[name] = eps
        if args.raw and earlier is None:
            with atomic_path(args.raw, suffix=".json") as tmp:
                with open(tmp, "w") as f:
                    json.dump(raw, f)
        out["rows"][name] = {"faults": ROWS[name].to_dict(), "wall_s": wall, "table": table}
        print(f"{name}: {time.perf_counter() - t0:.0f} s", flush=True)
        for r in table:
            print("  ", json.dumps(r), flush=True)
        with atomic_path(args.out, suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
