"""A rendering-free environment with `NavEnv`'s interface and `State` contract
(`env.kind: synthetic`): agent, update, checkpoint and scaling code runs on it in a
fraction of the compile time, because nothing is ray cast and no MuJoCo scene is built.
It is a test bench for that code, not a navigation task (docs/environment.md).

B agents walk a grid of `SIDE` x `SIDE` one-metre cells, facing one of four headings.
Each of the S scenes (`env.scene.num_scenes`) paints its cells in colours of its own.
An observation is drawn from (scene, cell, heading) in four horizontal bands: the
heading's colour, the cell's, the colour of the cell ahead (a wall colour at the edge),
and a grey floor; depth is the distance to the wall ahead (the floor band nearer);
segmentation gives each band a class. Every pose looks different, so a goal pose is
recognisable from its image. Each scene has `env.goals_per_scene` goal poses (cell and
heading); the target image is the view from the goal. Reaching the goal's cell facing
its heading ends the episode with reward 1 (`terminated`); `env.max_episode_steps`
truncates it. Actions are the configured action set's, read by what they do: a forward
or backward move goes one cell along the heading, a sideways move one cell to the
side (moves into the edge leave the agent where it is), a rotation turns by 90 degrees,
a camera tilt changes nothing. There is no motion noise. Episodes auto-reset as in
`NavEnv`, start within `complexity` of the farthest start (cells plus quarter turns),
and with `env.new_scene_per_episode` each draws its scene. Distances and path lengths
are in cells (metres): the shortest path to a goal moves the cells between them.

`State.data` holds each agent's integer cell and heading [B, 3] (what `NavEnv` keeps in
its `mjx.Data`); `Info.pose` is the same pose in metres and radians.
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.config import EnvConfig
from a2catvn_jax.configio import ConfigError
from a2catvn_jax.env.navenv import (ACTION_SETS, Info, NavEnv, Observation, State, action_names, episode_metrics,
                                    select_where, uniform_index)
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS

SIDE = 4  # cells along each side of the grid
HEADINGS = 4  # east, north, west, south
POSES = SIDE * SIDE * HEADINGS
_STEPS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], np.int32)  # one cell along each heading
_FLOOR, _WALL = 1, 2  # segmentation classes of the floor band and of a wall ahead


def _action_moves(action_set: str) -> np.ndarray:
    """[A, 3] int32 per action: cells forward, cells to the left, quarter turns left."""
    moves = np.array([m for _, m in ACTION_SETS[action_set]], np.float32)
    return np.stack([np.sign(moves[:, 0]), np.sign(moves[:, 1]), np.sign(moves[:, 2])], 1).astype(np.int32)


def _pose_table() -> np.ndarray:
    """[POSES, 3] int32: (x, y, heading) of every pose, in pose-index order."""
    x, y, h = np.meshgrid(np.arange(SIDE), np.arange(SIDE), np.arange(HEADINGS), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), h.ravel()], 1).astype(np.int32)


def _distance(a, b):
    """Cells plus quarter turns between integer poses (x, y, heading) a and b."""
    turns = jnp.abs(a[..., 2] - b[..., 2]) % HEADINGS
    return (jnp.abs(a[..., 0] - b[..., 0]) + jnp.abs(a[..., 1] - b[..., 1])
            + jnp.minimum(turns, HEADINGS - turns)).astype(jnp.float32)


class SyntheticEnv:
    """`NavEnv`'s reset / step / target images on a small analytic grid world."""

    def __init__(self, cfg: EnvConfig, seed_offset: int = 0):
        cfg.validate("env")
        self.cfg = cfg
        self.num_envs = cfg.num_envs
        self.action_names = action_names(cfg)
        self.num_actions = len(self.action_names)
        self.renderer = "synthetic"
        self._moves = jnp.asarray(_action_moves(cfg.action_set))
        self._poses = jnp.asarray(_pose_table())
        S, G = cfg.scene.num_scenes, cfg.goals_per_scene
        if G > POSES:
            raise ConfigError(f"env.goals_per_scene={G}: the synthetic environment has {POSES} poses per scene")
        rng = np.random.default_rng(cfg.scene.seed + seed_offset)
        # Colours: SIDE * SIDE cells, then HEADINGS headings, then the wall, per scene.
        self._palette = jnp.asarray(rng.integers(0, 256, (S, SIDE * SIDE + HEADINGS + 1, 3), dtype=np.uint8))
        self._goals = jnp.asarray(np.stack([_pose_table()[rng.choice(POSES, G, replace=False)] for _ in range(S)]))
        self._colors = jnp.asarray(SEGMENTATION_COLORS)
        goal_frames = jax.vmap(jax.vmap(self._render, in_axes=(None, 0)), in_axes=(0, 0))(
            jnp.arange(S, dtype=jnp.int32), self._goals)
        self._targets = jax.tree_util.tree_map(lambda a: a.reshape((S * G,) + a.shape[2:]), goal_frames)

    # -- NavEnv's interface -------------------------------------------------------------

    @property
    def num_scenes(self) -> int:
        return self.cfg.scene.num_scenes

    @property
    def num_targets(self) -> int:
        return self.num_scenes * self.cfg.goals_per_scene

    target_index = NavEnv.target_index  # the same indexing of the targets: scene-major

    def target_images(self, world=None) -> dict:
        """rgb [K, h, w, 3] uint8, depth [K, h, w], segmentation [K, h, w] uint8 of the K
        goals, indexed by `obs.target_index`."""
        _no_world(world)
        rgb, depth, seg = self._targets
        return {"rgb": rgb, "depth": depth, "segmentation": seg}

    def reset(self, key, complexity: Optional[float] = None, world=None) -> State:
        _no_world(world)
        B = self.num_envs
        if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
            key = jax.random.key_data(key)
        tau = jnp.full((B,), self.cfg.complexity if complexity is None else complexity, jnp.float32)
        keys = jax.random.split(key, B)
        scene = jnp.arange(B, dtype=jnp.int32) % self.num_scenes
        keys, info, cell = self._new_episodes(keys, scene, tau)
        zeros = jnp.zeros((B,), jnp.float32)
        no = zeros > 1
        return State(self._obs(info, cell), zeros, no, no, episode_metrics(no, no, info, no), info, cell)

    def step(self, state: State, action, world=None) -> State:
        _no_world(world)
        action = jnp.asarray(action, jnp.int32)
        if action.shape != (self.num_envs,):
            raise ValueError(f"actions of shape {action.shape}: expected ({self.num_envs},)")
        info, cell = state.info, state.data
        forward, left, turn = (self._moves[action, i] for i in range(3))
        steps = jnp.asarray(_STEPS)
        ahead, side = steps[cell[:, 2]], steps[(cell[:, 2] + 1) % HEADINGS]
        xy = cell[:, :2] + forward[:, None] * ahead + left[:, None] * side
        inside = jnp.all((xy >= 0) & (xy < SIDE), axis=1)
        xy = jnp.where(inside[:, None], xy, cell[:, :2])
        moved = jnp.where(inside, jnp.abs(forward) + jnp.abs(left), 0).astype(jnp.float32)
        cell = jnp.concatenate([xy, ((cell[:, 2] + turn) % HEADINGS)[:, None]], 1)
        success = jnp.all(cell == self._goals[info.scene, info.goal], axis=1)
        step = info.step + 1
        truncated = (step >= self.cfg.max_episode_steps) & ~success
        done = success | truncated
        reward = success.astype(jnp.float32)
        ended = info.replace(pose=_pose_of(cell), step=step, path_length=info.path_length + moved,
                             episode_return=info.episode_return + reward)
        keys, scene = info.key, info.scene
        if self.cfg.new_scene_per_episode:
            keys, sub = jax.vmap(jax.random.split, out_axes=1)(keys)
            scene = jax.vmap(lambda k: jax.random.randint(k, (), 0, self.num_scenes))(sub).astype(jnp.int32)
        keys, fresh, fresh_cell = self._new_episodes(keys, scene, info.complexity)
        new_info = jax.tree_util.tree_map(lambda a, b: select_where(done, a, b), fresh, ended.replace(key=keys))
        cell = select_where(done, fresh_cell, cell)
        metrics = episode_metrics(success, truncated, ended, jnp.zeros_like(success))
        return State(self._obs(new_info, cell), reward, success, truncated, metrics, new_info, cell)

    def with_data(self, state: State, world=None) -> State:
        """`state` with its integer poses made anew from `info.pose`."""
        _no_world(world)
        return state.replace(data=_cell_of(state.info.pose))

    set_complexity = NavEnv.set_complexity  # the same: complexity lives in Info

    def segmentation_rgb(self, classes):
        return self._colors[classes]

    def render_notes(self, per_device: int, platform: str) -> list[str]:
        return ["the synthetic environment draws its images analytically (env.kind=synthetic: a test bench, not a navigation task)"]

    # -- internals ------------------------------------------------------------------------

    def _render(self, scene, cell):
        """(rgb [h, w, 3] uint8, depth [h, w] float32, segmentation [h, w] uint8) seen from
        integer pose `cell` (x, y, heading) in `scene`."""
        n = self.cfg.render.image_size
        x, y, h = cell[0], cell[1], cell[2]
        ahead = cell[:2] + jnp.asarray(_STEPS)[h]
        wall = ~jnp.all((ahead >= 0) & (ahead < SIDE))
        ax, ay = jnp.clip(ahead[0], 0, SIDE - 1), jnp.clip(ahead[1], 0, SIDE - 1)
        palette = self._palette[scene]
        colours = jnp.stack([palette[SIDE * SIDE + h], palette[x * SIDE + y],
                             jnp.where(wall, palette[-1], palette[ax * SIDE + ay]), jnp.full((3,), 128, jnp.uint8)])
        classes = jnp.stack([3 + h, 3 + HEADINGS + (x + y) % 4, jnp.where(wall, _WALL, 3 + HEADINGS + (ax + ay) % 4),
                             _FLOOR]).astype(jnp.uint8)
        band = jnp.arange(n) * 4 // n  # [h] band of each row
        to_wall = jnp.stack([SIDE - x, SIDE - y, x + 1, y + 1])[h].astype(jnp.float32) - 0.5
        depth = jnp.where(band == 3, 0.5, to_wall).astype(jnp.float32)
        rgb = jnp.broadcast_to(colours[band][:, None, :], (n, n, 3))
        return rgb, jnp.broadcast_to(depth[:, None], (n, n)), jnp.broadcast_to(classes[band][:, None], (n, n))

    def _new_episodes(self, keys, scene, tau):
        """(keys, Info, integer poses [B, 3]) of new episodes in scenes [B] at complexity [B]."""

        def one(key, s, t):
            key, kg, ks = jax.random.split(key, 3)
            goal = jax.random.randint(kg, (), 0, self.cfg.goals_per_scene).astype(jnp.int32)
            target = self._goals[s, goal]
            dist = _distance(self._poses, target)
            limit = jnp.maximum(jnp.ceil(t * jnp.max(dist)), 1.0)
            start = self._poses[uniform_index(ks, (dist <= limit) & (dist > 0))]
            return key, goal, start, jnp.sum(jnp.abs(start[:2] - target[:2])).astype(jnp.float32)

        keys, goal, cell, dist = jax.vmap(one)(keys, scene, tau)
        zeros = jnp.zeros_like(tau)
        info = Info(scene=scene, goal=goal, pose=_pose_of(cell), target_pose=_pose_of(self._goals[scene, goal]),
                    start_distance=dist, step=jnp.zeros_like(scene), path_length=zeros, episode_return=zeros,
                    complexity=tau, key=keys, view_streak=jnp.zeros_like(scene))
        return keys, info, cell

    def _obs(self, info: Info, cell) -> Observation:
        rgb, depth, seg = jax.vmap(self._render)(info.scene, cell)
        index = self.target_index(info.scene, info.goal)
        t_rgb, t_depth, t_seg = (a[index] for a in self._targets)
        return Observation(rgb=rgb, depth=depth, segmentation=seg, segmentation_rgb=self._colors[seg],
                           target_rgb=t_rgb, target_depth=t_depth, target_segmentation=t_seg,
                           target_segmentation_rgb=self._colors[t_seg], target_index=index)


def _pose_of(cell):
    """Poses [..., 4] (x, y metres at the cell centres, yaw, tilt 0) of integer poses [..., 3]."""
    return jnp.stack([cell[..., 0] + 0.5, cell[..., 1] + 0.5, cell[..., 2] * (jnp.pi / 2),
                      jnp.zeros(cell.shape[:-1])], -1).astype(jnp.float32)


def _cell_of(pose):
    """Integer poses [..., 3] of poses [..., 4] (`_pose_of`'s inverse)."""
    heading = jnp.round(pose[..., 2] / (jnp.pi / 2)).astype(jnp.int32) % HEADINGS
    return jnp.stack([jnp.floor(pose[..., 0]).astype(jnp.int32), jnp.floor(pose[..., 1]).astype(jnp.int32), heading], -1)


def _no_world(world) -> None:
    if world is not None:
        raise ValueError("the synthetic environment has no world arrays to swap (env.kind=synthetic)")
