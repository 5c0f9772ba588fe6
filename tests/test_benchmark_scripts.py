"""The prepared device check (`benchmarks/device_check.sh`) and the planner benchmark's options refuse what
they cannot do before any work: a device call is short, and a part that fails late wastes it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax

ROOT = Path(__file__).resolve().parent.parent


def _run(cmd, **env):
    return subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env={**os.environ, **env}
    )


def test_the_device_check_refuses_an_unknown_part_before_any_work(tmp_path):
    out = tmp_path / "out"
    run = _run(["bash", "benchmarks/device_check.sh"], PARTS="wide bogus", OUT=str(out), BOXES="4")
    assert run.returncode == 2 and "unknown part bogus" in run.stderr
    assert not out.exists()  # nothing ran, not even the first, valid part


def test_the_planner_benchmark_refuses_structure_options_it_cannot_use():
    run = _run([sys.executable, "benchmarks/planner.py", "--unrolled-only"])
    assert run.returncode == 2 and "need --structure-only" in run.stderr
    if jax.default_backend() != "cpu":
        return  # there the accelerator part would run: minutes, not a check of the refusal
    run = _run(
        [sys.executable, "benchmarks/planner.py", "--structure-only", "--structure-devices", "accelerator"]
    )
    assert run.returncode == 2 and "--structure-devices accelerator: none here" in run.stderr
