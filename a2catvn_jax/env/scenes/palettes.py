"""Colour palettes of the generated scenes and the seeded draw of one colour from them.

Wall and floor palettes per room type give each kind of room its own look; the
material palettes (woods, fabrics, stone, ...) colour furniture; the maze palettes
give maze regions and landmark objects distinct colours.
"""

from __future__ import annotations

import numpy as np

ROOM_PALETTES: dict[str, dict[str, list[tuple[float, float, float]]]] = {
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
CEILING = (0.96, 0.96, 0.94)
DOOR_FRAME = [(0.95, 0.95, 0.93), (0.55, 0.38, 0.22), (0.35, 0.24, 0.15)]
WOODS = [(0.55, 0.37, 0.22), (0.40, 0.26, 0.15), (0.72, 0.56, 0.38), (0.30, 0.19, 0.11), (0.62, 0.45, 0.30)]
FABRICS = [
    (0.62, 0.18, 0.18),
    (0.20, 0.30, 0.58),
    (0.32, 0.50, 0.30),
    (0.62, 0.56, 0.46),
    (0.32, 0.32, 0.35),
    (0.55, 0.40, 0.60),
    (0.80, 0.60, 0.25),
]
WHITE = (0.93, 0.93, 0.91)
CERAMIC = (0.97, 0.97, 0.97)
METAL = (0.70, 0.72, 0.75)
DARK = (0.10, 0.10, 0.11)
STONE = [(0.25, 0.25, 0.27), (0.85, 0.83, 0.78), (0.45, 0.40, 0.36)]
FOLIAGE = [(0.18, 0.48, 0.20), (0.25, 0.55, 0.15), (0.12, 0.38, 0.18)]
POTS = [(0.70, 0.35, 0.20), (0.85, 0.85, 0.82), (0.25, 0.25, 0.28)]
SHADES = [(0.98, 0.92, 0.75), (0.95, 0.95, 0.95), (0.90, 0.75, 0.55)]
RUGS = [(0.60, 0.20, 0.20), (0.25, 0.30, 0.50), (0.75, 0.68, 0.50), (0.35, 0.45, 0.35)]
WATER = (0.70, 0.85, 0.95)
MAZE_WALLS = [
    (0.75, 0.30, 0.25),
    (0.85, 0.75, 0.45),
    (0.25, 0.55, 0.55),
    (0.55, 0.45, 0.70),
    (0.45, 0.55, 0.25),
    (0.40, 0.50, 0.75),
    (0.80, 0.55, 0.30),
    (0.60, 0.60, 0.62),
]
MAZE_OBJECTS = [
    (0.95, 0.15, 0.15),
    (0.15, 0.80, 0.20),
    (0.15, 0.35, 0.95),
    (0.95, 0.85, 0.10),
    (0.90, 0.20, 0.85),
    (0.10, 0.85, 0.85),
    (0.98, 0.55, 0.10),
]


def pick_color(rng: np.random.Generator, options, jitter: float = 0.04) -> np.ndarray:
    """One colour from `options` (a list of rgb or a single rgb) with seeded jitter."""
    options = list(options)
    base = options[rng.integers(len(options))] if isinstance(options[0], (tuple, list)) else options
    rgb = np.clip(np.asarray(base, np.float64) + rng.uniform(-jitter, jitter, 3), 0.0, 1.0)
    return np.round(np.append(rgb, 1.0), 3)


__all__ = [
    "CEILING",
    "CERAMIC",
    "DARK",
    "DOOR_FRAME",
    "FABRICS",
    "FOLIAGE",
    "MAZE_OBJECTS",
    "MAZE_WALLS",
    "METAL",
    "POTS",
    "ROOM_PALETTES",
    "RUGS",
    "SHADES",
    "STONE",
    "WATER",
    "WHITE",
    "WOODS",
    "pick_color",
]
