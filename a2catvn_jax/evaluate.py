"""Evaluate a trained agent: success rate, SPL, episode statistics, and a video.

    python -m a2catvn_jax.evaluate --workdir DIR [--episodes 100] [--step N]
        [--houses train|held-out] [--policy sample|greedy|random] [--video FILE.gif|.mp4]
        [--video-episodes 2] [--out FILE.json] [--seed 0] [--set KEY=VALUE ...]

The parameters of a checkpoint of the run in DIR (the latest, or update N) are
restored with the run's own configuration. The policy (sampled; its argmax with
`--policy greedy`; or, as a baseline, uniformly random actions with `--policy random`)
then acts in all B environments at curriculum complexity 1 until every environment
has finished ceil(episodes / B) episodes; the first `--episodes` of these, in
environment order, are counted, so that short episodes are not favoured.

`--houses held-out` generates houses the run never trained in (the same generator and
settings, seeds offset by `HELD_OUT_OFFSET`); `--houses new-targets` keeps the training
houses but draws their goals anew (other target poses and images, goal seed offset by
`NEW_TARGETS_OFFSET`). `--set` changes evaluation settings
(`env.num_envs`, `env.max_episode_steps`, `env.complexity`, noise, ...); keys that
shape the network are refused.

The result is printed and written as JSON (default DIR/eval_<step>_<houses>_<policy>.json).
`--video` shows agent 0's first episodes: observation | target image | top-down map
with the path so far, the agent's pose (blue) and the target pose (red).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from a2catvn_jax.config import ConfigError, apply_overrides

HELD_OUT_OFFSET = 1_000_003  # scene seed offset of held-out houses
NEW_TARGETS_OFFSET = 2_000_029  # goal seed offset of new targets in the training houses
HOUSES = ("train", "held-out", "new-targets")
# Keys the network's shapes depend on ("agent." is the whole section).
NETWORK_KEYS = ("agent.", "env.render.image_size", "env.action_set", "train.pixel_control_cell", "train.aux_downsize")
VIDEO_PANEL = 128  # video images are upscaled by an integer factor to at least this height
VIDEO_FPS = 10
END_FRAMES = 5  # video frames holding an episode's outcome
MAX_CHUNK = 128  # environment steps per compiled call
MAX_MESSAGE = 500  # characters of an error message the command prints
EPISODE_FIELDS = {  # per-episode list -> environment metric
    "success": "success",
    "length": "episode_length",
    "spl": "episode_spl",
    "return": "episode_return",
    "start_distance": "episode_start_distance",
}


class EvaluationError(RuntimeError):
    """The evaluation cannot run as asked (e.g. no writer for the video format)."""


def eval_config(run_cfg, overrides: Sequence[str] = ()):
    """The run's configuration at complexity 1 with `overrides`; `ConfigError` if they change the network."""
    from a2catvn_jax.checkpoint import config_differences

    base = apply_overrides(run_cfg, ["env.complexity=1.0"])
    cfg = apply_overrides(base, list(overrides))
    refused = []
    for diff in config_differences(base, cfg, ignore=()):
        key, values = diff.split(": ", 1)
        if any(key == k or (k.endswith(".") and key.startswith(k)) for k in NETWORK_KEYS):
            run_value, given = values.split(" != ", 1)
            refused.append((key, f"{key}: the network depends on it; evaluation keeps the run's value {run_value} "
                                 f"(given {given})"))
    if refused:
        raise ConfigError("; ".join(message for _, message in refused), key=refused[0][0])
    return cfg


def make_env(env_cfg, houses: str = "train"):
    """A `NavEnv` in the run's training houses, in held-out houses generated with offset
    seeds, or in the training houses with new goals ("new-targets")."""
    from a2catvn_jax.env import NavEnv
    from a2catvn_jax.world import World, make_scenes

    if houses not in HOUSES:
        raise ValueError(f"houses must be one of {HOUSES}, got {houses!r}")
    if houses == "held-out" and env_cfg.scene.kind == "mjcf":
        raise ValueError("held-out houses need generated scenes; env.scene.kind is 'mjcf' (one fixed file)")
    if houses == "new-targets":
        world = World(env_cfg, make_scenes(env_cfg), seed=env_cfg.scene.seed + NEW_TARGETS_OFFSET)
        return NavEnv(env_cfg, world=world)
    return NavEnv(env_cfg, seed_offset=0 if houses == "train" else HELD_OUT_OFFSET)


def _resolve_step(ckpt, step: Optional[int]) -> int:
    from a2catvn_jax.checkpoint import CheckpointError

    steps = sorted(ckpt.steps())
    if not steps:
        raise CheckpointError(f"{ckpt.workdir}: no checkpoint found in {ckpt.directory}")
    if step is None:
        return steps[-1]
    if step not in steps:
        raise CheckpointError(f"{ckpt.workdir}: no checkpoint at update {step}; available: {steps}")
    return step


def _check_video(path) -> None:
    suffix = Path(path).suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"video file must end in .gif or .mp4, got {str(path)!r}")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise EvaluationError("writing .mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); or write a .gif")


def write_video(path, frames: Sequence[np.ndarray], fps: int = VIDEO_FPS) -> None:
    """Write RGB frames as a GIF or (with imageio-ffmpeg) an MP4."""
    _check_video(path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if Path(path).suffix.lower() == ".gif":
        import imageio.v3 as iio

        iio.imwrite(path, np.stack(frames), duration=1000 // fps, loop=0)
    else:
        import imageio.v2 as imageio

        imageio.mimsave(path, frames, fps=fps)


POLICIES = ("sample", "greedy", "random")


def _chunk_fn(learner, steps: int, policy: str, video: bool):
    """Jitted: `steps` environment steps of the policy in all environments."""
    import jax

    env = learner.env

    def run(params, target_feats, env_state, agent, key):
        def body(carry, k):
            env_state, agent = carry
            core, action, _, _ = learner.act(params, target_feats, agent, env_state, k, policy == "greedy")
            if policy == "random":
                action = jax.random.randint(k, action.shape, 0, env.num_actions)
            nxt = env.step(env_state, action)
            out = {name: nxt.metrics[metric] for name, metric in EPISODE_FIELDS.items()}
            out["done"] = nxt.done
            if video:
                info = env_state.info
                out["video"] = {
                    "rgb": env_state.obs["rgb"][0],
                    "target_rgb": env_state.obs["target_rgb"][0],
                    **{k: info[k][0] for k in ("pose", "target_pose", "scene", "goal")},
                }
            return (nxt, learner.observe(core, action, nxt)), out

        key, sub = jax.random.split(key)
        (env_state, agent), out = jax.lax.scan(body, (env_state, agent), jax.random.split(sub, steps))
        return env_state, agent, key, out

    return jax.jit(run)


def _video_frames(env, steps: list[dict], episodes: int) -> list[np.ndarray]:
    """observation | target | map frames of agent 0's first `episodes` episodes."""
    from a2catvn_jax.scenes.plot import TopdownMap

    size = steps[0]["rgb"].shape[0]
    scale = -(-VIDEO_PANEL // size)
    target_scene = np.asarray(env.world.arrays.target_scene)
    maps: dict[int, TopdownMap] = {}
    frames, path, episode = [], [], 0
    for s in steps:
        scene, goal = int(s["scene"]), int(s["goal"])
        if scene not in maps:
            maps[scene] = TopdownMap(env.world.scenes[scene], size * scale)
        path.append(s["pose"][:2])
        target = s["target_pose"] if target_scene[scene, goal] == scene else None
        images = [np.asarray(s[k]).repeat(scale, 0).repeat(scale, 1) for k in ("rgb", "target_rgb")]

        def frame(text):
            return np.concatenate(images + [maps[scene].render(path, s["pose"], target, text)], axis=1)

        frames.append(frame(f"episode {episode + 1}, step {len(path) - 1}"))
        if s["done"]:
            frames += [frame(f"episode {episode + 1}: " + ("success" if s["success"] else "failed"))] * END_FRAMES
            episode, path = episode + 1, []
            if episode == episodes:
                break
    return frames


def restore(workdir, step: Optional[int] = None, houses: str = "train", overrides: Sequence[str] = (),
            log: Callable[[str], None] = lambda _: None):
    """Checkpoint `step` (default: the latest) of the run in `workdir`, ready to act in `houses`.

    Returns (cfg, run_cfg, env, learner, params, step, meta): the evaluation configuration
    (the run's at complexity 1 with `overrides`), the run's own, the environment, a
    learner over it, the parameters, the update restored and the checkpoint's metadata.
    """
    import jax

    from a2catvn_jax.checkpoint import Checkpointer, CheckpointError, read_run_config
    from a2catvn_jax.env import NavEnv
    from a2catvn_jax.learner import Learner

    if houses not in HOUSES:
        raise ValueError(f"houses must be one of {HOUSES}, got {houses!r}")
    workdir = Path(workdir)
    if not workdir.is_dir():
        raise CheckpointError(f"{workdir}: no such directory")
    run_cfg = read_run_config(workdir)
    cfg = eval_config(run_cfg, overrides)

    ckpt = Checkpointer(workdir, create=False)
    try:
        step = _resolve_step(ckpt, step)
        t0 = time.perf_counter()
        env = make_env(cfg.env, houses)
        log(f"built {env.num_scenes} {houses} scene(s) in {time.perf_counter() - t0:.1f} s")
        # Only the parameters are read (not the optimiser state or the replay buffer). Their
        # shapes do not depend on the scenes: the template borrows env's world.
        template = jax.eval_shape(Learner(run_cfg, NavEnv(run_cfg.env, world=env.world)).init_params,
                                  jax.random.PRNGKey(0))
        params, meta = ckpt.restore_params(template, run_cfg, step)
    finally:
        ckpt.close()
    log(f"restored update {step} ({meta['frames']:,} training frames) from {ckpt.directory}")
    return cfg, run_cfg, env, Learner(cfg, env), params, step, meta


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
    log: Callable[[str], None] = print,
) -> dict:
    """Evaluate checkpoint `step` (default: the latest) of the run in `workdir`.

    Returns a JSON-ready dict: step and frames (the checkpoint's update and training
    frames), houses, scenes (names), policy, seed, complexity, num_envs,
    max_episode_steps, eval_frames (environment steps taken), episodes, success_rate,
    spl, episode_length and episode_return (means over the counted episodes),
    per_episode (lists success, length, spl, return, start_distance), and video (its
    path) when one is written. Raises `CheckpointError` (no run, no or unreadable
    checkpoint), `ConfigError` (bad overrides), `ValueError` (bad arguments) and
    `EvaluationError`.
    """
    import jax

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
    if video is not None:
        if video_episodes < 1:
            raise ValueError(f"video_episodes must be >= 1, got {video_episodes}")
        _check_video(video)
    cfg, _, env, learner, params, step, meta = restore(workdir, step, houses, overrides, log)
    B = env.num_envs
    per_env = math.ceil(episodes / B)
    chunk = min(MAX_CHUNK, per_env * cfg.env.max_episode_steps)
    run = _chunk_fn(learner, chunk, policy, video is not None)
    k_reset, key = jax.random.split(jax.random.PRNGKey(seed))
    env_state = jax.jit(lambda k: env.reset(k, complexity=cfg.env.complexity))(k_reset)
    agent = learner.initial_agent()
    target_feats = jax.jit(learner.target_features)(params)

    found: list[list[dict]] = [[] for _ in range(B)]
    video_steps: list[dict] = []
    video_done = 0
    steps = 0
    t0 = time.perf_counter()
    while min(len(f) for f in found) < per_env or (video is not None and video_done < video_episodes):
        env_state, agent, key, out = run(params, target_feats, env_state, agent, key)
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
    result = {
        "workdir": str(workdir),
        "step": step,
        "frames": int(meta["frames"]),
        "houses": houses,
        "scenes": [scene.name for scene in env.world.scenes],
        "policy": policy,
        "seed": seed,
        "complexity": cfg.env.complexity,
        "num_envs": B,
        "max_episode_steps": cfg.env.max_episode_steps,
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
        frames = _video_frames(env, video_steps, video_episodes)
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", required=True, help="the training run's work directory")
    parser.add_argument("--episodes", type=int, default=100, help="episodes to count (default 100)")
    parser.add_argument("--step", type=int, default=None, help="checkpoint update to evaluate (default: the latest)")
    parser.add_argument("--houses", choices=HOUSES, default="train", help="the training houses, held-out ones, or the training houses with new targets")
    parser.add_argument("--policy", choices=POLICIES, default="sample",
                        help="sample from the policy, take its argmax, or act uniformly at random (a baseline)")
    parser.add_argument("--video", default=None, metavar="FILE",
                        help="video of agent 0 (.gif, or .mp4 with imageio-ffmpeg)")
    parser.add_argument("--video-episodes", type=int, default=2, help="episodes in the video (default 2)")
    parser.add_argument("--out", default=None, metavar="FILE",
                        help="result JSON (default DIR/eval_<step>_<houses>_<policy>.json)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", dest="overrides", metavar="KEY=VALUE", nargs="+", action="append", default=[],
                        help="evaluation settings, e.g. --set env.num_envs=32 env.max_episode_steps=500")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.video_episodes < 1:
        parser.error(f"--video-episodes must be >= 1, got {args.video_episodes}")
    if args.video is not None and Path(args.video).suffix.lower() not in (".gif", ".mp4"):
        parser.error(f"--video must end in .gif or .mp4, got {args.video!r}")

    from a2catvn_jax.checkpoint import CheckpointError

    try:
        result = evaluate(args.workdir, args.episodes, step=args.step, houses=args.houses, policy=args.policy,
                          seed=args.seed, overrides=[o for group in args.overrides for o in group],
                          video=args.video, video_episodes=args.video_episodes)
    except ValueError as e:  # configuration errors included
        parser.error(str(e))
    except (CheckpointError, EvaluationError) as e:
        message = str(e)  # orbax's messages can list a whole checkpoint tree
        parser.exit(2, f"error: {message if len(message) <= MAX_MESSAGE else message[:MAX_MESSAGE] + ' ...'}\n")
    out = Path(args.out) if args.out else default_output(args.workdir, result)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(to_json(result))
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
