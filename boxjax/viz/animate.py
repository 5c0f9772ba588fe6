"""Episodes you can watch: a top view of the gripper, frame by frame (`rotate --animate FILE.gif`).

Each frame shows, in the conveyor frame (x along the belts, y across them, cm): the two belts at their
carriage positions P1, P2 with stripes that move with each belt's surface, the carriages at the belts'
ends, the 4 cm corridor around the belts' midline (P1 + P2) / 2 in which the box's geometric centre must
stay, the box outline at its pose (red once the balance limit is crossed) with a tick on its +x face,
its geometric centre and its track, the centre of mass (when the distribution is given), the target
orientation as a dashed outline, and the time, yaw and balance error.

The figure is built once and its artists are moved per frame (matplotlib's Agg canvas, no pyplot); the
GIF is written with matplotlib's PillowWriter, atomically. Drawing is from an `EpisodeTrace` alone, so any
episode (controller, simulate, a Gymnasium rollout) can be animated.
"""

from __future__ import annotations

import math
import os

import numpy as np

from boxjax import massdist
from boxjax.config import Config
from boxjax.fileio import atomic_path, save_figure

STRIPE_SPACING = 0.05  # m, between the stripes drawn on a belt
MAX_FRAMES = 150  # longer episodes are subsampled (every k-th control step), played back in real time


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


class _Scene:
    """The figure and its artists; `draw(i)` moves them to control step i of the trace."""

    def __init__(
        self,
        trace,
        cfg: Config,
        dist=None,
        title: str | None = None,
        outcome: str | None = None,
        figsize=(6.4, 4.6),
    ):
        from matplotlib import patches
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import LineCollection
        from matplotlib.figure import Figure

        self.cfg, self.trace, self.outcome = cfg, trace, outcome
        g, b = cfg.gripper, cfg.box
        self.s = np.asarray(trace.s, np.float64)
        self.bal = np.asarray(trace.balance_error, np.float64)
        dt = g.control_dt
        speed = np.asarray(trace.belt_speed, np.float64)
        # belt surface travel (m) at each step: the stripes move with it
        self.travel = np.concatenate(
            [np.zeros((1, 2)), np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt, axis=0)]
        )
        self.com = None
        if dist is not None:
            self.com = np.asarray(massdist.mass_properties(dist, b).com, np.float64)[:2]
        self.target = float(self.s[0, 4]) + cfg.task.target_yaw_delta
        self.half = np.array(b.half_size[:2])
        self.corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * self.half

        fig = Figure(figsize=figsize)
        FigureCanvasAgg(fig)
        self.fig = fig
        ax = fig.add_axes((0.1, 0.1, 0.86, 0.76))
        self.ax = ax
        L, w = g.belt_length, g.belt_width
        reach_y = max(abs(g.p1_range[0]), abs(g.p2_range[1])) + w / 2 + 0.02
        ax.set_xlim(-100 * L / 2 - 3, 100 * L / 2 + 3)
        ax.set_ylim(-100 * reach_y, 100 * reach_y)
        ax.set_aspect("equal")
        ax.set_xlabel("x, along the belts (cm)")
        ax.set_ylabel("y, across (cm)")
        self.L, self.w = L, w
        self.belts = [
            patches.Rectangle((-50 * L, 0), 100 * L, 100 * w, fc="0.82", ec="0.45", lw=0.8, zorder=1)
            for _ in range(2)
        ]
        self.carriages = [
            [patches.Rectangle((0, 0), 2.5, 100 * w + 2, fc="0.3", ec="none", zorder=2) for _ in range(2)]
            for _ in range(2)
        ]
        self.stripes = [LineCollection([], colors="0.55", linewidths=1.0, zorder=1.5) for _ in range(2)]
        for belt, ends, stripes in zip(self.belts, self.carriages, self.stripes, strict=True):
            ax.add_patch(belt)
            for c in ends:
                ax.add_patch(c)
            ax.add_collection(stripes)
        lim = 100 * cfg.task.balance_limit
        self.corridor = patches.Rectangle(
            (-50 * L - 3, 0),
            100 * L + 6,
            2 * lim,
            fc="tab:green",
            alpha=0.18,
            ec="tab:green",
            lw=0.8,
            zorder=3,
        )
        ax.add_patch(self.corridor)
        (self.midline,) = ax.plot([], [], color="tab:green", ls="--", lw=0.8, zorder=3)
        self.target_box = patches.Polygon(
            self.corners * 100, closed=True, fill=False, ec="0.35", ls=":", lw=1.0
        )
        self.box = patches.Polygon(
            self.corners * 100, closed=True, fc="tab:orange", alpha=0.35, ec="k", lw=1.6
        )
        for p in (self.target_box, self.box):
            p.set_zorder(4)
            ax.add_patch(p)
        (self.face,) = ax.plot([], [], color="k", lw=2.2, zorder=5)
        (self.track,) = ax.plot([], [], color="tab:blue", lw=0.8, alpha=0.7, zorder=5)
        (self.centre,) = ax.plot(
            [], [], "+", color="tab:blue", ms=10, mew=2, zorder=6, label="geometric centre"
        )
        (self.com_dot,) = ax.plot([], [], "o", color="k", ms=6, zorder=6, label="centre of mass")
        ax.legend(loc="lower right", fontsize=7, framealpha=0.8)
        self.text = ax.text(
            0.0, 1.02, "", transform=ax.transAxes, fontsize=9, va="bottom", family="monospace"
        )
        self.legend = ax.get_legend()
        # what moves from frame to frame; everything else (axes, ticks, labels, title) is drawn once
        self.dynamic = [
            *self.belts,
            *self.stripes,
            *(c for ends in self.carriages for c in ends),
            self.corridor,
            self.midline,
            self.target_box,
            self.box,
            self.face,
            self.track,
            self.centre,
            self.com_dot,
            self.legend,
            self.text,
        ]
        if title:
            fig.suptitle(title, fontsize=10, y=0.985)

    def __len__(self) -> int:
        return self.s.shape[0]

    def draw(self, i: int) -> None:
        P1, P2, x, y, yaw = self.s[i]
        L, w = self.L, self.w
        for k, (p, belt, ends, stripes) in enumerate(
            zip((P1, P2), self.belts, self.carriages, self.stripes, strict=True)
        ):
            belt.set_y(100 * (p - w / 2))
            for c, xe in zip(ends, (-L / 2 - 0.025, L / 2), strict=True):
                c.set_xy((100 * xe, 100 * (p - w / 2) - 1))
            xs = (np.arange(0, L, STRIPE_SPACING) + self.travel[i, k]) % L - L / 2
            stripes.set_segments([[(100 * s, 100 * (p - w / 2)), (100 * s, 100 * (p + w / 2))] for s in xs])
        mid = 0.5 * (P1 + P2)
        lim = self.cfg.task.balance_limit
        self.corridor.set_y(100 * (mid - lim))
        self.midline.set_data([-50 * L - 3, 50 * L + 3], [100 * mid] * 2)
        r = _rot(yaw)
        centre = np.array([x, y])
        self.box.set_xy(100 * (centre + self.corners @ r.T))
        self.target_box.set_xy(100 * (centre + self.corners @ _rot(self.target).T))
        over = self.bal[i] > lim
        self.box.set_edgecolor("tab:red" if over else "k")
        face = (
            centre + np.array([[self.half[0], -0.4 * self.half[1]], [self.half[0], 0.4 * self.half[1]]]) @ r.T
        )
        self.face.set_data(100 * face[:, 0], 100 * face[:, 1])
        self.track.set_data(100 * self.s[: i + 1, 2], 100 * self.s[: i + 1, 3])
        self.centre.set_data([100 * x], [100 * y])
        if self.com is not None:
            c = centre + r @ self.com
            self.com_dot.set_data([100 * c[0]], [100 * c[1]])
        t = i * self.cfg.gripper.control_dt
        turned = math.degrees(yaw - self.s[0, 4])
        goal = math.degrees(self.cfg.task.target_yaw_delta)
        self.text.set_text(
            f"t {t:5.2f} s   yaw {turned:+6.1f} of {goal:+.0f} deg   "
            f"balance {100 * self.bal[i]:4.1f} cm (limit {100 * lim:.0f})"
            + ("  OVER" if over else "")
            + (f"\nend: {self.outcome}" if self.outcome and i == len(self) - 1 else "")
        )
        self.text.set_color("tab:red" if over else "k")


class _BlitWriter:
    """Blitting for the animation: the static background is rasterised once; each frame restores it and
    draws only the moving artists (the axes' ticks and labels cost most of a full redraw)."""

    def __init__(self, scene: _Scene, dpi: int):
        self.scene = scene
        fig = scene.fig
        fig.set_dpi(dpi)
        for a in scene.dynamic:
            a.set_animated(True)
        fig.canvas.draw()
        self.background = fig.canvas.copy_from_bbox(fig.bbox)

    def frame(self, i: int):
        """The RGB PIL image of control step i."""
        from PIL import Image

        canvas = self.scene.fig.canvas
        canvas.restore_region(self.background)
        self.scene.draw(i)
        for a in self.scene.dynamic:
            self.scene.ax.draw_artist(a)
        w, h = canvas.get_width_height()
        return Image.frombuffer("RGBA", (w, h), canvas.buffer_rgba(), "raw", "RGBA", 0, 1).convert("RGB")


def _frames(n: int, max_frames: int) -> np.ndarray:
    stride = max(1, math.ceil(n / max_frames))
    idx = np.arange(0, n, stride)
    return idx if idx[-1] == n - 1 else np.append(idx, n - 1)


def check_path(path) -> str:
    """`path` if it can take a GIF, else ValueError naming the problem (checked before an episode runs)."""
    path = os.fspath(path)
    if not path.lower().endswith(".gif"):
        raise ValueError(f"--animate writes a GIF: the path must end in .gif, got {path!r}")
    if os.path.isdir(path):
        raise ValueError(f"--animate {path!r} is a directory")
    return path


def animate_episode(
    trace,
    path,
    cfg: Config,
    dist=None,
    title: str | None = None,
    outcome: str | None = None,
    max_frames: int = MAX_FRAMES,
    dpi: int = 80,
) -> str:
    """Write a GIF of the episode (module docstring), atomically; returns the path.

    Args:
      trace: an `EpisodeTrace` (time, s (T+1, 5), belt_speed (T+1, 2), balance_error (T+1,)).
      dist: the box's MassDistribution, to draw its centre of mass (optional).
      outcome: how the episode ended ("success", "unbalanced", ...), written on the last frame.
      max_frames: at most this many frames (every k-th step), played back in real time (20 / k fps).
    """
    from matplotlib.animation import PillowWriter

    path = check_path(path)
    scene = _Scene(trace, cfg, dist, title, outcome)
    idx = _frames(len(scene), max_frames)
    stride = int(idx[1] - idx[0]) if len(idx) > 1 else 1
    writer = PillowWriter(fps=1.0 / (stride * cfg.gripper.control_dt))
    blit = _BlitWriter(scene, dpi)
    with atomic_path(path, suffix=".gif") as tmp:
        with writer.saving(scene.fig, tmp, dpi):
            # PillowWriter's own grab_frame re-renders the whole figure; its frame list takes the blitted
            # images instead, and its finish() writes the GIF.
            writer._frames.extend(blit.frame(int(i)) for i in idx)
    return path


def save_frame(
    trace, path, cfg: Config, dist=None, index: int = -1, title: str | None = None, outcome: str | None = None
) -> str:
    """One frame of the animation (control step `index`) as a PNG, atomically; returns the path."""

    scene = _Scene(trace, cfg, dist, title, outcome)
    scene.draw(int(np.arange(len(scene))[index]))
    return save_figure(scene.fig, path)


def frame_rgb(trace, cfg: Config, dist=None, index: int = -1) -> np.ndarray:
    """One frame as an (H, W, 3) uint8 array (the Gymnasium env's `render()`)."""
    scene = _Scene(trace, cfg, dist)
    scene.draw(int(np.arange(len(scene))[index]))
    scene.fig.canvas.draw()
    return np.asarray(scene.fig.canvas.buffer_rgba())[..., :3].copy()
