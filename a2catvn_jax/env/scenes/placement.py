"""Placing furniture in a room: poses at multiples of 90 degrees that keep wall
clearance, gaps between pieces, the floor in front of doorways clear, and the
room's free floor connected for the agent (`free_space_ok`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import numpy as np
from scipy import ndimage

from .builder import WALL_CLEARANCE, SceneBuilder, quantize
from .furniture import ROOM_FURNITURE, Part, Piece

DOOR_CLEAR_DEPTH = 0.8  # free floor depth kept in front of each doorway (both sides)
DOOR_CLEAR_MARGIN = 0.1  # extra width of that zone on each side of the opening
PIECE_GAP = 0.05  # minimum xy gap between two furniture pieces
# Disc radii for which each room's free floor must stay one connected component.
FREE_SPACE_RADII = (0.2, 0.25, 0.3)
WIDE_GAP = 0.65  # gaps between furniture and walls are flush or at least this wide
DOOR_POINT_DEPTH = 0.4  # reference point inside the room in front of a doorway

# Quaternions turning a capsule's local z axis onto world x / world y.
_CAPSULE_QUAT = {
    "z": np.array([1.0, 0.0, 0.0, 0.0]),
    "x": np.array([math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0]),
    "y": np.array([math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0]),
}


def _rotate_xy(x: float, y: float, k: int) -> tuple[float, float]:
    """Rotate (x, y) by k * 90 degrees counter-clockwise."""
    k %= 4
    if k == 0:
        return x, y
    if k == 1:
        return -y, x
    if k == 2:
        return -x, -y
    return y, -x


def _rotated_aabb(rect, k) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = rect
    pts = [_rotate_xy(x, y, k) for x, y in ((x0, y0), (x1, y0), (x0, y1), (x1, y1))]
    xs, ys = zip(*pts)
    return (min(xs), min(ys), max(xs), max(ys))


def _union_rect(rects):
    rects = np.asarray(rects)
    return (rects[:, 0].min(), rects[:, 1].min(), rects[:, 2].max(), rects[:, 3].max())


def _part_world(part: Part, k: int, cx: float, cy: float):
    """(type, pos, size, quat) of a part placed at (cx, cy) with rotation k."""
    x, y = _rotate_xy(part.pos[0], part.pos[1], k)
    pos = (quantize(cx + x, 0.0005), quantize(cy + y, 0.0005), part.pos[2])
    size = list(part.size)
    quat = None
    odd = k % 2 == 1
    if part.type in ("box", "ellipsoid") and odd:
        size[0], size[1] = size[1], size[0]
    if part.type == "capsule" and part.axis != "z":
        axis = part.axis
        if odd:
            axis = "y" if axis == "x" else "x"
        quat = _CAPSULE_QUAT[axis]
    return part.type, pos, tuple(size), quat


def _rects_overlap(a, b, gap=0.0) -> bool:
    return a[0] < b[2] + gap and b[0] < a[2] + gap and a[1] < b[3] + gap and b[1] < a[3] + gap


@dataclasses.dataclass
class Doorway:
    """A doorway seen from one room: wall side, opening interval along the wall."""

    side: str  # "W", "E", "S", "N"
    a0: float
    a1: float


def _door_zone_and_point(rect, door: Doorway):
    x0, y0, x1, y1 = rect
    m, dd, mid = DOOR_CLEAR_MARGIN, DOOR_CLEAR_DEPTH, (door.a0 + door.a1) / 2
    if door.side == "W":
        return (x0, door.a0 - m, x0 + dd, door.a1 + m), (x0 + DOOR_POINT_DEPTH, mid)
    if door.side == "E":
        return (x1 - dd, door.a0 - m, x1, door.a1 + m), (x1 - DOOR_POINT_DEPTH, mid)
    if door.side == "S":
        return (door.a0 - m, y0, door.a1 + m, y0 + dd), (mid, y0 + DOOR_POINT_DEPTH)
    return (door.a0 - m, y1 - dd, door.a1 + m, y1), (mid, y1 - DOOR_POINT_DEPTH)


def free_space_ok(rect, obstacles, points, res=0.05, radii=FREE_SPACE_RADII) -> bool:
    """Whether a disc can move between all free places of a room, with margin.

    rect: room interior (x0, y0, x1, y1); obstacles: xy AABBs; points: places that
    must be free (e.g. in front of doorways). With r0 = min(radii) and r1 = max(radii):
    for every radius the free disc centres on a `res` grid form one non-empty
    4-connected component holding every point, and every place free for radius r0
    lies within r1 - r0 (+ one cell) of a place free for r1. The last condition rules
    out passages narrower than 2 * r1, so coarser occupancy grids built for a disc
    of radius r0 see the same single connected free area without slivers.
    """
    x0, y0, x1, y1 = rect
    xs = np.arange(x0 + res / 2, x1, res)
    ys = np.arange(y0 + res / 2, y1, res)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    d2 = np.full(px.shape, np.inf)  # squared distance to the nearest obstacle
    for ax0, ay0, ax1, ay1 in obstacles:
        dx = np.maximum(np.maximum(ax0 - px, px - ax1), 0.0)
        dy = np.maximum(np.maximum(ay0 - py, py - ay1), 0.0)
        d2 = np.minimum(d2, dx * dx + dy * dy)
    wall = np.minimum(np.minimum(px - x0, x1 - px), np.minimum(py - y0, y1 - py))
    cells = [
        (int(np.clip((x - x0) // res, 0, len(xs) - 1)), int(np.clip((y - y0) // res, 0, len(ys) - 1)))
        for x, y in points
    ]
    frees = []
    for radius in sorted(radii):
        free = (wall >= radius) & (d2 >= radius * radius)
        _, n = ndimage.label(free)
        if n != 1 or not all(free[c] for c in cells):
            return False
        frees.append(free)
    if len(frees) > 1:
        reach = ndimage.distance_transform_edt(~frees[-1], sampling=res)
        if np.any(reach[frees[0]] > max(radii) - min(radii) + res * 1.01):
            return False
    return True


def _axis_pos(rng, lo: float, hi: float, flush_prob: float, centre_jitter: Optional[float] = None) -> float:
    """A piece centre coordinate in [lo, hi] (lo/hi: piece flush with a wall).

    Gaps between a piece and a wall are either closed (flush) or wide enough for
    the agent with margin (>= WIDE_GAP): the free-space test rejects anything in
    between. With probability `flush_prob`, or when the room is too narrow for two
    wide gaps, the piece goes flush to one side; otherwise it is drawn uniformly
    (or around the middle, +- centre_jitter of the span) among positions that keep
    both gaps wide.
    """
    g = WIDE_GAP - WALL_CLEARANCE
    a, b = lo + g, hi - g
    if a > b or rng.random() < flush_prob:
        return lo if rng.random() < 0.5 else hi
    if centre_jitter is not None:
        m = (a + b) / 2
        return float(np.clip(m + rng.uniform(-centre_jitter, centre_jitter) * (b - a), a, b))
    return rng.uniform(a, b)


def _try_place(rng, piece: Piece, rect, zones, points, placed_rects, obstacles, attempts: int):
    """Sample poses for a piece until one passes every rule.

    Returns (k, cx, cy, part_rects, bbox) or None. The first half of the attempts
    use the piece's preferred mode, the rest a relaxed one ("corner" -> "wall",
    "center" -> "free").
    """
    x0, y0, x1, y1 = rect
    c = WALL_CLEARANCE
    side_k = {"S": 0, "E": 1, "N": 2, "W": 3}
    local_parts = [p.local_xy_aabb() for p in piece.parts]
    local = _union_rect(local_parts)
    for attempt in range(attempts):
        mode = piece.mode
        if attempt >= attempts // 2:
            mode = {"corner": "wall", "center": "free"}.get(mode, mode)
        side = "SENW"[rng.integers(4)]
        k = side_k[side] if mode in ("wall", "corner") else int(rng.integers(4))
        fx0, fy0, fx1, fy1 = _rotated_aabb(local, k)
        lo_x, hi_x = x0 + c - fx0, x1 - c - fx1  # feasible centre range
        lo_y, hi_y = y0 + c - fy0, y1 - c - fy1
        if lo_x > hi_x or lo_y > hi_y:
            continue
        if mode in ("wall", "corner"):
            # back against the wall of `side`; position along it
            along_lo, along_hi = (lo_x, hi_x) if side in "SN" else (lo_y, hi_y)
            if mode == "corner":
                along = along_lo if rng.random() < 0.5 else along_hi
            else:
                along = _axis_pos(rng, along_lo, along_hi, flush_prob=0.35)
            cx, cy = {"S": (along, lo_y), "N": (along, hi_y), "W": (lo_x, along), "E": (hi_x, along)}[side]
        elif mode == "center":
            cx = _axis_pos(rng, lo_x, hi_x, flush_prob=0.0, centre_jitter=0.25)
            cy = _axis_pos(rng, lo_y, hi_y, flush_prob=0.0, centre_jitter=0.25)
        else:
            cx = _axis_pos(rng, lo_x, hi_x, flush_prob=0.3)
            cy = _axis_pos(rng, lo_y, hi_y, flush_prob=0.3)
        cx, cy = quantize(cx), quantize(cy)
        world_parts = [_rotated_aabb(r, k) for r in local_parts]
        world_parts = [(a + cx, b + cy, e + cx, f + cy) for a, b, e, f in world_parts]
        bb = _union_rect(world_parts)
        m = 0.05 - 1e-9  # required wall clearance
        if bb[0] < x0 + m or bb[1] < y0 + m or bb[2] > x1 - m or bb[3] > y1 - m:
            continue
        if any(_rects_overlap(bb, z) for z in zones):
            continue
        if any(_rects_overlap(bb, r, PIECE_GAP) for r in placed_rects):
            continue
        if not free_space_ok(rect, obstacles + world_parts, points):
            continue
        return k, cx, cy, world_parts, bb
    return None


def furnish_room(builder: SceneBuilder, rng, room_index: int, room_type: str, rect, doors: Sequence[Doorway]):
    """Place the furniture of one room. Returns the number of pieces placed.

    Required pieces get three differently sized tries of 25 poses each, optional
    ones a single try of 20 poses; optional pieces are skipped once furniture covers
    45% of the floor.
    """
    x0, y0, x1, y1 = rect
    rw, rd = x1 - x0, y1 - y0
    zones, points = [], []
    for door in doors:
        z, p = _door_zone_and_point(rect, door)
        zones.append(z)
        points.append(p)
    placed_rects: list[tuple] = []  # piece AABBs
    obstacles: list[tuple] = []  # part AABBs
    max_fill = 0.45 * rw * rd
    filled = 0.0
    count = 0
    for make, prob in ROOM_FURNITURE[room_type]:
        required = prob >= 1.0
        if not required and rng.random() >= prob:
            continue
        for _ in range(3 if required else 1):
            piece = make(rng, rw, rd)
            local = _union_rect([p.local_xy_aabb() for p in piece.parts])
            area = (local[2] - local[0]) * (local[3] - local[1])
            if not required and piece.parts[0].cls != "rug" and filled + area > max_fill:
                break
            found = _try_place(rng, piece, rect, zones, points, placed_rects, obstacles, 25 if required else 20)
            if found is None:
                continue
            k, cx, cy, world_parts, bb = found
            placed_rects.append(bb)
            obstacles += world_parts
            filled += area
            count += 1
            for part in piece.parts:
                gtype, pos, size, quat = _part_world(part, k, cx, cy)
                builder.add(gtype, pos, size, part.rgba, part.cls, room_index, quat)
            break
    return count


__all__ = [
    "DOOR_CLEAR_DEPTH",
    "DOOR_CLEAR_MARGIN",
    "DOOR_POINT_DEPTH",
    "Doorway",
    "FREE_SPACE_RADII",
    "PIECE_GAP",
    "WIDE_GAP",
    "free_space_ok",
    "furnish_room",
]
