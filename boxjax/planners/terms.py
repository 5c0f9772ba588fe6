"""Cost terms on one planned state, shared by the paper planner and the sampling planner (pure jnp)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from boxjax import geometry
from boxjax.config import Config


def overhang(s, cfg: Config) -> jax.Array:
    """() m: how far the box's footprint reaches beyond the nearer belt end along x (negative: inside).

    extent(yaw) = |cos| l / 2 + |sin| w / 2 is the box's half-extent along x; the belts end at
    +-belt_length / 2.
    """
    hx, hy, _ = cfg.box.half_size
    c, sn = jnp.abs(jnp.cos(s[geometry.YAW])), jnp.abs(jnp.sin(s[geometry.YAW]))
    return jnp.abs(s[geometry.X]) + c * hx + sn * hy - cfg.gripper.belt_length / 2


def y_excess(s, cfg: Config, y_margin: float) -> jax.Array:
    """() m: how far the box's geometric centre lies outside the band of y in which the carriages can still
    centre the belts on it, shrunk by y_margin (negative: inside). The belt midpoint (P1 + P2) / 2 can
    reach [(p1_min + p2_min) / 2, (p1_max + p2_max) / 2] (+-7 cm by default)."""
    g = cfg.gripper
    lo = 0.5 * (g.p1_range[0] + g.p2_range[0]) + y_margin
    hi = 0.5 * (g.p1_range[1] + g.p2_range[1]) - y_margin
    y = s[geometry.Y]
    return jnp.maximum(y - hi, lo - y)
