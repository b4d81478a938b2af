"""Occupancy grids and geodesic distances of scenes (host side, numpy/scipy).

The agent is a disc of radius r on the floor. A geom blocks it when its height range
meets the agent's body (from just above the floor to `body_height`); its footprint
is the geom's xy bounding rectangle. The agent's centre may stand anywhere outside
every blocking footprint grown by r on each side (a square grown rectangle, a little
more cautious than a disc). The same rectangles drive collisions in the environment,
so "free" means the same thing in both places.

Geodesic distances are shortest 8-connected paths between free cell centres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from a2catvn_jax.env import rects
from a2catvn_jax.env.scenes.errors import SceneError
from a2catvn_jax.env.scenes.mjcf import geom_aabb
from a2catvn_jax.env.scenes.spec import Scene

FLOOR_CLEARANCE = 0.02  # geoms entirely below this height (rugs) do not block


def obstacle_rects(scene: Scene, body_height: float) -> np.ndarray:
    """Footprints (xmin, ymin, xmax, ymax) [N, 4] of the static geoms that block the
    agent (moving geoms block it where each episode places them, `NavEnv`)."""
    footprints = []
    for g in scene.geoms:
        if g.moving:
            continue
        lo, hi = geom_aabb(g)
        if hi[2] > FLOOR_CLEARANCE and lo[2] < body_height and g.cls not in ("floor", "ceiling"):
            footprints.append([lo[0], lo[1], hi[0], hi[1]])
    return np.asarray(footprints, np.float64).reshape(-1, 4)


@dataclasses.dataclass
class NavGrid:
    """Occupancy grid of one scene. Cell (i, j) has centre origin + ((j, i) + 0.5) * res."""

    origin: np.ndarray  # (x0, y0)
    resolution: float
    free: np.ndarray  # bool [H, W]: the agent's centre may stand at the cell centre
    room: np.ndarray  # int [H, W]: index of the room the cell centre lies in, or -1
    obstacles: np.ndarray  # [N, 4] blocking footprints

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape

    def centres(self) -> np.ndarray:
        h, w = self.shape
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        return self.origin + (np.stack([jj, ii], -1) + 0.5) * self.resolution

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of the cells holding points xy [..., 2] (clipped to the grid)."""
        return rects.cell_of(np.asarray(xy), self.origin, self.resolution, self.shape)


def grid_shape(scene: Scene, resolution: float) -> tuple[int, int]:
    """(rows, columns) of the occupancy grid over the scene's bounds."""
    x0, y0, x1, y1 = scene.bounds
    return max(int(np.ceil((y1 - y0) / resolution)), 1), max(int(np.ceil((x1 - x0) / resolution)), 1)


def build(scene: Scene, resolution: float, agent_radius: float, body_height: float) -> NavGrid:
    """Occupancy grid over the scene's bounds."""
    x0, y0, x1, y1 = scene.bounds
    h, w = grid_shape(scene, resolution)
    origin = np.array([x0, y0], np.float64)
    obstacles = obstacle_rects(scene, body_height)
    grid = NavGrid(origin, resolution, np.zeros((h, w), bool), np.full((h, w), -1, np.int32), obstacles)
    c = grid.centres()
    within = (c[..., 0] > x0 + agent_radius) & (c[..., 0] < x1 - agent_radius)
    within &= (c[..., 1] > y0 + agent_radius) & (c[..., 1] < y1 - agent_radius)
    grid.free = within & ~rects.inside(c, obstacles, agent_radius + 1e-3).any(-1)
    for k, room in enumerate(scene.rooms):
        rx0, ry0, rx1, ry1 = room.rect
        grid.room[(c[..., 0] >= rx0) & (c[..., 0] < rx1) & (c[..., 1] >= ry0) & (c[..., 1] < ry1)] = k
    if not grid.free.any():
        raise SceneError(
            f"{scene.name}: no free floor for an agent of radius {agent_radius} m "
            f"at grid resolution {resolution} m (its floor is {x1 - x0:.2f} x {y1 - y0:.2f} m; the agent's "
            f"centre stays {agent_radius} m away from the floor's edges and from every obstacle)"
        )
    return grid


def _graph(free: np.ndarray, resolution: float) -> scipy.sparse.csr_matrix:
    """8-connected graph of free cells; diagonal steps may not cut a blocked corner."""
    h, w = free.shape
    index = np.arange(h * w).reshape(h, w)
    pad = np.zeros((h + 2, w + 2), bool)
    pad[1:-1, 1:-1] = free

    def shifted(di, dj):  # free[i + di, j + dj] aligned with [i, j]; False outside
        return pad[1 + di : 1 + di + h, 1 + dj : 1 + dj + w]

    rows, cols, vals = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ok = free & shifted(di, dj)
        if di and dj:
            ok &= shifted(di, 0) & shifted(0, dj)
        i, j = np.nonzero(ok)
        rows.append(index[i, j])
        cols.append(index[i + di, j + dj])
        vals.append(np.full(i.size, resolution * np.hypot(di, dj)))
    r, c, v = (np.concatenate(x) for x in (rows, cols, vals))
    return scipy.sparse.csr_matrix((v, (r, c)), shape=(h * w, h * w))


def geodesic(grid: NavGrid, sources: np.ndarray) -> np.ndarray:
    """Shortest free-space path length from every cell to the nearest source cell,
    [H, W] metres; inf for blocked or unreachable cells. sources: bool [H, W]."""
    src = np.flatnonzero(sources & grid.free)
    if src.size == 0:
        return np.full(grid.shape, np.inf)
    d = scipy.sparse.csgraph.dijkstra(_graph(grid.free, grid.resolution), directed=False, indices=src, min_only=True)
    d = d.reshape(grid.shape)
    d[~grid.free] = np.inf
    return d


def diameter(grid: NavGrid, sweeps: int = 4, seed: int = 0) -> float:
    """Largest geodesic distance between two free cells (repeated double sweeps from
    random cells: a lower bound that is exact on most floor plans)."""
    rng = np.random.default_rng(seed)
    free = np.flatnonzero(grid.free)
    best = 0.0
    start = rng.choice(free)
    for _ in range(sweeps):
        src = np.zeros(grid.shape, bool)
        src.flat[start] = True
        d = geodesic(grid, src)
        finite = np.where(np.isfinite(d), d, -1.0)
        far = int(np.argmax(finite))
        best = max(best, float(finite.flat[far]))
        start = far if finite.flat[far] > 0 else rng.choice(free)
    return best
