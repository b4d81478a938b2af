"""What every scene generator shares: geometry conventions, coordinate rounding and
the builder that collects and names geoms.

Conventions of all generated scenes:

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

import numpy as np

from .spec import Geom

FLOOR_THICKNESS = 0.1
CEILING_THICKNESS = 0.1
WALL_OVERLAP = 0.05  # walls reach this far into the floor and ceiling slabs
WALL_CLEARANCE = 0.06  # furniture distance from walls (>= 0.05 guaranteed)
AGENT_RADIUS = 0.2  # the disc-shaped agent the generators plan for


def quantize(v: float, step: float = 0.005) -> float:
    """Round to a grid so that the MJCF text and the geometry agree exactly."""
    return round(round(v / step) * step, 6)


class SceneBuilder:
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


__all__ = [
    "AGENT_RADIUS",
    "CEILING_THICKNESS",
    "FLOOR_THICKNESS",
    "SceneBuilder",
    "WALL_CLEARANCE",
    "WALL_OVERLAP",
    "quantize",
]
