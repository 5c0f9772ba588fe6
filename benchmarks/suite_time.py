"""Where the default test suite's time goes: runs it (`pytest -n WORKERS --dist loadfile`, as `make test`)
with a plugin (`benchmarks/_compile_probe.py`) that records, per test, JAX's tracing, lowering and XLA
compile seconds and the persistent cache's hits, and pytest's own per-test time (junit XML). Prints one
JSON line: the wall time, the summed test time, the compile / trace / lowering totals, and the tests that
take longest with their compile share; `--out FILE` writes it too (atomically).

    python benchmarks/suite_time.py [--workers 2] [--top 25] [--out FILE] [-- extra pytest arguments]

The session's compilation cache is the suite's own (tests/conftest.py): a fresh folder per run. The
listener adds a little time of its own; compare runs of this script with each other, not with `make test`.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict

from _util import emit_to

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
SAVED = "/jax/compilation_cache/compile_time_saved_sec"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (default 2, as `make test`)")
    p.add_argument("--top", type=int, default=25, help="how many of the longest tests to list (default 25)")
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument("pytest_args", nargs="*", help="after --: passed to pytest")
    a = p.parse_args(argv)
    if a.workers < 1 or a.top < 1:
        p.error("--workers and --top must be >= 1")
    if a.out:
        folder = os.path.dirname(os.path.abspath(a.out))
        if not os.access(folder, os.W_OK):
            p.error(f"--out: cannot write into {folder}")
    with tempfile.TemporaryDirectory(prefix="boxjax-suite-time-") as tmp:
        junit = os.path.join(tmp, "junit.xml")
        env = {**os.environ, "BOXJAX_COMPILE_PROBE_DIR": tmp}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [HERE, env.get("PYTHONPATH")]))
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "_compile_probe", f"--junitxml={junit}"]
        if a.workers > 1:
            cmd += ["-n", str(a.workers), "--dist", "loadfile"]
        t0 = time.perf_counter()
        run = subprocess.run([*cmd, *a.pytest_args], cwd=ROOT, env=env)
        wall = time.perf_counter() - t0
        probes: dict[str, dict] = {}
        for path in glob.glob(os.path.join(tmp, "*.json")):
            with open(path) as f:
                probes.update(json.load(f))
        tests = {}
        for case in ET.parse(junit).iter("testcase"):
            node = f"{case.get('classname').replace('.', '/')}.py::{case.get('name')}"
            tests[node] = float(case.get("time") or 0.0)
    totals: dict[str, float] = defaultdict(float)
    for d in probes.values():
        for k, v in d.items():
            totals[k] += v
    longest = sorted(tests.items(), key=lambda kv: -kv[1])[: a.top]
    result = {
        "benchmark": "suite_time",
        "pytest_exit": run.returncode,
        "workers": a.workers,
        "wall_s": round(wall, 1),
        "tests": len(tests),
        "test_time_s": round(sum(tests.values()), 1),
        "xla_compile_s": round(totals[COMPILE], 1),
        "xla_compiles": int(totals[COMPILE + "#n"]),
        "trace_s": round(totals[TRACE], 1),
        "lowering_s": round(totals[LOWER], 1),
        "cache_hits": int(totals[SAVED + "#n"]),
        "cache_saved_s": round(totals[SAVED], 1),
        "longest": [
            {
                "test": node,
                "s": round(s, 1),
                "xla_compile_s": round(probes.get(node, {}).get(COMPILE, 0.0), 1),
                "trace_s": round(probes.get(node, {}).get(TRACE, 0.0), 1),
            }
            for node, s in longest
        ],
        "command": " ".join(
            ["python", "benchmarks/suite_time.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    }
    emit_to(result, a.out)
    return 0 if run.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
