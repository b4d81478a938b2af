"""Seeded procedural scene generators: multi-room houses, single rooms and mazes.

Every generator is a pure function of its seed and arguments and returns a host-side
`Scene` (see `spec.py`). Geometry conventions shared by all generators:

* The floor top is the plane z=0. Floors are boxes from z=-0.1 to 0 that tile the
  whole footprint (including the space under walls and door openings); adjacent
  floor boxes touch along wall centre lines but never overlap in area.
* Ceilings are boxes whose bottom face is at z=height.
* Walls are axis-aligned boxes from z=-0.05 to height+0.05, i.e. they reach into the
  floor and ceiling slabs, so every wall spans floor to ceiling. Wall boxes meeting
  at a corner either cross or touch face to face; no two wall boxes share a visible
  coplanar face over an area.
* Furniture is built from boxes (axis-aligned), spheres, capsules (vertical or
  horizontal) and ellipsoids (axis-aligned); pieces are rotated about z by multiples
  of 90 degrees only, lie inside their room with at least 0.05 m clearance from the
  walls, keep the floor in front of doorways clear and leave the free floor of every
  room connected for a disc-shaped agent of radius `AGENT_RADIUS`.
* Geoms are named "<class>_<k>" with k counting per class, unique in the scene.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional, Sequence

import numpy as np
from scipy import ndimage

from .spec import ROOM_TYPES, Geom, Room, Scene

FLOOR_THICKNESS = 0.1
CEILING_THICKNESS = 0.1
WALL_OVERLAP = 0.05  # walls reach this far into the floor and ceiling slabs
DOOR_HEIGHT = 2.1
DOOR_CLEAR_DEPTH = 0.8  # free floor depth kept in front of each doorway (both sides)
DOOR_CLEAR_MARGIN = 0.1  # extra width of that zone on each side of the opening
WALL_CLEARANCE = 0.06  # furniture distance from walls (>= 0.05 guaranteed)
PIECE_GAP = 0.05  # minimum xy gap between two furniture pieces
AGENT_RADIUS = 0.2
# Disc radii for which each room's free floor must stay one connected component.
FREE_SPACE_RADII = (0.2, 0.25, 0.3)
WIDE_GAP = 0.65  # gaps between furniture and walls are flush or at least this wide
DOOR_POINT_DEPTH = 0.4  # reference point inside the room in front of a doorway

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

# ----------------------------------------------------------------------------------
# Colours
# ----------------------------------------------------------------------------------

_ROOM_PALETTES: dict[str, dict[str, list[tuple[float, float, float]]]] = {
    "bedroom": {
        "wall": [(0.72, 0.78, 0.88), (0.80, 0.74, 0.84), (0.88, 0.84, 0.74)],
        "floor": [(0.66, 0.50, 0.34), (0.74, 0.60, 0.44)],
    },
    "kitchen": {
        "wall": [(0.95, 0.93, 0.78), (0.90, 0.90, 0.88), (0.80, 0.88, 0.80)],
        "floor": [(0.62, 0.62, 0.64), (0.80, 0.78, 0.72)],
    },
    "bathroom": {
        "wall": [(0.70, 0.86, 0.86), (0.92, 0.95, 0.96), (0.75, 0.80, 0.92)],
        "floor": [(0.85, 0.87, 0.90), (0.45, 0.52, 0.60)],
    },
    "living_room": {
        "wall": [(0.92, 0.82, 0.68), (0.88, 0.72, 0.62), (0.84, 0.84, 0.76)],
        "floor": [(0.50, 0.34, 0.22), (0.58, 0.42, 0.28)],
    },
    "dining_room": {
        "wall": [(0.72, 0.82, 0.66), (0.80, 0.55, 0.45), (0.90, 0.86, 0.70)],
        "floor": [(0.60, 0.44, 0.30), (0.46, 0.30, 0.20)],
    },
    "office": {
        "wall": [(0.70, 0.72, 0.74), (0.78, 0.82, 0.86), (0.86, 0.86, 0.82)],
        "floor": [(0.38, 0.42, 0.50), (0.46, 0.46, 0.46)],
    },
    "hallway": {
        "wall": [(0.94, 0.92, 0.88), (0.86, 0.80, 0.70)],
        "floor": [(0.72, 0.46, 0.34), (0.60, 0.58, 0.54)],
    },
}
_CEILING = (0.96, 0.96, 0.94)
_DOOR_FRAME = [(0.95, 0.95, 0.93), (0.55, 0.38, 0.22), (0.35, 0.24, 0.15)]
_WOODS = [(0.55, 0.37, 0.22), (0.40, 0.26, 0.15), (0.72, 0.56, 0.38), (0.30, 0.19, 0.11), (0.62, 0.45, 0.30)]
_FABRICS = [
    (0.62, 0.18, 0.18),
    (0.20, 0.30, 0.58),
    (0.32, 0.50, 0.30),
    (0.62, 0.56, 0.46),
    (0.32, 0.32, 0.35),
    (0.55, 0.40, 0.60),
    (0.80, 0.60, 0.25),
]
_WHITE = (0.93, 0.93, 0.91)
_CERAMIC = (0.97, 0.97, 0.97)
_METAL = (0.70, 0.72, 0.75)
_DARK = (0.10, 0.10, 0.11)
_STONE = [(0.25, 0.25, 0.27), (0.85, 0.83, 0.78), (0.45, 0.40, 0.36)]
_FOLIAGE = [(0.18, 0.48, 0.20), (0.25, 0.55, 0.15), (0.12, 0.38, 0.18)]
_POTS = [(0.70, 0.35, 0.20), (0.85, 0.85, 0.82), (0.25, 0.25, 0.28)]
_SHADES = [(0.98, 0.92, 0.75), (0.95, 0.95, 0.95), (0.90, 0.75, 0.55)]
_RUGS = [(0.60, 0.20, 0.20), (0.25, 0.30, 0.50), (0.75, 0.68, 0.50), (0.35, 0.45, 0.35)]
_WATER = (0.70, 0.85, 0.95)
_MAZE_WALLS = [
    (0.75, 0.30, 0.25),
    (0.85, 0.75, 0.45),
    (0.25, 0.55, 0.55),
    (0.55, 0.45, 0.70),
    (0.45, 0.55, 0.25),
    (0.40, 0.50, 0.75),
    (0.80, 0.55, 0.30),
    (0.60, 0.60, 0.62),
]
_MAZE_OBJECTS = [
    (0.95, 0.15, 0.15),
    (0.15, 0.80, 0.20),
    (0.15, 0.35, 0.95),
    (0.95, 0.85, 0.10),
    (0.90, 0.20, 0.85),
    (0.10, 0.85, 0.85),
    (0.98, 0.55, 0.10),
]


def _color(rng: np.random.Generator, options, jitter: float = 0.04) -> np.ndarray:
    """One colour from `options` (a list of rgb or a single rgb) with seeded jitter."""
    options = list(options)
    base = options[rng.integers(len(options))] if isinstance(options[0], (tuple, list)) else options
    rgb = np.clip(np.asarray(base, np.float64) + rng.uniform(-jitter, jitter, 3), 0.0, 1.0)
    return np.round(np.append(rgb, 1.0), 3)


def _q(v: float, step: float = 0.005) -> float:
    """Round to a grid so that the MJCF text and the geometry agree exactly."""
    return round(round(v / step) * step, 6)


# ----------------------------------------------------------------------------------
# Scene assembly
# ----------------------------------------------------------------------------------


class _Builder:
    """Collects geoms and names them "<class>_<k>"."""

    def __init__(self):
        self.geoms: list[Geom] = []
        self._count: dict[str, int] = {}

    def add(self, gtype, pos, size, rgba, cls, room=-1, quat=None) -> Geom:
        k = self._count.get(cls, 0)
        self._count[cls] = k + 1
        g = Geom(
            type=gtype,
            pos=np.round(np.asarray(pos, np.float64), 6),
            size=np.round(np.asarray(size, np.float64), 6),
            rgba=rgba,
            cls=cls,
            room=room,
            name=f"{cls}_{k}",
        )
        if quat is not None:
            g.quat = np.asarray(quat, np.float64)
        self.geoms.append(g)
        return g

    def slab(self, lo, hi, rgba, cls, room=-1) -> Geom:
        """Axis-aligned box from corner `lo` to corner `hi`."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        if np.any(hi - lo <= 1e-9):
            raise AssertionError(f"degenerate box {lo} {hi} ({cls})")
        return self.add("box", (lo + hi) / 2, (hi - lo) / 2, rgba, cls, room)


# ----------------------------------------------------------------------------------
# Furniture
# ----------------------------------------------------------------------------------

# Quaternions turning a capsule's local z axis onto world x / world y.
_CAPSULE_QUAT = {
    "z": np.array([1.0, 0.0, 0.0, 0.0]),
    "x": np.array([math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0]),
    "y": np.array([math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0]),
}


@dataclasses.dataclass
class _Part:
    """One geom of a furniture piece in the piece's local frame.

    Local frame: the piece's back is towards -y (against a wall), its front faces +y.
    `size` follows MJCF (box half-sizes, sphere radius, capsule radius + half-length,
    ellipsoid radii); `axis` is the capsule's axis.
    """

    type: str
    pos: tuple[float, float, float]
    size: tuple[float, ...]
    rgba: np.ndarray
    cls: str
    axis: str = "z"

    def local_xy_aabb(self) -> tuple[float, float, float, float]:
        x, y, _ = self.pos
        s = self.size
        if self.type == "box" or self.type == "ellipsoid":
            hx, hy = s[0], s[1]
        elif self.type == "sphere":
            hx = hy = s[0]
        else:  # capsule
            r, h = s[0], s[1]
            hx = r + h if self.axis == "x" else r
            hy = r + h if self.axis == "y" else r
        return (x - hx, y - hy, x + hx, y + hy)


@dataclasses.dataclass
class _Piece:
    """A furniture piece: its parts and how it prefers to be placed.

    mode: "wall" (back against a wall), "corner" (back against a wall, in a corner),
    "center" (near the room centre, any 90-degree rotation) or "free".
    """

    name: str
    parts: list[_Part]
    mode: str


def _box(x0, y0, z0, x1, y1, z1, rgba, cls) -> _Part:
    return _Part(
        "box",
        ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
        ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
        rgba,
        cls,
    )


def _vcapsule(x, y, z0, z1, r, rgba, cls) -> _Part:
    """Vertical capsule whose extent (caps included) is z0..z1."""
    return _Part("capsule", (x, y, (z0 + z1) / 2), (r, (z1 - z0) / 2 - r), rgba, cls)


def _u(rng, lo, hi, step=0.01) -> float:
    return _q(rng.uniform(lo, hi), step)


def _f_bed(rng, rw, rd) -> _Piece:
    w = float(rng.choice([1.0, 1.4, 1.6])) if min(rw, rd) >= 2.6 else 1.0
    length = _u(rng, 1.95, 2.1)
    hx, hy = w / 2, length / 2
    wood = _color(rng, _WOODS)
    fabric = _color(rng, _FABRICS)
    head_h = _u(rng, 0.85, 1.1)
    return _Piece(
        "bed",
        [
            _box(-hx, -hy, 0, hx, -hy + 0.08, head_h, wood, "bed"),  # headboard
            _box(-hx, -hy + 0.08, 0, hx, hy, 0.3, wood, "bed"),  # frame
            _box(-hx + 0.03, -hy + 0.08, 0.3, hx - 0.03, hy - 0.03, 0.52, fabric, "bed"),  # mattress
            _Part("ellipsoid", (0, -hy + 0.32, 0.58), (min(0.32, hx - 0.12), 0.15, 0.07), _color(rng, _WHITE), "bed"),
        ],
        "wall",
    )


def _f_wardrobe(rng, rw, rd) -> _Piece:
    w, d, h = _u(rng, 0.9, 1.3), _u(rng, 0.55, 0.62), _u(rng, 1.9, 2.1)
    return _Piece("wardrobe", [_box(-w / 2, -d / 2, 0, w / 2, d / 2, h, _color(rng, _WOODS + [_WHITE]), "wardrobe")], "wall")


def _f_cabinet(rng, rw, rd, small=False) -> _Piece:
    if small:
        w, d, h = _u(rng, 0.4, 0.55), _u(rng, 0.38, 0.45), _u(rng, 0.45, 0.6)
    else:
        w, d, h = _u(rng, 0.8, 1.4), _u(rng, 0.4, 0.5), _u(rng, 0.7, 0.95)
    return _Piece("cabinet", [_box(-w / 2, -d / 2, 0, w / 2, d / 2, h, _color(rng, _WOODS + [_WHITE]), "cabinet")], "wall")


def _f_lamp(rng, rw, rd) -> _Piece:
    shade_r = _u(rng, 0.14, 0.2)
    stand_top = _u(rng, 1.15, 1.4)
    metal = _color(rng, [_METAL, _DARK, (0.75, 0.6, 0.3)])
    return _Piece(
        "lamp",
        [
            _box(-0.13, -0.13, 0, 0.13, 0.13, 0.03, metal, "lamp"),
            _vcapsule(0, 0, 0.03, stand_top, 0.022, metal, "lamp"),
            _Part("sphere", (0, 0, _q(stand_top + 0.6 * shade_r)), (shade_r,), _color(rng, _SHADES), "lamp"),
        ],
        "corner",
    )


def _f_plant(rng, rw, rd) -> _Piece:
    p, ph = _u(rng, 0.12, 0.18), _u(rng, 0.28, 0.45)
    stem = _u(rng, 0.15, 0.4)
    r = _u(rng, 0.22, 0.34)
    pot = _color(rng, _POTS)
    green = _color(rng, _FOLIAGE, 0.06)
    top = ph + stem
    if rng.random() < 0.5:
        foliage = _Part("sphere", (0, 0, _q(top + 0.7 * r)), (r,), green, "plant")
    else:
        rz = _q(1.4 * r, 0.01)
        foliage = _Part("ellipsoid", (0, 0, _q(top + 0.7 * rz)), (r, r, rz), green, "plant")
    return _Piece(
        "plant",
        [
            _box(-p, -p, 0, p, p, ph, pot, "plant"),
            _vcapsule(0, 0, ph, top + 0.05, 0.025, _color(rng, (0.35, 0.25, 0.12)), "plant"),
            foliage,
        ],
        "corner",
    )


def _f_counter(rng, rw, rd) -> _Piece:
    length = _u(rng, 1.4, max(1.45, min(2.6, max(rw, rd) - 1.2)))
    body = _color(rng, _WOODS + [_WHITE, (0.55, 0.65, 0.60)])
    top = _color(rng, _STONE)
    return _Piece(
        "counter",
        [
            _box(-length / 2, -0.3, 0, length / 2, 0.28, 0.86, body, "counter"),
            _box(-length / 2, -0.3, 0.86, length / 2, 0.32, 0.9, top, "counter"),
        ],
        "wall",
    )


def _f_refrigerator(rng, rw, rd) -> _Piece:
    w, h = _u(rng, 0.65, 0.8), _u(rng, 1.7, 1.95)
    body = _color(rng, [_WHITE, _METAL, (0.30, 0.30, 0.32)])
    return _Piece(
        "refrigerator",
        [
            _box(-w / 2, -0.35, 0, w / 2, 0.33, h, body, "refrigerator"),
            _vcapsule(w / 2 - 0.1, 0.345, 0.85, 1.45, 0.018, _color(rng, _METAL), "refrigerator"),
        ],
        "wall",
    )


def _f_stove(rng, rw, rd) -> _Piece:
    w = _u(rng, 0.58, 0.76)
    return _Piece(
        "stove",
        [
            _box(-w / 2, -0.3, 0, w / 2, 0.3, 0.88, _color(rng, [_WHITE, _METAL]), "stove"),
            _box(-w / 2, -0.3, 0.88, w / 2, 0.3, 0.91, _color(rng, _DARK), "stove"),
        ],
        "wall",
    )


def _chair(x, y_front, facing, seat_rgba, back_rgba) -> list[_Part]:
    """Dining chair whose seat starts at y_front and which faces -y (facing=-1) or +y."""
    s = 0.42
    if facing < 0:  # chair on the +y side of a table, looking towards -y
        seat = _box(x - s / 2, y_front, 0, x + s / 2, y_front + s, 0.46, seat_rgba, "chair")
        back = _box(x - s / 2, y_front + s, 0, x + s / 2, y_front + s + 0.05, 0.95, back_rgba, "chair")
    else:
        seat = _box(x - s / 2, y_front - s, 0, x + s / 2, y_front, 0.46, seat_rgba, "chair")
        back = _box(x - s / 2, y_front - s - 0.05, 0, x + s / 2, y_front - s, 0.95, back_rgba, "chair")
    return [seat, back]


def _f_table_chairs(rng, rw, rd, n_chairs=None) -> _Piece:
    if n_chairs is None:
        n_chairs = 4 if min(rw, rd) >= 3.2 and rng.random() < 0.8 else 2
    if n_chairs >= 4:
        # chairs 0.2 m apart: too close for the agent to squeeze in between
        length, width = _u(rng, 1.5, 1.9), _u(rng, 0.85, 1.0)
        xs = [-0.31, 0.31]
    else:
        length, width = _u(rng, 0.9, 1.2), _u(rng, 0.7, 0.8)
        xs = [0.0]
    wood = _color(rng, _WOODS)
    chair_wood = _color(rng, _WOODS)
    seat = _color(rng, _FABRICS) if rng.random() < 0.5 else chair_wood
    hx, hy = length / 2, width / 2
    parts = [
        _box(-hx, -hy, 0.72, hx, hy, 0.76, wood, "table"),
        _box(-hx + 0.06, -hy + 0.08, 0, -hx + 0.11, hy - 0.08, 0.72, wood, "table"),
        _box(hx - 0.11, -hy + 0.08, 0, hx - 0.06, hy - 0.08, 0.72, wood, "table"),
    ]
    for x in xs:
        parts += _chair(_q(x), hy - 0.1, -1, seat, chair_wood)
        parts += _chair(_q(x), -hy + 0.1, +1, seat, chair_wood)
    return _Piece("table_chairs", parts, "center")


def _f_sink(rng, rw, rd) -> _Piece:
    w = _u(rng, 0.55, 0.8)
    return _Piece(
        "sink",
        [
            _box(-w / 2, -0.23, 0, w / 2, 0.23, 0.82, _color(rng, _WOODS + [_WHITE]), "sink"),
            _Part("ellipsoid", (0, 0.02, 0.84), (_q(w / 2 - 0.08, 0.01), 0.16, 0.06), _color(rng, _CERAMIC, 0.02), "sink"),
        ],
        "wall",
    )


def _f_toilet(rng, rw, rd) -> _Piece:
    white = _color(rng, _CERAMIC, 0.02)
    return _Piece(
        "toilet",
        [
            _box(-0.2, -0.35, 0.3, 0.2, -0.17, 0.78, white, "toilet"),
            _Part("ellipsoid", (0, 0.03, 0.2), (0.19, 0.25, 0.2), white, "toilet"),
        ],
        "wall",
    )


def _f_bathtub(rng, rw, rd) -> _Piece:
    length, width = _u(rng, 1.4, 1.7), _u(rng, 0.7, 0.8)
    hx, hy = length / 2, width / 2
    return _Piece(
        "bathtub",
        [
            _box(-hx, -hy, 0, hx, hy, 0.55, _color(rng, _CERAMIC, 0.02), "bathtub"),
            _box(-hx + 0.08, -hy + 0.08, 0.3, hx - 0.08, hy - 0.08, 0.56, _color(rng, _WATER), "bathtub"),
        ],
        "corner",
    )


def _f_sofa(rng, rw, rd) -> _Piece:
    length, depth = _u(rng, 1.6, 2.2), _u(rng, 0.85, 0.95)
    hx, hy = length / 2, depth / 2
    fabric = _color(rng, _FABRICS)
    return _Piece(
        "sofa",
        [
            _box(-hx, -hy, 0, hx, -hy + 0.2, 0.85, fabric, "sofa"),
            _box(-hx, -hy + 0.2, 0, -hx + 0.16, hy, 0.6, fabric, "sofa"),
            _box(hx - 0.16, -hy + 0.2, 0, hx, hy, 0.6, fabric, "sofa"),
            _box(-hx + 0.16, -hy + 0.2, 0, hx - 0.16, hy - 0.02, 0.42, _color(rng, fabric[:3], 0.06), "sofa"),
        ],
        "wall",
    )


def _f_tv(rng, rw, rd) -> _Piece:
    length = _u(rng, 1.2, 1.7)
    tw = _q(min(length - 0.1, rng.uniform(0.9, 1.4)), 0.01)
    th = _q(0.58 * tw, 0.01)
    return _Piece(
        "tv",
        [
            _box(-length / 2, -0.22, 0, length / 2, 0.22, 0.5, _color(rng, _WOODS + [_WHITE, _DARK]), "cabinet"),
            _box(-tw / 2, -0.1, 0.5, tw / 2, -0.04, 0.5 + th, _color(rng, _DARK, 0.02), "tv"),
        ],
        "wall",
    )


def _f_coffee_rug(rng, rw, rd) -> _Piece:
    rl, rwid = _u(rng, 1.4, 2.0), _u(rng, 1.0, 1.4)
    wood = _color(rng, _WOODS)
    return _Piece(
        "coffee_table_rug",
        [
            _box(-rl / 2, -rwid / 2, 0, rl / 2, rwid / 2, 0.01, _color(rng, _RUGS), "rug"),
            _box(-0.5, -0.28, 0.36, 0.5, 0.28, 0.42, wood, "table"),
            _box(-0.4, -0.2, 0.01, 0.4, 0.2, 0.36, wood, "table"),
        ],
        "center",
    )


def _f_rug(rng, rw, rd, runner=False) -> _Piece:
    if runner:
        rl, rwid = _u(rng, 1.4, 2.4), _u(rng, 0.7, 0.9)
    else:
        rl, rwid = _u(rng, 1.2, 1.8), _u(rng, 0.8, 1.2)
    return _Piece("rug", [_box(-rl / 2, -rwid / 2, 0, rl / 2, rwid / 2, 0.01, _color(rng, _RUGS), "rug")], "center")


def _f_desk_chair(rng, rw, rd) -> _Piece:
    length, depth = _u(rng, 1.1, 1.6), _u(rng, 0.6, 0.75)
    hx, hy = length / 2, depth / 2
    wood = _color(rng, _WOODS + [_WHITE])
    chair = _color(rng, [_DARK, (0.20, 0.25, 0.45), (0.45, 0.15, 0.15)])
    return _Piece(
        "desk",
        [
            _box(-hx, -hy, 0.72, hx, hy, 0.76, wood, "desk"),
            _box(-hx, -hy + 0.02, 0, -hx + 0.04, hy - 0.05, 0.72, wood, "desk"),
            _box(hx - 0.04, -hy + 0.02, 0, hx, hy - 0.05, 0.72, wood, "desk"),
            _box(-0.24, hy - 0.1, 0.42, 0.24, hy + 0.38, 0.5, chair, "chair"),
            _vcapsule(0, hy + 0.14, 0.0, 0.42, 0.03, _color(rng, _METAL), "chair"),
            _box(-0.22, hy + 0.38, 0.5, 0.22, hy + 0.43, 1.0, chair, "chair"),
        ],
        "wall",
    )


def _f_shelf(rng, rw, rd) -> _Piece:
    w, h = _u(rng, 0.8, 1.2), _u(rng, 1.5, 2.0)
    return _Piece("shelf", [_box(-w / 2, -0.18, 0, w / 2, 0.16, h, _color(rng, _WOODS + [_WHITE]), "shelf")], "wall")


_Builderfn = Callable[[np.random.Generator, float, float], _Piece]

# Per room type: (builder, probability); probability 1 marks required pieces, which
# are placed first (in list order) and retried harder.
_ROOM_FURNITURE: dict[str, list[tuple[_Builderfn, float]]] = {
    "bedroom": [
        (_f_bed, 1.0),
        (_f_wardrobe, 1.0),
        (lambda r, w, d: _f_cabinet(r, w, d, small=True), 0.6),
        (_f_lamp, 0.8),
        (_f_rug, 0.3),
        (_f_plant, 0.3),
    ],
    "kitchen": [
        (_f_counter, 1.0),
        (_f_refrigerator, 1.0),
        (_f_stove, 1.0),
        (lambda r, w, d: _f_table_chairs(r, w, d, n_chairs=2), 0.8),
        (_f_cabinet, 0.3),
        (_f_plant, 0.2),
    ],
    "bathroom": [
        (_f_toilet, 1.0),
        (_f_sink, 1.0),
        (_f_bathtub, 0.85),
        (lambda r, w, d: _f_cabinet(r, w, d, small=True), 0.3),
        (_f_plant, 0.2),
    ],
    "living_room": [
        (_f_sofa, 1.0),
        (_f_tv, 1.0),
        (_f_coffee_rug, 1.0),
        (_f_plant, 0.7),
        (_f_shelf, 0.4),
        (_f_lamp, 0.4),
    ],
    "dining_room": [
        (_f_table_chairs, 1.0),
        (_f_cabinet, 0.7),
        (_f_plant, 0.5),
        (_f_lamp, 0.3),
    ],
    "office": [
        (_f_desk_chair, 1.0),
        (_f_shelf, 1.0),
        (_f_cabinet, 0.4),
        (_f_plant, 0.5),
        (_f_lamp, 0.3),
    ],
    "hallway": [
        (_f_plant, 0.8),
        (_f_shelf, 0.7),
        (lambda r, w, d: _f_cabinet(r, w, d, small=True), 0.3),
        (lambda r, w, d: _f_rug(r, w, d, runner=True), 0.4),
    ],
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


def _part_world(part: _Part, k: int, cx: float, cy: float):
    """(type, pos, size, quat) of a part placed at (cx, cy) with rotation k."""
    x, y = _rotate_xy(part.pos[0], part.pos[1], k)
    pos = (_q(cx + x, 0.0005), _q(cy + y, 0.0005), part.pos[2])
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
class _Doorway:
    """A doorway seen from one room: wall side, opening interval along the wall."""

    side: str  # "W", "E", "S", "N"
    a0: float
    a1: float


def _door_zone_and_point(rect, door: _Doorway):
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


def _try_place(rng, piece: _Piece, rect, zones, points, placed_rects, obstacles, attempts: int):
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
        cx, cy = _q(cx), _q(cy)
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


def _furnish_room(builder: _Builder, rng, room_index: int, room_type: str, rect, doors: Sequence[_Doorway]):
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
    for make, prob in _ROOM_FURNITURE[room_type]:
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


# ----------------------------------------------------------------------------------
# Houses
# ----------------------------------------------------------------------------------


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
    if not 1.5 <= lo <= hi:
        raise ValueError(f"room_size must be (min, max) with 1.5 <= min <= max, got {room_size}")
    if height < 1.5:
        raise ValueError(f"height must be at least 1.5 m, got {height}")
    t = float(wall_thickness)
    rng = np.random.default_rng(seed)
    widths = [_q(rng.uniform(lo, hi), 0.01) for _ in range(cols)]
    depths = [_q(rng.uniform(lo, hi), 0.01) for _ in range(rows)]
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
    room_doors: dict[tuple[int, int], list[_Doorway]] = {k: [] for k in rects}
    margin = 0.3
    for a, b_ in sorted(door_edges):
        dw = _q(rng.uniform(*door_width), 0.01)
        if a[0] == b_[0]:  # same row: vertical wall line between columns
            r, i = a[0], b_[1]
            s_lo, s_hi = rects[a][1] + margin, rects[a][3] - margin
        else:
            j, c = b_[0], a[1]
            s_lo, s_hi = rects[a][0] + margin, rects[a][2] - margin
        centre = _q(rng.uniform(s_lo + dw / 2, max(s_lo + dw / 2, s_hi - dw / 2)), 0.01)
        opening = (round(centre - dw / 2, 6), round(centre + dw / 2, 6))
        if a[0] == b_[0]:
            vdoor[(r, i)] = opening
            room_doors[a].append(_Doorway("E", *opening))
            room_doors[b_].append(_Doorway("W", *opening))
        else:
            hdoor[(j, c)] = opening
            room_doors[a].append(_Doorway("N", *opening))
            room_doors[b_].append(_Doorway("S", *opening))

    b = _Builder()
    wall_rgba = {}
    for (r, c), ty in zip(sorted(rects), types):
        pal = _ROOM_PALETTES[ty]
        wall_rgba[(r, c)] = _color(rng, pal["wall"], 0.03)
        floor = _color(rng, pal["floor"], 0.04)
        k = rid(r, c)
        b.slab((xs[c], ys[r], -FLOOR_THICKNESS), (xs[c + 1], ys[r + 1], 0.0), floor, "floor", k)
        ceiling = _color(rng, _CEILING, 0.01)
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
    frame_rgba = _color(rng, _DOOR_FRAME, 0.02)
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
            room_doors[key] = [_Doorway(d.side, d.a0 + 0.05, d.a1 - 0.05) for d in room_doors[key]]

    rooms = []
    for (r, c), ty in zip(sorted(rects), types):
        rooms.append(Room(ty, rects[(r, c)]))
        if furniture:
            _furnish_room(b, rng, rid(r, c), ty, rects[(r, c)], room_doors[(r, c)])

    bounds = (round(xs[0] + t / 2, 6), round(ys[0] + t / 2, 6), round(xs[-1] - t / 2, 6), round(ys[-1] - t / 2, 6))
    return Scene(
        name=name or f"house_{seed}",
        geoms=b.geoms,
        rooms=rooms,
        bounds=bounds,
        height=float(height),
        closed=True,
    )


def single_room(
    seed: int,
    size: tuple[float, float] = (4.0, 5.0),
    room_type: Optional[str] = None,
    height: float = 2.6,
    **kwargs,
) -> Scene:
    """One furnished room (in the spirit of an AI2-THOR room).

    size: (min, max) side length in metres; both sides are drawn in that range (pass
    equal values for a fixed square room). room_type: one of the house room types, or
    None for a seeded random choice. Extra keyword arguments go to `house`.
    """
    room_types = None if room_type is None else [room_type]
    kwargs.setdefault("name", f"room_{seed}")
    return house(seed, grid=(1, 1), room_size=size, height=height, room_types=room_types, **kwargs)


# ----------------------------------------------------------------------------------
# Mazes
# ----------------------------------------------------------------------------------


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
    b = _Builder()
    b.slab((xs[0], ys[0], -FLOOR_THICKNESS), (xs[-1], ys[-1], 0.0), _color(rng, [(0.55, 0.52, 0.48), (0.45, 0.45, 0.5)], 0.03), "floor", 0)
    b.slab((xs[0], ys[0], height), (xs[-1], ys[-1], height + CEILING_THICKNESS), _color(rng, _CEILING, 0.01), "ceiling", 0)

    # region colours: zones of about 2x2 cells each get a palette colour
    zx, zy = max(1, math.ceil(nx / 2)), max(1, math.ceil(ny / 2))
    perm = rng.permutation(len(_MAZE_WALLS))
    zone_cols = perm[np.arange(zx * zy).reshape(zx, zy) % len(_MAZE_WALLS)]

    def zone_rgba(px, py):
        i = min(int(px / cs / 2), zx - 1)
        j = min(int(py / cs / 2), zy - 1)
        return _color(rng, _MAZE_WALLS[zone_cols[i, j]], 0.03)

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
        rgba = _color(rng, _MAZE_OBJECTS, 0.03)
        kind = rng.integers(3)
        if kind == 0:
            e = _q(rng.uniform(0.18, 0.28) * scale, 0.01)
            gtype, size, z = "sphere", (e,), e
        elif kind == 1:
            e, rz = _q(rng.uniform(0.15, 0.25) * scale, 0.01), _q(rng.uniform(0.3, 0.45), 0.01)
            gtype, size, z = "ellipsoid", (e, e, rz), rz
        else:
            e = _q(rng.uniform(0.15, 0.25) * scale, 0.01)
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


# ----------------------------------------------------------------------------------
# Batches
# ----------------------------------------------------------------------------------

GENERATORS: dict[str, Callable[..., Scene]] = {"house": house, "room": single_room, "maze": maze}


def make_scenes(kind: str, num: int, seed: int, **kwargs) -> list[Scene]:
    """`num` scenes of one kind ("house", "room" or "maze") with seeds derived from `seed`.

    Scene i uses its own seed drawn from numpy's SeedSequence(seed), so the list is
    reproducible and the scenes differ from each other. kwargs go to the generator.
    """
    if kind not in GENERATORS:
        raise ValueError(f"unknown scene kind {kind!r}; valid kinds: {sorted(GENERATORS)}")
    if num < 0:
        raise ValueError(f"num must be >= 0, got {num}")
    seeds = np.random.SeedSequence(seed).generate_state(max(num, 1), dtype=np.uint32)[:num]
    fn = GENERATORS[kind]
    return [fn(int(s), name=f"{kind}_{seed}_{i}", **kwargs) for i, s in enumerate(seeds)]


__all__ = [
    "AGENT_RADIUS",
    "GENERATORS",
    "HOUSE_ROOM_TYPES",
    "free_space_ok",
    "house",
    "make_scenes",
    "maze",
    "single_room",
]

