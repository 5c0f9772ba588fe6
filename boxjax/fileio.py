"""Atomic file writes: a reader never sees a half-written file, and a crash never destroys the old one."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import zipfile

import numpy as np


@contextlib.contextmanager
def atomic_path(path, suffix: str = ""):
    """Yield a temporary path in the destination's directory; on success move it onto `path`.

    Example:
        with atomic_path("out/model.npz", suffix=".npz") as tmp:
            np.savez_compressed(tmp, **arrays)
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as f:  # on disk before it replaces the old file
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes files owner-only; give the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_writable_dir(path, what: str = "output directory") -> None:
    """Make sure `path` is (or can be made) a directory we can write files in, before any work is done:
    it is created if missing, a probe file is written and removed. Raises ValueError naming the problem."""
    path = os.fspath(path)
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".boxjax-probe-")
        os.close(fd)
        os.remove(probe)
    except OSError as e:
        raise ValueError(f"{what} {path!r} cannot be written: {e.strerror or e}") from None


def save_figure(fig, path, dpi: int = 110) -> str:
    """Save a matplotlib figure as PNG atomically; returns the path."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return os.fspath(path)


def read_npz(path, error: type[Exception], what: str) -> dict[str, np.ndarray]:
    """All arrays of an .npz file (no pickle), or `error` with a message naming the problem.

    Args:
      error: the exception class to raise (e.g. CheckpointError); `what` names the file kind in messages.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise error(f"{path}: no such {what} file (it does not exist)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise error(f"{path}: not a valid {what}: corrupt, truncated or not an .npz file ({e})") from e
    except Exception as e:  # zlib.error, NotImplementedError (zip features) ... from a damaged member
        raise error(f"{path}: corrupt {what} ({type(e).__name__}: {e})") from e


META_KEY = "__meta__"  # the JSON metadata entry of a boxjax .npz file


def write_npz_with_meta(path, arrays: dict, meta: dict, fmt: str, version: int) -> str:
    """Write `arrays` and a JSON `meta` (stamped with `fmt` and `version`) as one compressed .npz,
    atomically; no pickle is needed to read it back (`read_npz_with_meta`)."""
    payload = dict(arrays)
    payload[META_KEY] = np.array([json.dumps({**meta, "format": fmt, "version": version}, sort_keys=True)])
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **payload)
    return os.fspath(path)


def read_npz_with_meta(path, error: type[Exception], what: str, fmt: str, version: int):
    """(arrays, meta) of a file written by `write_npz_with_meta`, or `error` naming the problem: missing,
    corrupt or truncated file, no or unreadable metadata, another format, another format version."""
    arrays = read_npz(path, error, what)
    if META_KEY not in arrays:
        raise error(f"{path}: not a boxjax {what} (no {META_KEY!r} metadata entry)")
    try:
        meta = json.loads(str(arrays.pop(META_KEY).reshape(-1)[0]))
    except (ValueError, IndexError) as e:
        raise error(f"{path}: corrupt {what} metadata ({e})") from e
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        raise error(f"{path}: not a boxjax {what} (format is not {fmt!r})")
    if meta.get("version") != version:
        raise error(
            f"{path}: {what} format version {meta.get('version')!r}; this boxjax reads version {version}"
        )
    return arrays, meta
