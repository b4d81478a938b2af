"""Axis-aligned rectangles on the floor plane and the grid over it, shared by the host
(NumPy) and the jitted environment and renderer (JAX).

Rectangles are [..., 4] arrays (xmin, ymin, xmax, ymax): geom footprints, the
obstacles that block the agent. Functions marked "NumPy or JAX" compute with the
library of their inputs, so the occupancy grid built on the host and the environment
stepping under `jax.jit` use one definition.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def array_module(*arrays):
    """`jax.numpy` if any argument is a JAX array (or tracer), else `numpy`."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def inside(points, rects, grow: float = 0.0):
    """Whether each point [..., 2] lies inside (or on) each rect [N, 4] grown by `grow`
    on every side: [..., N]. NumPy or JAX."""
    p = points[..., None, :]
    return (
        (p[..., 0] >= rects[:, 0] - grow)
        & (p[..., 0] <= rects[:, 2] + grow)
        & (p[..., 1] >= rects[:, 1] - grow)
        & (p[..., 1] <= rects[:, 3] + grow)
    )


def distance(points, rects):
    """Distance from each point [..., 2] to each rect [..., 4] (0 inside), broadcast
    together. NumPy or JAX."""
    xp = array_module(points, rects)
    dx = xp.maximum(xp.maximum(rects[..., 0] - points[..., 0], points[..., 0] - rects[..., 2]), 0.0)
    dy = xp.maximum(xp.maximum(rects[..., 1] - points[..., 1], points[..., 1] - rects[..., 3]), 0.0)
    return xp.sqrt(dx * dx + dy * dy)


def safe_inv(v):
    """1 / v with |v| kept at least 1e-12 (sign kept): finite slab distances for rays
    parallel to an axis."""
    return 1.0 / jnp.where(jnp.abs(v) < 1e-12, jnp.where(v < 0, -1e-12, 1e-12), v)


def slab(origin, direction, rects):
    """Entry and exit parameters (t_near, t_far) of the 2-D rays origin + t direction
    ([..., 2] each) through the rects [N, 4]: [..., N] each. The ray meets a rect where
    t_near <= t_far (the slab test)."""
    inv = safe_inv(direction)[..., None, :]
    o = origin[..., None, :]
    t1, t2 = (rects[..., :2] - o) * inv, (rects[..., 2:] - o) * inv
    return jnp.max(jnp.minimum(t1, t2), -1), jnp.min(jnp.maximum(t1, t2), -1)


def cell_of(xy, origin, resolution: float, shape):
    """Row and column (i, j) of the grid cell holding points xy [..., 2] on a grid of
    `shape` (H, W) cells of side `resolution` whose cell (0, 0) starts at `origin`
    (x0, y0); points outside are clipped to the border cells. NumPy or JAX."""
    xp = array_module(xy, origin)
    ij = xp.floor((xy - origin) / resolution).astype(xp.int32)
    h, w = shape
    return xp.clip(ij[..., 1], 0, h - 1), xp.clip(ij[..., 0], 0, w - 1)
