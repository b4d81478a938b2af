"""The synthetic environment (env.kind=synthetic): NavEnv's State contract, and dynamics
checked against a shortest-path search written here."""

import collections

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.configio import ConfigError
from a2catvn_jax.env import NavEnv, SyntheticEnv, make_env, require_world
from a2catvn_jax.env.synthetic import HEADINGS, SIDE

BASE = ["env.num_envs=6", "env.render.image_size=16", "env.scene.num_scenes=2", "env.goals_per_scene=3",
        "env.max_episode_steps=40", "env.action_set=grid"]


def _env(*extra):
    return make_env(load_config(None, ["env.kind=synthetic", *BASE, *extra]).env)


@pytest.fixture(scope="module")
def env():
    return _env()


@pytest.fixture(scope="module")
def step(env):
    return jax.jit(env.step)


def _spec(tree):
    return jax.tree_util.tree_map(lambda a: (a.shape, a.dtype), tree)


def test_reset_and_step_honour_navenv_state_contract(env):
    """Observation, Info, metrics, reward and flags: the same fields, shapes and dtypes
    as NavEnv's for the same configuration (only `data` is the environment's own)."""
    cfg = load_config(None, [*BASE, "env.scene.kind=room", "env.render.culling=false"]).env
    real = NavEnv(cfg)
    key = jax.random.PRNGKey(0)
    for fn in (lambda e: e.reset(key), lambda e: e.step(e.reset(key), jnp.zeros((6,), jnp.int32))):
        ours, theirs = jax.eval_shape(lambda: fn(env)), jax.eval_shape(lambda: fn(real))
        for name in ("obs", "info", "metrics", "reward", "terminated", "truncated"):
            assert _spec(getattr(ours, name)) == _spec(getattr(theirs, name)), name
    assert env.num_actions == real.num_actions and env.num_targets == 6
    ours, theirs = env.target_images(), jax.eval_shape(real.target_images)
    assert {k: (v.shape, v.dtype) for k, v in ours.items()} == {k: (v.shape, v.dtype) for k, v in theirs.items()}


def test_every_pose_has_its_own_image(env):
    frames = set()
    for x in range(SIDE):
        for y in range(SIDE):
            for h in range(HEADINGS):
                rgb, depth, seg = env._render(jnp.int32(0), jnp.array([x, y, h], jnp.int32))
                frames.add(np.asarray(rgb).tobytes())
                assert np.all(np.asarray(depth) > 0) and np.asarray(seg).max() < 20
    assert len(frames) == SIDE * SIDE * HEADINGS


def _shortest_actions(env, start, goal):
    """Breadth-first search over (x, y, heading) with the grid action set's moves: the
    action sequence of a shortest path, found without the environment's code."""
    moves = [(1, 0), (0, 1), (-1, 0), (0, -1)]
    names = env.action_names

    def succ(p, a):
        x, y, h = p
        if names[a] == "forward" or names[a] == "backward":
            s = 1 if names[a] == "forward" else -1
            nx, ny = x + s * moves[h][0], y + s * moves[h][1]
            return (nx, ny, h) if 0 <= nx < SIDE and 0 <= ny < SIDE else p
        return (x, y, (h + (1 if "left" in names[a] else -1)) % HEADINGS)

    prev = {start: None}
    queue = collections.deque([start])
    while queue:
        p = queue.popleft()
        if p == goal:
            break
        for a in range(len(names)):
            q = succ(p, a)
            if q not in prev:
                prev[q] = (p, a)
                queue.append(q)
    path = []
    while prev[goal] is not None:
        goal, a = prev[goal]
        path.append(a)
    return path[::-1]


def test_shortest_paths_reach_the_goal_with_reward_and_reset(env, step):
    state = env.reset(jax.random.PRNGKey(3))
    cells, goals = np.asarray(state.data), np.asarray(env._goals)[np.asarray(state.info.scene), np.asarray(state.info.goal)]
    plans = [_shortest_actions(env, tuple(c), tuple(g)) for c, g in zip(cells, goals)]
    np.testing.assert_array_equal(np.asarray(state.info.start_distance), np.abs(cells - goals)[:, :2].sum(1))
    start_goal = np.asarray(state.info.goal).copy()
    ended = np.zeros(6, bool)
    for t in range(max(map(len, plans))):
        # Agents whose plan is over turn in place no more: they already ended (auto-reset).
        action = [p[t] if t < len(p) else 0 for p in plans]
        state = step(state, jnp.array(action, jnp.int32))
        last = np.array([t == len(p) - 1 for p in plans])
        np.testing.assert_array_equal(np.asarray(state.terminated)[last], True)
        np.testing.assert_array_equal(np.asarray(state.reward)[last], 1.0)
        assert not np.asarray(state.terminated)[~last & ~ended].any()
        for b in np.flatnonzero(last):
            assert state.metrics["episode_spl"][b] == pytest.approx(1.0)
            assert int(state.metrics["episode_length"][b]) == len(plans[b])
            assert int(state.info.step[b]) == 0  # the next episode began
        ended |= last
    assert ended.all() and start_goal.shape == (6,)


def test_moves_into_the_edge_are_blocked_and_time_outs_truncate(step):
    env = _env("env.max_episode_steps=3", "env.goals_per_scene=1")
    state = env.reset(jax.random.PRNGKey(0))
    data = jnp.tile(jnp.array([[0, 0, 2]], jnp.int32), (6, 1))  # the corner, facing west, out of the grid
    state = env.with_data(state.replace(info=state.info.replace(pose=state.info.pose.at[:, :3].set(
        jnp.array([0.5, 0.5, jnp.pi])))))
    np.testing.assert_array_equal(np.asarray(state.data), np.asarray(data))
    forward = jnp.full((6,), env.action_names.index("forward"), jnp.int32)
    goal_here = np.all(np.asarray(env._goals)[np.asarray(state.info.scene), np.asarray(state.info.goal)] == [0, 0, 2], 1)
    state = jax.jit(env.step)(state, forward)
    keep = ~goal_here
    np.testing.assert_array_equal(np.asarray(state.data)[keep], np.asarray(data)[keep])
    np.testing.assert_array_equal(np.asarray(state.info.path_length)[keep], 0.0)
    state = jax.jit(env.step)(jax.jit(env.step)(state, forward), forward)
    assert np.asarray(state.truncated)[keep].all() and not np.asarray(state.terminated)[keep].any()
    assert (np.asarray(state.metrics["episode_length"])[keep] == 3).all()


def test_complexity_bounds_the_start_distance(env):
    near = env.reset(jax.random.PRNGKey(1), complexity=0.0)
    far = env.reset(jax.random.PRNGKey(1), complexity=1.0)
    assert np.asarray(near.info.start_distance).max() <= 1.0  # one cell or one turn away
    assert np.asarray(far.info.start_distance).max() > 2.0
    assert np.all(np.asarray(env.set_complexity(near, 0.5).info.complexity) == 0.5)


def test_target_images_are_the_views_from_the_goals(env):
    state = env.reset(jax.random.PRNGKey(2))
    at_goal = env._goals[state.info.scene, state.info.goal]
    rgb, _, _ = jax.vmap(env._render)(state.info.scene, at_goal)
    np.testing.assert_array_equal(np.asarray(state.obs.target_rgb), np.asarray(rgb))
    np.testing.assert_array_equal(np.asarray(env.target_images()["rgb"])[np.asarray(state.obs.target_index)],
                                  np.asarray(rgb))


def test_what_needs_houses_refuses_the_synthetic_environment_in_one_line(env):
    assert isinstance(env, SyntheticEnv)
    with pytest.raises(ConfigError, match="evaluation needs the MuJoCo environment.*env.kind is 'synthetic'"):
        require_world(env.cfg, "evaluation")
    with pytest.raises(ConfigError, match="env.goals_per_scene=65: the synthetic environment has 64 poses"):
        _env("env.goals_per_scene=65")
    with pytest.raises(ValueError, match="no world"):
        env.step(env.reset(jax.random.PRNGKey(0)), jnp.zeros((6,), jnp.int32), world=object())
