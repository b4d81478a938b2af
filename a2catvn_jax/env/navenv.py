"""The batched, pure-functional navigation environment.

`NavEnv.reset(key) -> State` and `NavEnv.step(state, action) -> State` act on B agents
spread over the world's S scenes (agent b lives in scene b mod S) and are jit- and
vmap-able. An episode ends on success (`terminated`, reward 1; with `env.stop_action`
on any stop, below) or after
`max_episode_steps` (`truncated`: a time-out, not a terminal state); the agent is
then reset in the same step (auto-reset): `obs` shows the new episode's first frame
while `reward`, `terminated`, `truncated` and `metrics` describe the step that ended.

Each environment's state holds the `mjx.Data` of its scene (`State.data`, `mjx_world`):
the agent is the scene's mocap body with its camera, each move writes the agent's
pose into it, and the renderers read the camera and the geoms from it. A scene with
bodies on joints gets new joint positions each episode; their geoms block the agent
where they are.

The world (`WorldArrays`: geometry, occupancy grids, goals, target images) is data:
`reset` and `step` read it from their `world` argument (the environment's own world
when omitted), so one compiled step serves every world of the same shapes: training,
held-out and new-target houses built with the same geom layout (`World(..., layout=...)`).

Success (reward 1, `terminated`) depends on the goal kind (`env.goal`):
- image: the agent stands within `success_distance` of where the target image was taken
  and faces within `success_heading_deg` of its heading (it sees what the image shows);
- room: the agent is inside a room of the target's type, and
- object: within `object_distance` of the pictured object, and for both
  the goal is in sight: pixels of what shows it (a room type's characteristic objects,
  `spec.ROOM_TARGET_CLASSES`; the object itself) cover at least `view_fraction` of the
  observation in `view_steps` observations in a row. The observation is rendered after
  the move, so this is known one step late: the step after such a streak ends the
  episode with reward 1 whatever its action (the action is not carried out). With
  `view_fraction` 0 only the position counts and success comes with the move.

With `env.stop_action` the action set gains a last action, "stop", which does not move
and always ends the episode (`terminated`): with reward 1 where the criterion above
holds when it is taken (`goal_reached`), else unrewarded; reaching the goal without
stopping ends nothing. Success must then be declared, as in ObjectNav, so an agent
that passes through the goal without recognising it does not succeed.

Actions (paper): forward 0.5 m, backward 0.2 m, left/right 0.35 m sideways, rotate
+-30 deg, tilt camera +-30 deg ("full"); the same without tilt ("no_tilt"); or
forward/backward 0.33 m and rotate +-90 deg without noise ("grid"). After each action
of the continuous sets the position gets N(0, 0.02^2) noise per axis and the heading
N(0, (2 deg)^2). Moves are swept against obstacle footprints grown by the agent's
radius and stop just before contact, so the agent never ends inside a geom.

Agent b lives in scene b mod S, or with `new_scene_per_episode` each of its episodes
starts in a scene drawn uniformly from the S scenes (training over more houses than
agents).

The curriculum complexity tau is data (`State.info.complexity`): a new start is
drawn uniformly among free cells whose geodesic distance to the goal is at most
tau * (the scene's largest geodesic distance).
"""

from __future__ import annotations

from typing import Optional

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from mujoco import mjx

from a2catvn_jax.config import EnvConfig
from a2catvn_jax.env import camera, rects
from a2catvn_jax.env.camera import Frame
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS
from a2catvn_jax.env.world import BODY_MARGIN, World, WorldArrays, cam_position, make_scenes

# (forward, left, rotate, tilt) per action; metres and degrees.
ACTION_SETS = {
    "full": (
        ("forward", (0.5, 0.0, 0.0, 0.0)),
        ("backward", (-0.2, 0.0, 0.0, 0.0)),
        ("left", (0.0, 0.35, 0.0, 0.0)),
        ("right", (0.0, -0.35, 0.0, 0.0)),
        ("rotate_left", (0.0, 0.0, 30.0, 0.0)),
        ("rotate_right", (0.0, 0.0, -30.0, 0.0)),
        ("tilt_up", (0.0, 0.0, 0.0, 30.0)),
        ("tilt_down", (0.0, 0.0, 0.0, -30.0)),
    ),
    "grid": (
        ("forward", (0.33, 0.0, 0.0, 0.0)),
        ("backward", (-0.33, 0.0, 0.0, 0.0)),
        ("rotate_left", (0.0, 0.0, 90.0, 0.0)),
        ("rotate_right", (0.0, 0.0, -90.0, 0.0)),
    ),
}
ACTION_SETS["no_tilt"] = ACTION_SETS["full"][:6]
_CONTACT_GAP = 1e-3  # metres kept between the grown footprints and the agent's centre


@struct.dataclass
class Observation:
    """What the agents see, [B, ...] (h = w = env.render.image_size).

    rgb [B, h, w, 3] uint8; depth [B, h, w] float32 metres along each pixel's ray (0
    where nothing is hit); segmentation [B, h, w] uint8 class ids; segmentation_rgb
    [B, h, w, 3] uint8 class colours (the paper's encoding). The same four of the
    target image, prefixed target_. target_index [B] int32: the target image's index
    in `NavEnv.target_images()`.
    """

    rgb: jnp.ndarray
    depth: jnp.ndarray
    segmentation: jnp.ndarray
    segmentation_rgb: jnp.ndarray
    target_rgb: jnp.ndarray
    target_depth: jnp.ndarray
    target_segmentation: jnp.ndarray
    target_segmentation_rgb: jnp.ndarray
    target_index: jnp.ndarray


@struct.dataclass
class Info:
    """Each agent's episode, [B, ...].

    scene, goal [B] int32; pose [B, 4] (x, y, yaw, tilt); target_pose [B, 4] where the
    target image was taken; start_distance [B] geodesic start-to-goal distance (m);
    step [B] int32 steps taken; path_length [B] metres travelled; episode_return [B];
    complexity [B] curriculum tau of the next episodes; key [B, 2] PRNG keys;
    view_streak [B] int32 observations in a row, up to the current one, that showed the
    goal from inside its region (goals that must be seen; 0 otherwise).
    """

    scene: jnp.ndarray
    goal: jnp.ndarray
    pose: jnp.ndarray
    target_pose: jnp.ndarray
    start_distance: jnp.ndarray
    step: jnp.ndarray
    path_length: jnp.ndarray
    episode_return: jnp.ndarray
    complexity: jnp.ndarray
    key: jnp.ndarray
    view_streak: jnp.ndarray


@struct.dataclass
class State:
    """Batched environment state (leading axis B everywhere).

    obs: `Observation`; reward [B] float32; terminated [B] bool (the step ended the
    episode in a terminal state: it reached the goal, or with `env.stop_action` the agent
    stopped, successfully or not; `metrics["success"]` tells which); truncated [B] bool
    (the episode hit the time limit); info: `Info`;
    data: each environment's `mjx.Data` of its scene (`mjx_world`): the agent's mocap
    body and camera at `info.pose`, the scene's bodies where the episode placed them.
    metrics (of the step just taken; episode_* are meaningful where `done`):
      success, truncated, episode_length, episode_return, episode_spl,
      episode_start_distance, fallback (renderer fell back to brute force).
    """

    obs: Observation
    reward: jnp.ndarray
    terminated: jnp.ndarray
    truncated: jnp.ndarray
    metrics: dict
    info: Info
    data: mjx.Data

    @property
    def done(self):
        """[B] bool: the step ended an episode (terminated or truncated)."""
        return self.terminated | self.truncated


class NavEnv:
    """Target-driven visual navigation over a batch of scenes."""

    def __init__(self, cfg: EnvConfig, world: Optional[World] = None, seed_offset: int = 0):
        cfg.validate("env")  # the schema's checks (ConfigError): a tree built directly is not validated yet
        self.cfg = cfg
        self.world = world if world is not None else World(cfg, make_scenes(cfg, seed_offset), seed=cfg.scene.seed + seed_offset)
        self.num_envs = cfg.num_envs
        self.action_names = action_names(cfg)
        self.num_actions = len(self.action_names)
        moves = np.array([m for _, m in ACTION_SETS[cfg.action_set]] + [(0.0,) * 4] * cfg.stop_action, np.float32)
        moves[:, 2:] = np.deg2rad(moves[:, 2:])
        self._moves = moves
        self.stop_index = self.num_actions - 1 if cfg.stop_action else None  # the stop action, if any
        self._grid = cfg.action_set == "grid"
        self._seen = cfg.goal in ("room", "object") and cfg.view_fraction > 0  # success needs the goal in sight
        self._spec = self.world.spec
        self._colors = jnp.asarray(SEGMENTATION_COLORS)

    # -- public API -------------------------------------------------------------------

    @property
    def num_scenes(self) -> int:
        return len(self.world.scenes)

    @property
    def renderer(self) -> str:
        """The render backend the world uses (`env.render.backend`, resolved)."""
        return self.world.backend

    def render_notes(self, per_device: int, platform: str) -> list[str]:
        """Lines for a run's log: why the backend was chosen, and for the ray caster the
        frames it renders per pass of `per_device` (the default on `platform`)."""
        notes = [self.world.backend_note] if self.world.backend_note else []
        if self.world.backend == "raycast":
            notes.append(f"the ray caster renders {self.world.spec.chunk(per_device)} of each device's {per_device} "
                         f"frames per pass (the default on {platform})")
        return notes

    @property
    def moves(self):
        """[A, 4] float32 per action: forward and left (metres), rotation and tilt (radians)."""
        return self._moves

    @property
    def num_targets(self) -> int:
        """K: the distinct target images of the world (goals of every scene)."""
        return int(np.prod(self.world.arrays.target_rgb.shape[:2]))

    def reset(self, key, complexity: Optional[float] = None, world: Optional[WorldArrays] = None) -> State:
        """Fresh episodes for all B agents in `world` (default: the environment's own)."""
        w = self._world(world)
        B = self.num_envs
        if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
            key = jax.random.key_data(key)
        tau = jnp.full((B,), self.cfg.complexity if complexity is None else complexity, jnp.float32)
        keys = jax.random.split(key, B)
        scene = jnp.arange(B, dtype=jnp.int32) % w.free.shape[0]
        keys, scene = self._next_scene(w, keys, scene)
        keys, data = self._scene_data(w, keys, scene)
        keys, start = jax.vmap(self._sample_episode, in_axes=(None, 0, 0, 0, 0))(
            w, keys, scene, tau, self._moving_footprints(data))
        info = self._episode_info(w, start, scene, tau, keys)
        data = self.world.place_agent(data, info.pose)
        frame = self._render(w, scene, info.pose, data)
        info = self._count_views(w, info, frame, jnp.zeros((B,), bool))
        zeros = jnp.zeros((B,), jnp.float32)
        metrics = episode_metrics(zeros > 1, zeros > 1, info, frame.fallback)
        return State(self._obs(w, frame, info), zeros, zeros > 1, zeros > 1, metrics, info, data)

    def step(self, state: State, action, world: Optional[WorldArrays] = None) -> State:
        """Apply actions [B] (int) in `world` (default: the environment's own) and auto-reset
        finished episodes."""
        action = jnp.asarray(action)
        chex.assert_shape(action, (self.num_envs,))
        chex.assert_type(action, int)
        w = self._world(world)
        info = state.info
        keys, noise_key = jax.vmap(jax.random.split, out_axes=1)(info.key)
        pose, moved = jax.vmap(self._move, in_axes=(None, 0, 0, 0, 0, 0))(
            w, info.scene, info.pose, jnp.asarray(action, jnp.int32), noise_key, self._moving_footprints(state.data))
        if self.stop_index is not None:  # success only where the agent stops; any stop ends the episode
            terminal = jnp.asarray(action) == self.stop_index
            pose = select_where(terminal, info.pose, pose)  # a stop stays put, without motion noise
            moved = jnp.where(terminal, 0.0, moved)
            success = terminal & self._criterion(w, info, pose)
        elif self._seen:  # the streak up to the current observation decides; the move is not made
            success = terminal = self._criterion(w, info, pose)
            pose = select_where(success, info.pose, pose)
            moved = jnp.where(success, 0.0, moved)
        else:  # the pose after the move decides
            success = terminal = self._criterion(w, info, pose)
        step = info.step + 1
        truncated = (step >= self.cfg.max_episode_steps) & ~terminal
        done = terminal | truncated
        reward = success.astype(jnp.float32)
        ended = info.replace(pose=pose, step=step, path_length=info.path_length + moved,
                             episode_return=info.episode_return + reward)

        keys, scene = self._next_scene(w, keys, info.scene)
        keys, fresh_data = self._scene_data(w, keys, scene)
        keys, start = jax.vmap(self._sample_episode, in_axes=(None, 0, 0, 0, 0))(
            w, keys, scene, info.complexity, self._moving_footprints(fresh_data))
        fresh = self._episode_info(w, start, scene, info.complexity, keys)
        ended = ended.replace(key=keys)
        new_info = jax.tree_util.tree_map(lambda a, b: select_where(done, a, b), fresh, ended)
        data = jax.tree_util.tree_map(lambda a, b: select_where(done, a, b), fresh_data, state.data)
        data = self.world.place_agent(data, new_info.pose)
        frame = self._render(w, new_info.scene, new_info.pose, data)
        new_info = self._count_views(w, new_info, frame, ~done)
        metrics = episode_metrics(success, truncated, ended, frame.fallback)
        return State(self._obs(w, frame, new_info), reward, terminal, truncated, metrics, new_info, data)

    def goal_reached(self, state: State, world: Optional[WorldArrays] = None):
        """[B] bool: the success criterion holds now, so that a stop (`env.stop_action`)
        would succeed: the view streak for goals that must be seen, else the pose."""
        return self._criterion(self._world(world), state.info, state.info.pose)

    def with_data(self, state: State, world: Optional[WorldArrays] = None) -> State:
        """`state` with each environment's `mjx.Data` made anew from its scene and pose
        (the scenes' bodies in their reference configuration): for states saved before
        the environment's state held its data."""
        w = self._world(world)
        return state.replace(data=self.world.data(w, state.info.scene, state.info.pose))

    def set_complexity(self, state: State, complexity) -> State:
        """The same state with curriculum complexity tau for the episodes that follow."""
        tau = jnp.broadcast_to(jnp.asarray(complexity, jnp.float32), state.info.complexity.shape)
        return state.replace(info=state.info.replace(complexity=tau))

    def target_index(self, scene, goal):
        """Index in `target_images()` of goal `goal` of scene `scene` (int arrays of one shape)."""
        return (scene * self.cfg.goals_per_scene + goal).astype(jnp.int32)

    def target_images(self, world: Optional[WorldArrays] = None) -> dict:
        """The K distinct target images, indexed by `obs.target_index`: rgb [K, h, w, 3]
        uint8, depth [K, h, w] metres, segmentation [K, h, w] uint8 class ids."""
        w = self._world(world)
        flat = lambda a: a.reshape((-1,) + a.shape[2:])  # noqa: E731
        return {"rgb": flat(w.target_rgb), "depth": flat(w.target_depth), "segmentation": flat(w.target_seg)}

    # Debugging API: hold the renderer against MuJoCo for any pose.
    def scene_mjcf(self, scene_index: int) -> str:
        """The MJCF (padded to the batch's geom layout) that scene `scene_index` compiles from."""
        return self.world.mjcf[scene_index]

    def camera_rays(self, pose):
        """World ray origin [3] and unit per-pixel directions [H, W, 3] of a pose (x, y, yaw, tilt)."""
        pose = jnp.asarray(pose, jnp.float32)
        s = self._spec
        return cam_position(pose, self.cfg.camera_height), camera.ray_directions(pose[2], pose[3], s.height, s.width, s.fovy)

    def render_pose(self, scene_index: int, pose) -> Frame:
        """RGB, depth, geom ids and classes seen from pose (x, y, yaw, tilt) in a scene."""
        frame = self.render_poses(jnp.array([scene_index]), jnp.asarray(pose)[None])
        return jax.tree_util.tree_map(lambda a: a[0], frame)

    def render_poses(self, scenes, poses, world: Optional[WorldArrays] = None, data=None) -> Frame:
        """Frames [N] seen from poses [N, 4] in scenes [N], with the scenes' bodies where
        `data` [N] has them (default: their reference configuration)."""
        return self._render(self._world(world), jnp.asarray(scenes, jnp.int32), jnp.asarray(poses, jnp.float32), data)

    def sample_starts(self, keys, scenes, complexity, world: Optional[WorldArrays] = None):
        """(goal [N], pose [N, 4], start distance [N]) of new episodes in scenes [N], one per key,
        drawn as `reset` draws them at curriculum complexity [N]."""
        w = self._world(world)
        _, start = jax.vmap(self._sample_episode, in_axes=(None, 0, 0, 0, None))(w, keys, jnp.asarray(scenes, jnp.int32),
                                                                                complexity, None)
        return start

    def preview(self, scene, pose, action, world: Optional[WorldArrays] = None):
        """The pose [4] that `action` would lead to from `pose` [4] in `scene` without motion
        noise (one agent; vmap for more)."""
        return self._move(self._world(world), scene, pose, action, None)[0]

    def segmentation_rgb(self, classes):
        """The paper's encoding of class ids as colours evenly spread in hue: [..., 3] uint8."""
        return self._colors[classes]

    # -- internals ----------------------------------------------------------------------

    def _world(self, world: Optional[WorldArrays]) -> WorldArrays:
        return self.world.arrays if world is None else world

    def _render(self, w: WorldArrays, scene, pose, data=None) -> Frame:
        return self.world.render(w, scene, pose, data)

    def _scene_data(self, w: WorldArrays, keys, scene):
        """(keys, data [B] of new episodes in scenes [B]): joint positions drawn uniformly
        within their ranges (scenes with moving bodies); the agent is not placed yet."""
        qpos = None
        if self.world.mjx.has_joints:
            keys, sub = jax.vmap(jax.random.split, out_axes=1)(keys)
            qpos = jax.vmap(self.world.mjx.draw_qpos)(sub)
        return keys, self.world.scene_data(w, scene, qpos)

    def _moving_footprints(self, data):
        """[B, K, 4] footprints of the K moving geoms where `data` has them; None when the
        scenes have no moving geoms."""
        if self.world.mjx.moving.size == 0:
            return None
        return self.world.mjx.footprints(data, self.cfg.camera_height + BODY_MARGIN)

    def _obs(self, w: WorldArrays, frame: Frame, info: Info) -> Observation:
        s, g = info.scene, info.goal
        seg = frame.cls.astype(jnp.uint8)
        tseg = w.target_seg[s, g]
        return Observation(
            rgb=frame.rgb,
            depth=frame.depth,
            segmentation=seg,
            segmentation_rgb=self._colors[seg],
            target_rgb=w.target_rgb[s, g],
            target_depth=w.target_depth[s, g],
            target_segmentation=tseg,
            target_segmentation_rgb=self._colors[tseg],
            target_index=self.target_index(s, g),
        )

    def _criterion(self, w: WorldArrays, info: Info, pose):
        """[B] bool: the success criterion at `pose`: for goals that must be seen the view
        streak up to the current observation (the pose is not used), else being at the goal."""
        if self._seen:
            return info.view_streak >= self.cfg.view_steps
        return jax.vmap(self._at_goal, in_axes=(None, 0, 0, 0))(w, info.scene, info.goal, pose)

    def _in_region(self, w: WorldArrays, scene, goal, pose):
        i, j = rects.cell_of(pose[:2], w.grid_origin[scene], self.cfg.grid_resolution, w.free.shape[1:])
        return w.goal_success[scene, goal, i, j]

    def _at_goal(self, w: WorldArrays, scene, goal, pose):
        """Success by position (and for image goals heading) alone."""
        ok = self._in_region(w, scene, goal, pose)
        if self.cfg.goal == "image" and self.cfg.success_heading_deg < 180:
            off = _wrap(pose[2] - w.target_pose[scene, goal, 2])
            ok &= jnp.abs(off) <= jnp.deg2rad(self.cfg.success_heading_deg)
        return ok

    def in_view(self, w: WorldArrays, scene, goal, frame: Frame):
        """[N] bool: frames [N] (of agents in scenes [N] pursuing goals [N]) in which what
        shows the goal covers at least `view_fraction` of the image."""
        shows = w.goal_classes[scene[:, None, None], goal[:, None, None], frame.cls]
        shows |= w.goal_geoms[scene[:, None, None], goal[:, None, None], frame.geom + 1]
        return shows.mean((1, 2)) >= self.cfg.view_fraction

    def _count_views(self, w: WorldArrays, info: Info, frame: Frame, keep):
        """`info` with the view streak of the frames just rendered (continued where `keep`)."""
        if not self._seen:
            return info
        region = jax.vmap(self._in_region, in_axes=(None, 0, 0, 0))(w, info.scene, info.goal, info.pose)
        seen = region & self.in_view(w, info.scene, info.goal, frame)
        streak = jnp.where(seen, jnp.where(keep, info.view_streak, 0) + 1, 0)
        return info.replace(view_streak=streak.astype(jnp.int32))

    def _next_scene(self, w: WorldArrays, keys, scene):
        """(keys, the scenes [B] of the agents' next episodes): their own, or with
        `new_scene_per_episode` one drawn uniformly from the world's S scenes."""
        if not self.cfg.new_scene_per_episode:
            return keys, scene
        keys, sub = jax.vmap(jax.random.split, out_axes=1)(keys)
        drawn = jax.vmap(lambda k: jax.random.randint(k, (), 0, w.free.shape[0]))(sub)
        return keys, drawn.astype(jnp.int32)

    def _sample_episode(self, w: WorldArrays, key, scene, tau, moving=None):
        """(next key, (goal, pose, start distance)) of a new episode in `scene`; `moving`
        [K, 4]: footprints of moving geoms, where no start may lie."""
        key, kg, kc, kj, ky = jax.random.split(key, 5)
        goal = jax.random.randint(kg, (), 0, w.goal_dist.shape[1])
        dist = w.goal_dist[scene, goal]
        limit = jnp.maximum(tau * w.diameter[scene], w.goal_min_dist[scene, goal])
        ok = w.free[scene] & ~w.goal_success[scene, goal] & (dist <= limit)
        H, W = dist.shape
        reach = self.cfg.agent_radius + _CONTACT_GAP
        if moving is not None:
            centres = w.grid_origin[scene] + (jnp.stack(jnp.meshgrid(jnp.arange(W), jnp.arange(H)), -1) + 0.5) * self.cfg.grid_resolution
            ok &= ~rects.inside(centres, moving, reach).any(-1)
            obstacles = jnp.concatenate([w.obstacles[scene], moving])
        else:
            obstacles = w.obstacles[scene]
        cell = uniform_index(kc, ok.reshape(-1))
        i, j = cell // W, cell % W
        res = self.cfg.grid_resolution
        centre = w.grid_origin[scene] + (jnp.stack([j, i]).astype(jnp.float32) + 0.5) * res
        if self._grid:
            yaw = jax.random.randint(ky, (), 0, 4).astype(jnp.float32) * (jnp.pi / 2)
            xy = centre
        else:
            yaw = jax.random.uniform(ky, (), minval=-jnp.pi, maxval=jnp.pi)
            jitter = centre + jax.random.uniform(kj, (2,), minval=-0.5, maxval=0.5) * res
            blocked = rects.inside(jitter, obstacles, reach).any()
            xy = jnp.where(blocked, centre, jitter)
        pose = jnp.concatenate([xy, jnp.stack([yaw, 0.0])])
        return key, (goal, pose, dist[i, j])

    def _episode_info(self, w: WorldArrays, start, scene, tau, keys) -> Info:
        goal, pose, dist = start
        zeros = jnp.zeros_like(tau)
        return Info(
            scene=scene,
            goal=goal.astype(jnp.int32),
            pose=pose,
            target_pose=w.target_pose[scene, goal],
            start_distance=dist,
            step=jnp.zeros_like(scene),
            path_length=zeros,
            episode_return=zeros,
            complexity=tau,
            key=keys,
            view_streak=jnp.zeros_like(scene),
        )

    def _sweep(self, w: WorldArrays, scene, p0, p1, moving=None):
        """Fraction in [0, 1] of the segment p0 -> p1 the agent can travel before its
        grown footprint would touch an obstacle (or a moving geom's footprint [K, 4])."""
        r = self.cfg.agent_radius
        ob = w.obstacles[scene] if moving is None else jnp.concatenate([w.obstacles[scene], moving])
        grown = jnp.concatenate([ob[:, :2] - r, ob[:, 2:] + r], -1)
        d = p1 - p0
        tn, tf = rects.slab(p0, d, grown)
        hits = (tn <= tf) & (tf >= 0) & (tn <= 1.0)
        first = jnp.min(jnp.where(hits, tn, 1.0))
        length = jnp.linalg.norm(d)
        # Back off by the contact gap only when something is in the way: an
        # unobstructed move goes the whole way (grid moves rely on frac == 1).
        stop = jnp.clip(first - _CONTACT_GAP / jnp.maximum(length, 1e-9), 0.0, 1.0)
        return jnp.where(jnp.any(hits), stop, 1.0)

    def _move(self, w: WorldArrays, scene, pose, action, key, moving=None):
        """New pose after `action` and the distance actually travelled (no motion noise
        when `key` is None); `moving` [K, 4]: footprints of moving geoms that block too."""
        fwd, left, rot, tilt = (jnp.asarray(self._moves)[action, i] for i in range(4))
        x, y, yaw, cam_tilt = pose[0], pose[1], pose[2], pose[3]
        p0 = jnp.stack([x, y])
        step = jnp.stack([fwd * jnp.cos(yaw) - left * jnp.sin(yaw), fwd * jnp.sin(yaw) + left * jnp.cos(yaw)])
        yaw = yaw + rot
        if not self._grid and key is not None:
            kp, kh = jax.random.split(key)
            step = step + self.cfg.position_noise * jax.random.normal(kp, (2,))
            yaw = yaw + jnp.deg2rad(self.cfg.heading_noise_deg) * jax.random.normal(kh)
        frac = self._sweep(w, scene, p0, p0 + step, moving)
        if self._grid:
            frac = jnp.where(frac < 1.0, 0.0, 1.0)  # grid moves happen whole or not at all
        p1 = p0 + frac * step
        yaw = jnp.arctan2(jnp.sin(yaw), jnp.cos(yaw))
        max_tilt = jnp.deg2rad(self.cfg.max_tilt_deg)
        cam_tilt = jnp.clip(cam_tilt + tilt, -max_tilt, max_tilt)
        return jnp.concatenate([p1, jnp.stack([yaw, cam_tilt])]), frac * jnp.linalg.norm(step)

def episode_metrics(success, truncated, ended: Info, fallback) -> dict:
    """`State.metrics` of a step: its flags and, for the episodes it ended (`ended`:
    their info at the step), length, return, SPL and start distance."""
    d0 = ended.start_distance
    spl = success * d0 / jnp.maximum(jnp.maximum(ended.path_length, d0), 1e-6)
    return {
        "success": success,
        "truncated": truncated,
        "episode_length": ended.step,
        "episode_return": ended.episode_return,
        "episode_spl": spl,
        "episode_start_distance": d0,
        "fallback": fallback,
    }


def action_names(cfg: EnvConfig) -> tuple[str, ...]:
    """The names of the actions of the configured action set, in action-index order
    (with `env.stop_action`, "stop" last)."""
    return tuple(name for name, _ in ACTION_SETS[cfg.action_set]) + ("stop",) * cfg.stop_action


def uniform_index(key, mask, block: int = 128):
    """An index drawn uniformly among the True entries of `mask` [N]: the k-th of them in
    order, k uniform. Padding `mask` with False entries anywhere after or between the
    True ones does not change which of them is drawn.

    The k-th True entry is found in two steps, the block of `block` entries that holds
    it and then its place in that block: the same index as the first position where
    the running count of the whole mask exceeds k, without a running count (and an
    argmax) over all N entries, which on XLA's CPU backend cost as much as a tenth of
    a house task's environment step."""
    n = mask.shape[0]
    blocks = mask if n <= block else jnp.pad(mask, (0, -n % block))
    blocks = blocks.reshape(-1, min(n, block)).astype(jnp.int32)
    counts = blocks.sum(1)
    count = counts.sum()
    k = jnp.minimum(jnp.floor(jax.random.uniform(key) * count), count - 1).astype(jnp.int32)
    ends = jnp.cumsum(counts)
    b = jnp.argmax(ends > k)
    within = jnp.argmax(jnp.cumsum(blocks[b]) > k - (ends[b] - counts[b]))
    return b * blocks.shape[1] + within


def _wrap(angle):
    """An angle in radians brought into [-pi, pi]."""
    return jnp.arctan2(jnp.sin(angle), jnp.cos(angle))


def select_where(mask, a, b):
    return jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b)
