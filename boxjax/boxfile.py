"""Boxes as files: a user's own mass distribution for `--box FILE` and `boxjax box`.

Two formats, told apart by the file name's suffix:

* ``.npz``: the `massdist.MassDistribution` fields, ``occupancy`` (nx, ny, nz) with values 0 or 1 (index
  i along the box length x, j along the width y, k up z; the grid must be the config's `BoxConfig.grid`)
  and ``total_mass`` (a scalar, kg). ``np.savez("mine.npz", occupancy=occ, total_mass=4.2)`` makes one;
  `save` adds a ``__meta__`` entry (how the file was made), which `load` ignores.
* ``.json``: a gaussian-mixture spec, voxelised on the config's grid exactly as the named boxes A-D are
  (`massdist.from_mixture`)::

    {"means": [[0.08, -0.06, -0.03], [-0.08, 0.06, 0.0]],   # m, box frame (origin at the box centre)
     "stds": [[0.08, 0.06, 0.05], [0.05, 0.05, 0.04]],      # m, per axis
     "weights": [1.0, 0.8],                                  # relative peak heights
     "threshold": 0.4,      # occupied where the mixture >= threshold x its maximum over the voxels
     "total_mass": 5.0,     # kg
     "region": null}        # optional: "U1".."U4" confines the mass to that outer quarter

Every problem (missing file, wrong grid, empty grid, NaN, a negative mass, unknown JSON keys) raises
`BoxFileError`, a ValueError whose one-line message starts with the path and names the problem.
"""

from __future__ import annotations

import json
import os

import jax
import numpy as np

from boxjax import fileio, massdist
from boxjax.config import DEFAULT, BoxConfig

FORMAT, VERSION = "boxjax-box", 1
SUFFIXES = (".npz", ".json")
_JSON_REQUIRED = ("means", "stds", "weights", "threshold", "total_mass")
_JSON_KEYS = (*_JSON_REQUIRED, "region")


class BoxFileError(ValueError):
    """A box file is missing, unreadable, or holds an invalid mass distribution."""


def _suffix(path) -> str:
    suffix = os.path.splitext(os.fspath(path))[1].lower()
    if suffix not in SUFFIXES:
        raise BoxFileError(f"{path}: a box file must end in .npz (occupancy grid) or .json (mixture spec)")
    return suffix


def _floats(path, name, value, shape) -> np.ndarray:
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError) as e:
        raise BoxFileError(f"{path}: {name!r} must be numbers, got {value!r}") from e
    if a.ndim != len(shape) or any(n is not None and a.shape[i] != n for i, n in enumerate(shape)):
        want = " x ".join("G" if n is None else str(n) for n in shape)
        raise BoxFileError(f"{path}: {name!r} must have shape ({want}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise BoxFileError(f"{path}: {name!r} contains NaN or inf")
    return a


def _from_spec(path, spec, box: BoxConfig) -> massdist.MassDistribution:
    if not isinstance(spec, dict):
        raise BoxFileError(f"{path}: the JSON must be an object with keys {', '.join(_JSON_REQUIRED)}")
    unknown = sorted(set(spec) - set(_JSON_KEYS))
    if unknown:
        raise BoxFileError(f"{path}: unknown key(s) {unknown}; a mixture spec has {list(_JSON_KEYS)}")
    missing = [k for k in _JSON_REQUIRED if k not in spec]
    if missing:
        raise BoxFileError(f"{path}: missing key(s) {missing}")
    means = _floats(path, "means", spec["means"], (None, 3))
    g = means.shape[0]
    if g < 1:
        raise BoxFileError(f"{path}: 'means' needs at least one gaussian")
    stds = _floats(path, "stds", spec["stds"], (g, 3))
    weights = _floats(path, "weights", spec["weights"], (g,))
    threshold = _floats(path, "threshold", spec["threshold"], ())
    mass = _floats(path, "total_mass", spec["total_mass"], ())
    if np.any(stds <= 0):
        raise BoxFileError(f"{path}: every 'stds' entry must be > 0 m")
    if np.any(weights <= 0):
        raise BoxFileError(f"{path}: every 'weights' entry must be > 0")
    if not 0 < threshold <= 1:
        raise BoxFileError(f"{path}: 'threshold' must lie in (0, 1], got {float(threshold)}")
    if mass <= 0:
        raise BoxFileError(f"{path}: 'total_mass' must be > 0 kg, got {float(mass)}")
    region = spec.get("region")
    if region is not None:
        if region not in massdist.REGION_NAMES:
            raise BoxFileError(f"{path}: 'region' must be null or one of {list(massdist.REGION_NAMES)}")
        region = massdist.REGION_NAMES.index(region)
    return massdist.from_mixture(means, stds, weights, float(threshold), float(mass), region, box=box)


def load(path, box: BoxConfig = DEFAULT.box) -> massdist.MassDistribution:
    """The distribution in a box file (.npz grid or .json mixture), checked against `box`'s grid.

    Raises:
      BoxFileError naming the problem (see the module docstring).
    """
    suffix = _suffix(path)
    if not os.path.isfile(path):
        raise BoxFileError(f"{path}: no such box file")
    if suffix == ".json":
        try:
            with open(path) as f:
                spec = json.load(f)
        except (OSError, UnicodeDecodeError, ValueError) as e:
            raise BoxFileError(f"{path}: not valid JSON ({e})") from e
        dist = _from_spec(path, spec, box)
    else:
        arrays = fileio.read_npz(path, BoxFileError, "box (.npz)")
        arrays.pop(fileio.META_KEY, None)
        missing = [k for k in massdist.MassDistribution._fields if k not in arrays]
        if missing:
            raise BoxFileError(
                f"{path}: missing array(s) {missing}; a box .npz holds occupancy and total_mass"
            )
        unknown = sorted(set(arrays) - set(massdist.MassDistribution._fields))
        if unknown:
            raise BoxFileError(
                f"{path}: unknown array(s) {unknown}; a box .npz holds occupancy and total_mass"
            )
        dist = massdist.MassDistribution(arrays["occupancy"], arrays["total_mass"])
    try:
        massdist.validate(dist, box)
    except massdist.DistributionError as e:
        raise BoxFileError(f"{path}: {e}") from e
    return massdist.MassDistribution(
        np.asarray(dist.occupancy, np.float32), np.asarray(dist.total_mass, np.float32)
    )


def save(
    path, dist: massdist.MassDistribution, box: BoxConfig = DEFAULT.box, meta: dict | None = None
) -> str:
    """Write `dist` as a box .npz (atomically), after checking it. Returns the path."""
    if _suffix(path) != ".npz":
        raise BoxFileError(f"{path}: boxjax writes boxes as .npz (occupancy grid); use a name ending in .npz")
    try:
        massdist.validate(dist, box)
    except massdist.DistributionError as e:
        raise BoxFileError(f"{path}: {e}") from e
    arrays = {
        "occupancy": np.asarray(dist.occupancy, np.float32),
        "total_mass": np.asarray(dist.total_mass, np.float32),
    }
    info = {"grid": list(box.grid), "box_size_m": list(box.size), **(meta or {})}
    return fileio.write_npz_with_meta(path, arrays, info, FORMAT, VERSION)


def random_box(seed: int, box: BoxConfig = DEFAULT.box) -> massdist.MassDistribution:
    """`massdist.sample(jax.random.PRNGKey(seed), box)` as host arrays: a random mixture box (about 4 %
    of seeds give a hazardous one)."""
    return jax.tree.map(np.asarray, massdist.sample(jax.random.PRNGKey(seed), box))


def report(dist: massdist.MassDistribution, box: BoxConfig = DEFAULT.box) -> dict:
    """Plain data about one box: mass, centre of mass (m, box frame), fill, hazard region, inertia."""
    props = massdist.mass_properties(dist, box)
    occ = np.asarray(dist.occupancy) > 0.5
    region = int(massdist.hazard_region(dist, box))
    com = [round(float(c), 6) + 0.0 for c in np.asarray(props.com, np.float64)]
    return {
        "total_mass_kg": float(dist.total_mass),
        "com_m": com,
        "occupied_voxels": int(occ.sum()),
        "voxels": int(occ.size),
        "fill": float(occ.mean()),
        "grid": list(box.grid),
        "hazardous": region >= 0,
        "hazard_region": None if region < 0 else massdist.REGION_NAMES[region],
        "inertia_diag_kg_m2": [float(v) for v in np.diag(np.asarray(props.inertia, np.float64))],
    }
