"""Pinhole camera of the agent: pose -> world-frame ray origin and per-pixel directions,
the camera's static settings (`CameraSpec`) and what every render backend returns (`Frame`).

Conventions match MuJoCo's cameras: vertical field of view `fovy`, square pixels,
image row 0 at the top. The camera has no roll: `yaw` turns it about world z
(yaw 0 looks along +x) and `tilt` pitches it up (positive) or down.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

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


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Static camera and renderer settings (they fix array shapes).

    candidates: per tile, how many world-aligned boxes (walls, floors, most furniture)
      the culled renderer tests; 0 disables culling (every ray tests every geom).
    object_candidates: the same for each other geom family (oriented boxes,
      ellipsoids, capsules), capped by `candidates`.
    tile_columns: image columns per culling tile (reduced to a divisor of `width`).
    chunk_frames: `render_batch` renders its frames this many at a time (a loop over
      chunks keeps each chunk's images in cache); 0 picks about 2**18 pixels a chunk, at most 16 frames.
    """

    height: int
    width: int
    fovy: float = 60.0
    candidates: int = 24
    object_candidates: int = 2
    tile_columns: int = 6
    chunk_frames: int = 0

    def __post_init__(self):
        if self.height < 1 or self.width < 1:
            raise ValueError(f"image size must be positive, got {self.height}x{self.width}")
        if not 0.0 < self.fovy < 180.0:
            raise ValueError(f"fovy must be in (0, 180) degrees, got {self.fovy}")
        if min(self.candidates, self.object_candidates, self.chunk_frames) < 0 or self.tile_columns < 1:
            raise ValueError(
                "candidates, object_candidates and chunk_frames must be >= 0 and tile_columns >= 1, got "
                f"{self.candidates}, {self.object_candidates}, {self.chunk_frames}, {self.tile_columns}"
            )

    @property
    def tile(self) -> int:
        return max(c for c in range(1, min(self.tile_columns, self.width) + 1) if self.width % c == 0)

    def cap(self, family: str) -> int:
        """Candidates per tile of a geom family."""
        return self.candidates if family == "abox" else min(self.candidates, max(self.object_candidates, 1))

    def chunk(self, batch: int) -> int:
        n = self.chunk_frames or min(16, max(1, round(2**18 / (self.height * self.width))))
        return max(1, min(n, batch))


class Frame(NamedTuple):
    """Rendered outputs, row-major images [..., H, W]."""

    rgb: jnp.ndarray  # uint8 [..., H, W, 3]
    depth: jnp.ndarray  # float32 metres along the ray, 0 where nothing is hit
    geom: jnp.ndarray  # int32 MuJoCo geom id, -1 where nothing is hit
    cls: jnp.ndarray  # int32 semantic class, 0 where nothing is hit
    fallback: jnp.ndarray  # bool [...]: some tiles failed culling's check (render_batch
    # re-rendered those against every geom; `render` with culling leaves them wrong)
