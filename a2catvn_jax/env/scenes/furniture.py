"""Furniture pieces: their parts in the piece's local frame, one maker per kind of
piece, and which pieces each room type holds.

Every maker takes (rng, room width, room depth) and returns a seeded `Piece`;
`placement.furnish_room` decides where the pieces go.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from .builder import quantize
from .palettes import (
    CERAMIC,
    DARK,
    FABRICS,
    FOLIAGE,
    METAL,
    POTS,
    RUGS,
    SHADES,
    STONE,
    WATER,
    WHITE,
    WOODS,
    pick_color,
)


@dataclasses.dataclass
class Part:
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
class Piece:
    """A furniture piece: its parts and how it prefers to be placed.

    mode: "wall" (back against a wall), "corner" (back against a wall, in a corner),
    "center" (near the room centre, any 90-degree rotation) or "free".
    """

    name: str
    parts: list[Part]
    mode: str


def _box(x0, y0, z0, x1, y1, z1, rgba, cls) -> Part:
    return Part(
        "box",
        ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
        ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
        rgba,
        cls,
    )


def _vcapsule(x, y, z0, z1, r, rgba, cls) -> Part:
    """Vertical capsule whose extent (caps included) is z0..z1."""
    return Part("capsule", (x, y, (z0 + z1) / 2), (r, (z1 - z0) / 2 - r), rgba, cls)


def _u(rng, lo, hi, step=0.01) -> float:
    return quantize(rng.uniform(lo, hi), step)


def _f_bed(rng, rw, rd) -> Piece:
    w = float(rng.choice([1.0, 1.4, 1.6])) if min(rw, rd) >= 2.6 else 1.0
    length = _u(rng, 1.95, 2.1)
    hx, hy = w / 2, length / 2
    wood = pick_color(rng, WOODS)
    fabric = pick_color(rng, FABRICS)
    head_h = _u(rng, 0.85, 1.1)
    return Piece(
        "bed",
        [
            _box(-hx, -hy, 0, hx, -hy + 0.08, head_h, wood, "bed"),  # headboard
            _box(-hx, -hy + 0.08, 0, hx, hy, 0.3, wood, "bed"),  # frame
            _box(-hx + 0.03, -hy + 0.08, 0.3, hx - 0.03, hy - 0.03, 0.52, fabric, "bed"),  # mattress
            Part("ellipsoid", (0, -hy + 0.32, 0.58), (min(0.32, hx - 0.12), 0.15, 0.07), pick_color(rng, WHITE), "bed"),
        ],
        "wall",
    )


def _f_wardrobe(rng, rw, rd) -> Piece:
    w, d, h = _u(rng, 0.9, 1.3), _u(rng, 0.55, 0.62), _u(rng, 1.9, 2.1)
    return Piece("wardrobe", [_box(-w / 2, -d / 2, 0, w / 2, d / 2, h, pick_color(rng, WOODS + [WHITE]), "wardrobe")], "wall")


def _f_cabinet(rng, rw, rd, small=False) -> Piece:
    if small:
        w, d, h = _u(rng, 0.4, 0.55), _u(rng, 0.38, 0.45), _u(rng, 0.45, 0.6)
    else:
        w, d, h = _u(rng, 0.8, 1.4), _u(rng, 0.4, 0.5), _u(rng, 0.7, 0.95)
    return Piece("cabinet", [_box(-w / 2, -d / 2, 0, w / 2, d / 2, h, pick_color(rng, WOODS + [WHITE]), "cabinet")], "wall")


def _f_lamp(rng, rw, rd) -> Piece:
    shade_r = _u(rng, 0.14, 0.2)
    stand_top = _u(rng, 1.15, 1.4)
    metal = pick_color(rng, [METAL, DARK, (0.75, 0.6, 0.3)])
    return Piece(
        "lamp",
        [
            _box(-0.13, -0.13, 0, 0.13, 0.13, 0.03, metal, "lamp"),
            _vcapsule(0, 0, 0.03, stand_top, 0.022, metal, "lamp"),
            Part("sphere", (0, 0, quantize(stand_top + 0.6 * shade_r)), (shade_r,), pick_color(rng, SHADES), "lamp"),
        ],
        "corner",
    )


def _f_plant(rng, rw, rd) -> Piece:
    p, ph = _u(rng, 0.12, 0.18), _u(rng, 0.28, 0.45)
    stem = _u(rng, 0.15, 0.4)
    r = _u(rng, 0.22, 0.34)
    pot = pick_color(rng, POTS)
    green = pick_color(rng, FOLIAGE, 0.06)
    top = ph + stem
    if rng.random() < 0.5:
        foliage = Part("sphere", (0, 0, quantize(top + 0.7 * r)), (r,), green, "plant")
    else:
        rz = quantize(1.4 * r, 0.01)
        foliage = Part("ellipsoid", (0, 0, quantize(top + 0.7 * rz)), (r, r, rz), green, "plant")
    return Piece(
        "plant",
        [
            _box(-p, -p, 0, p, p, ph, pot, "plant"),
            _vcapsule(0, 0, ph, top + 0.05, 0.025, pick_color(rng, (0.35, 0.25, 0.12)), "plant"),
            foliage,
        ],
        "corner",
    )


def _f_counter(rng, rw, rd) -> Piece:
    length = _u(rng, 1.4, max(1.45, min(2.6, max(rw, rd) - 1.2)))
    body = pick_color(rng, WOODS + [WHITE, (0.55, 0.65, 0.60)])
    top = pick_color(rng, STONE)
    return Piece(
        "counter",
        [
            _box(-length / 2, -0.3, 0, length / 2, 0.28, 0.86, body, "counter"),
            _box(-length / 2, -0.3, 0.86, length / 2, 0.32, 0.9, top, "counter"),
        ],
        "wall",
    )


def _f_refrigerator(rng, rw, rd) -> Piece:
    w, h = _u(rng, 0.65, 0.8), _u(rng, 1.7, 1.95)
    body = pick_color(rng, [WHITE, METAL, (0.30, 0.30, 0.32)])
    return Piece(
        "refrigerator",
        [
            _box(-w / 2, -0.35, 0, w / 2, 0.33, h, body, "refrigerator"),
            _vcapsule(w / 2 - 0.1, 0.345, 0.85, 1.45, 0.018, pick_color(rng, METAL), "refrigerator"),
        ],
        "wall",
    )


def _f_stove(rng, rw, rd) -> Piece:
    w = _u(rng, 0.58, 0.76)
    return Piece(
        "stove",
        [
            _box(-w / 2, -0.3, 0, w / 2, 0.3, 0.88, pick_color(rng, [WHITE, METAL]), "stove"),
            _box(-w / 2, -0.3, 0.88, w / 2, 0.3, 0.91, pick_color(rng, DARK), "stove"),
        ],
        "wall",
    )


def _chair(x, y_front, facing, seat_rgba, back_rgba) -> list[Part]:
    """Dining chair whose seat starts at y_front and which faces -y (facing=-1) or +y."""
    s = 0.42
    if facing < 0:  # chair on the +y side of a table, looking towards -y
        seat = _box(x - s / 2, y_front, 0, x + s / 2, y_front + s, 0.46, seat_rgba, "chair")
        back = _box(x - s / 2, y_front + s, 0, x + s / 2, y_front + s + 0.05, 0.95, back_rgba, "chair")
    else:
        seat = _box(x - s / 2, y_front - s, 0, x + s / 2, y_front, 0.46, seat_rgba, "chair")
        back = _box(x - s / 2, y_front - s - 0.05, 0, x + s / 2, y_front - s, 0.95, back_rgba, "chair")
    return [seat, back]


def _f_table_chairs(rng, rw, rd, n_chairs=None) -> Piece:
    if n_chairs is None:
        n_chairs = 4 if min(rw, rd) >= 3.2 and rng.random() < 0.8 else 2
    if n_chairs >= 4:
        # chairs 0.2 m apart: too close for the agent to squeeze in between
        length, width = _u(rng, 1.5, 1.9), _u(rng, 0.85, 1.0)
        xs = [-0.31, 0.31]
    else:
        length, width = _u(rng, 0.9, 1.2), _u(rng, 0.7, 0.8)
        xs = [0.0]
    wood = pick_color(rng, WOODS)
    chair_wood = pick_color(rng, WOODS)
    seat = pick_color(rng, FABRICS) if rng.random() < 0.5 else chair_wood
    hx, hy = length / 2, width / 2
    parts = [
        _box(-hx, -hy, 0.72, hx, hy, 0.76, wood, "table"),
        _box(-hx + 0.06, -hy + 0.08, 0, -hx + 0.11, hy - 0.08, 0.72, wood, "table"),
        _box(hx - 0.11, -hy + 0.08, 0, hx - 0.06, hy - 0.08, 0.72, wood, "table"),
    ]
    for x in xs:
        parts += _chair(quantize(x), hy - 0.1, -1, seat, chair_wood)
        parts += _chair(quantize(x), -hy + 0.1, +1, seat, chair_wood)
    return Piece("table_chairs", parts, "center")


def _f_sink(rng, rw, rd) -> Piece:
    w = _u(rng, 0.55, 0.8)
    return Piece(
        "sink",
        [
            _box(-w / 2, -0.23, 0, w / 2, 0.23, 0.82, pick_color(rng, WOODS + [WHITE]), "sink"),
            Part("ellipsoid", (0, 0.02, 0.84), (quantize(w / 2 - 0.08, 0.01), 0.16, 0.06), pick_color(rng, CERAMIC, 0.02), "sink"),
        ],
        "wall",
    )


def _f_toilet(rng, rw, rd) -> Piece:
    white = pick_color(rng, CERAMIC, 0.02)
    return Piece(
        "toilet",
        [
            _box(-0.2, -0.35, 0.3, 0.2, -0.17, 0.78, white, "toilet"),
            Part("ellipsoid", (0, 0.03, 0.2), (0.19, 0.25, 0.2), white, "toilet"),
        ],
        "wall",
    )


def _f_bathtub(rng, rw, rd) -> Piece:
    length, width = _u(rng, 1.4, 1.7), _u(rng, 0.7, 0.8)
    hx, hy = length / 2, width / 2
    return Piece(
        "bathtub",
        [
            _box(-hx, -hy, 0, hx, hy, 0.55, pick_color(rng, CERAMIC, 0.02), "bathtub"),
            _box(-hx + 0.08, -hy + 0.08, 0.3, hx - 0.08, hy - 0.08, 0.56, pick_color(rng, WATER), "bathtub"),
        ],
        "corner",
    )


def _f_sofa(rng, rw, rd) -> Piece:
    length, depth = _u(rng, 1.6, 2.2), _u(rng, 0.85, 0.95)
    hx, hy = length / 2, depth / 2
    fabric = pick_color(rng, FABRICS)
    return Piece(
        "sofa",
        [
            _box(-hx, -hy, 0, hx, -hy + 0.2, 0.85, fabric, "sofa"),
            _box(-hx, -hy + 0.2, 0, -hx + 0.16, hy, 0.6, fabric, "sofa"),
            _box(hx - 0.16, -hy + 0.2, 0, hx, hy, 0.6, fabric, "sofa"),
            _box(-hx + 0.16, -hy + 0.2, 0, hx - 0.16, hy - 0.02, 0.42, pick_color(rng, fabric[:3], 0.06), "sofa"),
        ],
        "wall",
    )


def _f_tv(rng, rw, rd) -> Piece:
    length = _u(rng, 1.2, 1.7)
    tw = quantize(min(length - 0.1, rng.uniform(0.9, 1.4)), 0.01)
    th = quantize(0.58 * tw, 0.01)
    return Piece(
        "tv",
        [
            _box(-length / 2, -0.22, 0, length / 2, 0.22, 0.5, pick_color(rng, WOODS + [WHITE, DARK]), "cabinet"),
            _box(-tw / 2, -0.1, 0.5, tw / 2, -0.04, 0.5 + th, pick_color(rng, DARK, 0.02), "tv"),
        ],
        "wall",
    )


def _f_coffee_rug(rng, rw, rd) -> Piece:
    rl, rwid = _u(rng, 1.4, 2.0), _u(rng, 1.0, 1.4)
    wood = pick_color(rng, WOODS)
    return Piece(
        "coffee_table_rug",
        [
            _box(-rl / 2, -rwid / 2, 0, rl / 2, rwid / 2, 0.01, pick_color(rng, RUGS), "rug"),
            _box(-0.5, -0.28, 0.36, 0.5, 0.28, 0.42, wood, "table"),
            _box(-0.4, -0.2, 0.01, 0.4, 0.2, 0.36, wood, "table"),
        ],
        "center",
    )


def _f_rug(rng, rw, rd, runner=False) -> Piece:
    if runner:
        rl, rwid = _u(rng, 1.4, 2.4), _u(rng, 0.7, 0.9)
    else:
        rl, rwid = _u(rng, 1.2, 1.8), _u(rng, 0.8, 1.2)
    return Piece("rug", [_box(-rl / 2, -rwid / 2, 0, rl / 2, rwid / 2, 0.01, pick_color(rng, RUGS), "rug")], "center")


def _f_desk_chair(rng, rw, rd) -> Piece:
    length, depth = _u(rng, 1.1, 1.6), _u(rng, 0.6, 0.75)
    hx, hy = length / 2, depth / 2
    wood = pick_color(rng, WOODS + [WHITE])
    chair = pick_color(rng, [DARK, (0.20, 0.25, 0.45), (0.45, 0.15, 0.15)])
    return Piece(
        "desk",
        [
            _box(-hx, -hy, 0.72, hx, hy, 0.76, wood, "desk"),
            _box(-hx, -hy + 0.02, 0, -hx + 0.04, hy - 0.05, 0.72, wood, "desk"),
            _box(hx - 0.04, -hy + 0.02, 0, hx, hy - 0.05, 0.72, wood, "desk"),
            _box(-0.24, hy - 0.1, 0.42, 0.24, hy + 0.38, 0.5, chair, "chair"),
            _vcapsule(0, hy + 0.14, 0.0, 0.42, 0.03, pick_color(rng, METAL), "chair"),
            _box(-0.22, hy + 0.38, 0.5, 0.22, hy + 0.43, 1.0, chair, "chair"),
        ],
        "wall",
    )


def _f_shelf(rng, rw, rd) -> Piece:
    w, h = _u(rng, 0.8, 1.2), _u(rng, 1.5, 2.0)
    return Piece("shelf", [_box(-w / 2, -0.18, 0, w / 2, 0.16, h, pick_color(rng, WOODS + [WHITE]), "shelf")], "wall")


PieceMaker = Callable[[np.random.Generator, float, float], Piece]

# Per room type: (maker, probability); probability 1 marks required pieces, which
# are placed first (in list order) and retried harder.
ROOM_FURNITURE: dict[str, list[tuple[PieceMaker, float]]] = {
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


__all__ = [
    "Part",
    "Piece",
    "PieceMaker",
    "ROOM_FURNITURE",
]
