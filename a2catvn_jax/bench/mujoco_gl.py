"""Reference renderer built on MuJoCo's own OpenGL renderer (``mujoco.Renderer``).

Renders an MJCF scene headlessly from a mocap-driven agent camera and returns the
same three outputs as the package's ray-cast renderer:

* ``rgb``: ``uint8 [H, W, 3]``
* ``depth``: ``float32 [H, W]``, distance in metres from the camera centre along each
  pixel's ray, 0 where nothing is hit (``zdepth`` holds MuJoCo's native z-depth, the
  distance along the camera's viewing axis, far-plane distance for background;
  ``depth = zdepth * |d_cam|`` where ``d_cam`` is the pixel's camera-frame direction
  scaled to unit forward component)
* ``segmentation``: ``int32 [H, W]``, geom id per pixel, ``-1`` for background

Camera convention (shared with the ray caster, see :func:`camera_frame` and
:func:`pixel_ray_directions`): yaw rotates about world +z starting from +x, tilt
pitches the forward direction up, so forward is
``(cos(yaw) cos(tilt), sin(yaw) cos(tilt), sin(tilt))``. MuJoCo cameras look along
their local -z with local +y up and +x right. The field of view ``fovy`` is vertical,
pixels are square, and image row 0 is the top of the image.

Headless OpenGL backends
------------------------
MuJoCo picks its GL platform from the ``MUJOCO_GL`` environment variable when
``mujoco.rendering.classic.gl_context`` is first imported (``import mujoco`` does
that). :func:`ensure_gl_backend` probes ``egl`` then ``osmesa`` in a subprocess
(a user-set ``MUJOCO_GL`` is the only candidate tried), exports the working one,
and re-selects MuJoCo's GL context class in this process if ``mujoco`` was already
imported with another value. PyOpenGL binds one platform per process, so set
``MUJOCO_GL`` before anything imports ``OpenGL`` if you want a specific backend.

Debian / Ubuntu packages:

* EGL (preferred; Mesa's llvmpipe on CPU-only machines, the vendor driver on GPUs)::

      apt-get install -y libegl1 libopengl0 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1

* OSMesa (pure software fallback)::

      apt-get install -y libosmesa6

Both backends also need the ``PyOpenGL`` Python package (a dependency of the
``mujoco`` wheel).

Depth precision: the depth buffer stores a projective value between the clip
planes ``znear = model.vis.map.znear * model.stat.extent`` and
``zfar = model.vis.map.zfar * model.stat.extent``; background pixels have
``zdepth`` at the far plane and ``depth`` 0. Geometry closer to the camera than
``znear`` (measured along the viewing axis) is clipped, so scenes viewed from close
range should lower ``<visual><map znear/>``. Measured against ``mujoco.mj_ray`` (see
:meth:`MujocoRenderer.reference_raycast`): planar geoms (boxes) agree to ~1e-6
relative; spheres and cylinders differ by ~0.3% (median), ~3% (99th percentile) and
up to ~15% at grazing silhouettes, because OpenGL draws them tessellated
(``<visual><quality numslices/>``); geom ids agree on all but silhouette-edge pixels.
"""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import textwrap
import time
from typing import Optional, Sequence

import numpy as np

from a2catvn_jax.env import camera

__all__ = [
    "APT_HINT",
    "MujocoRenderer",
    "benchmark_fps",
    "camera_frame",
    "camera_ray_directions",
    "demo_scene_xml",
    "ensure_gl_backend",
    "gl_backend_available",
    "pixel_ray_directions",
    "probe_gl_backend",
    "zdepth_to_distance",
]

APT_HINT = (
    "apt-get update && apt-get install -y libegl1 libopengl0 libgl1 libegl-mesa0 "
    "libgl1-mesa-dri libgbm1   # EGL\n"
    "apt-get update && apt-get install -y libosmesa6"
    "   # OSMesa (software fallback)"
)

_DEFAULT_CANDIDATES: tuple[str, ...] = ("egl", "osmesa")
_BACKEND: Optional[str] = None  # backend selected in this process
_PROBE_CACHE: dict[str, tuple[bool, str]] = {}

_PROBE_SRC = textwrap.dedent(
    """
    import mujoco
    m = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><light pos="0 0 3"/>'
        '<geom type="box" size="1 1 1" pos="0 0 -2"/></worldbody></mujoco>')
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    r = mujoco.Renderer(m, 8, 8)
    r.update_scene(d)
    img = r.render()
    r.enable_depth_rendering()
    dep = r.render()
    assert img.shape == (8, 8, 3) and dep.shape == (8, 8)
    r.close()
    print("GL_PROBE_OK")
    """
)


# --------------------------------------------------------------------------------------
# GL backend selection
# --------------------------------------------------------------------------------------


def probe_gl_backend(backend: str, timeout: float = 120.0) -> tuple[bool, str]:
    """Tries to render a tiny scene with ``MUJOCO_GL=backend`` in a subprocess.

    Returns ``(ok, message)``; ``message`` holds the tail of the subprocess output
    when the probe fails. Results are cached per process.
    """
    backend = backend.lower().strip()
    if backend in _PROBE_CACHE:
        return _PROBE_CACHE[backend]
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    else:
        env.pop("PYOPENGL_PLATFORM", None)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_SRC],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        out = (proc.stdout or "") + (proc.stderr or "")
        ok = proc.returncode == 0 and "GL_PROBE_OK" in out
        msg = "ok" if ok else out.strip()[-800:] or f"exit code {proc.returncode}"
    except subprocess.TimeoutExpired:
        ok, msg = False, f"probe timed out after {timeout:.0f}s"
    except OSError as exc:  # pragma: no cover - interpreter could not start
        ok, msg = False, repr(exc)
    _PROBE_CACHE[backend] = (ok, msg)
    return ok, msg


def _select_in_process(backend: str) -> None:
    """Points MuJoCo's classic GL context at ``backend`` for this process."""
    os.environ["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        platform = os.environ.get("PYOPENGL_PLATFORM", "")
        if platform and platform.lower() != backend:
            raise RuntimeError(
                f"PYOPENGL_PLATFORM={platform!r} conflicts with MUJOCO_GL={backend!r}; "
                "unset PYOPENGL_PLATFORM or make both equal."
            )
    if "mujoco" not in sys.modules:
        return  # mujoco will read MUJOCO_GL when it is imported
    glc = sys.modules.get("mujoco.rendering.classic.gl_context")
    if glc is None:
        return
    current = getattr(glc, "_MUJOCO_GL", None)
    if current != backend:
        glc = importlib.reload(glc)
    if not hasattr(glc, "GLContext"):
        raise RuntimeError(f"MuJoCo could not load GL backend {backend!r}.")


def gl_backend_available(
    candidates: Optional[Sequence[str]] = None,
) -> Optional[str]:
    """Like :func:`ensure_gl_backend` but returns ``None`` instead of raising."""
    try:
        return ensure_gl_backend(candidates)
    except RuntimeError:
        return None


def ensure_gl_backend(candidates: Optional[Sequence[str]] = None) -> str:
    """Selects a working headless GL backend for ``mujoco.Renderer`` and returns it.

    If ``MUJOCO_GL`` is set in the environment it is the only backend tried;
    otherwise ``candidates`` (default ``("egl", "osmesa")``) are probed in order in a
    subprocess. The first working backend is exported as ``MUJOCO_GL`` and, if
    ``mujoco`` was already imported with a different value, MuJoCo's GL context
    module is reloaded so new ``mujoco.Renderer`` objects use it.

    Raises:
      RuntimeError: no backend works; the message lists each failure and the
        ``apt-get`` command that installs the system libraries.
    """
    global _BACKEND
    if _BACKEND is not None:
        return _BACKEND
    user = os.environ.get("MUJOCO_GL", "").lower().strip()
    if user:
        cands: tuple[str, ...] = (user,)
    else:
        cands = tuple(c.lower() for c in (candidates or _DEFAULT_CANDIDATES))
        platform = os.environ.get("PYOPENGL_PLATFORM", "").lower().strip()
        if platform in cands:
            # PyOpenGL may already be bound to this platform; only it can work.
            cands = (platform,)
    failures = []
    for cand in cands:
        ok, msg = probe_gl_backend(cand)
        if ok:
            _select_in_process(cand)
            _BACKEND = cand
            return cand
        failures.append(f"  MUJOCO_GL={cand}: {msg.splitlines()[-1] if msg else '?'}")
    origin = (
        "(from the MUJOCO_GL environment variable; unset it to auto-detect)" if user else ""
    )
    raise RuntimeError(
        f"No working headless OpenGL backend for MuJoCo among {list(cands)} {origin}.\n"
        + "\n".join(failures)
        + "\nInstall the system libraries, e.g.\n"
        + APT_HINT
    )


# --------------------------------------------------------------------------------------
# Camera geometry (pure numpy)
# --------------------------------------------------------------------------------------


def camera_frame(yaw: float, tilt: float) -> np.ndarray:
    """Camera orientation in the world frame as a 3x3 matrix.

    Columns are the camera's x (right), y (up) and z (backward) axes expressed in
    world coordinates, i.e. MuJoCo's camera frame: the camera looks along -z with
    forward ``(cos(yaw) cos(tilt), sin(yaw) cos(tilt), sin(tilt))``. The right axis
    stays horizontal (no roll).
    """
    right, up, forward = camera.camera_basis(float(yaw), float(tilt))
    return np.stack([right, up, -forward], axis=1)


def camera_ray_directions(height: int, width: int, fovy_deg: float) -> np.ndarray:
    """Camera-frame directions through pixel centres, ``[H, W, 3]``, not normalised.

    Each direction has z component -1 (unit distance along the viewing axis), so its
    norm is the factor that converts z-depth to distance along the ray. Row 0 is the
    top of the image, column 0 the left; the vertical field of view is ``fovy_deg``
    and pixels are square (horizontal extent scales with ``width / height``).
    """
    u, v = camera.image_plane(height, width, fovy_deg)
    uu, vv = np.meshgrid(u, v)  # [H, W]
    return np.stack([uu, vv, -np.ones_like(uu)], axis=-1)


def pixel_ray_directions(
    height: int, width: int, fovy_deg: float, yaw: float, tilt: float
) -> np.ndarray:
    """Unit world-frame ray directions through pixel centres, ``[H, W, 3]``.

    Uses the projection of MuJoCo's OpenGL camera (see
    :func:`camera_ray_directions`) rotated by :func:`camera_frame`.
    """
    d = camera_ray_directions(height, width, fovy_deg)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return d @ camera_frame(yaw, tilt).T


def zdepth_to_distance(zdepth: np.ndarray, fovy_deg: float) -> np.ndarray:
    """Converts z-depth ``[H, W]`` to distance along each pixel's ray (same dtype)."""
    h, w = zdepth.shape
    scale = np.linalg.norm(camera_ray_directions(h, w, fovy_deg), axis=-1)
    return (zdepth * scale).astype(zdepth.dtype, copy=False)


# --------------------------------------------------------------------------------------
# Renderer
# --------------------------------------------------------------------------------------


class MujocoRenderer:
    """Renders RGB, depth and geom segmentation with ``mujoco.Renderer``.

    The scene must contain a mocap body (default name ``"agent"``) holding a camera
    (default ``"agent_cam"``). :meth:`render` moves the mocap body so that the camera
    sits at ``pos`` with the orientation :func:`camera_frame` gives; a camera placed
    with an offset or rotation inside the body is accounted for.

    Args:
      xml: MJCF string.
      height, width: image size; must not exceed the model's
        ``<visual><global offwidth offheight/>``.
      camera: camera name.
      agent_body: mocap body name.
      geomgroup: six visibility flags for geom groups 0..5; default is MuJoCo's
        (groups 0, 1, 2 visible).
      shadows: render shadow maps in the RGB pass. Off by default: with Mesa's
        software rasteriser the shadow pass costs ~10-40 ms per frame, more than
        everything else together. Other render flags keep MuJoCo's defaults and can
        be changed through ``self.scene_flags``.
    """

    def __init__(
        self,
        xml: str,
        height: int,
        width: int,
        camera: str = "agent_cam",
        agent_body: str = "agent",
        geomgroup: Optional[Sequence[int]] = None,
        shadows: bool = False,
    ):
        self.backend = ensure_gl_backend()
        import mujoco  # after the backend is selected

        self._mj = mujoco
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.height, self.width = int(height), int(width)

        self.cam_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.cam_id < 0:
            raise ValueError(f"camera {camera!r} not found in the model")
        self.body_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, agent_body)
        if self.body_id < 0:
            raise ValueError(f"body {agent_body!r} not found in the model")
        self.mocap_id = int(m.body_mocapid[self.body_id])
        if self.mocap_id < 0:
            raise ValueError(f"body {agent_body!r} is not a mocap body")
        if int(m.cam_bodyid[self.cam_id]) != self.body_id:
            raise ValueError(f"camera {camera!r} is not attached to body {agent_body!r}")
        if int(m.cam_mode[self.cam_id]) != int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
            raise ValueError(f"camera {camera!r} must use mode='fixed'")
        if np.any(m.cam_sensorsize[self.cam_id] > 0):
            raise ValueError("cameras with sensorsize/focal intrinsics are not supported")
        self.fovy = float(m.cam_fovy[self.cam_id])

        # Camera pose relative to the agent body.
        self._cam_local_pos = np.array(m.cam_pos[self.cam_id], dtype=np.float64)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, np.array(m.cam_quat[self.cam_id], dtype=np.float64))
        self._cam_local_mat = mat.reshape(3, 3)

        self.option = mujoco.MjvOption()
        if geomgroup is not None:
            gg = np.asarray(geomgroup, dtype=np.uint8)
            if gg.shape != (6,):
                raise ValueError("geomgroup needs six entries")
            self.option.geomgroup[:] = gg
        self.geomgroup = np.array(self.option.geomgroup, dtype=np.uint8)

        self._renderer = mujoco.Renderer(m, self.height, self.width)
        self.scene_flags = self._renderer.scene.flags  # persistent mjvScene flags
        self.scene_flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(shadows)
        self.znear = float(m.vis.map.znear * m.stat.extent)
        self.zfar = float(m.vis.map.zfar * m.stat.extent)
        self._ray_scale = np.linalg.norm(
            camera_ray_directions(self.height, self.width, self.fovy), axis=-1
        ).astype(np.float32)
        self._quat = np.zeros(4)

    # -- pose -----------------------------------------------------------------------

    def set_pose(self, pos: Sequence[float], yaw: float, tilt: float) -> None:
        """Moves the agent so the camera is at ``pos`` looking along (yaw, tilt)."""
        mj = self._mj
        cam_mat = camera_frame(float(yaw), float(tilt))
        body_mat = cam_mat @ self._cam_local_mat.T
        body_pos = np.asarray(pos, dtype=np.float64) - body_mat @ self._cam_local_pos
        mj.mju_mat2Quat(self._quat, body_mat.reshape(-1))
        self.data.mocap_pos[self.mocap_id] = body_pos
        self.data.mocap_quat[self.mocap_id] = self._quat
        mj.mj_kinematics(self.model, self.data)
        mj.mj_camlight(self.model, self.data)

    # -- rendering ------------------------------------------------------------------

    def render(self, pos: Sequence[float], yaw: float, tilt: float = 0.0) -> dict:
        """Renders one frame from camera position ``pos`` (world, metres).

        Returns a dict with ``rgb`` (uint8 [H,W,3]), ``depth`` (float32 [H,W],
        distance along the pixel ray, 0 where no geom is hit), ``zdepth`` (float32
        [H,W], MuJoCo's z-depth, far plane for background) and ``segmentation``
        (int32 [H,W], geom id or -1).
        """
        self.set_pose(pos, yaw, tilt)
        r = self._renderer
        r.update_scene(self.data, camera=self.cam_id, scene_option=self.option)
        r.disable_depth_rendering()
        r.disable_segmentation_rendering()
        rgb = r.render()
        r.enable_depth_rendering()
        zdepth = r.render()
        r.enable_segmentation_rendering()
        seg2 = r.render()
        r.disable_segmentation_rendering()
        is_geom = seg2[..., 1] == int(self._mj.mjtObj.mjOBJ_GEOM)
        seg = np.where(is_geom, seg2[..., 0], -1).astype(np.int32)
        hit = seg2[..., 0] >= 0
        return {
            "rgb": rgb,
            "depth": np.where(hit, zdepth * self._ray_scale, np.float32(0.0)),
            "zdepth": zdepth,
            "segmentation": seg,
        }

    def camera_position(self) -> np.ndarray:
        """World position of the camera after the last :meth:`set_pose`/:meth:`render`."""
        return np.array(self.data.cam_xpos[self.cam_id])

    def camera_matrix(self) -> np.ndarray:
        """World orientation (3x3, columns = camera axes) after the last pose update."""
        return np.array(self.data.cam_xmat[self.cam_id]).reshape(3, 3)

    def reference_raycast(
        self,
        pos: Sequence[float],
        yaw: float,
        tilt: float = 0.0,
        pixels: Optional[np.ndarray] = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Casts ``mujoco.mj_ray`` through pixel centres from the camera pose.

        Uses :func:`pixel_ray_directions`, the renderer's geom-group mask and excludes
        the agent body. ``pixels`` is an optional ``[N, 2]`` array of (row, col);
        without it every pixel is cast. Returns ``(distance, geom_id)``, with -1 for
        both where the ray hits nothing; shapes ``[N]`` or ``[H, W]``.
        """
        mj = self._mj
        self.set_pose(pos, yaw, tilt)
        dirs = pixel_ray_directions(self.height, self.width, self.fovy, yaw, tilt)
        if pixels is None:
            rows, cols = np.indices((self.height, self.width))
            rows, cols = rows.ravel(), cols.ravel()
            out_shape: tuple[int, ...] = (self.height, self.width)
        else:
            pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
            rows, cols = pixels[:, 0], pixels[:, 1]
            out_shape = (len(pixels),)
        origin = np.array(self.data.cam_xpos[self.cam_id], dtype=np.float64)
        dist = np.empty(len(rows))
        gid = np.empty(len(rows), dtype=np.int32)
        g = np.zeros(1, dtype=np.int32)
        for k, (i, j) in enumerate(zip(rows, cols)):
            vec = np.ascontiguousarray(dirs[i, j], dtype=np.float64)
            dist[k] = mj.mj_ray(
                self.model, self.data, origin, vec, self.geomgroup, 1, self.body_id, g
            )
            gid[k] = g[0]
        return dist.reshape(out_shape), gid.reshape(out_shape)

    # -- lifetime -------------------------------------------------------------------

    def close(self) -> None:
        """Frees the GL context; the renderer cannot be used afterwards."""
        if getattr(self, "_renderer", None) is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> "MujocoRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------------------
# Demo scene and benchmark
# --------------------------------------------------------------------------------------


def demo_scene_xml(
    n_objects: int = 44,
    room_size: float = 8.0,
    seed: int = 0,
    offscreen: int = 512,
    fovy: float = 60.0,
    znear: float = 0.002,
) -> str:
    """A square room (floor, four walls, a light) with random boxes, spheres and
    cylinders plus the mocap ``agent`` body holding ``agent_cam``.

    Geom count is ``n_objects + 5`` (floor and four walls). ``znear`` is MuJoCo's
    ``<visual><map znear>``, a fraction of the model extent; MuJoCo's default (0.01)
    gives a near plane of ~0.17 m for this room, which clips objects the camera
    stands close to.
    """
    rng = np.random.default_rng(seed)
    half = room_size / 2.0
    wall_h = 1.5
    geoms = [
        f'<geom name="floor" type="box" size="{half} {half} 0.05" pos="0 0 -0.05" '
        'rgba="0.6 0.55 0.5 1"/>',
        f'<geom name="wall_n" type="box" size="{half} 0.05 {wall_h}" '
        f'pos="0 {half} {wall_h}" rgba="0.8 0.8 0.75 1"/>',
        f'<geom name="wall_s" type="box" size="{half} 0.05 {wall_h}" '
        f'pos="0 {-half} {wall_h}" rgba="0.75 0.8 0.8 1"/>',
        f'<geom name="wall_e" type="box" size="0.05 {half} {wall_h}" '
        f'pos="{half} 0 {wall_h}" rgba="0.8 0.75 0.8 1"/>',
        f'<geom name="wall_w" type="box" size="0.05 {half} {wall_h}" '
        f'pos="{-half} 0 {wall_h}" rgba="0.7 0.7 0.7 1"/>',
    ]
    kinds = ("box", "sphere", "cylinder")
    for i in range(n_objects):
        kind = kinds[i % 3]
        x, y = rng.uniform(-half + 0.5, half - 0.5, size=2)
        r, g, b = rng.uniform(0.1, 1.0, size=3)
        rgba = f'rgba="{r:.3f} {g:.3f} {b:.3f} 1"'
        if kind == "box":
            sx, sy, sz = rng.uniform(0.1, 0.5, size=3)
            yaw = rng.uniform(0, 180)
            geoms.append(
                f'<geom name="obj{i}" type="box" size="{sx:.3f} {sy:.3f} {sz:.3f}" '
                f'pos="{x:.3f} {y:.3f} {sz:.3f}" euler="0 0 {yaw:.1f}" material="m" {rgba}/>'
            )
        elif kind == "sphere":
            rad = rng.uniform(0.1, 0.4)
            z = rng.uniform(rad, 1.5)
            geoms.append(
                f'<geom name="obj{i}" type="sphere" size="{rad:.3f}" '
                f'pos="{x:.3f} {y:.3f} {z:.3f}" {rgba}/>'
            )
        else:
            rad, hh = rng.uniform(0.1, 0.3), rng.uniform(0.2, 0.8)
            geoms.append(
                f'<geom name="obj{i}" type="cylinder" size="{rad:.3f} {hh:.3f}" '
                f'pos="{x:.3f} {y:.3f} {hh:.3f}" {rgba}/>'
            )
    body = "\n    ".join(geoms)
    return f"""<mujoco model="demo_room">
  <visual>
    <global offwidth="{offscreen}" offheight="{offscreen}"/>
    <map znear="{znear}"/>
  </visual>
  <asset><material name="m" rgba="1 1 1 1"/></asset>
  <worldbody>
    <light name="top" pos="0 0 {2 * wall_h + 1}" dir="0 0 -1" directional="false"/>
    {body}
    <body name="agent" mocap="true" pos="0 0 1.0">
      <camera name="agent_cam" fovy="{fovy}"/>
    </body>
  </worldbody>
</mujoco>
"""


def _random_poses(renderer: MujocoRenderer, n: int, seed: int) -> np.ndarray:
    """Random (x, y, yaw, tilt) inside the xy box spanned by the model's geoms."""
    m, d = renderer.model, renderer.data
    renderer._mj.mj_kinematics(m, d)
    keep = m.geom_bodyid != renderer.body_id
    xy = np.asarray(d.geom_xpos)[keep, :2]
    if len(xy) == 0:
        lo, hi = m.stat.center[:2] - 1.0, m.stat.center[:2] + 1.0
    else:
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.1 * (hi - lo)
        lo, hi = lo + pad, hi - pad
    rng = np.random.default_rng(seed)
    poses = np.empty((n, 4))
    poses[:, 0] = rng.uniform(lo[0], hi[0], n)
    poses[:, 1] = rng.uniform(lo[1], hi[1], n)
    poses[:, 2] = rng.uniform(-np.pi, np.pi, n)
    poses[:, 3] = rng.uniform(-0.3, 0.3, n)
    return poses


def benchmark_fps(
    xml: str,
    height: int,
    width: int,
    n_frames: int = 200,
    seed: int = 0,
    poses: Optional[np.ndarray] = None,
    cam_height: Optional[float] = None,
    warmup: int = 5,
    shadows: bool = False,
) -> float:
    """Frames per second of :meth:`MujocoRenderer.render` (RGB + depth + segmentation).

    Args:
      xml, height, width: scene and image size.
      n_frames: frames timed; poses are cycled if fewer are given.
      seed: seed for random poses when ``poses`` is None.
      poses: optional ``[N, 4]`` array of (x, y, yaw, tilt).
      cam_height: camera z in metres; default is the camera's height in the model's
        initial configuration.
      warmup: untimed frames rendered first (shader and buffer setup).
      shadows: passed to :class:`MujocoRenderer`.
    """
    with MujocoRenderer(xml, height, width, shadows=shadows) as r:
        if cam_height is None:
            r._mj.mj_kinematics(r.model, r.data)
            r._mj.mj_camlight(r.model, r.data)
            cam_height = float(r.data.cam_xpos[r.cam_id][2])
        if poses is None:
            poses = _random_poses(r, n_frames, seed)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        if len(poses) == 0:
            raise ValueError("poses is empty")

        def frame(k: int) -> None:
            x, y, yaw, tilt = poses[k % len(poses)]
            r.render((x, y, cam_height), yaw, tilt)

        for k in range(warmup):
            frame(k)
        t0 = time.perf_counter()
        for k in range(n_frames):
            frame(k)
        dt = time.perf_counter() - t0
    return n_frames / dt


def _main(argv: Optional[Sequence[str]] = None) -> None:
    p = argparse.ArgumentParser(description="Benchmark the MuJoCo GL reference renderer.")
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 84, 174])
    p.add_argument("--n-objects", type=int, default=44)
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--shadows", action="store_true")
    args = p.parse_args(argv)
    backend = ensure_gl_backend()
    xml = demo_scene_xml(n_objects=args.n_objects)
    print(f"backend={backend} geoms={args.n_objects + 5} shadows={args.shadows}")
    for s in args.sizes:
        fps = benchmark_fps(xml, s, s, n_frames=args.frames, shadows=args.shadows)
        print(f"{s}x{s}: {fps:.1f} frames/s (rgb+depth+segmentation)")


if __name__ == "__main__":
    _main()
