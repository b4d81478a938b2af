"""Rendering alone, per core: the ray caster, `mjx.render` and MuJoCo Warp called directly.

`python -m a2catvn_jax.benchmark render` runs `measure` once per renderer, batch size
and resolution, each in its own process pinned to `--cores` CPU cores (default one, so
the figures are frames per second per core). Every renderer draws the same house
(`throughput.env_config`: one generated 2x3-room house) from the same camera poses (a
short random-action rollout, seed 0), with RGB, depth and segmentation:

- `raycast`: this project's ray caster (`World.render`, backend raycast) inside `jax.jit`;
- `mjx`: `mjx.render` with impl warp inside `jax.jit` (`World.render`, backend mjx),
  including the conversion of its buffers to the environment's images;
- `warp`: MuJoCo Warp's own `refit_bvh` and `render` on a Warp model of the same
  MJCF, camera poses written into its data, outputs left in its render context's
  buffers (no conversion): the renderer with nothing around it.

Each process also reports the geom id of every pixel of its first pose set, so that the
parent can check that the renderers drew the same thing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from a2catvn_jax import cli

RENDERERS = ("raycast", "mjx", "warp")


def _poses(env, sets: int, seed: int = 0):
    """`sets` pose arrays [B, 4] of a random-action rollout (one per step)."""
    import jax

    state = jax.jit(env.reset)(jax.random.PRNGKey(seed))
    step = jax.jit(env.step)
    actions = jax.random.randint(jax.random.PRNGKey(seed + 1), (sets, env.num_envs), 0, env.num_actions)
    out = []
    for k in range(sets):
        state = step(state, actions[k])
        out.append(state.info.pose)
    return out


def _timed(call, sets: int, repeats: int, sync) -> tuple[float, float]:
    """(median seconds per call over `repeats` rounds of `sets` calls, CPU cores busy)."""
    call(0)
    sync()
    times = []
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(repeats):
        t0 = time.perf_counter()
        for k in range(sets):
            call(k)
        sync()
        times.append((time.perf_counter() - t0) / sets)
    return float(np.median(times)), (time.process_time() - c0) / (time.perf_counter() - w0)


def measure(renderer: str, batch: int, resolution: int, repeats: int = 5, sets: int = 4) -> dict:
    """Frames/s of `renderer` for `batch` cameras at `resolution`, and the geom ids of the
    first pose set's frames [B, H, W]."""
    import jax
    import jax.numpy as jnp

    from a2catvn_jax.bench.throughput import env_config
    from a2catvn_jax.env import NavEnv

    backend = "raycast" if renderer == "warp" else renderer
    env = NavEnv(env_config(batch, resolution, [f"env.render.backend={backend}"]))
    world = env.world
    poses = _poses(env, sets)
    scene = jnp.zeros(batch, jnp.int32)
    t0 = time.perf_counter()
    if renderer in ("raycast", "mjx"):
        render = jax.jit(lambda pose: world.render(world.arrays, scene, pose))
        outs = {}

        def call(k):
            outs[k] = render(poses[k])

        def sync():
            jax.block_until_ready(list(outs.values()))

        call(0)
        sync()
        geom = np.asarray(outs[0].geom)
    else:
        call, sync, geom = _warp_direct(world, scene, poses, resolution)
    compile_s = time.perf_counter() - t0
    seconds, cores = _timed(call, sets, repeats, sync)
    return {"renderer": renderer, "batch": batch, "resolution": resolution, "geoms": int(world.models[0].ngeom),
            "frames_per_s": batch / seconds, "cores": cores, "pinned_cores": len(os.sched_getaffinity(0)),
            "compile_s": compile_s, "geom": geom}


def _warp_direct(world, scene, poses, resolution: int):
    """(call, sync, geom ids of pose set 0) for MuJoCo Warp's renderer on the world's
    first scene, with the same render settings as the mjx backend."""
    import jax
    import mujoco
    import mujoco.mjx.third_party.mujoco_warp as mjw
    import warp as wp

    from a2catvn_jax.env.mjx_render import MjxRenderer

    backend = MjxRenderer(world.models[0], world.spec)  # the mjx backend's model and render settings
    model, cam = backend.model, backend.camera
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    batch = scene.shape[0]
    m = mjw.put_model(model)
    d = mjw.put_data(model, data, nworld=batch)
    rc = mjw.create_render_context(model, nworld=batch, **backend.context_settings())
    camera_pose = jax.jit(lambda pose: world.mjx.camera_pose(world.data(world.arrays, scene, pose)))
    xpos0, xmat0 = d.cam_xpos.numpy(), d.cam_xmat.numpy()
    sets = []
    for pose in poses:  # camera poses as Warp arrays, made before anything is timed
        pos, mat = (np.asarray(a) for a in camera_pose(pose))
        xpos, xmat = xpos0.copy(), xmat0.copy()
        xpos[:, cam], xmat[:, cam] = pos, mat.reshape(batch, 3, 3)
        sets.append((wp.array(xpos, dtype=wp.vec3), wp.array(xmat, dtype=wp.mat33)))

    def call(k):
        wp.copy(d.cam_xpos, sets[k][0])
        wp.copy(d.cam_xmat, sets[k][1])
        mjw.refit_bvh(m, d, rc)
        mjw.render(m, d, rc)

    call(0)
    wp.synchronize()
    seg = wp.zeros((batch, resolution, resolution), dtype=wp.vec2i)
    mjw.get_segmentation(rc, cam, seg)
    return call, wp.synchronize, seg.numpy()[..., 0].astype(np.int32)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m a2catvn_jax.bench.render_speed")
    p.add_argument("renderer", choices=RENDERERS)
    p.add_argument("--batch", type=int, required=True)
    p.add_argument("--resolution", type=int, required=True)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", required=True, help="JSON of the result; the geom ids go to OUT.npy")
    args = p.parse_args(argv)
    with cli.errors(p):
        r = measure(args.renderer, args.batch, args.resolution, args.repeats)
    np.save(args.out + ".npy", r.pop("geom"))
    with open(args.out, "w") as f:
        json.dump(r, f)


if __name__ == "__main__":
    main(sys.argv[1:])
