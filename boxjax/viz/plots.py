"""Plots (matplotlib on an Agg canvas), imported inside the functions so ``import boxjax`` stays cheap.

Figures are built with the object-oriented API (``matplotlib.figure.Figure`` on an Agg canvas), not pyplot, so
plotting never changes the global backend or leaks open figures.
"""

from __future__ import annotations

import os

import numpy as np

from boxjax.config import DEFAULT, BoxConfig
from boxjax.fileio import save_figure
from boxjax.massdist import MassDistribution, hazard_region, mass_properties

_REGION_LABELS = ("U1", "U2", "U3", "U4")


def plot_mass_distribution(
    ax, dist: MassDistribution, box: BoxConfig = DEFAULT.box, title=None, color="tab:blue"
):
    """Draw one distribution's occupied voxels on a 3D axes, in the box frame (cm).

    Args:
      ax: a matplotlib 3D axes (``fig.add_subplot(projection="3d")``).
      dist: one distribution (occupancy (nx, ny, nz), total_mass ()).
      box: the box whose grid the occupancy uses.
      title: axes title; a short description (mass, hazard) is appended on a second line.
      color: face colour of the occupied voxels.
    Returns:
      ax. The centre of mass is marked with a black dot, and the box outline is drawn as a wire frame.
    """
    occ = np.asarray(dist.occupancy) > 0.5
    edges = [
        100 * (-h + np.arange(n + 1) * d)
        for h, n, d in zip(box.half_size, box.grid, box.voxel_size, strict=True)
    ]
    x, y, z = np.meshgrid(*edges, indexing="ij")
    ax.voxels(x, y, z, occ, facecolors=color, edgecolors="k", linewidth=0.3, alpha=0.6)

    hx, hy, hz = (100 * h for h in box.half_size)
    # Box outline: the 12 edges of the cuboid.
    for sy in (-hy, hy):
        for sz in (-hz, hz):
            ax.plot([-hx, hx], [sy, sy], [sz, sz], color="0.5", lw=0.6)
    for sx in (-hx, hx):
        for sz in (-hz, hz):
            ax.plot([sx, sx], [-hy, hy], [sz, sz], color="0.5", lw=0.6)
    for sx in (-hx, hx):
        for sy in (-hy, hy):
            ax.plot([sx, sx], [sy, sy], [-hz, hz], color="0.5", lw=0.6)

    com = np.round(100 * np.asarray(mass_properties(dist, box).com, np.float64), 1) + 0.0  # no "-0.0"
    ax.scatter([com[0]], [com[1]], [com[2]], color="k", s=30, depthshade=False, zorder=10)
    ax.set_xlim(-hx, hx)
    ax.set_ylim(-hy, hy)
    ax.set_zlim(-hz, hz)
    # zoom < 1 keeps the tick and axis labels inside the axes' own box, so that a layout engine can keep
    # them off the neighbouring plots (a 3-D axes draws its labels outside the box it reports).
    ax.set_box_aspect((2 * hx, 2 * hy, 2 * hz), zoom=0.9)
    ax.set_xlabel("x, length (cm)")
    ax.set_ylabel("y, width (cm)")
    ax.set_zlabel("z (cm)")
    region = int(hazard_region(dist, box))
    sub = f"{float(dist.total_mass):.1f} kg, CoM ({com[0]:+.1f}, {com[1]:+.1f}, {com[2]:+.1f}) cm"
    if region >= 0:
        sub += f", hazardous ({_REGION_LABELS[region]})"
    ax.set_title(sub if title is None else f"{title}\n{sub}", fontsize=9)
    return ax


def plot_mass_distributions(dists: dict[str, MassDistribution], box: BoxConfig, path) -> str:
    """Write a PNG with one 3D voxel plot per distribution (titled by its key), atomically.

    The figure is saved to a temporary file in the destination directory and moved into place with
    ``os.replace``, so a reader never sees a half-written PNG. Returns the path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not dists:
        raise ValueError("plot_mass_distributions needs at least one distribution")
    n = len(dists)
    ncols = min(n, 3)
    nrows = -(-n // ncols)
    fig = Figure(figsize=(4.6 * ncols, 3.9 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    for idx, (name, dist) in enumerate(dists.items()):
        ax = fig.add_subplot(nrows, ncols, idx + 1, projection="3d")
        plot_mass_distribution(ax, dist, box, title=str(name), color=f"C{idx % 10}")
    save_figure(fig, path)
    return os.fspath(path)


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _plot_yaw_balance(ax_yaw, ax_bal, trace, balance_limit: float, target_yaw: float):
    """Yaw against its target, and the balance error against its limit, over time."""
    t = np.asarray(trace.time)
    ax_yaw.plot(t, np.degrees(np.asarray(trace.s)[:, 4]), label="yaw")
    ax_yaw.axhline(np.degrees(target_yaw), color="k", ls="--", lw=0.8, label="target")
    ax_yaw.set_ylabel("yaw (deg)")
    ax_yaw.legend(loc="best", fontsize=8)
    ax_bal.plot(t, 100 * np.asarray(trace.balance_error), color="C3", label="|y - (P1+P2)/2|")
    ax_bal.axhline(100 * balance_limit, color="r", ls="--", lw=0.8, label="limit")
    ax_bal.set_ylabel("balance error (cm)")
    ax_bal.legend(loc="best", fontsize=8)


def plot_episode_axes(axes, trace, balance_limit: float, target_yaw: float, title: str | None = None):
    """Draw an episode on 4 axes: yaw vs target, balance error vs limit, belt speeds, belt positions.

    Args:
      trace: an `EpisodeTrace` (or anything with time, s (T+1, 5), belt_speed (T+1, 2), actions (T, 4),
        balance_error (T+1,) attributes).
    """
    t = np.asarray(trace.time)
    s = np.asarray(trace.s)
    a = np.asarray(trace.actions)
    ax_yaw, ax_bal, ax_v, ax_p = axes
    _plot_yaw_balance(ax_yaw, ax_bal, trace, balance_limit, target_yaw)
    ta = t[1:] if len(t) > 1 else t
    for i, c in enumerate(("C0", "C1")):
        ax_v.plot(t, np.asarray(trace.belt_speed)[:, i], color=c, label=f"belt {i + 1} speed")
        if len(a):
            ax_v.step(ta, a[:, i], where="pre", color=c, ls=":", label=f"v{i + 1} command")
    ax_v.set_ylabel("belt speed (m/s)")
    ax_v.legend(loc="best", fontsize=7, ncol=2)
    ax_p.plot(t, 100 * s[:, 0], label="P1")
    ax_p.plot(t, 100 * s[:, 1], label="P2")
    ax_p.plot(t, 100 * s[:, 3], label="box y", color="C3")
    ax_p.plot(t, 100 * s[:, 2], label="box x", color="C2", ls="--")
    ax_p.set_ylabel("position (cm)")
    ax_p.set_xlabel("time (s)")
    ax_p.legend(loc="best", fontsize=8)
    if title:
        ax_yaw.set_title(title, fontsize=10)


def plot_episode(trace, path, balance_limit: float, target_yaw: float, title: str | None = None) -> str:
    """Write a PNG of one episode (yaw, balance error, belt commands and speeds, belt positions)."""
    fig = _figure((7.5, 8.5))
    axes = fig.subplots(4, 1, sharex=True)
    plot_episode_axes(axes, trace, balance_limit, target_yaw, title)
    return save_figure(fig, path)


def plot_demo(
    truth,
    belief,
    trace,
    path,
    box: BoxConfig,
    balance_limit: float,
    target_yaw: float,
    title: str | None = None,
) -> str:
    """One figure of a whole episode: true vs estimated voxel grids (paper Fig. 2 c, d) beside the yaw and
    the balance error over time."""
    fig = _figure((12, 6.5))
    grid = fig.add_gridspec(2, 3, width_ratios=(1.6, 1, 1))
    plot_mass_distribution(fig.add_subplot(grid[0, 0], projection="3d"), truth, box, title="ground truth")
    plot_mass_distribution(
        fig.add_subplot(grid[1, 0], projection="3d"), belief, box, title="estimate", color="tab:orange"
    )
    ax_yaw = fig.add_subplot(grid[0, 1:])
    ax_bal = fig.add_subplot(grid[1, 1:], sharex=ax_yaw)
    _plot_yaw_balance(ax_yaw, ax_bal, trace, balance_limit, target_yaw)
    ax_bal.set_xlabel("time (s)")
    if title:
        fig.suptitle(title, fontsize=11)
    return save_figure(fig, path)


_FORCE_PANELS = (
    ("F1", "belt 1 speed increment dv1 (m/s)", 1.0, "F1 along x on S1 (N)"),
    ("F2", "belt 2 speed increment dv2 (m/s)", 1.0, "F2 along x on S2 (N)"),
    ("F3", "belt 1 position increment dp1 (mm)", 1000.0, "F3 along y on S1 (N)"),
    ("F4", "belt 2 position increment dp2 (mm)", 1000.0, "F4 along y on S2 (N)"),
)


def plot_force_map(fm, component, value, force, path, title: str | None = None) -> str:
    """The action -> force mapping (paper Fig. 3 a, b, for all four forces) as a 2 x 2 PNG, atomically.

    Each panel shows one component's recovered calibration samples (action value, force) as dots, the
    fitted mean per grid value as a line (hollow markers: bins without samples, filled by interpolation)
    and a band of +-1 standard deviation.

    Args:
      fm: a calibrate.ForceMap (grid, mean, std, count of shape (4, K)).
      component, value, force: (n,) the samples: active component 0..3, action value (m/s for 0, 1; m
        for 2, 3), recovered force (N); n may be 0 (the map alone is drawn).
    Returns the path written.
    """
    grid, mean, std, count = (np.asarray(a, np.float64) for a in (fm.grid, fm.mean, fm.std, fm.count))
    comp = np.asarray(component)
    val = np.asarray(value, np.float64)
    f = np.asarray(force, np.float64)
    fig = _figure((10, 7.5))
    axes = fig.subplots(2, 2).ravel()
    for c, (ax, (name, xlabel, scale, ylabel)) in enumerate(zip(axes, _FORCE_PANELS, strict=True)):
        sel = comp == c
        ax.scatter(
            scale * val[sel], f[sel], s=9, alpha=0.35, color="C0", lw=0, label=f"samples ({sel.sum()})"
        )
        x = scale * grid[c]
        ax.fill_between(x, mean[c] - std[c], mean[c] + std[c], color="C1", alpha=0.25, label="mean +- 1 std")
        ax.plot(x, mean[c], color="C1", lw=1.8, label="mean")
        ax.plot(x[count[c] > 0], mean[c][count[c] > 0], "o", color="C1", ms=4)
        if np.any(count[c] == 0):
            ax.plot(
                x[count[c] == 0],
                mean[c][count[c] == 0],
                "o",
                mfc="white",
                color="C1",
                ms=4,
                label="no sample (interpolated)",
            )
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.axvline(0.0, color="0.6", lw=0.6)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(f"{name}: {int(count[c].sum())} samples in {grid.shape[1]} bins", fontsize=9)
        ax.legend(loc="upper left", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=11)
    return save_figure(fig, path)


_OUTCOME_STYLE = {  # outcome -> (colour, marker)
    "success": ("C2", "o"),
    "aborted": ("0.5", "s"),
    "unbalanced": ("C3", "x"),
    "step_cap": ("C1", "^"),
    "tipped": ("C4", "v"),
    "off_belts": ("C5", "D"),
}


def plot_evaluation(ev, path, cfg=DEFAULT, title: str | None = None) -> str:
    """Paper Fig. 3 (c) and a map of outcomes: write a PNG for an `experiments.Evaluation`.

    Left: the balance error over time on the safe boxes that were not refused (median with a one-std band,
    the worst episode dashed), with the 4 cm limit. Right: each box's outcome at its centre of mass (x, y)
    in the box frame, with the outer quarters U1..U4 (the hazard slabs) shaded.
    """
    fig = _figure((11.0, 4.6))
    ax_b, ax_m = fig.subplots(1, 2, width_ratios=(1.3, 1.0))
    dt = cfg.gripper.control_dt
    safe = [j for j, r in enumerate(ev.rows) if not r["hazardous"] and r["outcome"] != "aborted"]
    if safe:
        n = max(len(ev.balance[j]) for j in safe)
        pad = np.full((len(safe), n), np.nan)
        for i, j in enumerate(safe):
            pad[i, : len(ev.balance[j])] = ev.balance[j]
        t = np.arange(n) * dt
        with np.errstate(all="ignore"):
            med, std = np.nanmedian(pad, axis=0), np.nanstd(pad, axis=0)
        ax_b.plot(t, 100 * med, color="C0", label=f"median ({len(safe)} safe boxes)")
        ax_b.fill_between(t, 100 * (med - std), 100 * (med + std), color="C0", alpha=0.25, label="one std")
        worst = safe[int(np.argmax([ev.rows[j]["max_balance_error_m"] for j in safe]))]
        bw = ev.balance[worst]
        ax_b.plot(np.arange(len(bw)) * dt, 100 * bw, "r--", lw=1.0, label=f"worst (box {worst})")
    ax_b.axhline(100 * cfg.task.balance_limit, color="k", ls=":", lw=1.0, label="limit")
    ax_b.set_xlabel("time (s)")
    ax_b.set_ylabel("balance error (cm)")
    ax_b.legend(loc="upper right", fontsize=8)
    ax_b.set_title("balance error over the episode (paper Fig. 3c)", fontsize=10)
    hx, hy, _ = (100 * h for h in cfg.box.half_size)
    for x0, x1, y0, y1 in (
        (-hx, -hx / 2, -hy, hy),
        (hx / 2, hx, -hy, hy),
        (-hx, hx, -hy, -hy / 2),
        (-hx, hx, hy / 2, hy),
    ):
        ax_m.fill_between([x0, x1], y0, y1, color="0.85", zorder=0, lw=0)
    ax_m.plot([-hx, hx, hx, -hx, -hx], [-hy, -hy, hy, hy, -hy], "k-", lw=0.8)
    for out in sorted({r["outcome"] for r in ev.rows}):
        colour, marker = _OUTCOME_STYLE.get(out, ("k", "."))
        pts = np.asarray([r["com_cm"][:2] for r in ev.rows if r["outcome"] == out])
        haz = np.asarray([r["hazardous"] for r in ev.rows if r["outcome"] == out])
        label = f"{out} ({len(pts)})"
        if marker == "x":  # unfilled: the stroke is the marker, so hazardous boxes are drawn larger instead
            ax_m.scatter(pts[:, 0], pts[:, 1], c=colour, marker=marker, s=np.where(haz, 60, 28), label=label)
        else:
            edge = np.where(haz, 1.2, 0.0)
            ax_m.scatter(
                pts[:, 0],
                pts[:, 1],
                c=colour,
                marker=marker,
                s=22,
                label=label,
                edgecolors="k",
                linewidths=edge,
            )
    ax_m.set_aspect("equal")
    ax_m.set_xlabel("centre of mass x (cm, box frame)")
    ax_m.set_ylabel("centre of mass y (cm)")
    ax_m.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    ax_m.set_title("outcome by centre of mass\n(shaded: U1..U4; outlined / large: hazardous)", fontsize=10)
    if title:
        fig.suptitle(title, fontsize=11)
    return save_figure(fig, path)


def plot_fault_table(table: dict, path) -> str:
    """The fault table (`experiments.fault_table`) as one panel per fault: the safe boxes turned (95 %
    interval) with the monitor on and off against the fault's level (the no-fault row at the model's own
    level), the monitor's safe stops, and the crossings of the balance limit (unnoticed ones filled)."""
    rows = table["rows"]
    none = rows.get("none")
    groups: dict[str, list] = {}
    for name, e in rows.items():
        if e["group"] in ("none",):
            continue
        groups.setdefault(e["group"], []).append((e["level"], name, e))
    origin = {"belt friction (model: 0.5)": 0.5, "one belt's friction (model: 0.5)": 0.5}
    n = max(1, len(groups))
    cols = min(4, n)
    fig = _figure((4.0 * cols, 3.4 * (-(-n // cols))))
    axes = np.atleast_1d(fig.subplots(-(-n // cols), cols, squeeze=False)).ravel()
    for ax, (group, pts) in zip(axes, groups.items(), strict=False):
        if none is not None and group != "realistic":
            pts = [(origin.get(group, 0.0), "none", none), *pts]
        pts.sort(key=lambda p: p[0])
        x = np.array([p[0] for p in pts])
        for m, colour, mark in (("on", "tab:blue", "o"), ("off", "tab:grey", "s")):
            have = [(xi, p[2][m]) for xi, p in zip(x, pts, strict=True) if m in p[2]]
            if not have:
                continue
            xs = np.array([h[0] for h in have])
            rate = np.array([100 * h[1]["safe_success_rate"] for h in have])
            lo = np.array([100 * h[1]["safe_success_ci95"][0] for h in have])
            hi = np.array([100 * h[1]["safe_success_ci95"][1] for h in have])
            ax.errorbar(xs, rate, yerr=[rate - lo, hi - rate], color=colour, marker=mark, capsize=3,
                        label=f"turned, monitor {m}")  # fmt: skip
            cross = np.array([h[1]["crossings"] for h in have])
            unnoticed = np.array([h[1]["unnoticed_crossings"] for h in have])
            ax.bar(xs + (0.02 if m == "on" else -0.02) * max(1, np.ptp(xs)), cross,
                   width=0.04 * max(1, np.ptp(xs)), color="none", edgecolor="tab:red")  # fmt: skip
            ax.bar(xs + (0.02 if m == "on" else -0.02) * max(1, np.ptp(xs)), unnoticed,
                   width=0.04 * max(1, np.ptp(xs)), color="tab:red", alpha=0.8)  # fmt: skip
            if m == "on":
                stops = np.array([h[1]["safe_stops"] for h in have])
                ax.plot(xs, stops, color="tab:orange", marker="v", label="safe stops (monitor on)")
        ax.set_title(group, fontsize=10)
        ax.set_ylim(0, 102)
        ax.set_ylabel("% of safe boxes / count")
        ax.grid(alpha=0.3)
    for ax in axes[len(groups) :]:
        ax.axis("off")
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(
        f"{table['boxes']} random safe boxes per row (seed {table['seed']}, {table['estimator']}); red: "
        "crossings of the 4 cm limit (filled: unnoticed)",
        fontsize=10,
    )
    return save_figure(fig, path)


def plot_paired_margins(a, b, path, near_tip: float, labels=("A", "B")) -> str:
    """Two settings' smallest true stability margins (m) on the same boxes, `a` and `b` (n,): a scatter of
    one against the other with the diagonal and `near_tip` (where boxes begin to tip), and the histogram
    of the paired differences b - a. Writes a PNG."""
    a, b = 1e3 * np.asarray(a, np.float64), 1e3 * np.asarray(b, np.float64)
    fig = _figure((10.0, 4.2))
    ax_s, ax_h = fig.subplots(1, 2)
    if len(a):
        ax_s.scatter(a, b, s=8, alpha=0.6)
        lo, hi = min(a.min(), b.min(), 0.0) - 2, max(a.max(), b.max()) + 2
        ax_s.plot([lo, hi], [lo, hi], "k:", lw=1.0)
        ax_s.axvline(1e3 * near_tip, color="r", ls="--", lw=0.8)
        ax_s.axhline(1e3 * near_tip, color="r", ls="--", lw=0.8)
        ax_h.hist(b - a, bins=40)
        ax_h.axvline(0.0, color="k", ls=":", lw=1.0)
    ax_s.set_xlabel(f"{labels[0]}: smallest true stability margin (mm)")
    ax_s.set_ylabel(f"{labels[1]}: the same box and key (mm)")
    ax_s.set_title(
        f"{len(a)} boxes; red: {1e3 * near_tip:.0f} mm, where boxes at rest begin to tip", fontsize=9
    )
    ax_h.set_xlabel(
        f"{labels[1]} - {labels[0]} (mm): positive, {labels[1]} kept the box further from tipping"
    )
    ax_h.set_ylabel("boxes")
    return save_figure(fig, path)
