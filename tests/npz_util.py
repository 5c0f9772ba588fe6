"""Test helper: rewrite a boxjax .npz (arrays + JSON metadata) with a mutation, to make bad files."""

from __future__ import annotations

import json

import numpy as np

from boxjax.fileio import META_KEY


def rewrite(src, dst, mutate):
    """Copy `src` to `dst` after `mutate(arrays, meta)` changed them in place (not atomic: tests only)."""
    with np.load(src, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    meta = json.loads(str(arrays.pop(META_KEY)[0]))
    mutate(arrays, meta)
    np.savez_compressed(dst, **{META_KEY: np.array([json.dumps(meta)])}, **arrays)
