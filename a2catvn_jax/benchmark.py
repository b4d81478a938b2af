"""Throughput benchmarks.

    python -m a2catvn_jax.benchmark env [--batch-sizes 16 64 256 1024] [--resolutions 64 84 174]

`env`: frames/s of `NavEnv.step` (one frame = one agent step with its RGB, depth and
segmentation rendered) in a multi-room house, for each batch size and resolution,
with compile times; and, for the same house MJCF at the same resolution, MuJoCo's own
OpenGL renderer (`mujoco.Renderer`, RGB + depth + segmentation passes) at the same
agent poses, and the ratio of the two.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.config import load_config


def _env_config(batch: int, resolution: int, overrides):
    return load_config(
        None,
        [
            f"env.num_envs={batch}",
            f"env.render.image_size={resolution}",
            "env.scene.kind=house",
            "env.scene.grid=[2,3]",
            "env.scene.num_scenes=1",
            "env.goals_per_scene=4",
            *overrides,
        ],
    ).env


def bench_env(batch: int, resolution: int, steps: int, overrides=(), world=None) -> dict:
    from a2catvn_jax.env import NavEnv

    cfg = _env_config(batch, resolution, overrides)
    env = NavEnv(cfg, world=world)
    reset = jax.jit(env.reset)
    step = jax.jit(env.step)
    t0 = time.perf_counter()
    state = jax.block_until_ready(reset(jax.random.PRNGKey(0)))
    actions = jax.random.randint(jax.random.PRNGKey(1), (steps + 1, batch), 0, env.num_actions)
    state = jax.block_until_ready(step(state, actions[0]))
    compile_s = time.perf_counter() - t0
    poses, fallbacks = [], 0
    t0 = time.perf_counter()
    for k in range(steps):
        state = step(state, actions[k + 1])
        if k < 4:
            poses.append(np.asarray(state.info["pose"]))
    jax.block_until_ready(state)
    dt = time.perf_counter() - t0
    fallbacks = int(np.asarray(state.metrics["fallback"]).sum())
    return {
        "batch": batch,
        "resolution": resolution,
        "frames_per_s": batch * steps / dt,
        "compile_s": compile_s,
        "geoms": int(env.world.models[0].ngeom),
        "fallback_frames_last_step": fallbacks,
        "poses": np.concatenate(poses),
        "env": env,
    }


def bench_mujoco_gl(env, resolution: int, poses: np.ndarray, frames: int) -> float:
    from a2catvn_jax import mujoco_gl

    return mujoco_gl.benchmark_fps(
        env.scene_mjcf(0), resolution, resolution, n_frames=frames, poses=poses, cam_height=env.cfg.camera_height
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.benchmark", description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=["env"], help="what to benchmark")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[16, 64, 256, 1024])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 84, 174])
    parser.add_argument("--steps", type=int, default=5, help="timed steps per setting")
    parser.add_argument("--gl-frames", type=int, default=200, help="frames timed for MuJoCo's renderer")
    parser.add_argument("--no-gl", action="store_true", help="skip MuJoCo's OpenGL renderer")
    parser.add_argument("--max-pixels", type=float, default=3.2e7, help="skip settings with more batch*pixels")
    parser.add_argument("--set", nargs="+", default=[], dest="overrides", metavar="KEY=VALUE")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args(argv)

    print(f"# {platform.node()} {platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}, "
          f"jax {jax.__version__}, {time.strftime('%Y-%m-%d')}")
    rows = []
    gl_cache = {}
    header = f"{'batch':>6} {'res':>5} {'geoms':>6} {'env fps':>10} {'compile s':>10} {'GL fps':>8} {'ratio':>7}"
    print(header)
    for res in args.resolutions:
        for batch in args.batch_sizes:
            if batch * res * res > args.max_pixels:
                print(f"{batch:>6} {res:>5}  skipped (batch*pixels > --max-pixels)")
                continue
            r = bench_env(batch, res, args.steps, args.overrides)
            env = r.pop("env")
            poses = r.pop("poses")
            if not args.no_gl and res not in gl_cache:
                try:
                    gl_cache[res] = bench_mujoco_gl(env, res, poses, args.gl_frames)
                except RuntimeError as e:
                    print(f"# MuJoCo OpenGL renderer unavailable: {e}", file=sys.stderr)
                    gl_cache[res] = None
            gl = gl_cache.get(res)
            r["mujoco_gl_fps"] = gl
            r["ratio"] = r["frames_per_s"] / gl if gl else None
            rows.append(r)
            gl_s = f"{gl:8.0f}" if gl else f"{'-':>8}"
            ratio_s = f"{r['ratio']:7.2f}" if gl else f"{'-':>7}"
            print(f"{batch:>6} {res:>5} {r['geoms']:>6} {r['frames_per_s']:10.0f} {r['compile_s']:10.1f} {gl_s} {ratio_s}", flush=True)
            del env
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
