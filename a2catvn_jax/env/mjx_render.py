"""The `mjx` render backend: MuJoCo's own batch ray tracer (`mjx.render`, impl warp).

`mjx.render` traces a BVH of the scene's geoms inside `jax.jit` on CPU and GPU
(package `warp-lang`). Its render context is built once from one MuJoCo model and
fixes the number of worlds it renders, so one context is kept per batch size. Every
world of the batch may be a different scene of the same geom layout: the scene's
geom sizes and colours are given per world (`MjxFields`), the camera's and the geoms'
world poses come from each environment's `mjx.Data` (`mjx_world`), and the BVH is
refitted to them before each render, so one context serves a batch of houses, bodies
that move render where they are, and a world passed as data (held-out houses) renders
exactly like the environment's own.

The observation is the one the `raycast` backend gives (`camera.Frame`): RGB, depth
along the pixel's ray in metres (MuJoCo reports planar depth; it is converted), the
geom hit and its semantic class. The hits are MuJoCo's, so depth and geom ids match
`mujoco.mj_ray` and the `raycast` backend; the colours are MuJoCo's shading (its
lights and materials), not the `raycast` shader's patterns.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from a2catvn_jax.env import camera
from a2catvn_jax.env.camera import CameraSpec, Frame
from a2catvn_jax.env.mjx_world import MjxFields
from a2catvn_jax.env.scenes.mjcf import AGENT_CAMERA
from a2catvn_jax.errors import UserError

_DEPTH_SCALE = 2.0**20  # metres

# Every geom group is rendered: a geom index that is padding in the scene the render
# context is built from may be a real geom in another scene. Geoms that `mujoco.mj_ray`
# does not see (padding, alpha 0) are moved out of reach instead (`mjx_world.fields_of`).
RENDER_GROUPS = tuple(range(mujoco.mjNGROUP))



class BackendError(ValueError, UserError):
    """The `mjx` backend cannot be used here (missing package, unusable model)."""


def unavailable() -> str:
    """Why `mjx.render` cannot run here ("" when it can): the `warp-lang` package is
    missing or does not import."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return "it needs the warp-lang package (pip install warp-lang)"
    except Exception as e:  # installed but broken
        return "the warp-lang package does not import: " + " ".join(str(e).split())
    return ""


def agent_camera_model(model: mujoco.MjModel, spec: CameraSpec) -> tuple[mujoco.MjModel, int]:
    """(a copy of `model` whose agent camera has the spec's field of view, that camera's
    id): a render context precomputes its rays from the model's camera."""
    camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, AGENT_CAMERA)
    if camera < 0:
        raise BackendError(f"the model has no camera {AGENT_CAMERA!r} for the mjx backend")
    model = copy.copy(model)
    model.cam_fovy[camera] = spec.fovy
    model.cam_sensorsize[camera] = 0.0
    return model, camera


class MjxRenderer:
    """Frames from `mjx.render` for a batch of scenes sharing `model`'s geom layout."""

    def __init__(self, model: mujoco.MjModel, spec: CameraSpec):
        why = unavailable()
        if why:
            raise BackendError(f"env.render.backend 'mjx': {why}")
        import warp

        warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)  # no banner on stdout at Warp's start
        self.model, self.camera = agent_camera_model(model, spec)
        self.spec = spec
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        self._mx = mjx.put_model(self.model, impl="warp")
        self._dx = mjx.put_data(self.model, data, impl="warp")
        x, y = camera.image_plane(spec.height, spec.width, spec.fovy)
        # |(1, x, y)|: along-ray distance over planar depth at each pixel (the camera never rolls).
        self._ray_scale = jnp.asarray(np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2), jnp.float32)
        self._contexts: dict[int, object] = {}

    def context_settings(self) -> dict:
        """The render context's settings besides the model and world count (also what
        `benchmark render` gives MuJoCo Warp called directly)."""
        return dict(cam_res=(self.spec.width, self.spec.height), render_rgb=True, render_depth=True, render_seg=True,
                    use_textures=True, use_shadows=False, enabled_geom_groups=list(RENDER_GROUPS),
                    cam_active=[i == self.camera for i in range(self.model.ncam)])

    def context(self, worlds: int):
        """The render context for batches of `worlds` frames (made on first use)."""
        if worlds not in self._contexts:
            self._contexts[worlds] = mjx.create_render_context(mjm=self.model, nworld=worlds, **self.context_settings())
        return self._contexts[worlds]

    def render(self, fields: MjxFields, geom_class, scene, cam_pos, cam_mat, geom_xpos, geom_xmat) -> Frame:
        """Frames [N] of cameras at cam_pos [N, 3] with rotations cam_mat [N, 3, 3] (MuJoCo's
        `cam_xmat`) in scenes [N] of `fields`, whose geoms are at geom_xpos [N, G, 3] with
        rotations geom_xmat [N, G, 3, 3] (each environment's `mjx.Data`); `geom_class`
        [S, G]: the semantic class of each geom."""
        if fields.geom_size.shape[-2] != self.model.ngeom:
            raise BackendError(f"the mjx backend renders worlds of {self.model.ngeom} geoms (its render context's layout); "
                               f"these arrays have {fields.geom_size.shape[-2]}: build every world with one geom layout "
                               "(World(..., layout=...))")
        n = scene.shape[0]
        rc = self.context(n).pytree()

        def world(s, pos, mat, xpos, xmat):
            m = self._mx.replace(geom_size=fields.geom_size[s], geom_rgba=fields.geom_rgba[s])
            d = self._dx.replace(cam_xpos=self._dx.cam_xpos.at[self.camera].set(pos),
                                 cam_xmat=self._dx.cam_xmat.at[self.camera].set(mat),
                                 geom_xpos=xpos, geom_xmat=xmat)
            return m, d

        m, d = jax.vmap(world)(scene, cam_pos, cam_mat, geom_xpos, geom_xmat)
        d = jax.vmap(mjx.refit_bvh, in_axes=(0, 0, None))(m, d, rc)
        rgb, depth, seg, _ = jax.vmap(mjx.render_with_segmentation, in_axes=(0, 0, None))(m, d, rc)
        rgb = jnp.round(mjx.get_rgb(rc, self.camera, rgb) * 255).astype(jnp.uint8)
        geom = mjx.get_segmentation(rc, self.camera, seg).astype(jnp.int32)
        # get_depth divides by a scale and clips to [0, 1]; a power of two keeps every value exact.
        planar = mjx.get_depth(rc, self.camera, depth, _DEPTH_SCALE)[..., 0] * _DEPTH_SCALE
        hit = geom >= 0
        s = scene[:, None, None]
        return Frame(
            rgb=rgb,
            depth=jnp.where(hit, planar * self._ray_scale, 0.0),
            geom=geom,  # -1 where nothing is hit
            cls=jnp.where(hit, jnp.asarray(geom_class)[s, jnp.maximum(geom, 0)], 0).astype(jnp.int32),
            fallback=jnp.zeros(n, bool),
        )
