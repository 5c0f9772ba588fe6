"""What ran where: the machine, the versions and the git commit a run reports, and JAX's on-disk
compilation cache (used by `boxjax reproduce`)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import boxjax

_REPO = Path(__file__).resolve().parent.parent


CACHE_ENV = "BOXJAX_COMPILATION_CACHE"


def use_compilation_cache(path: str | None = None) -> str | None:
    """Keep JAX's compiled programs on disk (`jax_compilation_cache_dir`) so that a second run skips most
    of the compilation (the planners' compile dominates a --quick run). The folder: `path`, else the
    environment variable BOXJAX_COMPILATION_CACHE ("off" or "" disables it), else
    $XDG_CACHE_HOME/boxjax/jax (default ~/.cache/boxjax/jax). Set it before the first compilation; a process
    that compiled already may keep running without it. Returns the folder, or None when disabled or when
    the folder cannot be made (a line on stderr says why; the command runs on without the cache)."""
    import jax

    if path is None:
        path = os.environ.get(CACHE_ENV)
        if path is None:
            base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
            path = os.path.join(base, "boxjax", "jax")
    if path in ("", "off"):
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:  # a read-only home, a file in the way: run without the cache, say so
        sys.stderr.write(f"boxjax: not keeping compiled programs ({path}: {e}); set {CACHE_ENV}\n")
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    # Every program is kept, the small ones too (unless JAX's own variable says otherwise): a command
    # compiles ~130 programs of ~30 ms besides its planner; kept, a second `evaluate --boxes 2 --hazardous
    # 1 --gradient-steps 0` takes 7.7-8.2 s instead of 12.8 s (2 cores, 2026-12-07), for ~1 MB of disk.
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


# ------------------------------------------------------------------------------------------------------
# What ran where


def machine() -> dict:
    """CPU, cores, load average (1, 5, 15 min), platform, JAX devices."""
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "jax_devices": [str(d) for d in jax.local_devices()],
    }


def _git(*args) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(_REPO), *args], capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def versions() -> dict:
    """python, jax, jaxlib, mujoco, numpy, boxjax and its git commit (None outside a git checkout)."""
    import jax
    import jaxlib
    import mujoco
    import numpy as np

    commit = _git("rev-parse", "HEAD")
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "boxjax": boxjax.__version__,
        "git_commit": commit or None,
        "git_dirty": None if commit is None or dirty is None else bool(dirty),
    }
