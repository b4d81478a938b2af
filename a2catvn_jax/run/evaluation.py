"""Evaluate a trained agent: success rate, SPL, episode statistics, and a video.

`evaluate(workdir)` restores the parameters of a checkpoint of the run in `workdir`
(`run.restore`). The policy (sampled; its argmax with `policy="greedy"`; or a baseline
that needs no network: uniformly random actions with `policy="random"`, the
shortest-path oracle with `policy="oracle"`, the goal-blind tour of the rooms with
`policy="tour"` on room-type goals) then acts in all B environments at
curriculum complexity 1 until every environment has finished ceil(episodes / B)
episodes; the first `episodes` of these, in environment order, are counted, so that
short episodes are not favoured. `evaluate_baseline(cfg)` runs a baseline on a
configuration without any run.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from a2catvn_jax.agent.acting import act_as, initial_agent, observe
from a2catvn_jax.agent.networks import Networks
from a2catvn_jax.config import AGENT_POLICIES, Config
from a2catvn_jax.env import NavEnv, tour
from a2catvn_jax.env.oracle import oracle_actions
from a2catvn_jax.memo import Memo
from a2catvn_jax.run import distributed
from a2catvn_jax.run.restore import HOUSES, Restored, check_houses, house_env, locate, make_envs
from a2catvn_jax.run.video import check_video_path, episode_frames, write_video

MAX_CHUNK = 128  # environment steps per compiled call
BASELINES = ("random", "oracle", "tour")  # policies that need no network
POLICIES = AGENT_POLICIES + BASELINES
EPISODE_FIELDS = {  # per-episode list -> environment metric
    "success": "success",
    "length": "episode_length",
    "spl": "episode_spl",
    "return": "episode_return",
    "start_distance": "episode_start_distance",
}


COMPILED = Memo("jitted evaluation functions, by what fixes them", keep=8)


def _chunk_fn(env: NavEnv, networks: Optional[Networks], steps: int, policy: str, video: bool):
    """Jitted: `steps` environment steps of the policy in all environments. The world is
    an argument, so environments of one configuration and shapes share one compile.
    `given` is what the policy reads besides the world (a network: its target
    features; the tour: its rooms' look-outs) and `agent` what it carries from step to
    step (a network: its recurrent state; the tour: the rooms looked into; random and
    oracle: None)."""

    def run(params, world, given, env_state, agent, key):
        def body(carry, k):
            env_state, agent = carry
            if policy == "random":
                action = jax.random.randint(k, (env.num_envs,), 0, env.num_actions)
            elif policy == "oracle":
                action = oracle_actions(env, env_state, k, world)
            elif policy == "tour":
                action, agent = tour.tour_actions(env, env_state, agent, k, given, world)
            else:
                core, action = act_as(policy, networks, params, given, agent, env_state.obs, k)
            nxt = env.step(env_state, action, world)
            out = {name: nxt.metrics[metric] for name, metric in EPISODE_FIELDS.items()}
            out["done"] = nxt.done
            if video:
                info = env_state.info
                out["video"] = {"rgb": env_state.obs.rgb[0], "target_rgb": env_state.obs.target_rgb[0],
                                "pose": info.pose[0], "target_pose": info.target_pose[0], "scene": info.scene[0],
                                "goal": info.goal[0]}
            if policy == "tour":
                agent = tour.after_step(agent, nxt.done)
            elif policy not in BASELINES:
                agent = observe(core, action, nxt)
            return (nxt, agent), out

        key, sub = jax.random.split(key)
        (env_state, agent), out = jax.lax.scan(body, (env_state, agent), jax.random.split(sub, steps))
        return env_state, agent, key, out

    key = ("chunk", env.cfg, None if policy in BASELINES else networks, steps, policy, video)
    return COMPILED.get(key, lambda: jax.jit(run))


def baselines_for(cfg) -> tuple[str, ...]:
    """The baselines that apply to environment configuration `cfg` (the tour: `tour.applies`)."""
    return tuple(p for p in BASELINES if p != "tour" or tour.applies(cfg))


def _check(episodes: int, policy: str, video, video_episodes: int) -> None:
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
    if video is not None:
        if video_episodes < 1:
            raise ValueError(f"video_episodes must be >= 1, got {video_episodes}")
        check_video_path(video)


def evaluate(
    workdir,
    episodes: int = 100,
    *,
    step: Optional[int] = None,
    houses: str = "train",
    policy: str = "sample",
    seed: int = 0,
    overrides: Sequence[str] = (),
    video=None,
    video_episodes: int = 2,
    baselines: bool = False,
    log: Callable[[str], None] = print,
    devices: Optional[int] = None,
) -> dict:
    """Evaluate checkpoint `step` (default: the latest) of the run in `workdir`.

    Returns a JSON-ready dict: step and frames (the checkpoint's update and training
    frames), houses, scenes (names), policy, seed, complexity, num_envs,
    max_episode_steps, eval_frames (environment steps taken), episodes, success_rate,
    spl, episode_length and episode_return (means over the counted episodes),
    per_episode (lists success, length, spl, return, start_distance), video (its
    path) when one is written, and with `baselines` the success rate, SPL and episode
    length of the baselines that apply (`baselines_for`: the random policy, the
    shortest-path oracle and on room-type goals the tour) in the same houses with the
    same seed ({"random": {...}, "oracle": {...}, ...}). Raises `CheckpointError` (no run, no or unreadable
    checkpoint), `ConfigError` (bad overrides), `ValueError` (bad arguments) and
    `VideoError`.
    """
    _check(episodes, policy, video, video_episodes)
    check_houses(houses)
    run = locate(workdir, step, overrides)
    t0 = time.perf_counter()
    env = house_env(run.cfg.env, houses)
    log(f"built {env.num_scenes} {houses} scene(s) in {time.perf_counter() - t0:.1f} s")
    restored = run.restore(log)
    result = run_episodes(restored, env, houses, episodes, policy=policy, seed=seed, video=video, devices=devices,
                          video_episodes=video_episodes, log=log)
    if baselines:
        result["baselines"] = {}
        for p in baselines_for(env.cfg):
            r = run_episodes(None, env, houses, episodes, policy=p, seed=seed, log=log, devices=devices)
            result["baselines"][p] = {k: r[k] for k in ("success_rate", "spl", "episode_length")}
    return result


def evaluate_sets(workdir, episodes: int = 100, *, houses: Sequence[str] = HOUSES, step: Optional[int] = None,
                  policies: Sequence[str] = ("sample",), seed: int = 0, overrides: Sequence[str] = (),
                  log: Callable[[str], None] = print, devices: Optional[int] = None) -> dict:
    """`evaluate` of one checkpoint in several house sets with several policies, restoring
    it once and compiling once for all sets of one shape: {(houses, policy): result}."""
    for p in policies:
        _check(episodes, p, None, 1)
    run = locate(workdir, step, overrides)
    envs = make_envs(run.cfg.env, houses)
    restored = run.restore(log)
    return {(h, p): run_episodes(restored, envs[h], h, episodes, policy=p, seed=seed, log=log, devices=devices)
            for h in houses for p in policies}


def evaluate_baseline(cfg: Config, episodes: int = 100, *, houses: str = "train", policy: str = "random",
                      seed: int = 0, video=None, video_episodes: int = 2,
                      log: Callable[[str], None] = print, devices: Optional[int] = None) -> dict:
    """A baseline policy ("random", "oracle" or "tour") in the houses of configuration `cfg`, no run
    needed: the result of `evaluate` with step and frames 0 and workdir None."""
    if policy not in BASELINES:
        raise ValueError(f"a baseline policy is one of {BASELINES}, got {policy!r}")
    if policy == "tour":
        tour.check_goal(cfg.env)
    check_houses(houses)
    t0 = time.perf_counter()
    env = house_env(cfg.env, houses)
    log(f"built {env.num_scenes} {houses} scene(s) in {time.perf_counter() - t0:.1f} s")
    return run_episodes(None, env, houses, episodes, policy=policy, seed=seed, video=video, devices=devices,
                        video_episodes=video_episodes, log=log)


def split_over_devices(per_env, shared, batch: int, devices: Optional[int] = None):
    """(`per_env` split along its leading environment axis of `batch`, `shared`
    replicated) over the first `devices` local devices (default: all); unchanged on
    one device. A batch that does not split evenly is a `distributed.DevicesError` (a
    `ValueError`) naming both numbers."""
    used = distributed.devices_for(batch, devices)
    if len(used) == 1:
        return per_env, shared
    mesh = Mesh(np.array(used), ("batch",))
    put = lambda tree, spec: jax.device_put(  # noqa: E731
        tree, jax.tree_util.tree_map(lambda _: NamedSharding(mesh, spec), tree))
    return put(per_env, PartitionSpec("batch")), put(shared, PartitionSpec())


def run_episodes(restored: Optional[Restored], env: NavEnv, houses: str, episodes: int, *, policy: str = "sample",
                 seed: int = 0, video=None, video_episodes: int = 2, log: Callable[[str], None] = print,
                 devices: Optional[int] = None) -> dict:
    """Episodes of the restored agent (None: a baseline policy, no network) in `env` (see
    `evaluate`), the environments split over `devices` local devices (default: all)."""
    _check(episodes, policy, video, video_episodes)
    if restored is None and policy not in BASELINES:
        raise ValueError(f"policy {policy!r} needs a trained run; without one use one of {BASELINES}")
    networks = None if restored is None else restored.networks
    params = None if restored is None else restored.params
    world = env.world.arrays
    B = env.num_envs
    per_env = math.ceil(episodes / B)
    chunk = min(MAX_CHUNK, per_env * env.cfg.max_episode_steps)
    run = _chunk_fn(env, networks, chunk, policy, video is not None)
    k_reset, key = jax.random.split(jax.random.PRNGKey(seed))
    reset = COMPILED.get(("reset", env.cfg), lambda: jax.jit(lambda k, tau, w: env.reset(k, complexity=tau, world=w)))
    env_state = reset(k_reset, env.cfg.complexity, world)
    if policy == "tour":
        given = tour.rooms(env.world)
        agent = tour.initial_memory(B, given)
    elif policy in BASELINES:
        agent = given = None
    else:
        agent = initial_agent(networks, B)
        target_stream = COMPILED.get(("targets", networks), lambda: jax.jit(networks.target_stream))
        given = target_stream(params, env.target_images(world)["rgb"])
    (env_state, agent), (params, world, given) = split_over_devices(
        (env_state, agent), (params, world, given), B, devices)

    found: list[list[dict]] = [[] for _ in range(B)]
    video_steps: list[dict] = []
    video_done = 0
    steps = 0
    t0 = time.perf_counter()
    while min(len(f) for f in found) < per_env or (video is not None and video_done < video_episodes):
        env_state, agent, key, out = run(params, world, given, env_state, agent, key)
        out = jax.device_get(out)
        steps += chunk
        for t, b in zip(*np.nonzero(out["done"])):
            if len(found[b]) < per_env:
                found[b].append({name: out[name][t, b].item() for name in EPISODE_FIELDS})
        if video is not None and video_done < video_episodes:
            v = out["video"]
            for t in range(chunk):
                done = bool(out["done"][t, 0])
                video_steps.append({**{k: a[t] for k, a in v.items()}, "done": done,
                                    "success": bool(out["success"][t, 0])})
                video_done += done
                if video_done == video_episodes:
                    break
    seconds = time.perf_counter() - t0

    counted = [e for env_episodes in found for e in env_episodes][:episodes]
    lists = {name: [e[name] for e in counted] for name in EPISODE_FIELDS}
    step = 0 if restored is None else restored.step
    result = {
        "workdir": None if restored is None else str(restored.workdir),
        "step": step,
        "frames": 0 if restored is None else restored.frames,
        "houses": houses,
        "scenes": [scene.name for scene in env.world.scenes],
        "policy": policy,
        "seed": seed,
        "complexity": env.cfg.complexity,
        "num_envs": B,
        "max_episode_steps": env.cfg.max_episode_steps,
        "eval_frames": steps * B,
        "episodes": len(counted),
        "success_rate": float(np.mean(lists["success"])),
        "spl": float(np.mean(lists["spl"])),
        "episode_length": float(np.mean(lists["length"])),
        "episode_return": float(np.mean(lists["return"])),
        "per_episode": lists,
    }
    log(f"update {step} ({result['frames']:,} frames), {houses} houses, {policy} policy: {len(counted)} episodes, "
        f"success {result['success_rate']:.3f}, SPL {result['spl']:.3f}, length {result['episode_length']:.1f}, "
        f"return {result['episode_return']:.3f} ({steps * B:,} frames in {seconds:.1f} s incl. compile)")
    if video is not None:
        frames = episode_frames(env, video_steps, video_episodes)
        write_video(video, frames)
        result["video"] = str(video)
        log(f"wrote {video} ({len(frames)} frames: observation | target | map)")
    return result


def default_output(workdir, result: dict) -> Path:
    return Path(workdir) / f"eval_{result['step']}_{result['houses']}_{result['policy']}.json"


def to_json(result: dict) -> str:
    """The result as JSON, one line per key and per per-episode list."""

    def block(d: dict, pad: str) -> str:
        return ",\n".join(
            f"{pad}{json.dumps(k)}: "
            + (f"{{\n{block(v, pad + ' ')}\n{pad}}}" if isinstance(v, dict) else json.dumps(v))
            for k, v in d.items()
        )

    return "{\n" + block(result, " ") + "\n}\n"
