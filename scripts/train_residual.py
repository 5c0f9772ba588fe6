"""Train a learned residual on the physics prior (`boxjax.prior.residual`) from closed-loop episodes.

    python benchmarks/closed_loop_error.py --boxes 192 --seed 7 --traces /tmp/tr7.npz   # episodes
    python benchmarks/closed_loop_error.py --boxes 64 --seed 8 --traces /tmp/tr8.npz
    python scripts/train_residual.py --traces /tmp/tr7.npz --val /tmp/tr8.npz --out residual.npz
    python scripts/planner_study.py --boxes 100 --seed 0 --controller residual=residual.npz

Use seeds no evaluation uses (the README's evaluations use 0-2). Prints one JSON line: the loss of the
prior alone and with the residual on the validation episodes, the training curve and times.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax
import numpy as np
from tqdm.auto import tqdm

from boxjax.prior import residual


def _load(paths: list[str], horizon: int, stride: int, start: str) -> dict:
    parts = [residual.segments(dict(np.load(p)), horizon, stride, start) for p in paths]
    if len(parts) == 1:
        return parts[0]
    offset, boxes = 0, []
    for p in parts:
        boxes.append(p["box"] + offset)
        offset += len(p["masses"])
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "box"}
    out["box"] = np.concatenate(boxes)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--traces", nargs="+", required=True, help="training episodes (npz)")
    ap.add_argument("--val", required=True, help="validation episodes (npz), other boxes")
    ap.add_argument("--out", required=True, help="the residual checkpoint to write (npz)")
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--start", choices=("exploration", "all"), default="exploration")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--clip", type=float, default=100.0, help="global gradient-norm clip")
    ap.add_argument("--hidden", default="64,64")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.horizon < 1 or args.stride < 1 or args.steps < 1 or args.batch < 1:
        ap.error("--horizon, --stride, --steps and --batch must be >= 1")
    cfg = residual.ResidualConfig(hidden=tuple(int(h) for h in args.hidden.split(",")))
    train = _load(args.traces, args.horizon, args.stride, args.start)
    val = _load([args.val], args.horizon, 3, "exploration")
    bar = tqdm(total=args.steps, desc="residual", unit="step", file=sys.stderr)

    def progress(i, row):
        bar.update(i - bar.n)
        bar.set_postfix({k: round(v, 4) for k, v in row.items() if k.endswith("loss")})

    net, log = residual.fit(
        jax.random.PRNGKey(args.seed),
        train,
        val,
        cfg,
        steps=args.steps,
        batch=args.batch,
        lr=args.lr,
        progress=progress,
    )
    bar.close()
    meta = {"traces": args.traces, "val": args.val, **{k: v for k, v in vars(args).items() if k != "out"}}
    meta.update({k: log[k] for k in ("train_cases", "val_cases", "val_loss_prior", "val_loss")})
    residual.save(args.out, net, cfg, meta)
    print(json.dumps({"out": args.out, **log}))
    return log


if __name__ == "__main__":
    main()
