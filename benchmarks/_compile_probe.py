"""A pytest plugin for `benchmarks/suite_time.py`: per test, the seconds JAX spends tracing, lowering and
XLA-compiling (its `jax.monitoring` duration events) and the persistent cache's hits, written as one JSON
file per pytest process into $BOXJAX_COMPILE_PROBE_DIR when the session ends. Load with `-p _compile_probe`
(benchmarks/ on PYTHONPATH); pytest-xdist's workers load it too."""

from __future__ import annotations

import json
import os

import jax.monitoring

from boxjax.fileio import atomic_path

_current: dict = {"test": None}
_per_test: dict[str, dict[str, float]] = {}


def _listen(event: str, duration: float, **_) -> None:
    test = _current["test"]
    if test is None:
        return
    d = _per_test.setdefault(test, {})
    d[event] = d.get(event, 0.0) + duration
    d[event + "#n"] = d.get(event + "#n", 0) + 1


jax.monitoring.register_event_duration_secs_listener(_listen)


def pytest_runtest_setup(item) -> None:
    _current["test"] = item.nodeid


def pytest_sessionfinish(session) -> None:
    folder = os.environ.get("BOXJAX_COMPILE_PROBE_DIR")
    if not folder:
        return
    name = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with atomic_path(os.path.join(folder, f"{name}.json"), suffix=".json") as tmp, open(tmp, "w") as f:
        json.dump(_per_test, f)
