"""Test-session settings shared by every test module."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

from boxjax.run_info import CACHE_ENV, use_compilation_cache

# Compiled programs are kept on disk for the session, in a folder of its own shared by its processes
# (pytest-xdist's workers inherit the environment of the process that starts them, which loads this
# file first and removes the folder when it exits): many test modules compile the same programs (the
# default planner takes ~15 s on 2 cores), and from the second module on they are read back. Nothing is
# written to the user's cache (~/.cache/boxjax/jax). A folder named in the environment is used instead,
# and BOXJAX_COMPILATION_CACHE=off runs the session without one.
if CACHE_ENV not in os.environ:
    _folder = tempfile.mkdtemp(prefix="boxjax-tests-jax-cache-")
    os.environ[CACHE_ENV] = _folder
    # JAX reads these in every process it starts in: the README's snippets, the CLI run as a command and
    # the distributed test's processes share the folder too.
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _folder
    # Every program kept, as `use_compilation_cache` does (from 0.5 s: 59 read back, the suite 709 s on
    # 2 cores; from 0.1 s: 210 and 666 s; `benchmarks/suite_time.py`, 2026-12-07).
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    atexit.register(shutil.rmtree, _folder, True)
use_compilation_cache()

# The longest modules first (`make test` runs `-n 2 --dist loadfile`: a module is one worker's unit, handed
# out in collection order): a long module collected last would run alone at the end while the other worker
# idles. Their summed test seconds on 2 cores (`pytest --durations=0`, 2026-12-07); the others keep their
# order after these.
_LONGEST = (
    "test_monitor.py", "test_prior.py", "test_readme.py", "test_faults.py", "test_cli.py",
    "test_device_loop.py", "test_pets.py", "test_sampling_planner.py", "test_planning.py",
    "test_estimator.py", "test_baseline.py", "test_batch.py", "test_sim_mjx.py", "test_distributed.py",
    "test_mjx_contacts.py", "test_experiments.py",
)  # fmt: skip


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(_LONGEST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
