"""The paper's experiments as functions that return plain data (the CLI prints them, plots draw them).

`evaluate` is the validation of paper §4.3 and beyond: many random label-safe boxes (random distributions,
hazardous ones rejected) and random hazardous boxes, one closed-loop episode each, with the outcome of
every episode, the success rate with a 95 % Wilson interval, false aborts, hazard recall and the balance
error over time. Boxes and episode keys are derived from one seed, so any episode replays alone
(`replay`): box j's episode key is `fold_in(key_episodes, j)`, whatever the other boxes are.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections import Counter
from typing import Any, NamedTuple

import jax
import numpy as np

from boxjax import fileio, massdist, prior
from boxjax.config import Config
from boxjax.control import batch, device_loop, monitor
from boxjax.control.config import ControllerConfig
from boxjax.control.episode import NEAR_TIP_M, run_episode
from boxjax.control.monitor import MonitorConfig
from boxjax.control.state_estimate import FilterConfig
from boxjax.estimator.belief import learned_estimator
from boxjax.experiments import distributed
from boxjax.planners.sampling import SamplingOptions
from boxjax.sim.faults import NONE as NO_FAULTS
from boxjax.sim.faults import Faults
from boxjax.viz import animate

HAZARD_FAMILIES = ("gaussian", "items", "slabs", "scatter")
RESULTS_FORMAT, RESULTS_VERSION = "boxjax-evaluation", 1


class EvalBoxes(NamedTuple):
    """The boxes of one evaluation. N = safe + hazardous; the safe ones come first.

    occupancy: (N, nx, ny, nz) float32; total_mass: (N,) kg; hazardous: (N,) bool (as drawn);
    family: (N,) str, how each box was drawn ("safe" or "safe-F", `safe_label`; or a hazardous family);
    keys: (N, 2) uint32 episode keys (raw `jax.random.PRNGKey` data).
    """

    occupancy: np.ndarray
    total_mass: np.ndarray
    hazardous: np.ndarray
    family: np.ndarray
    keys: np.ndarray

    def dist(self, j: int) -> massdist.MassDistribution:
        return massdist.MassDistribution(
            np.asarray(self.occupancy[j], np.float32), np.asarray(self.total_mass[j], np.float32)
        )

    def __len__(self) -> int:
        return int(self.total_mass.shape[0])


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion (sensible at 0 and n, unlike the normal one)."""
    if n <= 0:
        return (float("nan"), float("nan"))
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


def sample_safe(key, n: int, cfg: Config, family: str = "gaussian") -> list[massdist.MassDistribution]:
    """n random label-safe distributions: draws of a family's free sampler (`massdist.sampler(family,
    hazardous=False)`; "gaussian" is `massdist.sample`, paper §4.3) with the hazardous ones rejected; draw i
    uses `fold_in(key, i)`."""
    if family not in HAZARD_FAMILIES:
        raise ValueError(f"unknown safe-box family {family!r}; choose one of {HAZARD_FAMILIES}")
    draw = massdist.sampler(family, hazardous=False)
    out, i = [], 0
    while len(out) < n:
        d = draw(jax.random.fold_in(key, i), cfg.box)
        i += 1
        if not bool(massdist.is_hazardous(d, cfg.box)):
            out.append(jax.tree.map(np.asarray, d))
    return out


def sample_hazard_family(
    key, n: int, cfg: Config, family: str = "gaussian"
) -> list[massdist.MassDistribution]:
    """n hazardous distributions: "gaussian" (`massdist.sample_hazardous`, the family H was trained on),
    "items" (`massdist.sample_items_hazardous`: 1-16 occupied voxels inside one outer quarter), "slabs"
    (a wall or layer 1-2 voxels thick in a quarter) or "scatter" (loose contents in a quarter: each voxel
    of a random sub-box occupied by chance; held out of every training and tuning decision)."""
    if family not in HAZARD_FAMILIES:
        raise ValueError(f"unknown hazardous family {family!r}; choose one of {HAZARD_FAMILIES}")
    draw = massdist.sampler(family, hazardous=True)
    return [jax.tree.map(np.asarray, draw(jax.random.fold_in(key, i), cfg.box)) for i in range(n)]


def safe_label(safe_family: str) -> str:
    """How `EvalBoxes.family` names a safe box: "safe" for the paper's family, "safe-F" for family F."""
    return "safe" if safe_family == "gaussian" else f"safe-{safe_family}"


def make_boxes(
    cfg: Config,
    n_safe: int,
    n_hazardous: int,
    seed: int,
    family: str = "gaussian",
    safe_family: str = "gaussian",
) -> EvalBoxes:
    """The boxes and episode keys of `evaluate(..., seed)`: the safe boxes of `safe_family`, the hazardous
    ones of `family`. The draws do not depend on the other family's choice (each has its own key)."""
    key_safe, key_haz, key_ep = jax.random.split(jax.random.PRNGKey(seed), 3)
    dists = sample_safe(key_safe, n_safe, cfg, safe_family)
    dists += sample_hazard_family(key_haz, n_hazardous, cfg, family)
    n = len(dists)
    keys = np.stack([np.asarray(jax.random.key_data(jax.random.fold_in(key_ep, j))) for j in range(n)])
    occ = np.stack([d.occupancy for d in dists]) if n else np.zeros((0, *cfg.box.grid), np.float32)
    return EvalBoxes(
        occupancy=occ.astype(np.float32),
        total_mass=np.asarray([float(d.total_mass) for d in dists], np.float32),
        hazardous=np.asarray([bool(massdist.is_hazardous(d, cfg.box)) for d in dists], bool),
        family=np.asarray([safe_label(safe_family)] * n_safe + [family] * n_hazardous),
        keys=keys.astype(np.uint32).reshape(n, 2),
    )


def outcome(summary: dict) -> str:
    """One word for an episode: "success", "aborted", "safe_stop" (the runtime safety monitor stopped it
    with the box balanced), or the failure reason."""
    if summary["success"]:
        return "success"
    if summary["aborted"]:
        return "aborted"
    if summary.get("safe_stop"):
        return "safe_stop"
    return str(summary["failed_reason"])


def _row(j: int, boxes: EvalBoxes, res, cfg: Config) -> dict:
    d = boxes.dist(j)
    props = massdist.mass_properties(d, cfg.box)
    s = res.summary
    row = {
        "index": j,
        "family": str(boxes.family[j]),
        "hazardous": bool(boxes.hazardous[j]),
        "total_mass_kg": float(d.total_mass),
        "com_cm": [round(100 * float(c), 3) for c in np.asarray(props.com)],
        "fill": float(np.mean(d.occupancy)),
        "outcome": outcome(s),
        "steps": int(s["steps"]),
        "max_balance_error_m": float(s["max_balance_error_m"]),
        "final_yaw_error_deg": math.degrees(float(s["final_yaw_error_rad"])),
        "lost_exploring": bool(s.get("lost_exploring", False)),
        "safe_stop_reason": s.get("safe_stop_reason"),
        "monitor_stops": int(s.get("monitor_stops", 0)),
        "monitor_recoveries": int(s.get("monitor_recoveries", 0)),
        "crossing": bool(s.get("crossing", False)),
        "unnoticed_crossing": bool(s.get("unnoticed_crossing", False)),
        "min_stability_margin_m": s.get("min_stability_margin_m"),
        "turn_min_stability_margin_m": s.get("turn_min_stability_margin_m"),
        "plan_ms_median": s["plan_ms_median"],
        "wall_s": float(s["wall_s"]),
    }
    for k in ("iou", "com_error_cm", "mass_error_kg", "hazard_prob", "moments", "moments_z"):
        if k in s:
            row[k] = s[k]
    return row


def moments_coverage(rows: list[dict]) -> dict | None:
    """Per moment, the share of boxes whose truth lay within 1 and 1.96 stated std of the estimate (the
    learned estimator's moments; None when no row has them)."""
    zs = [r["moments_z"] for r in rows if r.get("moments_z")]
    if not zs:
        return None
    return {
        "boxes": len(zs),
        **{
            level: {q: float(np.mean([abs(z[q]) <= k for z in zs])) for q in zs[0]}
            for level, k in (("0.683", 1.0), ("0.95", 1.959964))
        },
    }


def _median_max(xs) -> dict:
    xs = [float(x) for x in xs]
    if not xs:
        return {"median": None, "max": None}
    return {"median": float(np.median(xs)), "max": float(np.max(xs))}


def summarize(rows: list[dict]) -> dict:
    """The evaluation's figures from its rows (see `evaluate`)."""
    safe = [r for r in rows if not r["hazardous"]]
    haz = [r for r in rows if r["hazardous"]]
    n_ok = sum(r["outcome"] == "success" for r in safe)
    lo, hi = wilson_interval(n_ok, len(safe))
    failures = Counter(r["outcome"] for r in safe if r["outcome"] not in ("success", "aborted", "safe_stop"))
    stops = [r for r in safe if r["outcome"] == "safe_stop"]
    turned = [r for r in safe if r["outcome"] == "success"]
    refused = sum(r["outcome"] == "aborted" for r in haz)
    return {
        "safe_boxes": len(safe),
        "safe_success": n_ok,
        "safe_success_rate": n_ok / len(safe) if safe else None,
        "safe_success_ci95": [lo, hi] if safe else None,
        "false_aborts": sum(r["outcome"] == "aborted" for r in safe),
        "safe_stops": len(stops),
        "safe_stop_reasons": dict(sorted(Counter(r.get("safe_stop_reason") for r in stops).items())),
        "failures": dict(sorted(failures.items())),
        # the TRUE balance error passed the limit (any box) / with no stop issued before it
        "crossings": sum(r.get("crossing", False) for r in rows),
        "unnoticed_crossings": sum(r.get("unnoticed_crossing", False) for r in rows),
        "monitor_stops": sum(r.get("monitor_stops", 0) for r in rows),
        "monitor_recoveries": sum(r.get("monitor_recoveries", 0) for r in rows),
        "lost_exploring": sum(r["lost_exploring"] for r in safe),
        "hazardous_boxes": len(haz),
        "hazard_aborted": refused,
        "hazard_recall": refused / len(haz) if haz else None,
        "hazard_outcomes": dict(sorted(Counter(r["outcome"] for r in haz).items())),
        "steps_success": _median_max(r["steps"] for r in turned),
        "max_balance_error_m": _median_max(
            r["max_balance_error_m"] for r in safe if r["outcome"] != "aborted"
        ),
        # the true box's smallest exact stability margin over its episode (safe boxes, not refused), and
        # how many came within NEAR_TIP_M of tipping: what tips, too rare to count, leave out
        "min_stability_margin_m": _margins(r for r in safe if r["outcome"] != "aborted"),
        "turn_min_stability_margin_m": _margins(safe, "turn_min_stability_margin_m"),  # the turn alone
        "moments_coverage": moments_coverage(rows),
    }


def _margins(rows, key: str = "min_stability_margin_m") -> dict:
    xs = [float(r[key]) for r in rows if r.get(key) is not None]
    if not xs:
        return {"median": None, "min": None, "near_tips": None}
    return {
        "median": float(np.median(xs)),
        "min": float(np.min(xs)),
        "near_tips": int(sum(x < NEAR_TIP_M for x in xs)),
    }


class Evaluation(NamedTuple):
    """What `evaluate` returns: `summary` (plain data; the CLI's JSON), one `rows` dict per box, the
    boxes, each episode's balance error over time (`balance`, (T_j + 1,) m, for the plots) and actions."""

    summary: dict
    rows: list[dict]
    boxes: EvalBoxes
    balance: list[np.ndarray]
    actions: list[np.ndarray] | None = None  # (T_j, 4) per episode: what was sent (`replay` re-simulates)


def settings(
    estimator: str,
    ctrl: ControllerConfig,
    seed: int,
    family: str,
    faults: Faults = NO_FAULTS,
    safe_family: str = "gaussian",
) -> dict:
    """What an evaluation ran with (enough to rebuild the same episodes)."""
    c = dataclasses.asdict(ctrl)
    return {
        "estimator": estimator,
        "seed": seed,
        "hazard_family": family,
        "safe_family": safe_family,
        "faults": faults.to_dict(),
        "controller": json.loads(
            json.dumps(c, default=lambda o: dataclasses.asdict(o) if dataclasses.is_dataclass(o) else str(o))
        ),
    }


def evaluate(
    cfg: Config,
    n_safe: int,
    n_hazardous: int = 0,
    seed: int = 0,
    *,
    estimator: str = "oracle",
    ctrl: ControllerConfig = ControllerConfig(),  # noqa: B008 (frozen dataclass: immutable)
    family: str = "gaussian",
    safe_family: str = "gaussian",
    progress: bool = True,
    estimator_fn: Any = None,
    batched: bool | None = None,
    slots: int | None = None,
    faults: Faults = NO_FAULTS,
    backend: str = "native",
) -> Evaluation:
    """Run one closed-loop episode on each of n_safe random label-safe boxes and n_hazardous hazardous
    boxes (paper §4.3). Every episode ends with an outcome: success, aborted (refused after exploring),
    or a failure reason (task.REASONS); a box lost while exploring is a failure, never an exception.

    Args:
      estimator: "oracle" (the true distribution) or "learned" (the shipped H, or `estimator_fn`).
      ctrl: the controller (planner, prior variant, options, its runtime safety monitor). family: the
        hazardous boxes' family; safe_family: the safe boxes' (`sample_safe`; "gaussian" is the paper's).
      faults: how the simulated world differs from the controller's (`boxjax.sim.faults`), each box's drawn
        from its own episode key.
      batched: run the episodes together (`boxjax.control.batch`: `slots` boxes per planner call; default
      where
        the controller allows it, `batch.supports`) or one at a time (`controller.run_episode`). The two
        agree in distribution, not bit for bit (see boxjax/batch.py); each episode's actions are kept,
        so `replay` re-simulates any of them exactly either way.
      backend: "native" (MuJoCo on the host, the planner batched on the device) or "mjx" (the whole
        closed loop on the device, `boxjax.control.device_loop`: no faults, the jnp planners).

    Under `jax.distributed` (`boxjax.experiments.distributed`) each process runs its share of the boxes
    and every process returns the whole evaluation.
    """
    if n_safe < 0 or n_hazardous < 0 or n_safe + n_hazardous < 1:
        raise ValueError(
            f"need at least one box and no negative counts, got {n_safe} safe, {n_hazardous} hazardous"
        )
    if estimator not in ("oracle", "learned"):
        raise ValueError(f"unknown estimator {estimator!r}; choose 'oracle' or 'learned'")
    if ctrl.belief == "ensemble" and estimator == "oracle":
        raise ValueError("belief='ensemble' plans over the learned H's members; the oracle has none")
    if backend not in ("native", "mjx"):
        raise ValueError(f"unknown backend {backend!r}; choose 'native' or 'mjx'")
    why_not = batch.supports(ctrl)
    if backend == "mjx":
        why_mjx = device_loop.supports(ctrl, faults)
        if why_mjx is not None or batched is False:
            raise ValueError(f"--backend mjx cannot run these episodes: {why_mjx or 'they run batched'}")
    if batched and why_not is not None:
        raise ValueError(f"cannot batch these episodes: {why_not}")
    if slots is not None and (slots < 1 or batched is False or why_not is not None):
        raise ValueError("slots (boxes per planner call) needs batched episodes and must be >= 1")
    batched = why_not is None if batched is None else batched
    est: Any = "oracle"
    if estimator == "learned":
        est = estimator_fn or learned_estimator(cfg)
    t0 = time.perf_counter()
    boxes = make_boxes(cfg, n_safe, n_hazardous, seed, family, safe_family)
    mine = distributed.share(len(boxes))  # every box, unless this is one process of several
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(mine), desc=f"evaluate ({estimator}, {ctrl.planner})", unit="box", leave=False)
    results: list[Any] = [None] * len(boxes)
    ended = {"safe": 0, "turned": 0}

    def done(j: int, res) -> None:
        results[j] = res
        if not boxes.hazardous[j]:
            ended["safe"] += 1
            ended["turned"] += bool(res.summary["success"])
        if bar is not None:
            bar.set_postfix_str(f"safe turned {ended['turned']}/{ended['safe']}")
            bar.update(1)

    dists = [boxes.dist(j) for j in mine]
    keys = [jax.random.wrap_key_data(boxes.keys[j]) for j in mine]
    if backend == "mjx" and mine:
        device_loop.run_episodes(
            cfg,
            dists,
            keys,
            estimator=est,
            ctrl=ctrl,
            slots=slots,
            progress=lambda i, res: done(mine[i], res),
        )
    elif batched and mine:  # (a process of several may have no box: more processes than boxes)
        batch.run_episodes(
            cfg, dists, keys, estimator=est, ctrl=ctrl, slots=slots, faults=faults,
            progress=lambda i, res: done(mine[i], res),
        )  # fmt: skip
    else:
        for i, j in enumerate(mine):
            done(j, run_episode(cfg, dists[i], keys[i], estimator=est, ctrl=ctrl, faults=faults))
    local = [
        (_row(j, boxes, results[j], cfg), results[j].trace.balance_error, results[j].trace.actions)
        for j in mine
    ]
    ran = [x for part in distributed.gather(local) for x in part]  # every process's, box order restored
    ran.sort(key=lambda x: x[0]["index"])
    rows = [r for r, _, _ in ran]
    balance = [np.asarray(b, np.float32) for _, b, _ in ran]
    if bar is not None:
        bar.close()
    summary = {
        **summarize(rows),
        **settings(estimator, ctrl, seed, family, faults, safe_family),
        "batched": bool(batched),
        "backend": backend,
        **({"processes": jax.process_count()} if jax.process_count() > 1 else {}),
        "wall_s": time.perf_counter() - t0,
    }
    return Evaluation(summary, rows, boxes, balance, [np.asarray(a) for _, _, a in ran])


def write_evaluation(ev: Evaluation, out_dir, command: str | None = None) -> dict[str, str]:
    """Write `out_dir/evaluation.json` (summary, settings, one row per box) and `out_dir/boxes.npz` (the
    boxes, their episode keys and balance traces), each atomically. Returns the paths."""
    os.makedirs(out_dir, exist_ok=True)
    json_path = os.path.join(out_dir, "evaluation.json")
    npz_path = os.path.join(out_dir, "boxes.npz")
    lengths = np.asarray([len(b) for b in ev.balance], np.int32)
    pad = np.full((len(ev.balance), int(lengths.max(initial=1))), np.nan, np.float32)
    for j, b in enumerate(ev.balance):
        pad[j, : len(b)] = b
    arrays = {
        **{k: np.asarray(v) for k, v in ev.boxes._asdict().items()},
        "balance": pad,
        "balance_len": lengths,
    }
    if ev.actions is not None:  # what each episode sent, NaN-padded: `replay` re-simulates it exactly
        n_act = np.asarray([len(a) for a in ev.actions], np.int32)
        acts = np.full((len(ev.actions), int(n_act.max(initial=1)), 4), np.nan, np.float64)
        for j, a in enumerate(ev.actions):
            acts[j, : len(a)] = a
        arrays.update(actions=acts, actions_len=n_act)
    arrays["family"] = arrays["family"].astype("U16")
    fileio.write_npz_with_meta(npz_path, arrays, {"summary": ev.summary}, RESULTS_FORMAT, RESULTS_VERSION)
    doc = {"command": command, "summary": ev.summary, "rows": ev.rows}
    with fileio.atomic_path(json_path, suffix=".json") as tmp:
        with open(tmp, "w") as f:
            json.dump(doc, f, indent=1)
    return {"evaluation": json_path, "boxes": npz_path}


def animate_failures(ev: Evaluation, cfg: Config, out_dir, max_frames: int | None = None) -> list[str]:
    """A top-view GIF (`animate.animate_episode`) of every failed episode of an evaluation: the safe boxes
    not turned and not refused, the hazardous boxes not refused. Each episode is re-simulated from its
    recorded actions (`batch.replay_episode`: the same states bit for bit); files
    `out_dir/failures/box_K.gif`, written atomically. Returns their paths."""

    if ev.actions is None:
        raise ValueError("this evaluation kept no actions: run it again to animate its failures")
    # the controller the episodes ran with (its exploration guard decides what the replay expects)
    ctrl = controller_from_settings(ev.summary) if "controller" in ev.summary else ControllerConfig()
    paths = []
    for row in ev.rows:
        kept = ("aborted", "safe_stop") if row["hazardous"] else ("success", "aborted", "safe_stop")
        failed = row["outcome"] not in kept
        if not failed:
            continue
        j = row["index"]
        truth, key = ev.boxes.dist(j), jax.random.wrap_key_data(ev.boxes.keys[j])
        faults = faults_from_settings(ev.summary)
        trace = batch.replay_episode(cfg, truth, key, ev.actions[j], ctrl=ctrl, faults=faults).trace
        os.makedirs(os.path.join(out_dir, "failures"), exist_ok=True)
        path = os.path.join(out_dir, "failures", f"box_{j}.gif")
        kw = {} if max_frames is None else {"max_frames": max_frames}
        title = f"box {j} ({row['family']}): {row['outcome']}"
        paths.append(
            animate.animate_episode(trace, path, cfg, truth, title=title, outcome=row["outcome"], **kw)
        )
    return paths


class EvaluationFileError(ValueError):
    """An evaluation output is missing, corrupt or of another format."""


def load_boxes(out_dir) -> tuple[EvalBoxes, dict]:
    """(boxes, summary) of an evaluation written by `write_evaluation`."""
    path = os.path.join(out_dir, "boxes.npz") if os.path.isdir(out_dir) else out_dir
    arrays, meta = fileio.read_npz_with_meta(
        path, EvaluationFileError, "evaluation boxes", RESULTS_FORMAT, RESULTS_VERSION
    )
    boxes = EvalBoxes(**{k: arrays[k] for k in EvalBoxes._fields})
    return boxes, meta["summary"]


def load_actions(out_dir) -> list[np.ndarray] | None:
    """Each episode's actions (T_j, 4) of an evaluation written by `write_evaluation` (None for files
    written before actions were kept)."""
    path = os.path.join(out_dir, "boxes.npz") if os.path.isdir(out_dir) else out_dir
    arrays, _ = fileio.read_npz_with_meta(
        path, EvaluationFileError, "evaluation boxes", RESULTS_FORMAT, RESULTS_VERSION
    )
    if "actions" not in arrays:
        return None
    return [arrays["actions"][j, :n] for j, n in enumerate(arrays["actions_len"])]


def controller_from_settings(st: dict) -> ControllerConfig:
    """The ControllerConfig an evaluation ran with (its `settings(...)["controller"]`)."""
    c = dict(st["controller"])
    c.setdefault("explore_guard", None)  # evaluations written before the guard explored without one
    c.setdefault("explore_guard_lead", 0)  # and before its lead, on the present balance error alone
    c.setdefault("explore_guard_stop", "recentre")  # and before its stop was chosen by the sensor
    c.setdefault("delay_reference", None)  # and before a late loop slowed the planner
    if c.get("sampling") is not None:
        c["sampling"] = SamplingOptions(**c["sampling"])
    if isinstance(c.get("pose_filter"), dict):
        c["pose_filter"] = FilterConfig(**c["pose_filter"])
    # evaluations written before the runtime safety monitor ran without one
    if isinstance(c.get("monitor"), dict):  # and before recover_until_worse, the tipping watch and its modes
        old = {"recover_until_worse": False, "tip_stop": 0.0, "tip_uncertainty": "y", "tip_drag_std": 0.0}
        m = {**old, **c["monitor"]}
        if isinstance(m.get("prior_params"), dict):
            m["prior_params"] = prior.PriorParams(**m["prior_params"])
        c["monitor"] = MonitorConfig(**m)
    else:
        c["monitor"] = monitor.OFF
    if isinstance(c.get("friction_set"), list):  # JSON keeps the tuple as a list
        c["friction_set"] = tuple(c["friction_set"])
    pp = c.get("prior_params")
    if isinstance(pp, list | tuple):  # a mixture of priors
        c["prior_params"] = tuple(prior.PriorParams(**p) for p in pp)
    elif pp is not None:
        c["prior_params"] = prior.PriorParams(**pp)
    known = {f.name for f in dataclasses.fields(ControllerConfig)}
    unknown = sorted(set(c) - known)
    if unknown:
        raise EvaluationFileError(f"evaluation was run with controller options this boxjax lacks: {unknown}")
    return ControllerConfig(**c)


def faults_from_settings(st: dict) -> Faults:
    """The faults an evaluation ran with (none for files written before faults existed)."""
    return Faults.from_dict(st["faults"]) if st.get("faults") else NO_FAULTS


# Why an evaluation of the on-device loop cannot be replayed (measured: benchmarks/mjx_sensitivity.py).
NO_MJX_REPLAY = (
    "its episodes cannot be re-simulated: an MJX world's step depends at float32 round-off on the program "
    "it runs in (vmapped, how wide, sharded), and slip makes those differences millimetres within a few "
    "steps (docs/design.md#slip-chaos); its rows and balance traces are in the files"
)


def replay(cfg: Config, out_dir, index: int, *, estimator_fn: Any = None):
    """Box `index` of a written evaluation again: its recorded actions re-simulated with its own episode
    key (the same states bit for bit, however the evaluation ran), the estimator and the decision
    re-run on the exploration. Files without recorded actions: the episode re-run closed loop with
    `run_episode`. Returns (controller.EpisodeResult, the evaluation's summary)."""
    boxes, summary = load_boxes(out_dir)
    if summary.get("backend", "native") != "native":
        raise ValueError(f"{out_dir} ran on {summary['backend']}: {NO_MJX_REPLAY}")
    if not 0 <= index < len(boxes):
        raise ValueError(
            f"--index {index} is outside the evaluation's {len(boxes)} boxes (0..{len(boxes) - 1})"
        )
    est: Any = "oracle"
    if summary["estimator"] == "learned":
        est = estimator_fn or learned_estimator(cfg)
    ctrl = controller_from_settings(summary)
    truth, key = boxes.dist(index), jax.random.wrap_key_data(boxes.keys[index])
    actions = load_actions(out_dir)
    faults = faults_from_settings(summary)
    if actions is None:
        return run_episode(cfg, truth, key, estimator=est, ctrl=ctrl, faults=faults), summary
    return (
        batch.replay_episode(cfg, truth, key, actions[index], estimator=est, ctrl=ctrl, faults=faults),
        summary,
    )
