"""The shortest-path oracle: a baseline that knows the map and the goal.

Each step it looks one move ahead on the occupancy grid. Outside the place it heads for
(`WorldArrays.oracle_dist`: the goal region, or for goals that must be seen the part of
it within sight of what shows them) it takes the move whose noise-free end point lies
geodesically closest to that place, counting the metres walked beyond the progress made
(so that it arrives with the shortest move that does); a turn is scored by the move
forward that would follow it, and moves win ties, so it turns only to face a better way. There it turns
to the heading it should face (`oracle_yaw`: the target image's, or towards the object
it should see) and then steps forward, which keeps that object in sight. Where no move
brings it closer it acts at random, which frees it from the rare corner that a move of
fixed length cannot leave. It never tilts the camera. With `env.stop_action` it stops
as soon as stopping succeeds (`NavEnv.goal_reached`).

Its success rate is the ceiling of a task and its SPL checks the SPL computation: on
image goals it follows the geodesic up to the motion noise and the moves' fixed length.
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.env import rects
from a2catvn_jax.env.navenv import NavEnv, State
from a2catvn_jax.env.world import WorldArrays

_TURN_PENALTY = 1e-3  # metres per turn: of equal ways, the one with fewer turns wins, and moves win over turns


def oracle_actions(env: NavEnv, state: State, key, world: Optional[WorldArrays] = None):
    """The oracle's actions [B] int32 for the agents of `state` in `world` (default: the
    environment's own)."""
    w = env.world.arrays if world is None else world
    info = state.info
    keys = jax.random.split(key, info.scene.shape[0])

    def act(scene, goal, pose, k):
        return steer(env, w, scene, pose, k, w.oracle_dist[scene, goal], w.oracle_yaw[scene, goal])[0]

    action = jax.vmap(act)(info.scene, info.goal, info.pose, keys)
    if env.stop_index is None:
        return action
    return jnp.where(env.goal_reached(state, w), env.stop_index, action).astype(jnp.int32)


def steer(env: NavEnv, w: WorldArrays, scene, pose, key, field, heading):
    """(action, settled) of one agent at `pose` in `scene` heading for the place where
    geodesic distance `field` [H, W] is 0 and there turning to `heading` [H, W]: the
    oracle's rule above for any such place. settled: it is there and faces that way."""
    moves = jnp.asarray(env.moves)  # [A, 4]: forward, left, rotate, tilt
    res = env.cfg.grid_resolution

    def cell(p):
        return rects.cell_of(p[:2], w.grid_origin[scene], res, field.shape)

    def dist_at(p):
        return field[cell(p)]

    A = moves.shape[0]
    forward = jnp.argmax(moves[:, 0])
    ends = jax.vmap(lambda a: env.preview(scene, pose, a, w))(jnp.arange(A))
    translates = (moves[:, 0] != 0) | (moves[:, 1] != 0)
    turns = moves[:, 2] != 0
    # A turn is worth the best move forward after turning that way 1 .. n times (n turns
    # make half a circle); each further turn costs a little, turns walk no distance.
    smallest_turn = float(np.min(np.abs(env.moves[:, 2][env.moves[:, 2] != 0])))
    n = int(np.ceil(np.pi / smallest_turn))
    k = jnp.arange(1, n + 1, dtype=jnp.float32)

    def after_turns(rotation):
        yaws = pose[2] + k * rotation
        starts = jnp.concatenate([jnp.broadcast_to(pose[:2], (n, 2)), yaws[:, None],
                                  jnp.broadcast_to(pose[3:], (n, 1))], -1)
        ahead = jax.vmap(lambda p: dist_at(env.preview(scene, p, forward, w)))(starts) + k * _TURN_PENALTY
        return jnp.min(ahead)

    ahead = jax.vmap(after_turns)(moves[:, 2])
    # Where each action leads (a turn: the move forward after it) and the metres walked.
    reach = jnp.where(translates, jax.vmap(dist_at)(ends), jnp.where(turns, ahead, jnp.inf))
    walk = jnp.where(translates, jnp.hypot(moves[:, 0], moves[:, 1]), moves[forward, 0])
    # Distance left plus metres walked beyond the progress made: moves that walk
    # across the way (sideways past it, or a short step) lose to turning and walking
    # straight, and near the goal the shortest move that arrives beats a longer one.
    here = dist_at(pose)
    score = jnp.where(reach < here, 2 * reach + walk, jnp.inf)  # only actions that make progress
    best = jnp.argmin(score)
    stuck = ~jnp.isfinite(score[best])
    moving = A - (env.stop_index is not None)  # a random move never stops
    travel = jnp.where(stuck, jax.random.randint(key, (), 0, moving), best)
    # Where it should be: face the right way, then step forward.
    wanted = heading[cell(pose)]
    off = jnp.arctan2(jnp.sin(wanted - pose[2]), jnp.cos(wanted - pose[2]))
    turn = jnp.argmax(turns & (jnp.sign(moves[:, 2]) == jnp.sign(off)))
    facing = jnp.abs(off) <= smallest_turn / 2
    arrived = jnp.where(facing, forward, turn)
    return jnp.where(here <= 0, arrived, travel).astype(jnp.int32), (here <= 0) & facing
