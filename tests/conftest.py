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
    # Kept from 0.1 s (the user's default is 0.5 s): 210 programs read back instead of 59, the suite
    # 666 s instead of 709 s on 2 cores (`benchmarks/suite_time.py`, 2026-12-07).
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.1"
    atexit.register(shutil.rmtree, _folder, True)
use_compilation_cache()
