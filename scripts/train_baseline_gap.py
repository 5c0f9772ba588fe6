"""W's generalisation gap: one-step errors of W (shipped, trained on A), the physics prior (true masses) and
constant velocity on fresh episodes of boxes A and C (baseline_train's episode mix, another seed than W's
training data).

    python scripts/train_baseline_gap.py [--episodes 10] [--seed 1000] [--out FILE.json]

Prints one JSON object as its last stdout line (progress bars on stderr).
"""

from __future__ import annotations

import argparse
import json

from boxjax.experiments import comparison
from boxjax.fileio import atomic_path


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--boxes", nargs="+", default=["A", "C"])
    p.add_argument("--out")
    a = p.parse_args()
    res = comparison.generalisation_gap(boxes=tuple(a.boxes), n_episodes=a.episodes, seed=a.seed)
    res = {"episodes_per_box": a.episodes, "seed": a.seed, **res}
    if a.out:
        with atomic_path(a.out, suffix=".json") as tmp:
            with open(tmp, "w") as f:
                json.dump(res, f, indent=1)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
