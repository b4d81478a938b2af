"""The tour: a baseline that knows the map but not the goal.

On room-type goals it visits the rooms of the house one by one, each time heading for
the room it has not yet looked into that lies nearest (geodesically) when it chooses,
and keeping to it until it has looked, until the episode ends. A room is looked into as
the shortest-path oracle looks at a goal (`oracle.steer`): from within `goals.LOOK_RANGE`
of the objects that show the room's type, facing the nearest of them, and from then on it
acts as the oracle does there (steps forward, or back where that step left the look-out)
for `env.view_steps` + 1 steps, so that the environment's view criterion fires there when the
room is of the target's type. Rooms with nothing that shows their type are never goals
and are skipped. When every room has been looked into without success it starts over.
With `env.stop_action`, where success must be declared, it cannot know where to stop
and stops in the first room it has looked into: it guesses.

It never reads the goal or the target image, so it succeeds by finding alone: its
success rate and SPL are what a searcher that needs no recognition, only a map, reaches
on the task, between the random policy and the oracle. An agent that recognises the
goal but has to search for it in a house it has not seen cannot be expected to beat the
tour's path lengths by much.
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from a2catvn_jax.env import goals as goals_lib, navgrid, rects
from a2catvn_jax.env.navenv import NavEnv, State
from a2catvn_jax.env.oracle import steer
from a2catvn_jax.env.world import World, WorldArrays


@struct.dataclass
class Rooms:
    """Where the tour looks into each room: dist [S, R, H, W] geodesic distance to the
    place it looks from (inf: a room that shows nothing, or padding), heading [S, R, H, W]
    the heading it turns to there, valid [S, R] the rooms it visits."""

    dist: jnp.ndarray
    heading: jnp.ndarray
    valid: jnp.ndarray


@struct.dataclass
class Memory:
    """Per agent: looked [B, R] the rooms looked into this episode; room [B] the room it
    heads for (-1: none chosen yet); dwell [B] steps since it first faced that room's
    objects from its look-out (0: not yet)."""

    looked: jnp.ndarray
    room: jnp.ndarray
    dwell: jnp.ndarray


def applies(cfg) -> bool:
    """Whether the tour can run in an environment of configuration `cfg` (EnvConfig): its
    goals are room types."""
    return cfg.goal == "room"


def check_goal(cfg) -> None:
    """ValueError in one line unless the tour `applies` to `cfg` (EnvConfig)."""
    if not applies(cfg):
        raise ValueError(f"the tour baseline visits rooms and needs room-type goals (env.goal=room), "
                         f"got env.goal={cfg.goal}")


def rooms(world: World) -> Rooms:
    """The look-outs of every room of `world`'s scenes, padded to its arrays' grid shape."""
    check_goal(world.cfg)
    _, H, W = world.arrays.free.shape
    R = max(max(len(s.rooms) for s in world.scenes), 1)
    dist = np.full((len(world.scenes), R, H, W), np.inf, np.float32)
    heading = np.zeros((len(world.scenes), R, H, W), np.float32)
    for k, (scene, grid) in enumerate(zip(world.scenes, world.grids)):
        h, w = grid.shape
        for r, room in enumerate(scene.rooms):
            pieces = goals_lib.room_pieces(scene, room)
            if world.cfg.view_fraction > 0 and not pieces:
                continue
            inside = grid.room == r
            goal = goals_lib.Goal(inside, np.zeros(4), k, room.type,
                                  look=np.array([goals_lib.footprint(g) for g in pieces]).reshape(-1, 4))
            d, yaw = goals_lib.oracle_target(world.cfg, grid, goal, navgrid.geodesic(grid, inside))
            dist[k, r, :h, :w] = d
            heading[k, r, :h, :w] = yaw
    return Rooms(jnp.asarray(dist), jnp.asarray(heading), jnp.asarray(np.isfinite(dist).any((2, 3))))


def initial_memory(num_envs: int, rooms_: Rooms) -> Memory:
    return Memory(jnp.zeros((num_envs, rooms_.dist.shape[1]), bool), jnp.full((num_envs,), -1, jnp.int32),
                  jnp.zeros((num_envs,), jnp.int32))


def tour_actions(env: NavEnv, state: State, memory: Memory, key, rooms_: Rooms,
                 world: Optional[WorldArrays] = None):
    """(actions [B] int32, memory after them) of the tour for the agents of `state`."""
    w = env.world.arrays if world is None else world
    info = state.info
    keys = jax.random.split(key, info.scene.shape[0])
    dwell_needed = env.cfg.view_steps + 1

    def act(scene, pose, looked, room, dwell, k):
        field, valid = rooms_.dist[scene], rooms_.valid[scene]  # [R, H, W], [R]
        looked = jnp.where(jnp.all(looked | ~valid), False, looked)  # every room seen: start over
        # Choose the nearest room not yet looked into (from a cell off the free grid,
        # where no distance is known, the first such room).
        cell = rects.cell_of(pose[:2], w.grid_origin[scene], env.cfg.grid_resolution, field.shape[1:])
        here = jnp.minimum(field[:, cell[0], cell[1]], 1e9)
        nearest = jnp.argmin(jnp.where(looked | ~valid, jnp.inf, here))
        room = jnp.where(room < 0, nearest, room)
        action, settled = steer(env, w, scene, pose, k, field[room], rooms_.heading[scene, room])
        dwell = jnp.where(settled | (dwell > 0), dwell + 1, 0)
        seen = dwell >= dwell_needed
        looked = looked.at[room].set(looked[room] | seen)
        if env.stop_index is not None:
            action = jnp.where(seen, env.stop_index, action).astype(jnp.int32)
        return action, looked, jnp.where(seen, -1, room), jnp.where(seen, 0, dwell)

    action, looked, room, dwell = jax.vmap(act)(info.scene, info.pose, memory.looked, memory.room, memory.dwell, keys)
    return action, Memory(looked, room, dwell)


def after_step(memory: Memory, done) -> Memory:
    """The memory of the agents whose episode ended (`done` [B]) cleared."""
    return Memory(memory.looked & ~done[:, None], jnp.where(done, -1, memory.room), jnp.where(done, 0, memory.dwell))
