"""Timing helpers shared by the benchmarks: compile and run timed separately, medians over repeats."""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time

import jax


def timed(fn, *args, repeats: int = 5):
    """(first-call seconds, median seconds of `repeats` later calls, last result); blocks on JAX outputs."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), out


def machine() -> dict:
    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
    }


def emit_to(result: dict, path: str | None = None):
    """Print the result as ONE JSON line and, with a path, also write it there atomically."""
    text = json.dumps(result)
    if path:
        from boxjax.fileio import atomic_path

        with atomic_path(path, suffix=".json") as tmp, open(tmp, "w") as f:
            f.write(text + "\n")
    sys.stdout.write(text + "\n")


def emit(result: dict):
    """Print the result as ONE JSON line (the last line of output)."""
    sys.stdout.write(json.dumps(result) + "\n")
