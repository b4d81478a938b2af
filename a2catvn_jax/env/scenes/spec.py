"""Host-side scene description: geoms with semantic classes, rooms, bounds.

A `Scene` is plain numpy/Python data. Generators build it, `mjcf.py` turns it into
an MJCF string that MuJoCo compiles, and `batch.py` packs compiled scenes into the
arrays the renderer and the environment consume.
"""

from __future__ import annotations

import colorsys
import dataclasses
from typing import Optional

import numpy as np

# Semantic classes. Index 0 is "nothing hit". Names are also the prefixes that
# user-supplied MJCF geom names carry ("bed", "bed_2", "bed/left" are all class bed).
CLASS_NAMES: tuple[str, ...] = (
    "void",
    "wall",
    "floor",
    "ceiling",
    "door_frame",
    "bed",
    "sofa",
    "table",
    "chair",
    "sink",
    "toilet",
    "bathtub",
    "cabinet",
    "shelf",
    "tv",
    "plant",
    "lamp",
    "refrigerator",
    "stove",
    "desk",
    "wardrobe",
    "rug",
    "counter",
    "pillar",
    "object",
)
NUM_CLASSES = len(CLASS_NAMES)
CLASS_ID = {name: i for i, name in enumerate(CLASS_NAMES)}
# Classes that make up the building rather than its contents.
STRUCTURAL_CLASSES = frozenset({"wall", "floor", "ceiling", "door_frame", "pillar"})

ROOM_TYPES: tuple[str, ...] = (
    "bedroom",
    "kitchen",
    "bathroom",
    "living_room",
    "dining_room",
    "office",
    "hallway",
    "maze",
)
ROOM_TYPE_ID = {name: i for i, name in enumerate(ROOM_TYPES)}
# What shows a room's type: the classes of the pieces every room of that type is given
# (hallways have none, so they are never room-type goals that must be seen). A room-type
# goal with a view criterion is reached in a room of its type with these in sight.
ROOM_TARGET_CLASSES: dict[str, tuple[str, ...]] = {
    "bedroom": ("bed", "wardrobe"),
    "kitchen": ("counter", "refrigerator", "stove"),
    "bathroom": ("toilet", "sink", "bathtub"),
    "living_room": ("sofa", "tv"),
    "dining_room": ("table", "chair"),
    "office": ("desk", "shelf"),
}

GEOM_TYPES = ("box", "sphere", "capsule", "ellipsoid")


def half_extents(gtype: str, rot: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Half-sizes [3] along the world axes of the axis-aligned box around a geom of type
    `gtype` with world-from-local rotation `rot` [3, 3] and MuJoCo size parameters `size`
    (exact for every type: a box's corners, an ellipsoid's support along each axis, a
    capsule's segment grown by its radius)."""
    if gtype == "box":
        return np.abs(rot) @ size[:3]
    if gtype == "sphere":
        return np.full(3, size[0])
    if gtype == "capsule":  # along local z
        return np.abs(rot[:, 2]) * size[1] + size[0]
    return np.sqrt((rot**2) @ (size[:3] ** 2))  # ellipsoid


def class_of_name(name: str) -> int:
    """Semantic class id of a geom name, 0 if none.

    A name is of class C when it is C or starts with "C_" or "C/" ("bed", "bed_2",
    "door_frame/left"); the longest matching class wins.
    """
    best = ""
    for cname in CLASS_NAMES[1:]:
        if name == cname or name.startswith((cname + "_", cname + "/")):
            if len(cname) > len(best):
                best = cname
    return CLASS_ID[best] if best else 0


def class_colors(num_classes: int = NUM_CLASSES) -> np.ndarray:
    """Class-to-colour table [num_classes, 3] (uint8), hues spread evenly.

    Class 0 ("void") is black; the others take hues i/(n-1) at full saturation and
    brightness, which maximises their pairwise distance in hue as in the paper.
    """
    colors = np.zeros((num_classes, 3), np.uint8)
    for i in range(1, num_classes):
        r, g, b = colorsys.hsv_to_rgb((i - 1) / (num_classes - 1), 1.0, 1.0)
        colors[i] = np.round(np.array([r, g, b]) * 255).astype(np.uint8)
    return colors


@dataclasses.dataclass
class Geom:
    """One static geom. `size` follows MJCF: box half-sizes, sphere (r, 0, 0),
    capsule (r, half-length, 0), ellipsoid radii."""

    type: str
    pos: np.ndarray
    size: np.ndarray
    rgba: np.ndarray
    cls: str
    quat: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    room: int = -1
    name: Optional[str] = None
    # The MuJoCo type of a user's geom that only the `mjx` backend renders (mesh,
    # cylinder, plane); the geom is then its world bounding box (`type` box), which is
    # what the occupancy grid and the goals use, and the scene keeps its own model.
    native: Optional[str] = None
    # The geom's body moves (it or an ancestor has a hinge or slide joint): `pos` and
    # `quat` are its pose at the model's reference configuration (qpos0). Moving geoms
    # are not in the occupancy grid; the environment places them per episode.
    moving: bool = False

    def __post_init__(self):
        if self.type not in GEOM_TYPES:
            raise ValueError(f"geom type {self.type!r} not supported; use one of {GEOM_TYPES}")
        if self.cls not in CLASS_ID:
            raise ValueError(f"unknown semantic class {self.cls!r}; known: {CLASS_NAMES[1:]}")
        self.pos = np.asarray(self.pos, np.float64).reshape(3)
        self.size = np.asarray(self.size, np.float64).reshape(-1)
        self.size = np.pad(self.size, (0, 3 - self.size.size))
        self.rgba = np.asarray(self.rgba, np.float64).reshape(4)
        self.quat = np.asarray(self.quat, np.float64).reshape(4)


@dataclasses.dataclass
class Room:
    """An axis-aligned rectangular room: (x0, y0, x1, y1) of its free interior."""

    type: str
    rect: tuple[float, float, float, float]

    def __post_init__(self):
        if self.type not in ROOM_TYPE_ID:
            raise ValueError(f"unknown room type {self.type!r}; known: {ROOM_TYPES}")


@dataclasses.dataclass
class Scene:
    """An indoor scene (static, or with a user's bodies on hinge and slide joints).

    bounds: (x0, y0, x1, y1) of the walkable footprint (everything the agent may reach
      lies inside). height: ceiling height (floor top is z=0).
    closed: True when floor and ceiling cover the whole footprint and every geom of
      class wall spans floor to ceiling; the renderer then uses walls as exact 2D
      occluders. Generated houses are closed; user scenes are not assumed to be.
    source: a user's MJCF ("file", path) or ("xml", text) that the scene's model is
      compiled from as it is (with the agent added), for scenes with geoms of a type
      only the `mjx` backend renders (`Geom.native`) or with moving bodies
      (`Geom.moving`); None: the model is written from `geoms` (`mjcf.scene_to_mjcf`).
    """

    name: str
    geoms: list[Geom]
    rooms: list[Room]
    bounds: tuple[float, float, float, float]
    height: float
    closed: bool = False
    source: Optional[tuple[str, str]] = None


SEGMENTATION_COLORS = class_colors()  # the paper's colour of each class, what the segmentation heads regress
