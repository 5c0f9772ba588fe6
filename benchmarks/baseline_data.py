"""W's training episodes per second (`training.baseline.collect`): native MuJoCo one episode at a time
against MJX in batches on the device (`training.baseline_device`), the same episode kinds and keys,
measured in one run.

Each backend is compiled first (the same episodes with a 6-step cap: the cap is an argument of the
programs, not compiled in), so the timed part is episodes only; the compile time is reported apart. Also
reported per backend and episode kind: episodes, transitions, mean length and the outcomes (the backends
agree in kind, not episode by episode: `training.baseline_device`'s docstring).

Prints ONE JSON object (the last line).
Run: python benchmarks/baseline_data.py [--episodes 10] [--seed 0] [--backends native mjx]
                                        [--max-steps 600] [--devices 1]
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _util import emit_to, machine  # noqa: E402

from boxjax import massdist  # noqa: E402
from boxjax.config import DEFAULT  # noqa: E402
from boxjax.control import batch  # noqa: E402
from boxjax.training import baseline as baseline_train  # noqa: E402


def by_kind(episodes) -> dict:
    out = {}
    for kind in dict.fromkeys(e["kind"] for e in episodes):
        eps = [e for e in episodes if e["kind"] == kind]
        lengths = [e["actions"].shape[0] for e in eps]
        out[kind] = {
            "episodes": len(eps),
            "transitions": int(sum(lengths)),
            "mean_length": float(np.mean(lengths)),
            "outcomes": dict(collections.Counter(e["outcome"] for e in eps)),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=10, help="episodes per backend (5 kinds cycle)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backends", nargs="+", choices=("native", "mjx"), default=["native", "mjx"])
    ap.add_argument("--max-steps", type=int, default=DEFAULT.task.max_steps)
    ap.add_argument("--devices", type=int, default=1, help="host devices on a CPU (one per core)")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if args.episodes < 1 or args.max_steps < 1 or args.devices < 1:
        ap.error("--episodes, --max-steps and --devices must be >= 1")
    batch.use_host_devices(args.devices)
    cfg = DEFAULT
    truth = massdist.named("A", cfg.box)
    out = {"machine": machine(), "episodes": args.episodes, "seed": args.seed, "max_steps": args.max_steps}
    for backend in args.backends:
        t0 = time.perf_counter()
        baseline_train.collect(
            cfg, truth, 5, seed=10_000 + args.seed, progress=False, backend=backend, max_steps=6
        )
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        eps = baseline_train.collect(
            cfg,
            truth,
            args.episodes,
            seed=args.seed,
            progress=False,
            backend=backend,
            max_steps=args.max_steps,
        )
        run_s = time.perf_counter() - t0
        n_tr = sum(e["actions"].shape[0] for e in eps)
        out[backend] = {
            "compile_s": compile_s,
            "run_s": run_s,
            "episodes_per_s": args.episodes / run_s,
            "transitions_per_s": n_tr / run_s,
            "transitions": int(n_tr),
            "by_kind": by_kind(eps),
        }
        print(
            f"{backend}: {args.episodes} episodes in {run_s:.1f} s (compile {compile_s:.1f} s)",
            file=sys.stderr,
        )
    if "native" in out and "mjx" in out:
        out["mjx_speedup"] = out["mjx"]["episodes_per_s"] / out["native"]["episodes_per_s"]
    emit_to(out, args.out)


if __name__ == "__main__":
    main()
