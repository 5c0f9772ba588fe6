"""Episodes you can watch: the top-view animation and its frames."""

from __future__ import annotations

import json
import time

import jax
import numpy as np
import pytest
from PIL import Image

from boxjax import massdist
from boxjax.cli import main
from boxjax.config import DEFAULT
from boxjax.sim import make_env
from boxjax.sim.episode import naive_policy, run_episode
from boxjax.viz import animate


@pytest.fixture(scope="module")
def episode():
    dist = massdist.named("C")
    env = make_env(DEFAULT)
    key_reset, key_run = jax.random.split(jax.random.PRNGKey(0))
    _, trace = run_episode(env, env.reset(key_reset, dist), naive_policy(0.15), key_run, 40)
    return trace, dist


def test_a_frame_shows_the_box_belts_corridor_and_centre_of_mass(episode):
    trace, dist = episode
    scene = animate._Scene(trace, DEFAULT, dist)
    i = 30
    scene.draw(i)
    P1, P2, x, y, yaw = trace.s[i]
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = 0.20, 0.15
    corner = np.array([x + c * hx - s * -hy, y + s * hx + c * -hy])  # box corner (+x, -y), conveyor frame
    assert np.allclose(scene.box.get_xy()[1], 100 * corner, atol=1e-6)
    assert scene.belts[0].get_y() == pytest.approx(100 * (P1 - 0.05)) and scene.belts[
        1
    ].get_y() == pytest.approx(100 * (P2 - 0.05))
    assert scene.corridor.get_y() == pytest.approx(100 * ((P1 + P2) / 2 - 0.04))
    assert scene.corridor.get_height() == pytest.approx(8.0)
    com = np.asarray(massdist.mass_properties(dist).com)[:2]
    want = np.array([x, y]) + np.array([[c, -s], [s, c]]) @ com
    assert np.allclose(np.ravel(scene.com_dot.get_data()), 100 * want, atol=1e-4)
    assert "t  1.50 s" in scene.text.get_text() and "balance" in scene.text.get_text()
    rgb = animate.frame_rgb(trace, DEFAULT, dist, index=i)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.std() > 10


def test_animation_is_a_gif_with_one_frame_per_step(episode, tmp_path):
    trace, dist = episode
    t0 = time.perf_counter()
    path = animate.animate_episode(trace, tmp_path / "e.gif", DEFAULT, dist, title="C", outcome="step_cap")
    wall = time.perf_counter() - t0
    with Image.open(path) as im:
        assert im.format == "GIF" and im.n_frames == len(trace.time) and im.size[0] > 300
    assert wall < 60  # 41 frames; a few seconds on an idle 2-core CPU
    png = animate.save_frame(trace, tmp_path / "last.png", DEFAULT, dist, outcome="step_cap")
    assert Image.open(png).size[0] > 300


def test_long_episodes_are_subsampled_to_real_time():
    idx = animate._frames(601, 150)
    assert len(idx) <= 151 and idx[0] == 0 and idx[-1] == 600 and idx[1] - idx[0] == 5


def test_animate_path_must_be_a_gif(tmp_path, capsys):
    with pytest.raises(ValueError, match="must end in .gif"):
        animate.check_path(tmp_path / "x.png")
    t0 = time.perf_counter()
    assert main(["rotate", "--animate", str(tmp_path / "x.mp4")]) == 2
    assert (
        "must end in .gif" in capsys.readouterr().err and time.perf_counter() - t0 < 5
    )  # before the episode


def test_simulate_animate_writes_the_gif(tmp_path, capsys):
    gif = tmp_path / "s.gif"
    assert main(["simulate", "--distribution", "D", "--steps", "20", "--animate", str(gif), "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["animation"] == str(gif) and res["animation_s"] > 0 and gif.stat().st_size > 10_000
