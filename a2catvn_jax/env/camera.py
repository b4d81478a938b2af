"""Pinhole camera of the agent: pose -> world-frame ray origin and per-pixel directions.

Conventions match MuJoCo's cameras: vertical field of view `fovy`, square pixels,
image row 0 at the top. The camera has no roll: `yaw` turns it about world z
(yaw 0 looks along +x) and `tilt` pitches it up (positive) or down.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def camera_basis(yaw, tilt):
    """World-frame (right, up, forward) unit vectors, each [..., 3].

    NumPy in (Python or NumPy numbers), NumPy out in float64; otherwise JAX."""
    xp = np if isinstance(yaw, (int, float, np.number, np.ndarray)) else jnp
    cy, sy = xp.cos(yaw), xp.sin(yaw)
    ct, st = xp.cos(tilt), xp.sin(tilt)
    forward = xp.stack([cy * ct, sy * ct, st], -1)
    right = xp.stack([sy, -cy, xp.zeros_like(cy)], -1)
    up = xp.stack([-cy * st, -sy * st, ct], -1)
    return right, up, forward


def image_plane(height: int, width: int, fovy_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates on the plane at unit distance: (x [W], y [H]), float64.

    x grows to the right, y grows upwards (row 0 is the top row).
    """
    half = np.tan(np.deg2rad(fovy_deg) / 2.0)
    x = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * half * (width / height)
    y = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * half
    return x, y


def ray_directions(yaw, tilt, height: int, width: int, fovy_deg: float):
    """Unit world directions through pixel centres, [H, W, 3] (row-major image)."""
    return jnp.swapaxes(column_ray_directions(yaw, tilt, height, width, fovy_deg), 0, 1)


def column_ray_directions(yaw, tilt, height: int, width: int, fovy_deg: float):
    """Unit world directions through pixel centres, column-major: [W, H, 3]."""
    x, y = (a.astype(np.float32) for a in image_plane(height, width, fovy_deg))
    right, up, forward = camera_basis(yaw, tilt)
    d = (
        forward[None, None, :]
        + x[:, None, None] * right[None, None, :]
        + y[None, :, None] * up[None, None, :]
    )
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)
