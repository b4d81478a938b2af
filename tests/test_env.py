"""Tests of the batched navigation environment (`a2catvn_jax.env.NavEnv`).

Everything runs on CPU with tiny configurations (16x16 images, two small scenes, the
unculled renderer, which compiles fastest). Every test that renders runs with each
render backend (`raycast` and `mjx`); each environment is built once per backend and
each of its jitted functions is compiled once.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from a2catvn_jax.config import ConfigError, load_config  # noqa: E402
from a2catvn_jax.env import ACTION_SETS, NavEnv, State  # noqa: E402
from a2catvn_jax.env.scenes.mjcf import compile_scene, geom_aabb  # noqa: E402
from a2catvn_jax.env.scenes.spec import CLASS_ID, STRUCTURAL_CLASSES, half_extents  # noqa: E402
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS  # noqa: E402
from a2catvn_jax.env.world import BODY_MARGIN, World  # noqa: E402

B = 32  # agents per batch
T = 200  # steps per random rollout
TOL = 1e-4  # metres of slack in the collision checks
IMG = 16

BASE = [
    f"env.num_envs={B}",
    f"env.render.image_size={IMG}",
    "env.render.culling=false",
    "env.scene.num_scenes=2",
    "env.goals_per_scene=2",
    "env.scene.grid=[1,2]",
    "env.max_episode_steps=100000",
    # Small goal regions: random walkers rarely end episodes, so almost every pose the
    # agents reach is observed in the trajectory (the pose an episode ends at is not).
    "env.success_distance=0.15",
]

OBS_KEYS = (
    "rgb",
    "depth",
    "segmentation",
    "segmentation_rgb",
    "target_rgb",
    "target_depth",
    "target_segmentation",
    "target_segmentation_rgb",
    "target_index",
)


# ------------------------------------------------------------------------- helpers


def _action_probs(names):
    """Random-walk policy that favours translations (so walls get hit often)."""
    w = np.array([{"forward": 4.0, "backward": 1.5, "left": 1.5, "right": 1.5}.get(n, 1.0) for n in names])
    return w / w.sum()


def _random_actions(env: NavEnv, seed: int, steps: int = T) -> jnp.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.choice(env.num_actions, size=(steps, env.num_envs), p=_action_probs(env.action_names))
    return jnp.asarray(a, jnp.int32)


def _scan_steps(env: NavEnv, state: State, actions):
    """Step through actions [T, B]; returns (final state, per-step record)."""

    def body(s, a):
        s = env.step(s, a)
        rec = {
            "pose": s.info.pose,
            "step": s.info.step,
            "path_length": s.info.path_length,
            "done": s.done,
            "reward": s.reward,
            "success": s.metrics["success"],
            "truncated": s.metrics["truncated"],
            "rgb": s.obs.rgb,
            "depth": s.obs.depth,
            "segmentation": s.obs.segmentation,
        }
        return s, rec

    return jax.lax.scan(body, state, actions)


def make_rollout(env: NavEnv):
    """jit(state, actions [T, B]) -> (final state, record)."""
    return jax.jit(lambda state, actions: _scan_steps(env, state, actions))


def make_run(env: NavEnv):
    """jit(key, actions [T, B]) -> (first state, final state, record): reset + rollout."""

    def run(key, actions):
        s0 = env.reset(key)
        final, rec = _scan_steps(env, s0, actions)
        return s0, final, rec

    return jax.jit(run)


def _np(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def _all_poses(s0: State, rec) -> np.ndarray:
    """Poses [T + 1, B, 4]: the reset pose followed by the pose after every step."""
    return np.concatenate([np.asarray(s0.info.pose)[None], np.asarray(rec["pose"])], 0)


def _check_no_collisions(env: NavEnv, poses: np.ndarray, require_contact: bool = True):
    """Every agent centre stays outside (a) the grown obstacle rectangles the navgrid
    uses and (b) independently, every blocking geom's AABB grown as a disc."""
    cfg = env.cfg
    r = cfg.agent_radius
    S = env.num_scenes
    scene_of = np.arange(poses.shape[1]) % S
    closest = np.inf
    for s in range(S):
        xy = poses[:, scene_of == s, :2].reshape(-1, 2).astype(np.float64)
        assert np.all(np.isfinite(xy))
        # (a) The square-grown rectangles (what `free` and the sweep use).
        rects = np.asarray(env.world.arrays.obstacles[s], np.float64)
        grid_rects = env.world.grids[s].obstacles
        np.testing.assert_allclose(rects[: len(grid_rects)], grid_rects, atol=1e-5)
        rects = grid_rects
        assert len(rects) > 0
        p = xy[:, None, :]
        g = r - TOL
        inside = (
            (p[..., 0] > rects[:, 0] - g)
            & (p[..., 0] < rects[:, 2] + g)
            & (p[..., 1] > rects[:, 1] - g)
            & (p[..., 1] < rects[:, 3] + g)
        )
        if inside.any():
            k, n = np.argwhere(inside)[0]
            raise AssertionError(
                f"scene {s}: agent centre {xy[k]} lies within {g:.4f} m of obstacle rect {rects[n]} "
                f"({int(inside.any(1).sum())} of {len(xy)} poses)"
            )
        # (b) Independent disc test against the scene's geoms.
        scene = env.world.scenes[s]
        boxes = []
        for geom in scene.geoms:
            if geom.cls in ("floor", "ceiling"):
                continue
            lo, hi = geom_aabb(geom)
            if hi[2] >= 0.02 and lo[2] <= cfg.camera_height:
                boxes.append([lo[0], lo[1], hi[0], hi[1]])
        boxes = np.asarray(boxes)
        assert len(boxes) > 0
        dx = np.maximum(np.maximum(boxes[:, 0] - p[..., 0], p[..., 0] - boxes[:, 2]), 0.0)
        dy = np.maximum(np.maximum(boxes[:, 1] - p[..., 1], p[..., 1] - boxes[:, 3]), 0.0)
        dist = np.hypot(dx, dy)  # [N, G]
        if (dist < r - TOL).any():
            k, n = np.argwhere(dist < r - TOL)[0]
            raise AssertionError(
                f"scene {s}: agent centre {xy[k]} is {dist[k, n]:.4f} m from geom box {boxes[n]} "
                f"(agent radius {r})"
            )
        # Everyone stays inside the scene.
        x0, y0, x1, y1 = scene.bounds
        assert np.all((xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1))
        closest = min(closest, float(dist.min()))
    if require_contact:
        # The walk really pushed agents against obstacles (the check was exercised).
        assert closest < r + 0.05, f"agents never came near an obstacle (closest {closest:.3f} m)"


# ------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module", params=["raycast", "mjx"])
def backend(request):
    """Every environment test runs with each render backend (`env.render.backend`)."""
    return request.param


@pytest.fixture(scope="module")
def cfg(backend):
    return load_config(None, BASE + [f"env.render.backend={backend}"])


@pytest.fixture(scope="module")
def env_full(cfg):
    env = NavEnv(cfg.env)
    assert env.action_names == tuple(n for n, _ in ACTION_SETS["full"])
    return env


@pytest.fixture(scope="module")
def reset_full(env_full):
    return jax.jit(lambda k, c: env_full.reset(k, c))


@pytest.fixture(scope="module")
def rollout_full(env_full):
    return make_rollout(env_full)


@pytest.fixture(scope="module")
def traj_full(env_full, reset_full, rollout_full):
    s0 = reset_full(jax.random.PRNGKey(0), 1.0)
    actions = _random_actions(env_full, 0)
    final, rec = rollout_full(s0, actions)
    return {"s0": s0, "actions": actions, "final": final, "rec": _np(rec)}


@pytest.fixture(scope="module")
def env_grid(cfg, env_full):
    return NavEnv(dataclasses.replace(cfg.env, action_set="grid"), world=env_full.world)


@pytest.fixture(scope="module")
def traj_grid(env_grid):
    actions = _random_actions(env_grid, 1)
    s0, final, rec = make_run(env_grid)(jax.random.PRNGKey(1), actions)
    return {"s0": s0, "actions": np.asarray(actions), "final": final, "rec": _np(rec)}


@pytest.fixture(scope="module")
def env_maze(backend):
    cfg = load_config(None, BASE + ["env.scene.kind=maze", "env.scene.grid=[3,3]", f"env.render.backend={backend}"])
    return NavEnv(cfg.env)


@pytest.fixture(scope="module")
def traj_maze(env_maze):
    actions = _random_actions(env_maze, 2)
    s0, final, rec = make_run(env_maze)(jax.random.PRNGKey(2), actions)
    return {"s0": s0, "actions": actions, "final": final, "rec": _np(rec)}


@pytest.fixture(scope="module")
def env_exact(cfg, env_full):
    """No motion noise and 3-step episodes, on the same world as env_full."""
    c = dataclasses.replace(cfg.env, position_noise=0.0, heading_noise_deg=0.0, max_episode_steps=3)
    return NavEnv(c, world=env_full.world)


@pytest.fixture(scope="module")
def step_exact(env_exact):
    return jax.jit(env_exact.step)


# --------------------------------------------------------------------- 1. collisions


@pytest.mark.parametrize("which", ["full", "grid", "maze"])
def test_random_walks_never_enter_obstacles(request, which, backend):
    env = request.getfixturevalue({"full": "env_full", "grid": "env_grid", "maze": "env_maze"}[which])
    traj = request.getfixturevalue(f"traj_{which}")
    rec = traj["rec"]
    poses = _all_poses(traj["s0"], rec)
    assert poses.shape == (T + 1, B, 4)
    # Episodes are long: the walk is not a sequence of fresh starts.
    assert rec["done"].mean() < 0.05
    assert not rec["truncated"].any()
    _check_no_collisions(env, poses, require_contact=which != "grid")
    # Agents do move.
    moved = np.linalg.norm(np.diff(poses[..., :2], axis=0), axis=-1)[~rec["done"]]
    assert moved.mean() > 0.05
    assert float(np.asarray(traj["final"].info.path_length).mean()) > 1.0
    # info.path_length accumulates exactly the distance travelled.
    cont = ~rec["done"][1:]
    inc = (rec["path_length"][1:] - rec["path_length"][:-1])[cont]
    np.testing.assert_allclose(inc, np.linalg.norm(np.diff(rec["pose"][..., :2], axis=0), axis=-1)[cont], atol=1e-4)


# -------------------------------------------------------------------- 2. determinism


def test_same_key_same_trajectory(env_full, reset_full, rollout_full, traj_full):
    actions = traj_full["actions"]
    s0 = reset_full(jax.random.PRNGKey(0), 1.0)
    for k in OBS_KEYS:
        np.testing.assert_array_equal(np.asarray(getattr(s0.obs, k)), np.asarray(getattr(traj_full["s0"].obs, k)))
    final, rec = rollout_full(s0, actions)
    rec = _np(rec)
    for k in ("pose", "rgb", "depth", "reward", "done"):
        np.testing.assert_array_equal(rec[k], traj_full["rec"][k], err_msg=k)
    for k in OBS_KEYS:
        np.testing.assert_array_equal(np.asarray(getattr(final.obs, k)), np.asarray(getattr(traj_full["final"].obs, k)))

    other = reset_full(jax.random.PRNGKey(1), 1.0)
    assert not np.array_equal(np.asarray(other.info.pose), np.asarray(s0.info.pose))
    assert not np.array_equal(np.asarray(other.obs.rgb), np.asarray(s0.obs.rgb))
    _, rec2 = rollout_full(other, actions)
    assert not np.array_equal(np.asarray(rec2["pose"]), rec["pose"])
    # The same start with a different key differs too (motion noise comes from the key).
    keyed = s0.replace(info=s0.info.replace(key=other.info.key))
    _, rec3 = rollout_full(keyed, actions)
    assert not np.array_equal(np.asarray(rec3["pose"][:20]), rec["pose"][:20])


# ------------------------------------------------------------------ 3. reset and obs


def test_reset_shapes_dtypes_and_observations(env_full, reset_full):
    env = env_full
    s = reset_full(jax.random.PRNGKey(3), 1.0)
    shapes = {
        "rgb": ((B, IMG, IMG, 3), np.uint8),
        "depth": ((B, IMG, IMG), np.float32),
        "segmentation": ((B, IMG, IMG), np.uint8),
        "segmentation_rgb": ((B, IMG, IMG, 3), np.uint8),
    }
    assert {f.name for f in dataclasses.fields(s.obs)} == set(OBS_KEYS)
    for k, (shape, dtype) in shapes.items():
        for key in (k, "target_" + k):
            assert getattr(s.obs, key).shape == shape, key
            assert getattr(s.obs, key).dtype == dtype, key
    # The target index picks the observation's target out of the environment's distinct targets.
    index = np.asarray(s.obs.target_index)
    assert index.shape == (B,) and index.dtype == np.int32
    targets = env.target_images()
    assert targets["rgb"].shape[0] == env.num_targets
    for k, name in (("rgb", "target_rgb"), ("depth", "target_depth"), ("segmentation", "target_segmentation")):
        np.testing.assert_array_equal(np.asarray(targets[k])[index], np.asarray(getattr(s.obs, name)))
    assert s.reward.shape == (B,) and s.reward.dtype == jnp.float32
    assert s.done.shape == (B,) and s.done.dtype == jnp.bool_ and not bool(s.done.any())
    info = _np(s.info)
    assert info.scene.dtype == np.int32 and info.goal.dtype == np.int32
    np.testing.assert_array_equal(info.scene, np.arange(B) % env.num_scenes)
    assert np.all((info.goal >= 0) & (info.goal < env.cfg.goals_per_scene))
    assert info.pose.shape == (B, 4) and info.pose.dtype == np.float32
    assert np.all(np.abs(info.pose[:, 2]) <= np.pi + 1e-6) and np.all(info.pose[:, 3] == 0)
    np.testing.assert_array_equal(info.step, 0)
    np.testing.assert_array_equal(info.path_length, 0)
    np.testing.assert_array_equal(info.complexity, 1.0)
    for k in ("success", "truncated", "episode_length", "episode_return", "fallback"):
        assert s.metrics[k].shape == (B,)
    w = env.world.arrays
    sc, g = info.scene, info.goal
    np.testing.assert_array_equal(info.target_pose, np.asarray(w.target_pose)[sc, g])
    np.testing.assert_array_equal(np.asarray(s.obs.target_rgb), np.asarray(w.target_rgb)[sc, g])
    np.testing.assert_array_equal(np.asarray(s.obs.target_depth), np.asarray(w.target_depth)[sc, g])
    np.testing.assert_array_equal(np.asarray(s.obs.target_segmentation), np.asarray(w.target_seg)[sc, g])
    # Segmentation colours.
    assert np.all(SEGMENTATION_COLORS[0] == 0)
    np.testing.assert_array_equal(np.asarray(env.segmentation_rgb(jnp.zeros((), jnp.int32))), [0, 0, 0])
    for k in ("segmentation", "target_segmentation"):
        seg = getattr(s.obs, k)
        np.testing.assert_array_equal(np.asarray(getattr(s.obs, k + "_rgb")), np.asarray(env.segmentation_rgb(seg)))
        assert np.asarray(seg).max() > 0
    # Inside a closed house every ray hits something.
    assert np.all(np.asarray(s.obs.depth) > 0)
    assert np.all(np.asarray(s.obs.segmentation) > 0)
    # The observation is the rendering at the agent's pose.
    render = jax.jit(env.render_pose)
    for b in (0, 5):
        f = render(int(info.scene[b]), info.pose[b])
        np.testing.assert_array_equal(np.asarray(f.cls), np.asarray(s.obs.segmentation[b]))
        np.testing.assert_allclose(np.asarray(f.depth), np.asarray(s.obs.depth[b]), rtol=1e-5, atol=1e-5)
        diff = np.abs(np.asarray(f.rgb, np.int32) - np.asarray(s.obs.rgb[b], np.int32))
        assert diff.max() <= 1
    # ... and not that of another agent.
    f = render(int(info.scene[0]), info.pose[2])
    assert not np.array_equal(np.asarray(f.depth), np.asarray(s.obs.depth[0]))


# ---------------------------------------------------- 4. success, auto-reset, truncation


def test_success_auto_reset_and_truncation(env_exact, step_exact, reset_full):
    env = env_exact
    w = env.world.arrays
    names = env.action_names
    tilt = names.index("tilt_up")
    s = reset_full(jax.random.PRNGKey(4), 1.0)
    info = _np(s.info)
    # Nobody starts inside their goal region.
    gs = np.asarray(w.goal_success)
    for b in range(B):
        ii, jj = env.world.grids[info.scene[b]].cell_of(info.pose[b, :2])
        assert not gs[info.scene[b], info.goal[b], ii, jj]
    # Teleport agent 0 onto its goal (the target image's pose is the goal centre).
    pose = s.info.pose.at[0].set(s.info.target_pose[0])
    s = s.replace(info=s.info.replace(pose=pose))
    action = jnp.full((B,), tilt, jnp.int32)

    s1 = step_exact(s, action)
    r1, d1, m1, i1 = np.asarray(s1.reward), np.asarray(s1.done), _np(s1.metrics), _np(s1.info)
    assert r1[0] == 1.0 and d1[0] and m1["success"][0] and not m1["truncated"][0]
    assert m1["episode_length"][0] == 1 and m1["episode_return"][0] == 1.0
    assert 0.0 < m1["episode_spl"][0] <= 1.0 + 1e-6
    assert m1["episode_start_distance"][0] == info.start_distance[0]
    # Agent 0 was reset in the same step: a new episode, outside its new goal region.
    assert i1.step[0] == 0 and i1.path_length[0] == 0 and i1.episode_return[0] == 0
    assert not np.array_equal(i1.key[0], info.key[0])
    assert not np.allclose(i1.pose[0, :2], info.target_pose[0, :2])
    ii, jj = env.world.grids[i1.scene[0]].cell_of(i1.pose[0, :2])
    assert not gs[i1.scene[0], i1.goal[0], ii, jj]
    np.testing.assert_array_equal(np.asarray(s1.obs.target_rgb[0]), np.asarray(w.target_rgb)[i1.scene[0], i1.goal[0]])
    # Everybody else tilted in place: no reward, not done, one step further.
    assert np.all(r1[1:] == 0) and not d1[1:].any() and not m1["success"][1:].any()
    np.testing.assert_array_equal(i1.step[1:], 1)
    np.testing.assert_array_equal(i1.pose[1:, :2], info.pose[1:, :2])
    np.testing.assert_allclose(i1.pose[1:, 3], np.deg2rad(30.0), atol=1e-6)

    s2 = step_exact(s1, action)
    assert not bool(s2.done.any())
    s3 = step_exact(s2, action)
    r3, d3, m3, i3 = np.asarray(s3.reward), np.asarray(s3.done), _np(s3.metrics), _np(s3.info)
    # max_episode_steps=3: the others are truncated (no reward), agent 0 is at step 2.
    assert d3[1:].all() and m3["truncated"][1:].all() and not m3["success"][1:].any()
    np.testing.assert_array_equal(r3[1:], 0.0)
    np.testing.assert_array_equal(m3["episode_length"][1:], 3)
    np.testing.assert_array_equal(m3["episode_spl"][1:], 0.0)
    np.testing.assert_array_equal(i3.step[1:], 0)
    np.testing.assert_array_equal(i3.pose[1:, 3], 0.0)  # fresh episodes, level camera
    assert not d3[0] and not m3["truncated"][0] and i3.step[0] == 2
    # Tilt saturates at max_tilt_deg.
    np.testing.assert_allclose(np.asarray(s2.info.pose[1:, 3]), np.deg2rad(env.cfg.max_tilt_deg), atol=1e-6)

    # Without noise, unobstructed moves are exactly the commanded displacement.
    moves = {n: np.asarray(m[:2], np.float64) for n, m in ACTION_SETS["full"]}
    order = ("forward", "backward", "left", "right")
    action = jnp.asarray([names.index(order[b % 4]) for b in range(B)], jnp.int32)
    s4 = step_exact(s3, action)
    p3, p4 = np.asarray(s3.info.pose, np.float64), np.asarray(s4.info.pose, np.float64)
    live = ~np.asarray(s4.done)
    c, sn = np.cos(p3[:, 2]), np.sin(p3[:, 2])
    fl = np.stack([moves[order[b % 4]] for b in range(B)])
    want = np.stack([fl[:, 0] * c - fl[:, 1] * sn, fl[:, 0] * sn + fl[:, 1] * c], -1)
    got = p4[:, :2] - p3[:, :2]
    full_move = np.all(np.abs(got - want) < 1e-5, -1)
    assert full_move[live].mean() > 0.5
    # Blocked moves stop short along the same direction, never overshoot.
    frac = np.sum(got * want, -1) / np.sum(want * want, -1)
    np.testing.assert_allclose(got[live], frac[live, None] * want[live], atol=1e-5)
    assert np.all((frac[live] >= 0) & (frac[live] <= 1 + 1e-5))
    np.testing.assert_allclose(p4[live, 2:], p3[live, 2:], atol=1e-6)
    _check_no_collisions(env, p4[None], require_contact=False)


# --------------------------------------------------------------------- 5. curriculum


def test_complexity_is_data(env_full, env_exact, step_exact, reset_full):
    env = env_full
    w = env.world.arrays
    gmin = np.asarray(w.goal_min_dist)
    diam = np.asarray(w.diameter)

    def starts(c):
        out = []
        for seed in (10, 11):  # two batches of 32: 64 starts
            s = reset_full(jax.random.PRNGKey(seed), c)
            out.append(_np(s.info))
        return {k: np.concatenate([getattr(o, k) for o in out]) for k in ("scene", "goal", "start_distance", "complexity")}

    easy, hard = starts(0.0), starts(1.0)
    assert reset_full._cache_size() == 1
    np.testing.assert_array_equal(easy["complexity"], 0.0)
    assert np.all(np.isfinite(easy["start_distance"])) and np.all(easy["start_distance"] > 0)
    assert np.all(easy["start_distance"] <= gmin[easy["scene"], easy["goal"]] + 1e-5)
    assert np.all(hard["start_distance"] <= diam[hard["scene"]] + 1e-5)
    assert hard["start_distance"].mean() > easy["start_distance"].mean() + 0.5
    # Intermediate complexity bounds the start distance by tau * diameter.
    mid = starts(0.3)
    assert reset_full._cache_size() == 1
    lim = np.maximum(0.3 * diam[mid["scene"]], gmin[mid["scene"], mid["goal"]])
    assert np.all(mid["start_distance"] <= lim + 1e-5)

    # set_complexity changes the level of the episodes that follow.
    s = reset_full(jax.random.PRNGKey(12), 1.0)
    s = env.set_complexity(s, 0.0)
    assert s.info.complexity.shape == (B,) and s.info.complexity.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(s.info.complexity), 0.0)
    tilt = jnp.full((B,), env_exact.action_names.index("tilt_up"), jnp.int32)
    for _ in range(3):  # episodes of env_exact are 3 steps long
        s = step_exact(s, tilt)
    info = _np(s.info)
    assert np.asarray(s.done).all() and np.all(info.step == 0)
    assert np.all(info.start_distance <= gmin[info.scene, info.goal] + 1e-5)
    np.testing.assert_array_equal(info.complexity, 0.0)
    s = env.set_complexity(s, jnp.float32(0.7))
    np.testing.assert_allclose(np.asarray(s.info.complexity), 0.7)


# --------------------------------------------------------------------- 6. goal kinds


def _short_run(env, seed, steps=3):
    actions = _random_actions(env, seed, steps)
    s0, final, rec = make_run(env)(jax.random.PRNGKey(seed), actions)
    return s0, final, _np(rec)


def _check_targets(env, state):
    w = env.world.arrays
    rgb = np.asarray(w.target_rgb)
    assert rgb.shape[:2] == (env.num_scenes, env.cfg.goals_per_scene)
    for s in range(env.num_scenes):
        for g in range(env.cfg.goals_per_scene):
            assert rgb[s, g].max() > 0 and rgb[s, g].std() > 0
            assert np.asarray(w.target_depth[s, g]).max() > 0
            assert np.asarray(w.target_seg[s, g]).max() > 0
    info = _np(state.info)
    np.testing.assert_array_equal(np.asarray(state.obs.target_rgb), rgb[info.scene, info.goal])


@pytest.mark.parametrize("goal", ["room", "object"])
def test_goal_kinds(goal, backend):
    cfg = load_config(None, BASE + ["env.num_envs=8", f"env.goal={goal}", "env.scene.grid=[2,2]",
                                    f"env.render.backend={backend}"])
    env = NavEnv(cfg.env)
    s0, final, rec = _short_run(env, 5)
    assert rec["pose"].shape == (3, 8, 4)
    np.testing.assert_array_equal(rec["reward"], rec["success"].astype(np.float32))
    _check_targets(env, final)
    w = env.world
    gs = np.asarray(w.arrays.goal_success)
    free = np.asarray(w.arrays.free)
    for s, scene in enumerate(w.scenes):
        grid = w.grids[s]
        h, wd = grid.shape
        for g, goal_def in enumerate(w.goals[s]):
            region = gs[s, g, :h, :wd]
            assert region.any()
            assert not gs[s, g, h:].any() and not gs[s, g, :, wd:].any()
            assert np.all(free[s, :h, :wd][region])
            if goal == "room":
                rooms = grid.room[region]
                assert np.all(rooms >= 0)
                types = {scene.rooms[k].type for k in np.unique(rooms)}
                assert types == {goal_def.label}
                # ... and it is all the free floor of the rooms of that type.
                same = [k for k, room in enumerate(scene.rooms) if room.type == goal_def.label]
                np.testing.assert_array_equal(region, grid.free & np.isin(grid.room, same))
                # The target image is taken in a room of that type.
                ts = int(w.arrays.target_scene[s, g])
                tp = np.asarray(w.arrays.target_pose[s, g])
                ti, tj = w.grids[ts].cell_of(tp[:2])
                k = w.grids[ts].room[ti, tj]
                assert k >= 0 and w.scenes[ts].rooms[k].type == goal_def.label
            else:
                obj = [x for x in scene.geoms if x.name == goal_def.label]
                assert len(obj) == 1
                obj = obj[0]
                assert obj.cls not in STRUCTURAL_CLASSES and obj.cls != "rug"
                lo, hi = geom_aabb(obj)
                c = grid.centres()[region]
                dx = np.maximum(np.maximum(lo[0] - c[:, 0], c[:, 0] - hi[0]), 0)
                dy = np.maximum(np.maximum(lo[1] - c[:, 1], c[:, 1] - hi[1]), 0)
                assert np.all(np.hypot(dx, dy) <= cfg.env.object_distance + 1e-6)
                # The object is what the target image looks at.
                seg = np.asarray(w.arrays.target_seg[s, g])
                assert (seg == CLASS_ID[obj.cls]).any()
    # Starts lie outside the goal regions.
    info = _np(s0.info)
    for b in range(8):
        ii, jj = w.grids[info.scene[b]].cell_of(info.pose[b, :2])
        assert not gs[info.scene[b], info.goal[b], ii, jj]
    _check_no_collisions(env, _all_poses(s0, rec), require_contact=False)


# --------------------------------------------------------------- 7. grid action set


def test_grid_moves(env_grid, traj_grid):
    assert env_grid.action_names == ("forward", "backward", "rotate_left", "rotate_right")
    rec, actions = traj_grid["rec"], traj_grid["actions"]
    poses = _all_poses(traj_grid["s0"], rec)
    yaw = poses[..., 2].astype(np.float64)
    k = yaw / (np.pi / 2)
    assert np.all(np.abs(k - np.round(k)) < 1e-5), "yaw left the multiples of 90 degrees"
    np.testing.assert_array_equal(poses[..., 3], 0.0)
    # Starts sit at cell centres.
    res = env_grid.cfg.grid_resolution
    origin = np.asarray(env_grid.world.arrays.grid_origin)[np.arange(B) % env_grid.num_scenes]
    cell = (poses[0, :, :2] - origin) / res - 0.5
    assert np.all(np.abs(cell - np.round(cell)) < 1e-3)
    cont = ~rec["done"]  # transitions within an episode
    d = np.diff(poses[..., :2], axis=0)
    dist = np.linalg.norm(d, axis=-1)
    turn = np.angle(np.exp(1j * np.diff(yaw, axis=0)))
    moves = (actions == 0) | (actions == 1)
    ok = cont & moves
    assert np.all((np.abs(dist[ok] - 0.33) < 1e-5) | (dist[ok] < 1e-6))
    assert (np.abs(dist[ok] - 0.33) < 1e-5).mean() > 0.5  # most moves go through
    assert (dist[ok] < 1e-6).any()  # and some are blocked
    # Moves go along the heading (forward) or against it (backward) and keep the yaw.
    heading = np.stack([np.cos(yaw[:-1]), np.sin(yaw[:-1])], -1)
    sign = np.where(actions == 0, 1.0, -1.0)
    went = ok & (dist > 1e-6)
    np.testing.assert_allclose(d[went], (0.33 * sign[..., None] * heading)[went], atol=1e-5)
    np.testing.assert_allclose(turn[cont & moves], 0.0, atol=1e-5)
    # Rotations turn by exactly 90 degrees in place.
    for a, sgn in ((2, 1.0), (3, -1.0)):
        rot = cont & (actions == a)
        assert rot.any()
        np.testing.assert_allclose(turn[rot], sgn * np.pi / 2, atol=1e-5)
        np.testing.assert_array_equal(dist[rot], 0.0)


# -------------------------------------------------------------------- 8. bad input


def test_unknown_action_set(cfg):
    with pytest.raises(ValueError, match="bogus"):
        NavEnv(dataclasses.replace(cfg.env, action_set="bogus"))
    with pytest.raises(ConfigError, match="env.action_set"):
        load_config(None, ["env.action_set=bogus"])


def test_image_too_small(cfg):
    with pytest.raises(ConfigError, match="too small for the network") as e:
        load_config(None, ["env.render.image_size=8"])
    assert e.value.key == "env.render.image_size"
    bad = dataclasses.replace(cfg.env, render=dataclasses.replace(cfg.env.render, image_size=8))
    with pytest.raises(ValueError, match="too small for the network"):
        NavEnv(bad)


@pytest.mark.parametrize(
    "override, key",
    [
        ("env.agent_radius=-1", "env.agent_radius"),
        ("env.num_envs=0", "env.num_envs"),
        ("env.complexity=1.5", "env.complexity"),
        ("env.goal=teleport", "env.goal"),
        ("env.position_noise=-0.1", "env.position_noise"),
    ],
)
def test_invalid_config_values(override, key):
    with pytest.raises(ConfigError) as e:
        load_config(None, [override])
    assert e.value.key == key
    assert str(e.value).startswith(key)


def test_room_goals_need_houses():
    with pytest.raises(ConfigError, match="env.goal"):
        load_config(None, ["env.goal=room", "env.scene.kind=maze"])


def test_broken_mjcf(tmp_path):
    path = tmp_path / "broken.xml"
    path.write_text('<mujoco><worldbody><geom name="floor" type="box" size="1 1"</worldbody></mujoco>')
    cfg = load_config(None, BASE + ["env.scene.kind=mjcf", f"env.scene.mjcf_path={path}"])
    with pytest.raises(ValueError, match="MJCF does not compile"):
        NavEnv(cfg.env)
    cfg = load_config(None, BASE + ["env.scene.kind=mjcf", f"env.scene.mjcf_path={tmp_path / 'missing.xml'}"])
    with pytest.raises(ValueError, match="missing.xml: cannot read the MJCF file"):
        NavEnv(cfg.env)


USER_MJCF = """
<mujoco model="user_room">
  <asset>
    <material name="wood" rgba="0.6 0.4 0.2 1"/>
  </asset>
  <worldbody>
    <geom name="floor_0" type="box" pos="0 0 -0.05" size="1.5 1.5 0.05" rgba="0.8 0.8 0.8 1"/>
    <geom name="wall_n" type="box" pos="0 1.45 1.25" size="1.5 0.05 1.25" rgba="0.9 0.9 0.7 1"/>
    <geom name="wall_s" type="box" pos="0 -1.45 1.25" size="1.5 0.05 1.25" rgba="0.9 0.9 0.7 1"/>
    <geom name="wall_e" type="box" pos="1.45 0 1.25" size="0.05 1.4 1.25" rgba="0.7 0.9 0.9 1"/>
    <geom name="wall_w" type="box" pos="-1.45 0 1.25" size="0.05 1.4 1.25" rgba="0.7 0.9 0.9 1"/>
    <geom name="table_0" type="box" pos="0.5 0.4 0.4" size="0.4 0.3 0.4" material="wood"/>
  </worldbody>
</mujoco>
"""


def test_user_mjcf_scene(tmp_path, backend):
    path = tmp_path / "room.xml"
    path.write_text(USER_MJCF)
    cfg = load_config(
        None,
        BASE + ["env.num_envs=8", "env.scene.kind=mjcf", f"env.scene.mjcf_path={path}", "env.goal=image",
                f"env.render.backend={backend}"],
    )
    env = NavEnv(cfg.env)
    assert env.num_scenes == 1
    assert [g.name for g in env.world.scenes[0].geoms if g.cls == "table"] == ["table_0"]
    s0, final, rec = _short_run(env, 6, steps=20)
    _check_targets(env, final)
    poses = _all_poses(s0, rec)
    _check_no_collisions(env, poses, require_contact=False)
    assert np.all(np.abs(poses[..., :2]) < 1.4 - env.cfg.agent_radius + TOL)
    # The table is seen from somewhere.
    target_seg = np.asarray(env.world.arrays.target_seg[0])
    assert target_seg.shape == (2, IMG, IMG)
    seg = np.concatenate([np.asarray(s0.obs.segmentation), np.asarray(rec["segmentation"]).reshape(-1, IMG, IMG), target_seg])
    assert (seg == CLASS_ID["table"]).any()


NATIVE_MJCF = """
<mujoco model="native_room">
  <asset>
    <texture name="checker" type="2d" builtin="checker" width="32" height="32" rgb1=".3 .3 .3" rgb2=".8 .8 .8"/>
    <material name="tiles" texture="checker" texrepeat="3 3"/>
    <mesh name="chair_mesh" file="chair.obj"/>
  </asset>
  <worldbody>
    <light directional="true" dir="0.2 0.1 -1" diffuse="0.7 0.7 0.7" castshadow="false"/>
    <geom name="floor" type="plane" size="1.5 1.5 0.1" material="tiles"/>
    <geom name="wall_n" type="box" pos="0 1.45 1.25" size="1.5 0.05 1.25"/>
    <geom name="wall_s" type="box" pos="0 -1.45 1.25" size="1.5 0.05 1.25"/>
    <geom name="wall_e" type="box" pos="1.45 0 1.25" size="0.05 1.4 1.25"/>
    <geom name="wall_w" type="box" pos="-1.45 0 1.25" size="0.05 1.4 1.25"/>
    <geom name="table_0" type="cylinder" pos="0.5 0.4 0.4" size="0.35 0.4" rgba="0.2 0.6 0.2 1"/>
    <geom name="chair_0" type="mesh" mesh="chair_mesh" pos="-0.7 -0.6 0" rgba="0.8 0.2 0.2 1"/>
  </worldbody>
</mujoco>
"""
# A tetrahedron in Wavefront OBJ, next to the MJCF file that names it.
CHAIR_OBJ = "v 0 0 0\nv 0.5 0 0\nv 0 0.5 0\nv 0 0 0.7\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_user_mjcf_with_planes_cylinders_and_meshes(tmp_path):
    """With the mjx backend a user's scene keeps its own model: a textured plane floor,
    a cylinder table and a mesh chair (an OBJ file beside the MJCF) render with their
    classes, object goals find them, and their bounding boxes block the agent. `auto`
    takes mjx for such a scene and says why."""
    path = tmp_path / "room.xml"
    path.write_text(NATIVE_MJCF)
    (tmp_path / "chair.obj").write_text(CHAIR_OBJ)
    overrides = BASE + ["env.num_envs=8", "env.scene.kind=mjcf", f"env.scene.mjcf_path={path}", "env.goal=object"]
    env = NavEnv(load_config(None, overrides + ["env.render.backend=mjx"]).env)
    assert env.world.backend == "mjx" and env.world.scenes[0].source == ("file", str(path))
    assert {(g.name, g.native) for g in env.world.scenes[0].geoms if g.native} == {
        ("floor", "plane"), ("table_0", "cylinder"), ("chair_0", "mesh")}
    text = env.scene_mjcf(0)  # compiles from any folder: its mesh folder is absolute
    assert "chair_mesh" in text and "agent_cam" in text and compile_scene(text).nmesh == 1
    chair = next(g for g in env.world.scenes[0].geoms if g.name == "chair_0")
    np.testing.assert_allclose(chair.pos - chair.size, [-0.7, -0.6, 0.0], atol=1e-6)  # the OBJ's vertices, placed
    np.testing.assert_allclose(chair.pos + chair.size, [-0.2, -0.1, 0.7], atol=1e-6)
    s0, final, rec = _short_run(env, 6, steps=20)
    _check_targets(env, final)
    poses = _all_poses(s0, rec)
    _check_no_collisions(env, poses, require_contact=False)
    seg = np.concatenate([np.asarray(s0.obs.segmentation), np.asarray(rec["segmentation"]).reshape(-1, IMG, IMG),
                          np.asarray(env.world.arrays.target_seg[0])])
    assert (seg == CLASS_ID["table"]).any() and (seg == CLASS_ID["chair"]).any() and (seg == CLASS_ID["floor"]).any()
    auto = World(load_config(None, overrides + ["env.render.backend=auto"]).env, env.world.scenes)
    assert auto.backend == "mjx" and "only the mjx backend renders" in auto.backend_note


MOVING_MJCF = (Path(__file__).resolve().parent / "data" / "moving_scene.xml").read_text()


def test_scene_with_moving_bodies(tmp_path, backend):
    """A user's scene with a door on a hinge, a drawer on a slide and a lamp that is
    sometimes above the agent: every episode draws the joints' positions within their
    ranges into its `mjx.Data`; the agent never starts in, nor walks into, a moving
    geom where MuJoCo's own kinematics places it (a lamp above its body does not block
    it), a door in the way stops a step short, and what the agent sees is rendered
    from its data (the door shows up in the segmentation)."""
    path = tmp_path / "moving.xml"
    path.write_text(MOVING_MJCF)
    overrides = BASE + ["env.num_envs=8", "env.scene.kind=mjcf", f"env.scene.mjcf_path={path}", "env.goal=image",
                        "env.max_episode_steps=6", f"env.render.backend={backend}"]
    env = NavEnv(load_config(None, overrides).env)
    model, mw = env.world.models[0], env.world.mjx
    assert mw.nq == 4 and len(mw.moving) == 5
    actions = _random_actions(env, 3, 60)

    def run(key):
        s0 = env.reset(key)

        def body(s, a):
            s = env.step(s, a)
            return s, (s.info.pose, s.data.qpos, s.obs.segmentation, s.info.step, s.obs.depth)

        return s0, jax.lax.scan(body, s0, actions)[1]

    s0, (pose, qpos, seg, step, depth) = jax.jit(run)(jax.random.PRNGKey(0))
    pose = np.concatenate([np.asarray(s0.info.pose)[None], np.asarray(pose)]).reshape(-1, 4)
    qpos = np.concatenate([np.asarray(s0.data.qpos)[None], np.asarray(qpos)]).reshape(-1, 4)
    lo, hi = (np.asarray(a) for a in mw.qpos_range)
    assert np.all((qpos >= lo - 1e-6) & (qpos <= hi + 1e-6))
    assert len(np.unique(qpos[:, 0].round(4))) > 40  # a new door angle each episode (8 agents, ~10 episodes each)
    assert np.all(np.isfinite(np.asarray(depth)))
    r = env.cfg.agent_radius
    d = mujoco.MjData(model)
    above = 0
    for p, q in zip(pose, qpos):
        d.qpos[:] = q
        mujoco.mj_forward(model, d)
        for g in mw.moving:
            # The exact box of the geom where MuJoCo puts it (the static geoms' NumPy formula).
            kind = mujoco.mjtGeom(int(model.geom_type[g])).name.removeprefix("mjGEOM_").lower()
            half = half_extents(kind, d.geom_xmat[g].reshape(3, 3), model.geom_size[g])
            lo3, hi3 = d.geom_xpos[g] - half, d.geom_xpos[g] + half
            if lo3[2] >= env.cfg.camera_height + BODY_MARGIN:
                above += 1
                continue
            inside = np.all(p[:2] > lo3[:2] - r + TOL) and np.all(p[:2] < hi3[:2] + r - TOL)
            assert not inside, (p, q, mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(g)))
    assert above > 0  # the lamp was above the agent's body at times
    door = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "door_frame_leaf")
    assert (np.asarray(seg) == CLASS_ID["door_frame"]).any() and env.world.arrays.geometry.cls[0, door] == CLASS_ID["door_frame"]
    # A closed door (angle 0: along y = -0.6, x in [0, 1]) in front of an agent facing it.
    w = env.world.arrays
    scene = jnp.zeros(8, jnp.int32)
    start = jnp.tile(jnp.asarray([0.5, -1.2, np.pi / 2, 0.0], jnp.float32), (8, 1))
    data = jax.jit(lambda w, s, q, p: env.world.place_agent(env.world.scene_data(w, s, q), p))(w, scene, jnp.zeros((8, 4)), start)
    state = s0.replace(info=s0.info.replace(pose=start, step=jnp.zeros(8, jnp.int32), scene=scene), data=data)
    after = jax.jit(env.step)(state, jnp.zeros(8, jnp.int32))  # forward 0.5 m
    y = np.asarray(after.info.pose[:, 1])
    assert np.all(y <= -0.6 - 0.03 - r + 1e-3) and np.all(y > -1.2), y


# ------------------------------------------------------------- 8. the two backends agree


def test_backends_give_the_same_episodes(goal="room"):
    """The same world, seed and actions with `raycast` and with `mjx`: the same poses,
    rewards and episode ends, depth within 1e-3 m and the same segmentation (room goals,
    whose episodes end on what the agent sees). Only the colours differ (each backend's shading)."""
    runs = {}
    for backend in ("raycast", "mjx"):
        cfg = load_config(None, BASE + ["env.num_envs=8", f"env.goal={goal}", "env.scene.grid=[2,2]",
                                        "env.max_episode_steps=15", f"env.render.backend={backend}"])
        env = NavEnv(cfg.env)
        assert env.world.backend == backend
        runs[backend] = (env, *_short_run(env, 7, steps=40))
    (env_r, _, _, rec_r), (env_m, _, _, rec_m) = runs["raycast"], runs["mjx"]
    for key in ("pose", "reward", "success", "truncated", "done"):
        np.testing.assert_array_equal(rec_r[key], rec_m[key], err_msg=key)
    assert rec_r["done"].any()
    depth_r, depth_m = np.asarray(rec_r["depth"]), np.asarray(rec_m["depth"])
    np.testing.assert_allclose(depth_m, depth_r, atol=1e-3)  # mjx.render computes in float32
    # The same class everywhere but where two surfaces are hit at the same distance (a tie).
    differ = rec_m["segmentation"] != rec_r["segmentation"]
    assert differ.mean() < 1e-3, differ.mean()
    np.testing.assert_array_equal(env_m.target_images()["segmentation"], env_r.target_images()["segmentation"])
    np.testing.assert_allclose(env_m.target_images()["depth"], env_r.target_images()["depth"], atol=1e-3)
    assert not np.array_equal(rec_r["rgb"], rec_m["rgb"])
