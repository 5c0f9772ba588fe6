"""Why safe boxes are not turned: re-run an evaluation's not-turned safe boxes with another planner, and
compare the prior's yaw predictions with the simulator's along a stalled turn and along a reference turn.

    boxjax evaluate --boxes 100 --safe-family items --seed 0 --out runs/items_s0
    python scripts/stalled_turns.py rerun --evals runs/items_s0 --planner simulator --out ref.json
    python scripts/stalled_turns.py rerun --evals runs/items_s0 --planner wide --out wide.json
    python scripts/stalled_turns.py predict --eval runs/items_s0 --index 8 14 40 --out predict.json
    python scripts/stalled_turns.py carriage --eval runs/items_s0 --index 8 14 40 --out carriage.json

`rerun`: every safe box of the evaluations that was neither turned nor refused, run again closed loop with
the same box and episode key, planning with the simulator itself (`--planner simulator`, the
privileged reference: docs/results/random-boxes.md) or with 1024 rollouts and no gradient steps
(`--planner wide`). `predict`: the evaluation's episode (replayed bit for bit) and the reference's episode of
the same box; along each turn, every 5 control steps, the yaw change over the next 10 steps predicted by the
physics prior on the TRUE mass distribution from the observed window and the actions sent, against the
simulated one. `carriage`: along the same two turns, from every state of the turn's first 200 control
steps, one control step in the simulator and in the prior with the action sent and with its carriage moves
removed (dp = 0): how much of the yaw each says the carriage moves made, and whether they agree.

`rerun --planner simulator --start planar` plans with the simulator started from what a planar observation
shows (`SimulatorOptions(start="planar")`: the box flat, at the observed pose and finite-difference
velocities) instead of the exact state; `--start flat` / `--start velocity` drop only one half of that;
`--model belief` simulates the believed box instead of the true one. `rerun` runs the evaluation's own
estimator (the learned H on learned evaluations); simulating the true box needs an oracle evaluation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from boxjax import geometry
from boxjax.config import DEFAULT
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import env_for, run_episode
from boxjax.control.models import planning_model
from boxjax.estimator.belief import learned_estimator
from boxjax.experiments import evaluation as ev
from boxjax.fileio import atomic_path
from boxjax.planners import simulator as simp
from boxjax.planners.sampling import SamplingOptions
from boxjax.planners.simulator import MODELS, STARTS, SimulatorOptions
from boxjax.prior import predictor as prior

sys.path.insert(0, str(Path(__file__).resolve().parent))
import turn_evidence  # noqa: E402  (the k-step predictions along a recorded turn)

K = 10  # control steps of each yaw prediction
EVERY = 5  # control steps between predictions


def _controller(summary: dict, planner: str, sim: SimulatorOptions | None = None) -> ControllerConfig:
    base = ev.controller_from_settings(summary)
    if planner == "simulator":
        return dataclasses.replace(base, planner="simulator", simulator=sim)
    wide = dataclasses.replace(base.sampling or SamplingOptions(), n_samples=1024, gradient_steps=0)
    return dataclasses.replace(base, sampling=wide)


def rerun(dirs: list[str], planner: str, sim: SimulatorOptions | None = None) -> dict:
    out = {}
    for d in dirs:
        boxes, summary = ev.load_boxes(d)
        ctrl = _controller(summary, planner, sim)
        est = learned_estimator(DEFAULT) if summary["estimator"] == "learned" else "oracle"
        rows = json.load(open(os.path.join(d, "evaluation.json")))["rows"]
        for r in rows:
            if r["hazardous"] or r["outcome"] in ("success", "aborted"):
                continue
            j = r["index"]
            t0 = time.time()
            key = jax.random.wrap_key_data(boxes.keys[j])
            s = run_episode(DEFAULT, boxes.dist(j), key, estimator=est, ctrl=ctrl).summary
            out[f"{d}#{j}"] = {
                "evaluation": r["outcome"],
                planner: ev.outcome(s),
                "steps": int(s["steps"]),
                "mass_kg": round(r["total_mass_kg"], 2),
                "com_cm": r["com_cm"],
            }
            print(
                d, j, r["outcome"], "->", ev.outcome(s), s["steps"], f"{time.time() - t0:.0f} s", flush=True
            )
    return out


def yaw_predictions(res) -> dict:
    """10-step yaw changes along the turn of an episode, predicted on the truth and simulated (degrees)."""
    n0 = res.summary["exploration_steps"]
    s, belt, a = (
        jnp.asarray(x[n0:], jnp.float32) for x in (res.trace.s, res.trace.belt_speed, res.trace.actions)
    )
    model = planning_model(DEFAULT, ControllerConfig(), res.truth)
    # prediction - simulation from every window of the turn (turn_evidence: one jitted, vmapped call)
    err = turn_evidence.prediction_errors(model, s, belt, a, K)[::EVERY]
    starts = np.arange(turn_evidence.W - 1, s.shape[0] - K)[::EVERY]
    yaw = np.asarray(s[:, 4], np.float64)
    sim = yaw[starts + K] - yaw[starts]
    pred, sim = np.degrees(err[:, 4] + sim), np.degrees(sim)
    first = starts < 150  # the turn's first 150 control steps (a window every 5 steps: 10-step sums / 2)
    return {
        "outcome": ev.outcome(res.summary),
        "steps": int(res.summary["steps"]),
        "sim_mean_deg": float(sim.mean()),
        "prior_mean_deg": float(pred.mean()),
        "corr": float(np.corrcoef(sim, pred)[0, 1]),
        "first_150_steps_sim_deg": float(sim[first].sum() * EVERY / K),
        "first_150_steps_prior_deg": float(pred[first].sum() * EVERY / K),
        "carriages_cm": [float(100 * np.mean(s[:150, 0])), float(100 * np.mean(s[:150, 1]))],
    }


def predict(d: str, indices: list[int]) -> dict:
    out = {}
    for j in indices:
        out[f"{d}#{j}"] = {name: yaw_predictions(res) for name, res in _two_turns(d, j)[0].items()}
        print(json.dumps({f"{d}#{j}": out[f"{d}#{j}"]}), flush=True)
    return out


# One step of the prior for several actions; the model is an argument, so every episode reuses the program.
_predict_actions = jax.jit(jax.vmap(prior.predict, in_axes=(None, None, None, 0)))


def carriage_effects(res, key, steps: int = 200, every: int = 5) -> dict:
    """From each state of the turn (its first `steps` control steps), the yaw change of one control step
    with the action sent and with its carriage moves zeroed, in the simulator (the episode's states
    re-simulated from its key and actions) and in the prior on the true mass distribution (degrees).
    Beside it, what the planar pose does not show: the box's tilt and sink along the turn, and, every
    `every` steps, how far 10 steps of the actions sent from the planar, flat and velocity starts
    (`planners.simulator.planar_start`) end from the exact state's (median |yaw difference|, degrees)."""
    env = env_for(DEFAULT, "native")
    st = env.reset(key, res.truth)
    acts = np.asarray(res.trace.actions, np.float64)
    n0 = res.summary["exploration_steps"]
    model = planning_model(DEFAULT, ControllerConfig(), res.truth)
    idx = simp.model.ids(st.model)
    b, nq = idx.box_qpos, st.model.nq
    roll = simp.Rollouts(DEFAULT, 1, K, nthread=1)
    seen, rows, drift, tilt, sink = [np.asarray(st.s)], [], 0.0, [], []
    div = {k: [] for k in simp.STARTS[1:]}
    for t, a in enumerate(acts[: n0 + steps]):
        if t >= n0 + turn_evidence.W - 1:
            alt = np.stack([a, [a[0], a[1], 0.0, 0.0]])
            sim = [float(env.step(st, x).s[4] - st.s[4]) for x in alt]
            w = np.stack(seen[-turn_evidence.W :])
            p = np.asarray(
                _predict_actions(
                    model, jnp.asarray(w, jnp.float32), jnp.asarray(st.belt_speed, jnp.float32), alt
                )
            )
            rows.append([*sim, *(p[:, 4] - float(st.s[4]))])
            q = st.physics[1 : 1 + nq]
            tilt.append(float(geometry.tilt_from_quat(q[b + 3 : b + 7])))
            sink.append(DEFAULT.box.half_size[2] - q[b + 2])
            if (t - n0) % every == 0 and t + K <= len(acts):
                seqs = acts[None, t : t + K]
                end = {"exact": roll(st, seqs)[0][0, -1]}
                for k in div:
                    end[k] = roll(st._replace(physics=simp.planar_start(DEFAULT, st, w, start=k)), seqs)[0][
                        0, -1
                    ]
                yaw = {k: float(geometry.yaw_from_quat(q_end[b + 3 : b + 7])) for k, q_end in end.items()}
                for k in div:
                    div[k].append(abs(float(geometry.wrap_angle(yaw[k] - yaw["exact"]))))
        st = env.step(st, a)
        seen.append(np.asarray(st.s))
        drift = max(drift, float(np.max(np.abs(seen[-1] - np.asarray(res.trace.s[t + 1])))))
    r = np.degrees(np.array(rows))
    sim_eff, prior_eff = r[:, 0] - r[:, 1], r[:, 2] - r[:, 3]
    return {
        "outcome": ev.outcome(res.summary),
        "steps": len(rows),
        "replay_max_abs_diff": drift,  # the re-simulated states against the recorded ones (0: bit for bit)
        "sim_deg_per_step": float(r[:, 0].mean()),
        "sim_without_carriage_moves": float(r[:, 1].mean()),
        "prior_deg_per_step": float(r[:, 2].mean()),
        "prior_without_carriage_moves": float(r[:, 3].mean()),
        "carriage_effect_sim": float(sim_eff.mean()),
        "carriage_effect_prior": float(prior_eff.mean()),
        "carriage_effect_abs_sim": float(np.abs(sim_eff).mean()),
        "carriage_effect_abs_prior": float(np.abs(prior_eff).mean()),
        "carriage_effect_corr": float(np.corrcoef(sim_eff, prior_eff)[0, 1]),
        "tilt_deg_median": float(np.degrees(np.median(tilt))),
        "tilt_deg_max": float(np.degrees(np.max(tilt))),
        "sink_mm_max": float(1e3 * np.max(sink)),
        f"yaw_after_{K}_steps_vs_exact_deg": {k: float(np.degrees(np.median(v))) for k, v in div.items()},
    }


def _two_turns(d: str, j: int) -> tuple[dict, jax.Array]:
    """The evaluation's episode of box j (replayed) and the simulator reference's of the same box, and
    the episode key."""
    boxes, summary = ev.load_boxes(d)
    key = jax.random.wrap_key_data(boxes.keys[j])
    return {
        "evaluation": ev.replay(DEFAULT, d, j)[0],
        "simulator": run_episode(
            DEFAULT, boxes.dist(j), key, estimator="oracle", ctrl=_controller(summary, "simulator")
        ),
    }, key


def carriage(d: str, indices: list[int]) -> dict:
    out = {}
    for j in indices:
        runs, key = _two_turns(d, j)
        out[f"{d}#{j}"] = {name: carriage_effects(res, key) for name, res in runs.items()}
        print(json.dumps({f"{d}#{j}": out[f"{d}#{j}"]}), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("rerun", help="the not-turned safe boxes with another planner")
    r.add_argument("--evals", nargs="+", required=True, help="evaluation directories (evaluate --out)")
    r.add_argument("--planner", choices=("simulator", "wide"), default="simulator")
    r.add_argument("--start", choices=STARTS, help="the simulator's rollouts start from (default exact)")
    r.add_argument("--model", choices=MODELS, help="the box the simulator simulates (default truth)")
    p = sub.add_parser("predict", help="the prior's yaw predictions along the stalled and the reference turn")
    c = sub.add_parser(
        "carriage", help="the yaw the carriage moves make along both turns: simulator and prior"
    )
    for q in (p, c):
        q.add_argument("--eval", required=True, help="an evaluation directory (evaluate --out)")
        q.add_argument("--index", nargs="+", type=int, required=True, help="boxes of that evaluation")
    for q in (r, p, c):
        q.add_argument("--out", required=True, help="JSON file")
    args = ap.parse_args()
    sim = None
    if args.what == "rerun" and (args.start or args.model):
        if args.planner != "simulator":
            ap.error(
                "--start and --model set the simulator planner's rollouts: use them with --planner simulator"
            )
        sim = SimulatorOptions(start=args.start or "exact", model=args.model or "truth")
    for d in args.evals if args.what == "rerun" else [args.eval]:
        if not os.path.exists(os.path.join(d, "evaluation.json")):
            ap.error(f"{d} is not an evaluation output (no evaluation.json)")
        # rerun runs the evaluation's own estimator; predict and carriage run the reference with the oracle
        truth = args.what == "rerun" and args.planner == "simulator" and (sim is None or sim.model == "truth")
        estimator = json.load(open(os.path.join(d, "evaluation.json")))["summary"]["estimator"]
        if truth and estimator != "oracle":
            ap.error(
                f"{d} ran the {estimator} estimator: the simulator simulating the true box is oracle-only"
            )
    if not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        ap.error(f"--out {args.out}: its directory does not exist")
    if args.what == "rerun":
        result = rerun(args.evals, args.planner, sim)
    else:
        result = (predict if args.what == "predict" else carriage)(args.eval, args.index)
    with atomic_path(args.out, suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
