"""Which render backend a world uses (`env.render.backend`): `raycast`, `mjx`, or `auto`,
which times both on this device for the world's batch and takes the faster.

`choose` is called once per world; the timings it makes are cached per process in
`RATES`, by device platform, camera, camera height, batch size, scene count and layout.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Optional

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.env import mjx_render
from a2catvn_jax.env.goals import random_free_pose
from a2catvn_jax.env.scenes.errors import SceneError
from a2catvn_jax.memo import Memo

if TYPE_CHECKING:  # the world imports this module
    from a2catvn_jax.env.world import World

BACKENDS = ("raycast", "mjx")
RATES = Memo("frames/s of each render backend")


@dataclasses.dataclass(frozen=True)
class Choice:
    name: str  # the backend in use
    note: str  # why, when "auto" chose it ("" otherwise)
    renderer: Optional[mjx_render.MjxRenderer]  # the mjx backend's renderer (None for raycast)


def choose(world: "World", requested: str, geometry, fields) -> Choice:
    """The backend `world` renders with when `requested` ("raycast", "mjx" or "auto")."""
    if world.native:
        return _native(world, requested)
    if requested == "raycast":
        return Choice("raycast", "", None)
    if requested == "mjx":
        return Choice("mjx", "", _renderer(world))
    why = mjx_render.unavailable()
    if why:
        return _auto("raycast", f"the mjx backend cannot run here: {why}")
    key = (jax.default_backend(), world.spec, world.cfg.camera_height, world.cfg.num_envs, len(world.scenes),
           tuple(sorted(world.layout.items())))
    renderer = None
    try:
        renderer = _renderer(world)
        rates = RATES.get(key, lambda: measure(world, renderer, geometry, fields))
    except Exception as e:  # Warp could not build or run its kernels here: keep the ray caster
        return _auto("raycast", f"the mjx backend failed: {' '.join(str(e).split())}")
    best = max(rates, key=rates.get)
    note = (", ".join(f"{b} {r:,.0f} frames/s" for b, r in rates.items())
            + f" at {world.cfg.num_envs} frames a batch on {jax.default_backend()}")
    return _auto(best, note, renderer if best == "mjx" else None)


def measure(world: "World", renderer, geometry, fields, repeats: int = 3) -> dict[str, float]:
    """Frames/s of each backend rendering B = env.num_envs random poses (best of `repeats`)."""
    n = world.cfg.num_envs
    rng = np.random.default_rng(0)
    scene = jnp.asarray(np.arange(n) % len(world.scenes), jnp.int32)
    pose = jnp.asarray(np.stack([random_free_pose(world.grids[int(k)], rng) for k in np.asarray(scene)]), jnp.float32)
    data = jax.jit(world.fields_data)(fields, scene, pose)
    rates = {}
    for backend in BACKENDS:
        def fn(scene, pose, data, backend=backend):
            return world.render_with(backend, renderer, geometry, fields, scene, pose, data)

        fn = jax.jit(fn)
        jax.block_until_ready(fn(scene, pose, data))
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(scene, pose, data))
            best = min(best, time.perf_counter() - t0)
        rates[backend] = n / best
    return rates


def _native(world: "World", requested: str) -> Choice:
    """A scene with geoms only the mjx backend renders (planes, cylinders, meshes)."""
    name, kind = world.native[0]
    what = f"{world.scenes[0].name}: geom {name!r} has type {kind}, which only the mjx backend renders"
    if requested == "raycast":
        raise SceneError(f"{what}: set env.render.backend=mjx (or auto)")
    why = mjx_render.unavailable()
    if why:
        raise SceneError(f"{what}, and the mjx backend cannot run here: {why}")
    try:
        renderer = _renderer(world)
    except Exception as e:  # MJX refuses some of a model's settings (a solver, a plugin)
        raise SceneError(f"{world.scenes[0].name}: the mjx backend cannot use this model: "
                         f"{type(e).__name__}: {' '.join(str(e).split())}") from e
    return Choice("mjx", "" if requested == "mjx" else f"env.render.backend auto: mjx ({what})", renderer)


def _auto(name: str, why: str, renderer=None) -> Choice:
    return Choice(name, f"env.render.backend auto: {name} ({why})", renderer)


def _renderer(world: "World") -> mjx_render.MjxRenderer:
    return mjx_render.MjxRenderer(world.models[0], world.spec)
