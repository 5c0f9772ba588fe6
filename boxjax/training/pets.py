"""Offline training of the PETS ensemble (`pets.py`) on W's data (`training.baseline`), and its report.

The data are W's (`boxjax train-baseline --out DIR` writes DIR/dataset.npz: 200 episodes of box A, the
prior pipeline, its noisy variant and random exploration; training.baseline's module docstring), split the
same way (by episode, one in 10 held out), so the held-out one-step errors of PETS, W, the prior and
constant velocity are on the same transitions. Without a dataset, episodes are collected as for W.

    boxjax train-baseline --model pets --data DIR/dataset.npz --out OUT [--seed 0] [--epochs N] [--json]
    python -m boxjax.training.pets --data DIR/dataset.npz --out OUT [--seed 0] [--epochs N] [--json]

(`train_pets` is the function both run.) Writes OUT/pets.npz (the checkpoint) and OUT/pets_report.json
atomically (not report.json, so OUT may be W's own directory).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np
import optax

from boxjax import massdist, planning
from boxjax.blackbox import baseline, pets
from boxjax.config import DEFAULT, Config
from boxjax.fileio import atomic_path
from boxjax.training import baseline as baseline_train

REPORT = "pets_report.json"


def split_episodes(tr: dict, n_episodes: int) -> tuple[dict, dict]:
    """(train, held-out) by episode as `training.baseline.train_baseline` splits W's data: one episode in 10
    held out (one of n below 10 episodes; every second one if that leaves none held out)."""
    if n_episodes < 2:
        raise ValueError(f"need at least 2 episodes (one is held out), got {n_episodes}")
    train_tr, held = baseline_train.split(tr, 10 if n_episodes >= 10 else n_episodes)
    if held["action"].shape[0] == 0:
        train_tr, held = baseline_train.split(tr, 2)
    return train_tr, held


def train(
    train_tr: dict, config: pets.PETSConfig, seed: int, cfg: Config = DEFAULT, progress: bool = True
) -> tuple:
    """The ensemble trained on `train_tr` (AdamW with cosine decay over config.epochs; each member on its
    own bootstrap sample when config.bootstrap); returns (model, epoch losses)."""
    X, Y = baseline.batch_features(train_tr, cfg.gripper)
    key = jax.random.PRNGKey(seed)
    model = pets.init_model(key, config, cfg.gripper, baseline.normalisation(X, Y))
    Xn, Yn = pets.standardise(model, X, Y)
    n = Xn.shape[0]
    rng = np.random.default_rng(seed)
    idx = pets.member_indices(n, config.members, config.bootstrap, rng)
    nb = max(1, -(-n // config.batch))
    sched = optax.cosine_decay_schedule(config.lr, config.epochs * nb, alpha=0.02)
    opt = optax.adamw(sched, weight_decay=config.weight_decay)
    bar = baseline_train._tqdm(config.epochs * nb, "PETS training (batches)", progress)
    t0 = pets._trainable(model)
    model, _, losses = pets.run_epochs(
        model, Xn, Yn, opt, opt.init(t0), config.epochs, config.batch, rng, idx, bar
    )
    bar.close()
    return model, losses


def errors(model, tr: dict, truth, cfg: Config = DEFAULT, w_model=None) -> dict:
    """One-step errors on the same transitions: PETS (members' mean), each member, W (shipped unless
    given), the prior with the true masses, constant velocity; and the ensemble's calibration."""
    out = baseline_train.compare_errors(w_model or baseline.default_model(cfg.gripper), tr, truth, cfg)
    out["pets"] = baseline.summarise_errors(baseline.one_step_errors(model, tr))
    out["pets_members_median"] = [
        {
            k: v["median"]
            for k, v in baseline.summarise_errors(
                baseline.one_step_errors(_member_model(model, i), tr)
            ).items()
        }  # fmt: skip
        for i in range(model.n_members)
    ]
    out["pets_calibration"] = pets.calibration(model, tr)
    return out


def _member_model(model, i: int):

    return planning.member(model.members, i)


def train_pets(
    cfg: Config = DEFAULT,
    data: str | None = None,
    distribution: str = "A",
    n_episodes: int = 200,
    seed: int = 0,
    out: str | None = None,
    config: pets.PETSConfig | None = None,
    progress: bool = True,
    backend: str = "native",
) -> dict:
    """Load (or collect, with `backend`: `training.baseline.collect`) W's data, train, score on the
    held-out episodes, save. Returns the report."""
    if data is None and n_episodes < 2:
        raise ValueError(f"--episodes must be >= 2 (one is held out), got {n_episodes}")
    config = config or pets.PETSConfig()
    truth = massdist.named(distribution, cfg.box)
    t0 = time.perf_counter()
    if data is None:
        episodes = baseline_train.collect(cfg, truth, n_episodes, seed, progress, backend)
        tr = baseline_train.transitions_of(episodes)
        kinds = [e["kind"] for e in episodes]
    else:
        tr = baseline_train.load_dataset(data)
        kinds = list(tr["episode_kind"])
        n_episodes = len(kinds)
    tr = {k: v for k, v in tr.items() if k not in ("episode_kind", "episode_outcome")}
    t_data = time.perf_counter() - t0
    train_tr, held = split_episodes(tr, n_episodes)
    t1 = time.perf_counter()
    model, losses = train(train_tr, config, seed, cfg, progress)
    jax.block_until_ready(model.members.params)
    t_train = time.perf_counter() - t1
    t2 = time.perf_counter()
    held_err = errors(model, held, truth, cfg)
    report = {
        "command": "pets_train",
        "distribution": distribution,
        "episodes": n_episodes,
        "episodes_by_kind": {k: kinds.count(k) for k in dict.fromkeys(kinds)},
        "seed": seed,
        "transitions": int(tr["action"].shape[0]),
        "train_transitions": int(train_tr["action"].shape[0]),
        "heldout_transitions": int(held["action"].shape[0]),
        "n_params": pets.n_params(model),
        "w_n_params": baseline.n_params(baseline.default_model(cfg.gripper)),
        "config": config.to_dict(),
        "epoch_losses": [float(x) for x in losses],
        "heldout_errors": held_err,
        "data_from": data or "collected",
        "backend": None if data else backend,
        "data_s": t_data,
        "train_s": t_train,
        "eval_s": time.perf_counter() - t2,
    }
    if out:
        os.makedirs(out, exist_ok=True)
        info = {k: report[k] for k in ("distribution", "episodes", "transitions", "train_transitions",
                                       "episodes_by_kind", "data_from", "backend", "train_s")}  # fmt: skip
        info["heldout_errors"] = {m: held_err[m] for m in ("pets", "blackbox", "prior", "constant_velocity")}
        info["heldout_calibration"] = held_err["pets_calibration"]
        report["weights"] = pets.save(os.path.join(out, "pets.npz"), model, seed, info)
        with atomic_path(os.path.join(out, REPORT), suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(report, f, indent=1)
    report["total_s"] = time.perf_counter() - t0
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m boxjax.training.pets", description=__doc__.split("\n")[0])
    p.add_argument("--data", help="a dataset.npz of `boxjax train-baseline` (default: collect episodes)")
    p.add_argument("--distribution", default="A")
    p.add_argument("--episodes", type=int, default=200, help="episodes to collect without --data")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=None, help=f"default {pets.PETSConfig().epochs}")
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true", help="overwrite OUT/pets.npz")
    p.add_argument("--json", action="store_true", help="print the report as one JSON line (no progress bars)")
    a = p.parse_args(argv)
    if os.path.exists(os.path.join(a.out, "pets.npz")) and not a.force:
        print(f"error: --out {a.out} already holds pets.npz; pass --force to overwrite it", file=sys.stderr)
        return 2
    config = pets.PETSConfig()
    if a.epochs is not None:
        config = dataclasses.replace(config, epochs=a.epochs)
    rep = train_pets(DEFAULT, a.data, a.distribution, a.episodes, a.seed, a.out, config, not a.json)
    print(json.dumps(rep) if a.json else json.dumps(rep, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
