"""Run a uniformly random policy in the environment and write a video of it.

    python -m a2catvn_jax.random_agent [--config FILE [FILE ...]] [--set KEY=VALUE ...]
        [--steps 300] [--out random_agent.gif]

The video shows, for agent 0, its observation, the target image, depth and the
class-colour segmentation side by side; the episode statistics of all agents are
printed at the end.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from a2catvn_jax import cli
from a2catvn_jax.env import NavEnv
from a2catvn_jax.run.video import tile_frame, write_video

QUICK = ["env.num_envs=16", "env.render.image_size=64", "env.scene.num_scenes=2", "env.goals_per_scene=4"]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.random_agent", description=__doc__.split("\n\n")[0])
    cli.add_config_args(parser)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", default="random_agent.gif", help="video file (.gif, or .mp4 with imageio-ffmpeg)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.config is None:
        args.overrides = [QUICK] + list(args.overrides or [])
    t0 = time.perf_counter()
    with cli.errors(parser, code=2):
        env = NavEnv(cli.config_from_args(args).env)
    print(f"built {env.num_scenes} scene(s) in {time.perf_counter() - t0:.1f} s; actions: {', '.join(env.action_names)}")
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    key = jax.random.PRNGKey(args.seed)
    state = reset(key)
    frames = [tile_frame(state.obs)]
    ended = success = 0
    lengths, spls = [], []
    t0 = time.perf_counter()
    for k in range(args.steps):
        key, sub = jax.random.split(key)
        state = step(state, jax.random.randint(sub, (env.num_envs,), 0, env.num_actions))
        frames.append(tile_frame(state.obs))
        done = np.asarray(state.done)
        if done.any():
            m = jax.tree_util.tree_map(np.asarray, state.metrics)
            ended += int(done.sum())
            success += int(m["success"][done].sum())
            lengths += list(m["episode_length"][done])
            spls += list(m["episode_spl"][done])
    dt = time.perf_counter() - t0
    print(f"{args.steps} steps x {env.num_envs} agents in {dt:.1f} s ({args.steps * env.num_envs / dt:.0f} frames/s incl. compile)")
    print(f"episodes ended: {ended}, successes: {success}, mean length: {np.mean(lengths) if lengths else float('nan'):.1f}, "
          f"mean SPL: {np.mean(spls) if spls else float('nan'):.3f}")
    scale = max(1, 256 // frames[0].shape[0])
    frames = [np.kron(f, np.ones((scale, scale, 1), np.uint8)) for f in frames]
    write_video(args.out, frames)
    print(f"wrote {args.out} ({len(frames)} frames: observation | target | depth | segmentation)")


if __name__ == "__main__":
    main()
