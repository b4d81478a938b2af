"""The goal-blind tour baseline (`env.tour`): where it looks into each room, that it never
reads the goal, that it looks into every room of a house in turn, and that it finds
room goals; its place among the evaluation's policies.

Tiny houses (2x2 rooms, 16x16 images, the unculled renderer, no motion noise), built
once for the module.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.env import NavEnv, goals, rects, tour
from a2catvn_jax.run.evaluation import BASELINES, baselines_for, evaluate_baseline, run_episodes

B = 16
BASE = [f"env.num_envs={B}", "env.render.image_size=16", "env.render.culling=false", "env.scene.kind=house",
        "env.scene.num_scenes=3", "env.scene.grid=[2,2]", "env.goals_per_scene=2", "env.goal=room",
        "env.action_set=no_tilt", "env.position_noise=0.0", "env.heading_noise_deg=0.0", "env.max_episode_steps=120"]


def quiet(_):
    pass


@pytest.fixture(scope="module")
def env():
    return NavEnv(load_config(None, BASE).env)


@pytest.fixture(scope="module")
def rooms(env):
    return tour.rooms(env.world)


def _rollout(env, rooms, steps, seed=0):
    """The tour's rollout: per step the memory it acted with, the action, and whether the
    step ended the episode (with success)."""

    def body(carry, key):
        state, memory = carry
        action, after = tour.tour_actions(env, state, memory, key, rooms)
        nxt = env.step(state, action)
        return (nxt, tour.after_step(after, nxt.done)), (memory, after, action, nxt.done, nxt.terminated)

    run = jax.jit(lambda s, m, k: jax.lax.scan(body, (s, m), jax.random.split(k, steps)))
    state = jax.jit(lambda k: env.reset(k, complexity=1.0))(jax.random.PRNGKey(seed))
    return jax.device_get(run(state, tour.initial_memory(B, rooms), jax.random.PRNGKey(seed + 1))[1])


def test_look_outs_lie_in_their_room_near_what_shows_its_type(env, rooms):
    """A room's look-out (distance 0) is free cells of that room within `goals.LOOK_RANGE`
    of the objects that show its type; rooms with no such objects are skipped."""
    dist, valid = np.asarray(rooms.dist), np.asarray(rooms.valid)
    assert valid.any()
    for k, (scene, grid) in enumerate(zip(env.world.scenes, env.world.grids)):
        h, w = grid.shape
        for r, room in enumerate(scene.rooms):
            pieces = goals.room_pieces(scene, room)
            assert valid[k, r] == bool(pieces)
            if not pieces:
                assert np.isinf(dist[k, r]).all()
                continue
            there = dist[k, r, :h, :w] == 0
            assert there.any() and (grid.room[there] == r).all() and grid.free[there].all()
            near = np.min([rects.distance(grid.centres(), goals.footprint(g)) for g in pieces], axis=0)
            assert (near[there] <= goals.LOOK_RANGE).all()
        assert not valid[k, len(scene.rooms):].any()


def test_the_tour_never_reads_the_goal(env, rooms):
    """Changing the goal, its target image and the view streak changes no action and no memory."""
    state = jax.jit(lambda k: env.reset(k, complexity=1.0))(jax.random.PRNGKey(3))
    memory = tour.initial_memory(B, rooms)
    act = jax.jit(lambda s, m: tour.tour_actions(env, s, m, jax.random.PRNGKey(4), rooms))
    other = state.replace(info=state.info.replace(goal=1 - state.info.goal,
                                                  target_pose=state.info.target_pose[::-1],
                                                  view_streak=state.info.view_streak + 1),
                          obs=state.obs.replace(target_rgb=jnp.zeros_like(state.obs.target_rgb)))
    a, m = act(state, memory)
    b, n = act(other, memory)
    np.testing.assert_array_equal(a, b)
    for x, y in zip(jax.tree_util.tree_leaves(m), jax.tree_util.tree_leaves(n)):
        np.testing.assert_array_equal(x, y)


def test_the_tour_looks_into_every_room_in_turn(env, rooms):
    """Where success (nearly) cannot come (the goal's objects must fill 99% of the view,
    which only pressing against them does), the tour looks into one room at a time, keeps
    a chosen room until it has looked into it, counts each looked-into room until every
    valid room is, and within 250 steps has looked into all of them (agents whose episode
    ended are left out)."""
    strict = NavEnv(load_config(None, BASE + ["env.view_fraction=0.99", "env.max_episode_steps=500"]).env,
                    world=env.world)  # the same houses and goals (both criteria need the goal in sight)
    memory, after, _, done, _ = _rollout(strict, rooms, 250)
    scene = np.asarray(jax.jit(lambda k: strict.reset(k, complexity=1.0))(jax.random.PRNGKey(0)).info.scene)
    keep = ~done.any(0)
    assert keep.sum() >= B // 2
    valid = np.asarray(rooms.valid)[scene][keep]  # [b, R]
    looked, chosen, before = after.looked[:, keep], after.room[:, keep], memory.room[:, keep]
    assert (looked <= valid).all()  # only valid rooms are looked into
    full = (looked == valid).all(-1)  # [T, b]
    assert full.any(0).all(), looked.sum(-1).max(0)
    counts = looked.sum(-1)
    step = np.diff(counts, axis=0)  # grows by one at a time, drops only once all were seen
    assert (step <= 1).all() and full[:-1][step < 0].all()
    kept = (before >= 0) & (chosen >= 0)
    assert (chosen[kept] == before[kept]).all()


def test_the_tour_finds_room_goals_less_directly_than_the_oracle(env):
    """On room goals the tour succeeds in nearly every episode, with longer paths than the
    oracle; the baselines' evaluation runs it, and refuses it on other goals in one line."""
    cfg = load_config(None, BASE)
    tour_result = run_episodes(None, env, "train", B, policy="tour", seed=5, log=quiet)
    oracle = run_episodes(None, env, "train", B, policy="oracle", seed=5, log=quiet)
    assert tour_result["policy"] == "tour" and tour_result["episodes"] == B
    assert tour_result["success_rate"] >= 0.9
    assert tour_result["spl"] < oracle["spl"] and tour_result["episode_length"] > oracle["episode_length"]
    image = load_config(None, [o for o in BASE if o != "env.goal=room"] + ["env.goal=image", "env.scene.num_scenes=1"])
    assert baselines_for(image.env) == ("random", "oracle") and baselines_for(cfg.env) == BASELINES
    with pytest.raises(ValueError, match=r"^the tour baseline visits rooms and needs room-type goals \(env.goal=room\), "
                                         r"got env.goal=image$"):
        evaluate_baseline(image, 4, policy="tour", log=quiet)
