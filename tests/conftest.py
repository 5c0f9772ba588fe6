"""Test-session settings shared by every test module."""

from __future__ import annotations

import os

from boxjax.run_info import CACHE_ENV

# The CLI keeps JAX's compiled programs on disk (`run_info.use_compilation_cache`). Tests that call it
# in-process must not write into the user's cache: the session keeps none unless the environment
# names a folder (a test that wants one sets its own, as tests/test_reproduce.py's quick run does).
os.environ.setdefault(CACHE_ENV, "off")
