"""Force map (paper §2.4): fitting, interpolation, force recovery, storage."""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from boxjax import massdist
from boxjax.config import DEFAULT, BoxConfig
from boxjax.prior import force_map as calibrate
from boxjax.prior.force_map import CalibrationError, ForceMap

G = DEFAULT.gripper
BOX = DEFAULT.box
recover = jax.jit(lambda states, masses: calibrate.recover_forces(states, masses, BOX, G))


def _synthetic(seed=0, n=2000, noise=0.5):
    """Samples of a known linear mapping F_c = slope_c * value + offset_c, plus gaussian noise (N)."""
    rng = np.random.default_rng(seed)
    grid = calibrate.default_grid(G, 9)
    slopes = np.array([300.0, -250.0, 2000.0, -1500.0])  # N per (m/s) and N per m
    offsets = np.array([0.5, -0.3, 0.0, 0.2])
    comp = rng.integers(0, 4, n)
    lo, hi = grid[comp, 0], grid[comp, -1]
    val = rng.uniform(lo, hi)
    force = slopes[comp] * val + offsets[comp] + rng.normal(0, noise, n)
    return comp, val, force, grid, slopes, offsets


def test_fit_recovers_linear_mapping_with_noise():
    comp, val, force, grid, slopes, offsets = _synthetic()
    fm = calibrate.fit_force_map(comp, val, force, grid)
    assert fm.grid.shape == fm.mean.shape == fm.std.shape == fm.count.shape == (4, 9)
    assert int(np.sum(fm.count)) == comp.size
    truth = slopes[:, None] * np.asarray(grid) + offsets[:, None]
    # Bin means average a linear function over a bin of half-width h around the grid point: unbiased
    # except at the two end bins (half bins); the noise average is ~0.5 / sqrt(55) N.
    inner = np.asarray(fm.mean)[:, 1:-1] - truth[:, 1:-1]
    assert np.max(np.abs(inner)) < 0.5
    # Std: noise plus the spread of the line within a bin (uniform over width w: slope w / sqrt 12).
    w = np.diff(np.asarray(grid), axis=1)[:, 0]
    expect_std = np.sqrt(0.5**2 + (slopes * w) ** 2 / 12)
    assert np.allclose(np.asarray(fm.std)[:, 1:-1], expect_std[:, None], rtol=0.3)
    # Interpolation between grid points follows the line.
    x = np.array([0.011, -0.013, 0.0031, -0.0047], np.float32)
    got = np.asarray(calibrate.forces(fm, jnp.asarray(x)))
    assert np.allclose(got, slopes * x + offsets, atol=1.0)


def test_fit_empty_bins_are_interpolated_and_marked():
    grid = np.linspace(-1, 1, 5)
    comp = np.repeat(np.arange(4), 2)
    val = np.tile([-1.0, 1.0], 4)  # only the end bins get samples
    force = np.tile([-10.0, 10.0], 4)
    fm = calibrate.fit_force_map(comp, val, force, grid)
    assert np.allclose(np.asarray(fm.mean), np.tile([-10, -5, 0, 5, 10], (4, 1)))
    assert np.array_equal(np.asarray(fm.count), np.tile([1, 0, 0, 0, 1], (4, 1)))
    assert np.all(np.isfinite(np.asarray(fm.std)))


def test_fit_rejects_bad_input():
    grid = np.linspace(-1, 1, 5)
    with pytest.raises(ValueError, match="component 3"):
        calibrate.fit_force_map(np.array([0, 1, 2]), np.zeros(3), np.zeros(3), grid)
    with pytest.raises(ValueError, match="strictly increasing"):
        calibrate.fit_force_map(np.arange(4), np.zeros(4), np.zeros(4), grid[::-1])
    with pytest.raises(ValueError, match="finite"):
        calibrate.fit_force_map(np.arange(4), np.array([0, np.nan, 0, 0]), np.zeros(4), grid)
    with pytest.raises(ValueError, match="equal length"):
        calibrate.fit_force_map(np.arange(4), np.zeros(3), np.zeros(4), grid)


def test_forces_interpolates_clamps_and_is_differentiable():
    grid = jnp.tile(jnp.array([-1.0, 0.0, 1.0]), (4, 1))
    mean = jnp.array([[-2.0, 0.0, 4.0]] * 4)
    fm = ForceMap(grid, mean, jnp.zeros((4, 3)), jnp.ones((4, 3), jnp.int32))
    f = calibrate.forces(fm, jnp.array([0.5, -0.5, 2.0, -3.0]))
    assert np.allclose(np.asarray(f), [2.0, -1.0, 4.0, -2.0])
    g = jax.grad(lambda v: jnp.sum(calibrate.forces(fm, v)))(jnp.array([0.5, -0.5, 0.2, -0.2]))
    assert np.allclose(np.asarray(g), [4.0, 2.0, 4.0, 2.0])


def test_action_values_are_increments():
    v = calibrate.action_values(jnp.array([0.3, -0.1, 0.02, -0.004]), jnp.array([0.1, 0.05]), G)
    assert np.allclose(np.asarray(v), [G.belt_speed_limit - 0.1, -0.15, G.max_position_step, -0.004])


def _uniform_masses():
    return massdist.voxel_masses(massdist.named("uniform", BOX), BOX)


def test_recover_forces_constant_velocity_gives_zero():
    # Box gliding at constant velocity along x: no change of acceleration and the displacement is along
    # the velocity, so eq. 11 gives no additional friction: F = 0.
    dt = G.control_dt
    v = 0.05
    states = jnp.array([[-0.1, 0.1, v * dt * k, 0.0, 0.0] for k in range(4)])
    f, info = recover(states, _uniform_masses())
    assert np.allclose(np.asarray(f), 0.0, atol=1e-3)
    assert np.allclose(np.asarray(info["friction1"]), 0.0, atol=1e-3)


def test_recover_forces_from_rest_by_hand():
    # At rest, then displaced by d along +y in one step: delta(acc) = 2 d / dt^2; every column of V1 and
    # V2 gets friction mu g dm along -y (eq. 11 with zero velocity), so F = M 2 d / dt^2 + mu g m_V.
    dt = G.control_dt
    d = 0.002
    s = [-0.1, 0.1, 0.0, 0.0, 0.0]
    states = jnp.array([s, s, s, [-0.1, 0.1, 0.0, d, 0.0]])
    masses = _uniform_masses()
    f, info = recover(states, masses)
    # At yaw 0 with belts at +-0.1 m, S1 and S2 are 3 rows of 8 columns each: 48 of 64 columns.
    col = np.asarray(jnp.sum(masses, axis=2))
    m_v = 48 * col[0, 0]
    total = float(jnp.sum(masses))
    expect = total * 2 * d / dt**2 + G.friction * G.gravity * m_v
    assert np.isclose(float(f[1]), expect, rtol=1e-3)
    assert abs(float(f[0])) < 1e-3
    assert np.isclose(float(calibrate.component_force(f, 2)), expect, rtol=1e-3)
    assert float(calibrate.component_force(f, 0)) == pytest.approx(float(f[0]))


# ----------------------------------------------------------------------------------------------------------
# Storage.


def _map():
    comp, val, force, grid, *_ = _synthetic(1, 400)
    return calibrate.fit_force_map(comp, val, force, grid)


def test_save_load_round_trip(tmp_path):
    fm = _map()
    path = tmp_path / "calib.npz"
    calibrate.save(path, fm, DEFAULT, {"transitions": 400, "seed": 1})
    fm2, meta = calibrate.load(path, DEFAULT)
    for a, b in zip(fm, fm2, strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert meta == {"transitions": 400, "seed": 1}
    assert os.listdir(tmp_path) == ["calib.npz"]  # no temporary file left behind
    with np.load(path, allow_pickle=False) as z:  # readable without pickle
        assert int(z["format_version"]) == calibrate.FORMAT_VERSION


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(gripper=dataclasses.replace(G, friction=0.6)), "gripper.friction"),
        (dict(gripper=dataclasses.replace(G, control_dt=0.04)), "gripper.control_dt"),
        (dict(gripper=dataclasses.replace(G, belt_speed_limit=0.2)), "gripper.belt_speed_limit"),
        (dict(gripper=dataclasses.replace(G, belt_accel_limit=0.5)), "gripper.belt_accel_limit"),
        (dict(box=BoxConfig(size=(0.4, 0.3, 0.2))), "box.size"),
    ],
)
def test_load_rejects_other_configuration(tmp_path, change, field):
    path = tmp_path / "calib.npz"
    calibrate.save(path, _map(), DEFAULT.replace(**change))
    with pytest.raises(CalibrationError, match=field.replace(".", r"\.")):
        calibrate.load(path, DEFAULT)


def test_load_ignores_unrelated_configuration(tmp_path):
    path = tmp_path / "calib.npz"
    other = DEFAULT.replace(task=dataclasses.replace(DEFAULT.task, max_steps=10))
    calibrate.save(path, _map(), other)
    calibrate.load(path, DEFAULT)


def test_load_rejects_corrupt_and_foreign_files(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file at all")
    with pytest.raises(CalibrationError, match="corrupt"):
        calibrate.load(bad, DEFAULT)
    truncated = tmp_path / "trunc.npz"
    calibrate.save(truncated, _map(), DEFAULT)
    truncated.write_bytes(truncated.read_bytes()[:200])
    with pytest.raises(CalibrationError, match="corrupt"):
        calibrate.load(truncated, DEFAULT)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, grid=np.zeros((4, 3)))
    with pytest.raises(CalibrationError, match="missing"):
        calibrate.load(foreign, DEFAULT)
    with pytest.raises(CalibrationError, match="does not exist"):
        calibrate.load(tmp_path / "nope.npz", DEFAULT)


def test_load_rejects_other_version_and_bad_arrays(tmp_path):
    path = tmp_path / "c.npz"
    calibrate.save(path, _map(), DEFAULT)
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    np.savez(path, **{**data, "format_version": np.asarray(99)})
    with pytest.raises(CalibrationError, match="format version 99"):
        calibrate.load(path, DEFAULT)
    mean = data["mean"].copy()
    mean[0, 0] = np.nan
    np.savez(path, **{**data, "mean": mean})
    with pytest.raises(CalibrationError, match="mean"):
        calibrate.load(path, DEFAULT)


# ----------------------------------------------------------------------------------------------------------
# Calibration by simulation: the library function, `boxjax calibrate`, and the shipped file.


def _run_cli(capsys, *argv):
    from boxjax.cli import main

    code = main(["calibrate", *argv])
    captured = capsys.readouterr()
    return code, captured


def test_collect_transitions_are_disjoint_and_windows_chain():
    from boxjax.training import calibration as R

    tr = R.collect_transitions(DEFAULT, jax.random.PRNGKey(5), 24, progress=False)
    n = tr.component.size
    assert n == 24 and tr.windows.shape == (n, 4, 5) and tr.n_steps == n + 2 * tr.n_episodes
    vals = np.asarray(jax.vmap(lambda a, v: calibrate.action_values(a, v, G))(tr.actions, tr.belt_speed))
    # Exactly one non-zero action value per transition, the drawn component, within its increment bound.
    nonzero = np.abs(vals) > 1e-9
    assert np.array_equal(nonzero.sum(1), np.ones(n))
    assert np.array_equal(np.argmax(nonzero, 1), tr.component)
    bound = np.array([G.belt_accel_limit * G.control_dt] * 2 + [G.max_position_step] * 2)
    assert np.all(np.abs(vals) <= bound + 1e-9)
    # Consecutive transitions of one episode share three states: s_{t-1..t+1} of one = s_{t-2..t} of the next.
    same = tr.episode[1:] == tr.episode[:-1]
    assert same.any()
    assert np.array_equal(tr.windows[:-1][same][:, 1:], tr.windows[1:][same][:, :3])
    assert set(tr.component.tolist()) == {0, 1, 2, 3}


def test_calibrate_command_writes_loadable_reproducible_file(tmp_path, monkeypatch, capsys):
    files = []
    for sub in ("a", "b"):  # the same command in two folders: the file name (and so the meta) is the same
        d = tmp_path / sub
        d.mkdir()
        monkeypatch.chdir(d)
        plot = ["--plot", "fig3.png"] if sub == "a" else []
        code, cap = _run_cli(
            capsys, "--transitions", "40", "--seed", "7", "--out", "calib.npz", "--json", *plot
        )
        assert code == 0, cap.err
        res = json.loads(cap.out.strip().splitlines()[-1])
        files.append(d / "calib.npz")
    assert res["transitions"] == 40 and res["seed"] == 7 and res["out"] == "calib.npz" and res["wall_s"] > 0
    assert set(res["forces"]) == {"F1", "F2", "F3", "F4"}
    for f in res["forces"].values():
        lo, hi = f["mean_range_N"]
        assert np.isfinite([lo, hi]).all() and lo <= hi and f["std_range_N"][0] >= 0
    assert sum(f["samples"] for f in res["forces"].values()) == 40
    fm, meta = calibrate.load(files[0], DEFAULT)
    assert meta["command"] == "boxjax calibrate --transitions 40 --seed 7 --out calib.npz"
    assert meta["seed"] == 7 and meta["transitions"] == 40 and int(np.sum(fm.count)) == 40
    assert files[0].read_bytes() == files[1].read_bytes()  # same seed -> identical file
    png = (tmp_path / "a" / "fig3.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert not (tmp_path / "b" / "fig3.png").exists()
    # A file made for DEFAULT is refused for another configuration.
    other = DEFAULT.replace(gripper=dataclasses.replace(G, friction=0.6))
    with pytest.raises(CalibrationError, match=r"gripper\.friction"):
        calibrate.load(files[0], other)


def test_calibrate_seed_changes_the_data():
    from boxjax.training import calibration as R

    a = R.collect_transitions(DEFAULT, jax.random.PRNGKey(0), 12, progress=False)
    b = R.collect_transitions(DEFAULT, jax.random.PRNGKey(1), 12, progress=False)
    assert not np.array_equal(a.actions, b.actions)


def test_calibrate_command_bad_input_exits_2(tmp_path, capsys):
    code, cap = _run_cli(capsys, "--transitions", "3", "--out", str(tmp_path / "c.npz"))
    assert code == 2 and "--transitions must be >= 8" in cap.err
    code, cap = _run_cli(capsys, "--out", str(tmp_path))
    assert code == 2 and "--out must be a file path" in cap.err
    assert os.listdir(tmp_path) == []


def test_shipped_calibration_loads_and_is_physical():
    fm = calibrate.default_force_map(DEFAULT)
    _, meta = calibrate.load(calibrate.SHIPPED_CALIBRATION, DEFAULT)
    assert meta["command"].startswith("boxjax calibrate ") and "--seed" in meta["command"]
    assert meta["transitions"] == int(np.sum(fm.count))
    grid, mean = np.asarray(fm.grid, np.float64), np.asarray(fm.mean, np.float64)
    assert grid.shape == (4, 9) and np.all(np.asarray(fm.count) > 0)
    for c in range(4):
        # Faster belt (or a belt moved further in +y) -> larger force on the box in that direction: the
        # fitted means rise across the grid (least-squares slope), from end to end, and on average from
        # the negative to the positive half.
        slope = np.polyfit(grid[c], mean[c], 1)[0]
        assert slope > 0, (calibrate.FORCE_NAMES[c], mean[c])
        assert mean[c, -1] - mean[c, 0] > 5.0, (calibrate.FORCE_NAMES[c], mean[c])
        assert mean[c, 5:].mean() > mean[c, :4].mean() + 3.0, (calibrate.FORCE_NAMES[c], mean[c])


def test_default_force_map_rejects_other_configuration():
    other = DEFAULT.replace(box=BoxConfig(size=(0.4, 0.3, 0.2)))
    with pytest.raises(CalibrationError, match=r"box\.size.*boxjax calibrate"):
        calibrate.default_force_map(other)
