"""Multi-room houses: a grid of rectangular rooms joined by doorways, each room
typed, coloured and furnished."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from a2catvn_jax.config import MIN_ROOM_SIDE

from .builder import CEILING_THICKNESS, FLOOR_THICKNESS, WALL_OVERLAP, SceneBuilder, quantize
from .palettes import CEILING, DOOR_FRAME, ROOM_PALETTES, pick_color
from .placement import Doorway, furnish_room
from .spec import ROOM_TYPES, Room, Scene

DOOR_HEIGHT = 2.1
HOUSE_ROOM_TYPES: tuple[str, ...] = tuple(t for t in ROOM_TYPES if t != "maze")
_ROOM_TYPE_WEIGHTS = {
    "bedroom": 0.2,
    "kitchen": 0.15,
    "bathroom": 0.15,
    "living_room": 0.15,
    "dining_room": 0.1,
    "office": 0.13,
    "hallway": 0.12,
}


def _spanning_tree(rng, rows: int, cols: int):
    """Random spanning tree over the grid adjacency (Kruskal on shuffled edges).

    Returns (tree_edges, other_edges); an edge is ((r, c), (r2, c2)).
    """
    edges = [((r, c), (r, c + 1)) for r in range(rows) for c in range(cols - 1)]
    edges += [((r, c), (r + 1, c)) for r in range(rows - 1) for c in range(cols)]
    order = rng.permutation(len(edges))
    parent = {(r, c): (r, c) for r in range(rows) for c in range(cols)}

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    tree, other = [], []
    for i in order:
        a, b = edges[i]
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
            tree.append(edges[i])
        else:
            other.append(edges[i])
    return tree, other


def _subtract_interval(lo: float, hi: float, hole: Optional[tuple[float, float]]):
    if hole is None:
        return [(lo, hi)]
    return [(a, b) for a, b in ((lo, hole[0]), (hole[1], hi)) if b - a > 1e-6]


def house(
    seed: int,
    grid: tuple[int, int] = (2, 3),
    room_size: tuple[float, float] = (3.0, 5.0),
    height: float = 2.6,
    *,
    wall_thickness: float = 0.12,
    door_width: tuple[float, float] = (0.9, 1.1),
    extra_door_prob: float = 0.35,
    room_types: Optional[Sequence[str]] = None,
    furniture: bool = True,
    door_posts: bool = False,
    name: Optional[str] = None,
) -> Scene:
    """A house of rows x cols rectangular rooms on a grid, joined by doorways.

    grid: (rows, cols); room i = row * cols + col, rows along +y, columns along +x.
    Column widths and row depths (free interior sizes) are drawn in `room_size`
    (min, max) metres, so all walls between rooms are straight lines. Doorways follow
    a random spanning tree of the grid adjacency (every room is reachable) plus each
    remaining adjacency with probability `extra_door_prob`. Room types are drawn
    with replacement (so types repeat) unless `room_types` (row-major, one per room)
    is given. The house footprint starts at (0, 0).
    """
    rows, cols = int(grid[0]), int(grid[1])
    if rows < 1 or cols < 1:
        raise ValueError(f"grid must have at least one row and column, got {grid}")
    lo, hi = float(room_size[0]), float(room_size[1])
    if not MIN_ROOM_SIDE <= lo <= hi:
        raise ValueError(f"room_size must be (min, max) with {MIN_ROOM_SIDE} <= min <= max, got {room_size}")
    if height < 1.5:
        raise ValueError(f"height must be at least 1.5 m, got {height}")
    t = float(wall_thickness)
    rng = np.random.default_rng(seed)
    widths = [quantize(rng.uniform(lo, hi), 0.01) for _ in range(cols)]
    depths = [quantize(rng.uniform(lo, hi), 0.01) for _ in range(rows)]
    # wall centre lines
    xs = [-t / 2]
    for w in widths:
        xs.append(round(xs[-1] + w + t, 6))
    ys = [-t / 2]
    for d in depths:
        ys.append(round(ys[-1] + d + t, 6))

    n_rooms = rows * cols
    if room_types is None:
        weights = np.array([_ROOM_TYPE_WEIGHTS[k] for k in HOUSE_ROOM_TYPES])
        idx = rng.choice(len(HOUSE_ROOM_TYPES), size=n_rooms, p=weights / weights.sum())
        types = [HOUSE_ROOM_TYPES[i] for i in idx]
    else:
        types = list(room_types)
        if len(types) != n_rooms:
            raise ValueError(f"room_types needs {n_rooms} entries (rows*cols), got {len(types)}")
        for ty in types:
            if ty not in HOUSE_ROOM_TYPES:
                raise ValueError(f"unknown house room type {ty!r}; known: {HOUSE_ROOM_TYPES}")

    def rid(r, c):
        return r * cols + c

    rects = {}
    for r in range(rows):
        for c in range(cols):
            rects[(r, c)] = (
                round(xs[c] + t / 2, 6),
                round(ys[r] + t / 2, 6),
                round(xs[c + 1] - t / 2, 6),
                round(ys[r + 1] - t / 2, 6),
            )

    # doorways: vdoor[(r, i)] on vertical line x=xs[i] in row r; hdoor[(j, c)] on line y=ys[j]
    tree, other = _spanning_tree(rng, rows, cols)
    door_edges = list(tree) + [e for e in other if rng.random() < extra_door_prob]
    vdoor, hdoor = {}, {}
    room_doors: dict[tuple[int, int], list[Doorway]] = {k: [] for k in rects}
    margin = 0.3
    for a, b_ in sorted(door_edges):
        dw = quantize(rng.uniform(*door_width), 0.01)
        if a[0] == b_[0]:  # same row: vertical wall line between columns
            r, i = a[0], b_[1]
            s_lo, s_hi = rects[a][1] + margin, rects[a][3] - margin
        else:
            j, c = b_[0], a[1]
            s_lo, s_hi = rects[a][0] + margin, rects[a][2] - margin
        centre = quantize(rng.uniform(s_lo + dw / 2, max(s_lo + dw / 2, s_hi - dw / 2)), 0.01)
        opening = (round(centre - dw / 2, 6), round(centre + dw / 2, 6))
        if a[0] == b_[0]:
            vdoor[(r, i)] = opening
            room_doors[a].append(Doorway("E", *opening))
            room_doors[b_].append(Doorway("W", *opening))
        else:
            hdoor[(j, c)] = opening
            room_doors[a].append(Doorway("N", *opening))
            room_doors[b_].append(Doorway("S", *opening))

    b = SceneBuilder()
    wall_rgba = {}
    for (r, c), ty in zip(sorted(rects), types):
        pal = ROOM_PALETTES[ty]
        wall_rgba[(r, c)] = pick_color(rng, pal["wall"], 0.03)
        floor = pick_color(rng, pal["floor"], 0.04)
        k = rid(r, c)
        b.slab((xs[c], ys[r], -FLOOR_THICKNESS), (xs[c + 1], ys[r + 1], 0.0), floor, "floor", k)
        ceiling = pick_color(rng, CEILING, 0.01)
        b.slab((xs[c], ys[r], height), (xs[c + 1], ys[r + 1], height + CEILING_THICKNESS), ceiling, "ceiling", k)

    z0, z1 = -WALL_OVERLAP, height + WALL_OVERLAP
    # vertical wall lines (constant x)
    for i in range(cols + 1):
        x = xs[i]
        for r in range(rows):
            if i == 0 or i == cols:
                cell = (r, 0) if i == 0 else (r, cols - 1)
                ya = ys[r] + t / 2 if r == 0 else ys[r]
                yb = ys[r + 1] - t / 2 if r == rows - 1 else ys[r + 1]
                b.slab((x - t / 2, ya, z0), (x + t / 2, yb, z1), wall_rgba[cell], "wall", rid(*cell))
                continue
            hole = vdoor.get((r, i))
            for cell, (xa, xb) in (((r, i - 1), (x - t / 2, x)), ((r, i), (x, x + t / 2))):
                for ya, yb in _subtract_interval(ys[r], ys[r + 1], hole):
                    b.slab((xa, ya, z0), (xb, yb, z1), wall_rgba[cell], "wall", rid(*cell))
    # horizontal wall lines (constant y)
    for j in range(rows + 1):
        y = ys[j]
        for c in range(cols):
            if j == 0 or j == rows:
                cell = (0, c) if j == 0 else (rows - 1, c)
                xa = xs[c] - t / 2 if c == 0 else xs[c]
                xb = xs[c + 1] + t / 2 if c == cols - 1 else xs[c + 1]
                b.slab((xa, y - t / 2, z0), (xb, y + t / 2, z1), wall_rgba[cell], "wall", rid(*cell))
                continue
            hole = hdoor.get((j, c))
            for cell, (ya, yb) in (((j - 1, c), (y - t / 2, y)), ((j, c), (y, y + t / 2))):
                for xa, xb in _subtract_interval(xs[c], xs[c + 1], hole):
                    b.slab((xa, ya, z0), (xb, yb, z1), wall_rgba[cell], "wall", rid(*cell))
    # lintels (and optional posts) over doorways
    door_top = min(DOOR_HEIGHT, height - 0.2)
    frame_rgba = pick_color(rng, DOOR_FRAME, 0.02)
    for (r, i), (a0, a1) in sorted(vdoor.items()):
        x = xs[i]
        b.slab((x - t / 2, a0, door_top), (x + t / 2, a1, z1), frame_rgba, "door_frame", rid(r, i - 1))
        if door_posts:
            for pa, pb in ((a0, a0 + 0.05), (a1 - 0.05, a1)):
                b.slab((x - t / 2 - 0.02, pa, 0.0), (x + t / 2 + 0.02, pb, door_top), frame_rgba, "door_frame", rid(r, i - 1))
    for (j, c), (a0, a1) in sorted(hdoor.items()):
        y = ys[j]
        b.slab((a0, y - t / 2, door_top), (a1, y + t / 2, z1), frame_rgba, "door_frame", rid(j - 1, c))
        if door_posts:
            for pa, pb in ((a0, a0 + 0.05), (a1 - 0.05, a1)):
                b.slab((pa, y - t / 2 - 0.02, 0.0), (pb, y + t / 2 + 0.02, door_top), frame_rgba, "door_frame", rid(j - 1, c))

    # doorway posts narrow the opening: keep the clear zones based on the real opening
    if door_posts:
        for key in room_doors:
            room_doors[key] = [Doorway(d.side, d.a0 + 0.05, d.a1 - 0.05) for d in room_doors[key]]

    rooms = []
    for (r, c), ty in zip(sorted(rects), types):
        rooms.append(Room(ty, rects[(r, c)]))
        if furniture:
            furnish_room(b, rng, rid(r, c), ty, rects[(r, c)], room_doors[(r, c)])

    bounds = (round(xs[0] + t / 2, 6), round(ys[0] + t / 2, 6), round(xs[-1] - t / 2, 6), round(ys[-1] - t / 2, 6))
    return Scene(
        name=name or f"house_{seed}",
        geoms=b.geoms,
        rooms=rooms,
        bounds=bounds,
        height=float(height),
        closed=True,
    )


__all__ = [
    "DOOR_HEIGHT",
    "HOUSE_ROOM_TYPES",
    "house",
]
