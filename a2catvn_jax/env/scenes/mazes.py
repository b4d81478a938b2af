"""Perfect mazes with regionally coloured walls and landmark objects in dead ends."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .builder import AGENT_RADIUS, CEILING_THICKNESS, FLOOR_THICKNESS, WALL_CLEARANCE, WALL_OVERLAP, SceneBuilder, quantize
from .palettes import CEILING, MAZE_OBJECTS, MAZE_WALLS, pick_color
from .spec import Room, Scene


def _perfect_maze(rng, nx: int, ny: int):
    """Randomised depth-first search. Returns (hwall, vwall) boolean arrays.

    hwall[j, i]: wall on the line y=j between cells (i, j-1) and (i, j), shape (ny+1, nx).
    vwall[i, j]: wall on the line x=i between cells (i-1, j) and (i, j), shape (nx+1, ny).
    """
    hwall = np.ones((ny + 1, nx), bool)
    vwall = np.ones((nx + 1, ny), bool)
    seen = np.zeros((nx, ny), bool)
    start = (int(rng.integers(nx)), int(rng.integers(ny)))
    stack = [start]
    seen[start] = True
    while stack:
        i, j = stack[-1]
        nbrs = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        nbrs = [(a, c) for a, c in nbrs if 0 <= a < nx and 0 <= c < ny and not seen[a, c]]
        if not nbrs:
            stack.pop()
            continue
        a, c = nbrs[rng.integers(len(nbrs))]
        if a != i:
            vwall[max(a, i), j] = False
        else:
            hwall[max(c, j), i] = False
        seen[a, c] = True
        stack.append((a, c))
    return hwall, vwall


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [start, end) of True values."""
    out, start = [], None
    for k, f in enumerate(list(flags) + [False]):
        if f and start is None:
            start = k
        elif not f and start is not None:
            out.append((start, k))
            start = None
    return out


def maze(
    seed: int,
    cells: tuple[int, int] = (5, 5),
    cell_size: float = 1.5,
    height: float = 2.0,
    *,
    wall_thickness: float = 0.1,
    num_objects: Optional[int] = None,
    name: Optional[str] = None,
) -> Scene:
    """A perfect maze (randomised DFS) of cells[0] x cells[1] square cells.

    Collinear wall pieces are merged into one box per run. Walls get colours from a
    few distinct ones by region of the maze so that places can be told apart; a few
    landmark objects (class "object") stand in dead ends. One Room of type "maze"
    covers the whole footprint, which starts at (0, 0).
    """
    nx, ny = int(cells[0]), int(cells[1])
    if nx < 2 or ny < 2:
        raise ValueError(f"maze needs at least 2x2 cells, got {cells}")
    t, cs = float(wall_thickness), float(cell_size)
    if cs < 2 * AGENT_RADIUS + t + 0.2:
        raise ValueError(f"cell_size {cs} too small for the agent (radius {AGENT_RADIUS})")
    rng = np.random.default_rng(seed)
    hwall, vwall = _perfect_maze(rng, nx, ny)
    xs = [round(i * cs - t / 2, 6) for i in range(nx + 1)]
    ys = [round(j * cs - t / 2, 6) for j in range(ny + 1)]
    b = SceneBuilder()
    b.slab((xs[0], ys[0], -FLOOR_THICKNESS), (xs[-1], ys[-1], 0.0), pick_color(rng, [(0.55, 0.52, 0.48), (0.45, 0.45, 0.5)], 0.03), "floor", 0)
    b.slab((xs[0], ys[0], height), (xs[-1], ys[-1], height + CEILING_THICKNESS), pick_color(rng, CEILING, 0.01), "ceiling", 0)

    # region colours: zones of about 2x2 cells each get a palette colour
    zx, zy = max(1, math.ceil(nx / 2)), max(1, math.ceil(ny / 2))
    perm = rng.permutation(len(MAZE_WALLS))
    zone_cols = perm[np.arange(zx * zy).reshape(zx, zy) % len(MAZE_WALLS)]

    def zone_rgba(px, py):
        i = min(int(px / cs / 2), zx - 1)
        j = min(int(py / cs / 2), zy - 1)
        return pick_color(rng, MAZE_WALLS[zone_cols[i, j]], 0.03)

    def h_at(i, j):  # horizontal wall pieces touching grid point (i, j): left, right
        left = i > 0 and hwall[j, i - 1]
        right = i < nx and hwall[j, i]
        return left, right

    def v_at(i, j):  # vertical wall pieces touching grid point (i, j): down, up
        down = j > 0 and vwall[i, j - 1]
        up = j < ny and vwall[i, j]
        return down, up

    z0, z1 = -WALL_OVERLAP, height + WALL_OVERLAP
    # Corner squares belong to a run passing through the point; else to horizontal runs.
    for j in range(ny + 1):
        for i0, i1 in _runs(hwall[j]):
            v_pass0 = all(v_at(i0, j))
            v_pass1 = all(v_at(i1, j))
            xa = xs[i0] + t / 2 if v_pass0 else xs[i0] - t / 2
            xb = xs[i1] - t / 2 if v_pass1 else xs[i1] + t / 2
            rgba = zone_rgba((xa + xb) / 2, ys[j])
            b.slab((xa, ys[j] - t / 2, z0), (xb, ys[j] + t / 2, z1), rgba, "wall", 0)
    for i in range(nx + 1):
        for j0, j1 in _runs(vwall[i]):
            ya = ys[j0] + t / 2 if any(h_at(i, j0)) else ys[j0] - t / 2
            yb = ys[j1] - t / 2 if any(h_at(i, j1)) else ys[j1] + t / 2
            rgba = zone_rgba(xs[i], (ya + yb) / 2)
            b.slab((xs[i] - t / 2, ya, z0), (xs[i] + t / 2, yb, z1), rgba, "wall", 0)

    # landmark objects in dead ends, pushed towards the closed end
    dead = []
    for i in range(nx):
        for j in range(ny):
            open_dirs = []
            if not vwall[i, j]:
                open_dirs.append((-1, 0))
            if not vwall[i + 1, j]:
                open_dirs.append((1, 0))
            if not hwall[j, i]:
                open_dirs.append((0, -1))
            if not hwall[j + 1, i]:
                open_dirs.append((0, 1))
            if len(open_dirs) == 1:
                dead.append((i, j, open_dirs[0]))
    if num_objects is None:
        num_objects = max(2, (nx * ny) // 6)
    num_objects = min(num_objects, len(dead))
    chosen = rng.choice(len(dead), size=num_objects, replace=False) if num_objects else []
    # Objects stand in a corner of the dead end (against its closed wall and one side
    # wall, WALL_CLEARANCE away) so the rest of the cell stays one open area.
    interior = cs - t
    scale = min(1.0, interior / 1.4)
    for idx in sorted(int(v) for v in chosen):
        i, j, (dx, dy) = dead[idx]
        rgba = pick_color(rng, MAZE_OBJECTS, 0.03)
        kind = rng.integers(3)
        if kind == 0:
            e = quantize(rng.uniform(0.18, 0.28) * scale, 0.01)
            gtype, size, z = "sphere", (e,), e
        elif kind == 1:
            e, rz = quantize(rng.uniform(0.15, 0.25) * scale, 0.01), quantize(rng.uniform(0.3, 0.45), 0.01)
            gtype, size, z = "ellipsoid", (e, e, rz), rz
        else:
            e = quantize(rng.uniform(0.15, 0.25) * scale, 0.01)
            gtype, size, z = "box", (e, e, e), e
        shift = interior / 2 - WALL_CLEARANCE - e
        side = 1 if rng.random() < 0.5 else -1
        cx = (xs[i] + xs[i + 1]) / 2 - dx * shift + (side * shift if dx == 0 else 0.0)
        cy = (ys[j] + ys[j + 1]) / 2 - dy * shift + (side * shift if dy == 0 else 0.0)
        b.add(gtype, (round(cx, 6), round(cy, 6), z), size, rgba, "object", 0)

    bounds = (round(xs[0] + t / 2, 6), round(ys[0] + t / 2, 6), round(xs[-1] - t / 2, 6), round(ys[-1] - t / 2, 6))
    return Scene(
        name=name or f"maze_{seed}",
        geoms=b.geoms,
        rooms=[Room("maze", bounds)],
        bounds=bounds,
        height=float(height),
        closed=True,
    )


__all__ = [
    "maze",
]
