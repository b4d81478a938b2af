"""A batch of scenes built once on the host: MJCF, compiled MuJoCo models, render
geometry, occupancy grids, goals (`goals`) and their target images, packed into
`WorldArrays`, the pytree of fixed-shape arrays (leading scene axis S) the jitted
environment reads; `World.render` draws frames with the backend `backends.choose` picked.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from a2catvn_jax.config import BODY_MARGIN, EnvConfig
from a2catvn_jax.env import geometry as geometry_lib
from a2catvn_jax.env import backends, goals as goals_lib, mjx_world, navgrid, raycast
from a2catvn_jax.env.camera import CameraSpec, Frame
from a2catvn_jax.env.scenes import generate, mjcf
from a2catvn_jax.env.scenes.errors import SceneError
from a2catvn_jax.env.scenes.spec import CLASS_ID, NUM_CLASSES, Scene



@struct.dataclass
class WorldArrays:
    """Device arrays of a world, leading axis S (scenes), T goals per scene.

    geometry: render geometry; mjx: the scenes' own MuJoCo geom arrays (what the `mjx`
    render backend renders). obstacles [S, N, 4] blocking footprints (padding far
    away). grid_origin [S, 2]; free [S, H, W]; diameter [S] (metres).
    goal_dist [S, T, H, W] geodesic distance to the goal region (inf: unreachable);
    goal_success [S, T, H, W] cells inside the goal region; goal_min_dist [S, T]
    smallest distance of a free cell outside the region (start fallback);
    target_pose [S, T, 4] (x, y, yaw, tilt) of the target image's camera and
    target_scene [S, T] the scene it was taken in; target_rgb [S, T, h, w, 3],
    target_depth [S, T, h, w], target_seg [S, T, h, w] (class ids).
    goal_classes [S, T, C] and goal_geoms [S, T, G + 1]: the semantic classes and the
    geoms (index geom id + 1; 0: nothing hit) whose pixels show the goal (the view
    criterion of room and object goals). oracle_dist [S, T, H, W]: geodesic distance
    to where the shortest-path oracle heads (the goal region, or for goals that must
    be seen the part of it within sight of what shows them); oracle_yaw [S, T, H, W]:
    the heading the oracle turns to there.
    """

    geometry: geometry_lib.Geometry
    mjx: mjx_world.MjxFields
    obstacles: jnp.ndarray
    grid_origin: jnp.ndarray
    free: jnp.ndarray
    diameter: jnp.ndarray
    goal_dist: jnp.ndarray
    goal_success: jnp.ndarray
    goal_min_dist: jnp.ndarray
    target_pose: jnp.ndarray
    target_scene: jnp.ndarray
    target_rgb: jnp.ndarray
    target_depth: jnp.ndarray
    target_seg: jnp.ndarray
    goal_classes: jnp.ndarray
    goal_geoms: jnp.ndarray
    oracle_dist: jnp.ndarray
    oracle_yaw: jnp.ndarray

    def fits(self, other: "WorldArrays") -> bool:
        """Whether every array has the rank of `other`'s and no axis longer than it."""
        mine, theirs = jax.tree_util.tree_structure(self), jax.tree_util.tree_structure(other)
        return mine == theirs and not self.larger_than(other)

    def larger_than(self, other: "WorldArrays") -> list[str]:
        """The fields (paths) whose array has another rank than `other`'s or an axis longer."""
        return [jax.tree_util.keystr(path) for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(self),
                                                                  jax.tree_util.tree_leaves(other))
                if a.ndim != b.ndim or any(m > n for m, n in zip(a.shape, b.shape))]

    def padded_like(self, other: "WorldArrays") -> "WorldArrays":
        """These arrays padded to the shapes of `other`'s (which they must `fit`) with
        entries that change nothing: invalid geoms, far-away obstacles, blocked cells
        unreachable from every goal."""

        def pad(path, a, b):
            name = jax.tree_util.keystr(path[-1:]).strip(".[]'")
            fill = _PAD_FILL.get(name, 0)
            return jnp.pad(a, [(0, n - m) for m, n in zip(a.shape, b.shape)], constant_values=fill)

        return jax.tree_util.tree_map_with_path(pad, self, other)


# Fill values of padded entries (by field name; the rest are 0 / False): geoms with id -1
# are never hit, obstacles lie far away, padded cells are unreachable.
_PAD_FILL = {"gid": -1, "obstacles": 1e6, "goal_dist": np.inf, "oracle_dist": np.inf}


NEW_HOUSES_OFFSET = 3_000_017  # scene seed offset of the houses that replace the training houses (`new_houses`)


def _generated(cfg: EnvConfig, num: int, seed: int):
    """The configured kind's `num` generated scenes from `seed`, one at a time (`generate.scene_stream`)."""
    sc = cfg.scene
    if sc.kind == "house":
        return generate.scene_stream("house", num, seed, grid=tuple(sc.grid), room_size=tuple(sc.room_size),
                                     height=sc.height)
    if sc.kind == "room":
        return generate.scene_stream("room", num, seed, size=tuple(sc.room_size), height=sc.height)
    return generate.scene_stream("maze", num, seed, cells=tuple(sc.grid), height=sc.height)


def houses_at(env, every: int, update: int) -> Optional[WorldArrays]:
    """The arrays of the houses a run with `train.new_houses_every=every` was in after
    `update` updates (a checkpoint of that update holds its environments there): None
    for the environment's own (before the first replacement, or `every` 0)."""
    generation = (update - 1) // every if every and update > 0 else 0
    return new_houses(env.world, generation)[0] if generation else None


def make_scenes(cfg: EnvConfig, seed_offset: int = 0) -> list[Scene]:
    """The configured scenes; `seed_offset` gives a disjoint set (e.g. held-out houses)."""
    if cfg.scene.kind == "mjcf":
        return [mjcf.scene_from_mjcf_file(cfg.scene.mjcf_path)]
    return list(_generated(cfg, cfg.scene.num_scenes, cfg.scene.seed + seed_offset))


def new_houses(base: "World", generation: int, draws: int = 64) -> tuple[WorldArrays, int]:
    """(arrays, scenes drawn) of replacement `generation` (>= 1) of `base`'s generated
    scenes: as many new scenes of the same kind (seeds offset by `NEW_HOUSES_OFFSET` +
    generation), with their goals and target images, padded to `base.arrays`' shapes so
    that the functions compiled for `base` take them as data. A drawn scene with more
    geoms of a type than `base`'s layout holds, more obstacles or a larger occupancy grid
    is skipped for the next one; `SceneError` when `draws` times the scene count were
    drawn and too few fit."""
    cfg, S = base.cfg, len(base.scenes)
    seed = cfg.scene.seed + NEW_HOUSES_OFFSET + generation
    body, room = cfg.camera_height + BODY_MARGIN, base.arrays.obstacles.shape[1]
    H, W = base.arrays.free.shape[1:]

    def fits(scene: Scene) -> bool:
        h, w = navgrid.grid_shape(scene, cfg.grid_resolution)
        return (all(n <= base.layout[t] for t, n in mjcf.geom_counts(scene).items())
                and len(navgrid.obstacle_rects(scene, body)) <= room and h <= H and w <= W)

    fitting, drawn = [], 0
    for scene in _generated(cfg, draws * S, seed):  # each generated only when needed
        drawn += 1
        if fits(scene):
            fitting.append(scene)
            if len(fitting) == S:
                break
    if len(fitting) < S:
        raise SceneError(f"new houses {generation}: only {len(fitting)} of {drawn} drawn scenes fit the training "
                         f"houses' geoms, obstacles and floor; {S} are needed (more training houses, "
                         f"env.scene.num_scenes, make the room the new ones must fit)")
    raycast = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, backend="raycast"))  # as `base` renders
    world = World(raycast, fitting, seed=seed, layout=base.layout)
    if not world.arrays.fits(base.arrays):
        raise SceneError(f"new houses {generation}: their arrays {', '.join(world.arrays.larger_than(base.arrays))} "
                         f"are larger than the training houses'")
    return world.arrays.padded_like(base.arrays), drawn


class World:
    """S scenes with everything the environment needs (built once, on the host).

    `layout` (geom count per type, `mjcf.layout_of`) pads the scenes' models to a
    layout shared with other worlds (e.g. held-out houses), so that one compiled
    environment and one `mjx` render context serve all of them. `render` draws frames
    with the configured backend (`env.render.backend`; `backend` is the one in use)."""

    def __init__(self, cfg: EnvConfig, scenes: list[Scene], seed: int = 0, layout: Optional[dict] = None):
        self.cfg = cfg
        self.scenes = scenes
        self.layout = mjcf.layout_of(scenes) if layout is None else layout
        # Geoms only the mjx backend renders (a user's planes, cylinders, meshes): their
        # scene is compiled from its own MJCF, as it is.
        self.native = [(g.name, g.native) for s in scenes for g in s.geoms if g.native]
        if any(s.source is not None for s in scenes):
            if len(scenes) > 1:
                raise SceneError(f"scene {next(s.name for s in scenes if s.source)!r} has plane, cylinder or mesh geoms "
                                 "and is compiled from its own MJCF; it cannot share a batch with other scenes")
            xml, model = mjcf.native_model(scenes[0], cfg.render.fovy)
            self.mjcf, self.models = [xml], [model]
        else:
            self.mjcf = [mjcf.scene_to_mjcf(s, self.layout, fovy=cfg.render.fovy) for s in scenes]
            self.models = [mjcf.compile_scene(x) for x in self.mjcf]
        geometry = geometry_lib.pack(self.models, [s.closed for s in scenes], [s.height for s in scenes],
                                     skip_unsupported=bool(self.native))
        fields = mjx_world.fields_of(self.models)
        try:
            self.mjx = mjx_world.MjxWorld(self.models[0], cfg.camera_height)
        except Exception as e:  # MJX refuses some of a model's settings (a plugin, an unsupported field)
            raise SceneError(f"{scenes[0].name}: MJX cannot hold this model: {type(e).__name__}: "
                             f"{' '.join(str(e).split())}") from e
        moving = self.mjx.moving
        # The ray caster's families hold the moving geoms too (when it can render them):
        # each frame places them where its data has them.
        self._moving = None
        if moving.size and not self.native:
            self._moving = (geometry_lib.slots(geometry_lib.take(geometry, 0), moving), moving)
        body = cfg.camera_height + BODY_MARGIN
        self.grids = [navgrid.build(s, cfg.grid_resolution, cfg.agent_radius, body) for s in scenes]
        self.spec = CameraSpec(
            cfg.render.image_size,
            cfg.render.image_size,
            cfg.render.fovy,
            candidates=cfg.render.column_candidates if cfg.render.culling else 0,
            chunk_frames=render_chunk(jax.default_backend()),
        )
        choice = backends.choose(self, cfg.render.backend, geometry, fields)
        self.backend, self.backend_note, self._mjx = choice.name, choice.note, choice.renderer
        rng = np.random.default_rng(seed)
        self.goals = [goals_lib.draw_goals(cfg, scenes, self.grids, self.models, k, rng) for k in range(len(scenes))]
        self.arrays = self._arrays(geometry, fields)

    # -- rendering --------------------------------------------------------------------

    def data(self, arrays: WorldArrays, scene, pose, qpos=None):
        """`mjx.Data` [N] of agents at poses [N, 4] in scenes [N] of `arrays`, with joint
        positions qpos [N, nq] (default: the model's reference configuration)."""
        return self.fields_data(arrays.mjx, scene, pose, qpos)

    def scene_data(self, arrays: WorldArrays, scene, qpos=None):
        """`mjx.Data` [N] of scenes [N] of `arrays` with joint positions qpos [N, nq]
        (default: the reference configuration), the agent not yet placed (`place_agent`)."""
        return self._scene_data(arrays.mjx, scene, qpos)

    def place_agent(self, data, pose):
        """`data` [N] with the agents at poses [N, 4]."""
        return jax.vmap(self.mjx.place_agent)(data, pose)

    def _scene_data(self, fields, scene, qpos=None):
        return jax.vmap(self.mjx.data, in_axes=(None, 0, 0))(fields, scene, qpos)

    def fields_data(self, fields: mjx_world.MjxFields, scene, pose, qpos=None):
        """`data` of the scenes' `MjxFields` rather than a world's arrays."""
        return self.place_agent(self._scene_data(fields, scene, qpos), pose)

    def render(self, arrays: WorldArrays, scene, pose, data=None) -> Frame:
        """Frames [N] of agents at poses [N, 4] (x, y, yaw, tilt) in scenes [N] of `arrays`
        (this world's, or another's of the same layout), with this world's backend. The
        camera and the geoms are where `data` [N] (`World.data`; default: the scenes in
        their reference configuration) has them."""
        return self.render_with(self.backend, self._mjx, arrays.geometry, arrays.mjx, scene, pose, data)

    def render_with(self, backend: str, renderer, geometry, fields, scene, pose, data=None) -> Frame:
        """`render` with a given backend (and the mjx backend's `renderer`) on geometry and fields."""
        if data is None:
            data = self.fields_data(fields, scene, pose)
        if backend == "mjx":
            cam_pos, cam_mat = self.mjx.camera_pose(data)
            return renderer.render(fields, geometry.cls, scene, cam_pos, cam_mat, data.geom_xpos, data.geom_xmat)
        # The ray caster's geometry holds the static geoms' poses (the same as the data's);
        # the moving geoms are placed from the data.
        moving = None
        if self._moving is not None:
            where, gids = self._moving
            moving = (where, gids, data.geom_xpos[:, gids], data.geom_xmat[:, gids])
        cam_pos, _ = self.mjx.camera_pose(data)
        return raycast.render_batch(geometry, scene, cam_pos, pose[:, 2], pose[:, 3], self.spec, moving)

    # -- arrays ---------------------------------------------------------------------

    def _arrays(self, geometry, fields) -> WorldArrays:
        S, T = len(self.scenes), self.cfg.goals_per_scene
        H = max(g.shape[0] for g in self.grids)
        W = max(g.shape[1] for g in self.grids)

        def pad(a, fill):
            out = np.full((H, W), fill, a.dtype)
            out[: a.shape[0], : a.shape[1]] = a
            return out

        free = np.stack([pad(g.free, False) for g in self.grids])
        goal_dist = np.full((S, T, H, W), np.inf, np.float32)
        goal_success = np.zeros((S, T, H, W), bool)
        goal_min = np.zeros((S, T), np.float32)
        oracle_dist = np.full((S, T, H, W), np.inf, np.float32)
        oracle_yaw = np.zeros((S, T, H, W), np.float32)
        G = max(m.ngeom for m in self.models)
        goal_classes = np.zeros((S, T, NUM_CLASSES), bool)
        goal_geoms = np.zeros((S, T, G + 1), bool)
        for k, (grid, goals) in enumerate(zip(self.grids, self.goals)):
            for t, goal in enumerate(goals):
                d = navgrid.geodesic(grid, goal.success)
                goal_dist[k, t] = pad(d.astype(np.float32), np.inf)
                goal_success[k, t] = pad(goal.success & grid.free, False)
                outside = np.isfinite(d) & ~goal.success & grid.free
                goal_min[k, t] = d[outside].min() if outside.any() else 0.0
                goal_classes[k, t, [CLASS_ID[c] for c in goal.classes]] = True
                for name in goal.geoms:
                    goal_geoms[k, t, mujoco.mj_name2id(self.models[k], mujoco.mjtObj.mjOBJ_GEOM, name) + 1] = True
                region, yaw = goals_lib.oracle_target(self.cfg, grid, goal, d)
                oracle_dist[k, t] = pad(region.astype(np.float32), np.inf)
                oracle_yaw[k, t] = pad(yaw.astype(np.float32), 0.0)
        diameter = np.array([navgrid.diameter(g) for g in self.grids], np.float32)
        n_obs = max(max(len(g.obstacles) for g in self.grids), 1)
        obstacles = np.tile(np.array([1e6, 1e6, 1e6 + 1, 1e6 + 1], np.float32), (S, n_obs, 1))
        for k, g in enumerate(self.grids):
            obstacles[k, : len(g.obstacles)] = g.obstacles
        pose = np.array([[g.pose for g in goals] for goals in self.goals], np.float32)
        tscene = np.array([[g.scene for g in goals] for goals in self.goals], np.int32)
        flat = render_in_chunks(functools.partial(self.render_with, self.backend, self._mjx, geometry, fields), tscene.reshape(-1),
                                pose.reshape(-1, 4))
        h = w = self.cfg.render.image_size
        return WorldArrays(
            geometry=geometry,
            mjx=fields,
            obstacles=jnp.asarray(obstacles),
            grid_origin=jnp.asarray(np.stack([g.origin for g in self.grids]).astype(np.float32)),
            free=jnp.asarray(free),
            diameter=jnp.asarray(diameter),
            goal_dist=jnp.asarray(goal_dist),
            goal_success=jnp.asarray(goal_success),
            goal_min_dist=jnp.asarray(goal_min),
            target_pose=jnp.asarray(pose),
            target_scene=jnp.asarray(tscene),
            target_rgb=flat.rgb.reshape(S, T, h, w, 3),
            target_depth=flat.depth.reshape(S, T, h, w),
            target_seg=flat.cls.astype(jnp.uint8).reshape(S, T, h, w),
            goal_classes=jnp.asarray(goal_classes),
            goal_geoms=jnp.asarray(goal_geoms),
            oracle_dist=jnp.asarray(oracle_dist),
            oracle_yaw=jnp.asarray(oracle_yaw),
        )



def share_shapes(worlds: list[World]) -> None:
    """Pad the arrays of `worlds` (of one configuration) to their common largest shapes,
    so that one function compiled for one of them takes any of them as data."""
    shapes = [[a.shape for a in jax.tree_util.tree_leaves(w.arrays)] for w in worlds]
    largest = [tuple(max(dims) for dims in zip(*leaf)) for leaf in zip(*shapes)]
    target = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(worlds[0].arrays),
                                          [jax.ShapeDtypeStruct(s, a.dtype) for s, a in
                                           zip(largest, jax.tree_util.tree_leaves(worlds[0].arrays))])
    for w in worlds:
        w.arrays = w.arrays.padded_like(target)


WHOLE_BATCH = 2**30  # `CameraSpec.chunk_frames` that renders every frame of a batch in one pass


def render_chunk(platform: str) -> int:
    """The ray caster's frames per pass on a platform: on the CPU a few at a time (0: about
    2**18 pixels, at most 16 frames, so each pass stays in cache; docs/benchmarks.md), on
    an accelerator the whole batch at once (a sequential loop over chunks would serialise it)."""
    return 0 if platform == "cpu" else WHOLE_BATCH


def render_in_chunks(render_fn, scene, pose, chunk: int = 64):
    """`render_fn(scene [n], pose [n, 4]) -> Frame` of many poses [N, 4] (host loop over
    chunks of one compiled shape)."""
    fn = jax.jit(render_fn)
    n = len(scene)
    outs = []
    for i in range(0, n, chunk):
        s = np.zeros(chunk, np.int32)
        p = np.zeros((chunk, 4), np.float32)
        m = min(chunk, n - i)
        s[:m], p[:m] = scene[i : i + m], pose[i : i + m]
        outs.append(jax.tree_util.tree_map(lambda a: a[:m], fn(jnp.asarray(s), jnp.asarray(p))))
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *outs)


def cam_position(pose, camera_height: float):
    """World camera position [..., 3] of agent poses [..., 4]."""
    return jnp.concatenate([pose[..., :2], jnp.full(pose.shape[:-1] + (1,), camera_height, pose.dtype)], -1)

