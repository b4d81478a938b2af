"""Goals of a batch of scenes, drawn once on the host: where success is, where the target
image is taken, what shows the goal, and where the shortest-path oracle heads.

Goal kinds (`env.goal`): an image goal (success within `env.success_distance` of where
the target image was taken), a room-type goal (success in any room of the target's
type; the image is taken in another room of that type) and an object goal (success
within `env.object_distance` of the object in the image).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import mujoco
import numpy as np

from a2catvn_jax.config import EnvConfig
from a2catvn_jax.env import navgrid, rects
from a2catvn_jax.env.scenes.errors import SceneError
from a2catvn_jax.env.scenes.mjcf import geom_aabb
from a2catvn_jax.env.scenes.spec import ROOM_TARGET_CLASSES, STRUCTURAL_CLASSES, Scene

GOAL_KINDS = ("image", "room", "object")
LOOK_RANGE = 1.5  # metres: the shortest-path oracle looks at a room goal's objects from this close
PIECE_GAP = 0.05  # metres: geoms of one class this close to an object goal's geom are parts of the same object


@dataclasses.dataclass
class Goal:
    success: np.ndarray  # bool [H, W]
    pose: np.ndarray  # (x, y, yaw, tilt) of the target image camera
    scene: int  # scene the target image is taken in
    label: str
    classes: tuple[str, ...] = ()  # semantic classes whose pixels show the goal (room goals)
    geoms: tuple[str, ...] = ()  # names of the geoms whose pixels show the goal (object goals)
    look: Optional[np.ndarray] = None  # footprints [K, 4] of what shows the goal; None: face `pose`'s heading


def random_free_pose(grid: navgrid.NavGrid, rng, mask: Optional[np.ndarray] = None) -> np.ndarray:
    """(x, y, yaw, 0) at the centre of a free cell of `grid` (within `mask` when it has one)."""
    cells = np.flatnonzero(grid.free & (mask if mask is not None else True))
    if cells.size == 0:
        cells = np.flatnonzero(grid.free)
    c = grid.centres().reshape(-1, 2)[rng.choice(cells)]
    return np.array([c[0], c[1], rng.uniform(-np.pi, np.pi), 0.0])


def draw_goals(cfg: EnvConfig, scenes: list[Scene], grids: list[navgrid.NavGrid], models: list[mujoco.MjModel],
               k: int, rng) -> list[Goal]:
    """`cfg.goals_per_scene` goals of scene `k` (room-type goals take their target image
    in another scene of the batch when one has a room of that type)."""
    scene, grid = scenes[k], grids[k]
    centres = grid.centres()
    goals = []
    for _ in range(cfg.goals_per_scene):
        if cfg.goal == "image":
            pose = random_free_pose(grid, rng)
            near = np.hypot(*(centres - pose[:2]).transpose(2, 0, 1)) <= cfg.success_distance
            goals.append(Goal(near, pose, k, "image"))
        elif cfg.goal == "room":
            goals.append(_room_goal(cfg, scenes, grids, k, rng))
        else:
            goals.append(_object_goal(cfg, scene, grid, models[k], k, rng))
    return goals


def _room_goal(cfg: EnvConfig, scenes: list[Scene], grids: list[navgrid.NavGrid], k: int, rng) -> Goal:
    scene, grid = scenes[k], grids[k]
    if not scene.rooms:
        raise SceneError(f"scene {scene.name!r} has no rooms: room-type goals need houses")
    candidates = scene.rooms
    if cfg.view_fraction > 0:  # only rooms with something that shows their type
        candidates = [r for r in scene.rooms if room_pieces(scene, r)]
        if not candidates:
            raise SceneError(f"scene {scene.name!r} has no room with objects that show its type "
                             f"(room-type goals with env.view_fraction > 0)")
    rtype = candidates[rng.integers(len(candidates))].type
    rooms = [i for i, r in enumerate(scene.rooms) if r.type == rtype]
    success = np.isin(grid.room, rooms)
    # The target image is taken in another room of that type: in another scene of the
    # batch if one has such a room, else in this one.
    others = [(j, i) for j, s in enumerate(scenes) for i, r in enumerate(s.rooms) if r.type == rtype and j != k]
    if others:
        j, i = others[rng.integers(len(others))]
    else:
        j, i = k, rooms[rng.integers(len(rooms))]
    pose = random_free_pose(grids[j], rng, grids[j].room == i)
    look = [footprint(g) for r in rooms for g in room_pieces(scene, scene.rooms[r])]
    return Goal(success, pose, j, rtype, classes=ROOM_TARGET_CLASSES.get(rtype, ()), look=np.array(look).reshape(-1, 4))


def _object_goal(cfg: EnvConfig, scene: Scene, grid: navgrid.NavGrid, model: mujoco.MjModel, k: int, rng) -> Goal:
    objs = [g for g in scene.geoms if g.cls not in STRUCTURAL_CLASSES and g.cls != "rug"]
    if not objs:
        raise SceneError(f"scene {scene.name!r} has no objects for object goals")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    centres = grid.centres()
    for _ in range(50):
        obj = objs[rng.integers(len(objs))]
        lo, hi = geom_aabb(obj)
        dist = rects.distance(centres, np.array([lo[0], lo[1], hi[0], hi[1]]))
        success = dist <= cfg.object_distance
        view = grid.free & (dist >= 0.6) & (dist <= 2.0)
        target = (lo + hi) / 2
        for c in rng.permutation(np.argwhere(view))[:20]:
            eye = np.array([*centres[c[0], c[1]], cfg.camera_height])
            vec = target - eye
            gid = np.zeros(1, np.int32)
            mujoco.mj_ray(model, data, eye, vec / np.linalg.norm(vec), None, 1, -1, gid)
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(gid[0])) if gid[0] >= 0 else None
            if name == obj.name and success.any() and (success & grid.free).any():
                yaw = np.arctan2(vec[1], vec[0])
                tilt = np.clip(np.arctan2(vec[2], np.hypot(vec[0], vec[1])), -0.5, 0.5)
                parts = [g for g in objs if g.cls == obj.cls and _gap(geom_aabb(g), (lo, hi)) <= PIECE_GAP]
                return Goal(success, np.array([eye[0], eye[1], yaw, tilt]), k, obj.name,
                            geoms=tuple(g.name for g in parts), look=np.array([footprint(g) for g in parts]))
    raise SceneError(f"scene {scene.name!r}: found no visible object for an object goal")


def oracle_target(cfg: EnvConfig, grid: navgrid.NavGrid, goal: Goal, goal_dist: np.ndarray):
    """(geodesic distance [H, W] to where the oracle heads, heading [H, W] it turns to
    there). Goals that must be seen: the cells of the goal region within `LOOK_RANGE`
    of what shows the goal (the region itself when no such cell is free), facing the
    nearest of those objects; other goals: the goal region, facing the target
    image's heading."""
    seen = cfg.view_fraction > 0 and cfg.goal in ("room", "object")
    if not seen or goal.look is None or len(goal.look) == 0:
        return goal_dist, np.full(grid.shape, goal.pose[2])
    centres = grid.centres()
    dist = rects.distance(centres[..., None, :], goal.look)  # [H, W, K]
    region = goal.success & grid.free & (dist.min(-1) <= LOOK_RANGE)
    d = navgrid.geodesic(grid, region) if region.any() else goal_dist
    nearest = goal.look[dist.argmin(-1)]  # [H, W, 4]
    to = (nearest[..., :2] + nearest[..., 2:]) / 2 - centres
    return d, np.arctan2(to[..., 1], to[..., 0])


def footprint(g) -> np.ndarray:
    """A geom's xy footprint (x0, y0, x1, y1)."""
    lo, hi = geom_aabb(g)
    return np.array([lo[0], lo[1], hi[0], hi[1]])


def _gap(a, b) -> float:
    """The largest per-axis gap between two AABBs (lo, hi): <= 0 where they overlap."""
    return float(np.max(np.maximum(a[0] - b[1], b[0] - a[1])))


def room_pieces(scene: Scene, room) -> list:
    """The geoms that show a room's type (`ROOM_TARGET_CLASSES`) whose centre lies in it."""
    classes = ROOM_TARGET_CLASSES.get(room.type, ())
    x0, y0, x1, y1 = room.rect
    return [g for g in scene.geoms if g.cls in classes and x0 <= g.pos[0] < x1 and y0 <= g.pos[1] < y1]
