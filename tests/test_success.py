"""Success criteria of each goal kind, the stop action, the shortest-path oracle, and old
runs' settings.

Tiny houses (16x16 images, the unculled renderer, no motion noise); each environment
is built once per module.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import yaml

from a2catvn_jax.config import load_config, save_config
from a2catvn_jax.env import NavEnv
from a2catvn_jax.env.oracle import oracle_actions
from a2catvn_jax.env.scenes.spec import CLASS_ID
from a2catvn_jax.run.checkpoint import LEGACY_VALUES, read_run_config, with_legacy_values

B = 16
BASE = [
    f"env.num_envs={B}",
    "env.render.image_size=16",
    "env.render.culling=false",
    "env.scene.kind=house",
    "env.scene.num_scenes=2",
    "env.goals_per_scene=2",
    "env.position_noise=0.0",
    "env.heading_noise_deg=0.0",
]


def _env(*overrides):
    return NavEnv(load_config(None, BASE + list(overrides)).env)


@pytest.fixture(scope="module")
def image_env():
    return _env("env.scene.grid=[1,2]", "env.goal=image", "env.success_heading_deg=45")


def _at_target(env, yaw_offsets_deg):
    """A state whose agents stand where their target image was taken, turned by the offsets."""
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    target = state.info.target_pose
    yaw = target[:, 2] + jnp.deg2rad(jnp.asarray(yaw_offsets_deg, jnp.float32))
    pose = target.at[:, 2].set(jnp.arctan2(jnp.sin(yaw), jnp.cos(yaw))).at[:, 3].set(0.0)
    return state.replace(info=state.info.replace(pose=pose))


OFFSETS = [0, 10, -30, 44, -44, 46, -46, 60, 90, -90, 135, 180, 20, -20, 50, 40]


@pytest.mark.parametrize("heading", [45.0, 180.0])
def test_image_goals_need_the_target_heading(image_env, heading):
    """At the target's position, tilting the camera (no move) ends the episode exactly when
    the heading is within `success_heading_deg` of the target image's (180: any)."""
    env = image_env if heading == 45.0 else NavEnv(
        load_config(None, BASE + ["env.scene.grid=[1,2]", "env.goal=image", "env.success_heading_deg=180"]).env,
        world=image_env.world)
    state = _at_target(env, OFFSETS)
    tilt = env.action_names.index("tilt_up")
    after = jax.jit(env.step)(state, jnp.full((B,), tilt))
    expected = np.abs(OFFSETS) <= heading
    np.testing.assert_array_equal(np.asarray(after.terminated), expected)
    np.testing.assert_array_equal(np.asarray(after.reward), expected.astype(np.float32))


def _rollout(env, steps, seed=0):
    """The oracle's rollout: per step the observation's classes, the info it was taken
    with, and whether the step that followed ended the episode with success."""

    def body(state, key):
        action = oracle_actions(env, state, key)
        nxt = env.step(state, action)
        return nxt, (state.obs.segmentation, state.info.scene, state.info.goal, state.info.pose,
                     nxt.terminated, nxt.done, nxt.metrics["episode_spl"])

    run = jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, steps)))
    state = jax.jit(env.reset)(jax.random.PRNGKey(seed))
    return jax.device_get(run(state, jax.random.PRNGKey(seed + 1))[1])


def _region(env, scene, goal, pose):
    w = env.world
    out = np.zeros(scene.shape, bool)
    for idx in np.ndindex(scene.shape):
        i, j = w.grids[scene[idx]].cell_of(pose[idx][:2])
        out[idx] = np.asarray(w.arrays.goal_success)[scene[idx], goal[idx], i, j]
    return out


@pytest.mark.parametrize("steps_in_a_row", [1, 2])
def test_room_goals_need_their_objects_in_sight(steps_in_a_row):
    """Room-type goals: a step ends the episode with success exactly when the observations
    up to it showed, from inside a room of the target type, the type's characteristic
    objects on at least `view_fraction` of the image for `view_steps` steps in a row
    (checked against the observations the agent saw)."""
    fraction = 0.05
    env = _env("env.scene.grid=[2,2]", "env.goal=room", "env.action_set=no_tilt", "env.max_episode_steps=60",
               f"env.view_fraction={fraction}", f"env.view_steps={steps_in_a_row}")
    seg, scene, goal, pose, terminated, done, _ = _rollout(env, 120)
    classes = np.asarray(env.world.arrays.goal_classes)
    shows = classes[scene[..., None, None], goal[..., None, None], seg]  # [T, B, h, w]
    seen = _region(env, scene, goal, pose) & (shows.mean((-1, -2)) >= fraction)
    streak = np.zeros(B, int)
    for t in range(seen.shape[0]):
        new_episode = done[t - 1] if t else np.ones(B, bool)
        streak = np.where(seen[t], np.where(new_episode, 0, streak) + 1, 0)
        np.testing.assert_array_equal(terminated[t], streak >= steps_in_a_row, err_msg=f"step {t}")
    assert terminated.sum() >= B // 2  # the oracle gets there
    # Each room goal is shown by the classes of its room type.
    for s, goals in enumerate(env.world.goals):
        for g, goal_def in enumerate(goals):
            assert goal_def.classes and set(np.flatnonzero(classes[s, g])) == {CLASS_ID[c] for c in goal_def.classes}


def test_object_goals_count_the_objects_pixels():
    """Object goals are shown by the pixels of the pictured object's geoms (all parts of it,
    no other object): `in_view` against a count over rendered geom ids."""
    env = _env("env.scene.grid=[1,2]", "env.goal=object", "env.object_distance=1.5", "env.view_fraction=0.02")
    w = env.world
    poses, scenes, goals = [], [], []
    for s, goal_defs in enumerate(w.goals):
        for g, goal_def in enumerate(goal_defs):
            assert goal_def.label in goal_def.geoms
            for yaw in np.linspace(-np.pi, np.pi, 8, endpoint=False):
                poses.append([*goal_def.pose[:2], goal_def.pose[2] + yaw, 0.0])
                scenes.append(s)
                goals.append(g)
    scenes, goals = np.array(scenes), np.array(goals)
    frame = env.render_poses(scenes, np.array(poses, np.float32))
    got = np.asarray(env.in_view(w.arrays, jnp.asarray(scenes), jnp.asarray(goals), frame))
    geom = np.asarray(frame.geom)
    want = []
    for n, (s, g) in enumerate(zip(scenes, goals)):
        ids = [mujoco.mj_name2id(w.models[s], mujoco.mjtObj.mjOBJ_GEOM, name) for name in w.goals[s][g].geoms]
        want.append(np.isin(geom[n], ids).mean() >= 0.02)
    np.testing.assert_array_equal(got, want)
    assert np.any(want) and not np.all(want)  # facing it counts, facing away does not


def test_oracle_reaches_image_goals_on_short_paths(image_env):
    """The oracle ends every episode with success, on paths close to the shortest
    (SPL is at most 1 and its mean is high)."""
    *_, terminated, done, spl = _rollout(image_env, 150)
    first = done.argmax(0)
    assert done.any(0).all()
    assert terminated[first, np.arange(B)].all()
    spls = spl[done]
    assert np.all(spls <= 1.0 + 1e-6) and spls.mean() > 0.6


def test_runs_written_before_the_criteria_keep_their_behaviour(tmp_path):
    """A run whose saved configuration predates a key takes the value that reproduces how
    it behaved (position-only success), whatever the current default."""
    cfg = load_config(None)
    save_config(cfg, tmp_path / "config.yaml")
    text = yaml.safe_load((tmp_path / "config.yaml").read_text())
    for key in ("success_heading_deg", "view_fraction"):
        del text["env"][key]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(text))
    old = read_run_config(tmp_path)
    assert old.env.success_heading_deg == LEGACY_VALUES["env.success_heading_deg"] == 180.0
    assert old.env.view_fraction == LEGACY_VALUES["env.view_fraction"] == 0.0
    assert with_legacy_values(text)["env"]["view_fraction"] == 0.0
    # A saved configuration that has the keys keeps its own values.
    save_config(cfg, tmp_path / "config.yaml")
    assert read_run_config(tmp_path).env.success_heading_deg == cfg.env.success_heading_deg != 180.0


def test_new_scene_per_episode():
    """With `new_scene_per_episode` each episode starts in a scene drawn uniformly (the
    observation's target and the start follow it); without, agent b stays in scene b mod S."""
    cfgs = [load_config(None, BASE + ["env.scene.kind=room", "env.scene.num_scenes=4", "env.num_envs=4",
                                      "env.max_episode_steps=1", f"env.new_scene_per_episode={flag}"]).env
            for flag in ("true", "false")]
    first = NavEnv(cfgs[0])
    scenes = {}
    for cfg in cfgs:
        env = NavEnv(cfg, world=first.world)

        def body(state, key):
            nxt = env.step(state, jax.random.randint(key, (4,), 0, env.num_actions))
            return nxt, (nxt.info.scene, nxt.info.goal, nxt.obs.target_index, nxt.done)

        state = jax.jit(env.reset)(jax.random.PRNGKey(0))
        run = jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, 200)))
        scene, goal, target, done = jax.device_get(run(state, jax.random.PRNGKey(1))[1])
        assert done.all()
        np.testing.assert_array_equal(target, scene * cfg.goals_per_scene + goal)
        scenes[cfg.new_scene_per_episode] = scene
    np.testing.assert_array_equal(scenes[False], np.broadcast_to(np.arange(4), (200, 4)))
    counts = np.bincount(scenes[True].ravel(), minlength=4)
    assert counts.min() > 150 and counts.max() < 250  # 800 draws, 200 expected per scene
    assert all(len(np.unique(scenes[True][:, b])) == 4 for b in range(4))


@pytest.mark.parametrize("goal", ["room", "image"])
def test_with_a_stop_action_only_a_stop_at_the_goal_succeeds(goal):
    """`env.stop_action`: "stop" is the last action and does not move; every stop ends the
    episode (`terminated`), rewarded exactly where the criterion held when it was taken
    (`goal_reached`), and reaching the goal without stopping ends nothing. Checked on a
    rollout of the oracle, which stops where stopping succeeds, with a tenth of its
    actions replaced by random ones (stops among them)."""
    extra = (["env.scene.grid=[2,2]", "env.goal=room", "env.action_set=no_tilt"] if goal == "room" else
             ["env.scene.grid=[1,2]", "env.goal=image"])
    env = _env(*extra, "env.max_episode_steps=60", "env.stop_action=true")
    assert env.action_names[-1] == "stop" and env.stop_index == env.num_actions - 1
    np.testing.assert_array_equal(env.moves[-1], 0.0)

    def body(state, key):
        k1, k2, k3 = jax.random.split(key, 3)
        random = jax.random.randint(k2, (B,), 0, env.num_actions)
        oracle = oracle_actions(env, state, k1)
        action = jnp.where(jax.random.uniform(k3, (B,)) < 0.1, random, oracle)
        nxt = env.step(state, action)
        return nxt, (env.goal_reached(state), action, nxt.terminated, nxt.truncated, nxt.metrics["success"],
                     nxt.reward, oracle)

    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    run = jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, 150)))
    reached, action, terminated, truncated, success, reward, oracle = jax.device_get(
        run(state, jax.random.PRNGKey(1))[1])
    stopped = action == env.stop_index
    np.testing.assert_array_equal(terminated, stopped)
    np.testing.assert_array_equal(success, stopped & reached)
    np.testing.assert_array_equal(reward, success.astype(np.float32))
    assert (reached & ~stopped).any()  # the goal reached without a stop: the episode goes on
    assert success.sum() >= B and (stopped & ~reached).any()  # successes and failed stops both occur
    np.testing.assert_array_equal(oracle == env.stop_index, reached)  # the oracle stops exactly where that succeeds


def test_baselines_with_a_stop_action():
    """With a stop action the oracle still succeeds in every episode; the random policy
    stops within a few steps, nearly always in the wrong place."""
    cfg = load_config(None, BASE + ["env.scene.grid=[1,2]", "env.goal=image", "env.max_episode_steps=60",
                                    "env.stop_action=true"])
    from a2catvn_jax.run.evaluation import evaluate_baseline

    oracle = evaluate_baseline(cfg, B, policy="oracle", log=lambda _: None)
    random = evaluate_baseline(cfg, B, policy="random", log=lambda _: None)
    assert oracle["success_rate"] == 1.0
    assert random["success_rate"] <= 0.2 and random["episode_length"] < 20


def test_an_agent_trains_with_a_stop_action(tmp_path):
    """The network's policy gets one output per action, stop included: a tiny run trains
    two updates with finite losses (the trained policy's evaluation is the same code for
    any action count; the baselines' above covers the stop's). The training runs in a
    process with only one of the suite's two fast-compile XLA flags (conftest.py):
    together they make XLA's CPU backend return non-finite gradients (in the pixel-control
    term) for this learner whenever its action count is other than 4 or 8 (6, 7 and 9
    tried, with and without a stop action), while each flag alone, and the defaults, give
    finite ones."""
    import json
    import os
    import subprocess
    import sys

    from tiny import TINY_ROOM

    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if f != "--xla_cpu_use_fusion_emitters=false"]
    env = dict(os.environ, XLA_FLAGS=" ".join(flags))
    done = subprocess.run([sys.executable, "-m", "a2catvn_jax.train", "--workdir", str(tmp_path), "--updates", "2",
                           "--no-progress", "--set", *TINY_ROOM, "env.stop_action=true", "train.log_every=1",
                           "train.checkpoint_every=2"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "9 actions" in done.stdout + done.stderr  # the full set's 8 and stop
    rows = [json.loads(r) for r in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all(np.isfinite(r["loss/actor"]) and np.isfinite(r["grad_norm"]) for r in rows)
