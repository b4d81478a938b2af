"""Tests of the JAX ray-cast renderer against MuJoCo's own ray caster (CPU).

Every pixel ray of every frame is also cast with `mujoco.mj_multiRay` (the batched
form of `mj_ray`) on the very MJCF model the renderer's geometry was packed from;
depth and geom id must agree. Images are small and non-square, and the compiled
renderers are shared between tests, so the whole module takes well under a minute.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import a2catvn_jax.env.raycast as render_lib
from a2catvn_jax.env import camera, navgrid
from a2catvn_jax.env.geometry import Geometry, pack, slots, take
from a2catvn_jax.env.mjx_render import MjxRenderer
from a2catvn_jax.env.mjx_world import fields_of
from a2catvn_jax.env.mjx_world import MjxWorld, agent_pose
from a2catvn_jax.env.camera import CameraSpec, Frame
from a2catvn_jax.env.raycast import render, render_batch
from a2catvn_jax.env.scenes import (
    AGENT_RADIUS,
    CLASS_ID,
    CLASS_NAMES,
    Geom,
    Scene,
    compile_scene,
    layout_of,
    make_scenes,
    scene_from_mjcf,
    scene_to_mjcf,
)
from a2catvn_jax.env.scenes import mjcf as mjcf_lib

H, W, FOVY = 24, 32, 60.0  # non-square: exercises the horizontal field of view
SPEC = CameraSpec(H, W, FOVY, tile_columns=4)
CAM_Z = 1.0
POSES_PER_SCENE = 8
TOL = 1e-3  # metres
GRID_RES = 0.1
BODY_HEIGHT = 1.5  # free cells then have nothing around the camera at CAM_Z


# A hand-written scene of rotated primitives: oriented boxes (one rotated by exactly
# 90 degrees, which the packer turns into a world-aligned box), spheres, ellipsoids
# and capsules, some in a rotated static child body, colours from materials too.
PRIMITIVES_XML = """
<mujoco model="primitives">
  <compiler angle="radian"/>
  <asset>
    <material name="wood" rgba="0.55 0.35 0.2 1"/>
    <material name="cloth" rgba="0.2 0.3 0.7 1"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1"/>
    <geom name="floor_0" type="box" size="4 4 0.05" pos="0 0 -0.05" rgba="0.6 0.6 0.55 1"/>
    <geom name="wall_0" type="box" size="0.05 4 1.2" pos="4.05 0 1.2" rgba="0.8 0.8 0.8 1"/>
    <geom name="wall_1" type="box" size="1.5 0.05 1.0" pos="-1.5 3.2 1.0" euler="0 0 0.5"
          rgba="0.7 0.75 0.8 1"/>
    <geom name="table_0" type="box" size="0.6 0.4 0.04" pos="2 0.6 0.75" euler="0.15 -0.1 0.4"
          material="wood"/>
    <geom name="cabinet_0" type="box" size="0.3 0.25 0.5" pos="1.8 -1.6 0.9"
          quat="0.8 0.3 0.4 0.33" rgba="0.3 0.6 0.3 1"/>
    <geom name="bed_3" type="box" size="1.0 0.7 0.25" pos="-1.8 -1.8 0.25"
          euler="0 0 1.5707963267948966" material="cloth"/>
    <geom name="plant_0" type="sphere" size="0.3" pos="0.5 2.2 1.1" rgba="0.2 0.7 0.2 1"/>
    <geom name="sofa_0" type="ellipsoid" size="0.6 0.3 0.35" pos="-2.2 0.8 0.8"
          euler="0.3 0.2 0.9" rgba="0.6 0.2 0.2 1"/>
    <geom name="lamp_0" type="capsule" size="0.08 0.55" pos="1.0 -0.5 1.0" euler="0.6 0.35 0"
          rgba="0.9 0.9 0.3 1"/>
    <geom name="chair_0" type="capsule" fromto="-0.8 -2.6 0.9 0.4 -2.2 1.3" size="0.12"
          rgba="0.4 0.3 0.8 1"/>
    <body name="stand" pos="2.6 2.4 0.9" euler="0.2 0 -0.7">
      <geom name="object_0" type="ellipsoid" size="0.25 0.12 0.4" pos="0.2 0 0.1"
            euler="0 0.5 0" rgba="0.9 0.5 0.1 1"/>
      <geom name="shelf_0" type="box" size="0.4 0.15 0.3" pos="-0.4 0 0" euler="0.1 0.2 0.3"
            material="wood"/>
      <geom name="lamp_1" type="capsule" size="0.1 0.3" pos="0 0.4 0.3" quat="1 1 0 0"
            rgba="1 1 1 1"/>
    </body>
    <body name="agent" mocap="true">
      <camera name="agent_cam" xyaxes="0 -1 0 0 0 1"/>
    </body>
  </worldbody>
</mujoco>
"""


# ----------------------------------------------------------------------------------
# Batches of frames with their mj_ray reference.


@dataclasses.dataclass
class Batch:
    models: list  # MjModel per scene
    datas: list  # MjData per scene, after mj_forward
    geometry: Geometry  # batched over scenes
    spec: CameraSpec  # settings of the exact (culled + fallback) path
    scene: np.ndarray  # int32 [B]
    pos: np.ndarray  # float32 [B, 3]
    yaw: np.ndarray  # float32 [B]
    tilt: np.ndarray  # float32 [B]
    dirs: np.ndarray  # float64 [B, H, W, 3]: the renderer's own unit pixel rays
    ref_geom: np.ndarray  # int32 [B, H, W]: mj_ray's geom id, -1 where it misses
    ref_dist: np.ndarray  # float64 [B, H, W]: mj_ray's distance, -1 where it misses
    pair: tuple = ()  # two frames with one pose in scenes 0 and 1
    slit: int = -1  # the frame that looks through the slit of _slit_scene

    def args(self):
        return (
            self.geometry,
            jnp.asarray(self.scene),
            jnp.asarray(self.pos),
            jnp.asarray(self.yaw),
            jnp.asarray(self.tilt),
        )


def _make_batch(models, closed, heights, spec, scene, pos, yaw, tilt, skip_unsupported=False, **extra) -> Batch:
    scene = np.asarray(scene, np.int32)
    pos = np.asarray(pos, np.float32)
    yaw = np.asarray(yaw, np.float32)
    tilt = np.asarray(tilt, np.float32)
    datas = []
    for m in models:
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        datas.append(d)
    return Batch(
        models=models,
        datas=datas,
        geometry=pack(models, closed, heights, skip_unsupported=skip_unsupported),
        spec=spec,
        scene=scene,
        pos=pos,
        yaw=yaw,
        tilt=tilt,
        **_references(models, datas, scene, pos, yaw, tilt),
        **extra,
    )


def _references(models, datas, scene, pos, yaw, tilt) -> dict:
    """The renderer's pixel rays of each camera and what mj_multiRay finds along them:
    Batch's dirs, ref_geom and ref_dist."""
    rays = jax.vmap(lambda y, t: camera.ray_directions(y, t, H, W, FOVY))
    dirs = np.asarray(rays(jnp.asarray(yaw), jnp.asarray(tilt)), np.float64)
    n = H * W
    ref_geom = np.zeros((len(scene), n), np.int32)
    ref_dist = np.zeros((len(scene), n), np.float64)
    for b, k in enumerate(scene):
        mujoco.mj_multiRay(
            models[k], datas[k], pos[b].astype(np.float64), dirs[b].reshape(-1).copy(),
            None, 1, -1, ref_geom[b], ref_dist[b], None, n, mujoco.mjMAXVAL,
        )
    return {"dirs": dirs, "ref_geom": ref_geom.reshape(-1, H, W), "ref_dist": ref_dist.reshape(-1, H, W)}


def _box(name, lo, hi, rgba):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return Geom("box", (lo + hi) / 2, (hi - lo) / 2, rgba, name.split("_")[0], name=name)


def _slit_scene() -> Scene:
    """A closed room split by a wall with a narrow vertical slit, a cabinet behind it.

    Seen from SLIT_POSE, the slit lies strictly inside the wedge of one culling tile:
    both edges of the wedge meet the wall, so culling bounds the tile's reach just
    past the wall and drops the cabinet, yet the tile's middle rays pass through the
    slit and hit it. Only the renderer's verification of each ray can notice. Floor
    and ceiling reach far beyond the walls, so that without the cabinet and the far
    wall those rays still hit something (instead of nothing, which is easy to flag)."""
    grey, white, brown = (0.7, 0.7, 0.7, 1), (0.9, 0.9, 0.9, 1), (0.5, 0.3, 0.1, 1)
    h, s = 2.4, 0.09  # ceiling height, slit half-width
    geoms = [
        _box("floor_0", (-0.1, -20.0, -0.05), (500.0, 20.0, 0.0), grey),
        _box("ceiling_0", (-0.1, -20.0, h), (500.0, 20.0, h + 0.05), white),
        _box("wall_0", (-0.1, -2.0, 0.0), (0.0, 2.0, h), white),
        _box("wall_1", (7.0, -2.0, 0.0), (7.1, 2.0, h), white),
        _box("wall_2", (-0.1, -2.1, 0.0), (7.1, -2.0, h), white),
        _box("wall_3", (-0.1, 2.0, 0.0), (7.1, 2.1, h), white),
        _box("wall_4", (2.95, -2.0, 0.0), (3.05, -s, h), white),
        _box("wall_5", (2.95, s, 0.0), (3.05, 2.0, h), white),
        _box("cabinet_0", (4.3, -0.4, 0.0), (4.7, 0.4, 1.6), brown),
    ]
    return Scene("slit", geoms, [], (0.0, -2.0, 7.0, 2.0), h, closed=True)


# Camera at x = 1 turned left by the angle of the centre of image columns 16..19 (one
# culling tile): those columns then look straight along +x through the slit.
_TILE_CENTRE = float(np.arctan((18.0 / W * 2.0 - 1.0) * np.tan(np.deg2rad(FOVY / 2)) * W / H))
SLIT_POSE = ((1.0, 0.0, CAM_Z), _TILE_CENTRE, 0.0)


def _free_points(scene) -> np.ndarray:
    grid = navgrid.build(scene, GRID_RES, AGENT_RADIUS, BODY_HEIGHT)
    return grid.centres()[grid.free]


@pytest.fixture(scope="module")
def generated() -> Batch:
    """Three houses, a single room and a maze, one geom layout, one batch; 8 random
    poses per scene, plus one pose shared by houses 0 and 1, plus the slit scene."""
    scenes = (
        make_scenes("house", 2, 11, grid=(2, 2))
        + make_scenes("house", 1, 12, grid=(2, 3))
        + make_scenes("room", 1, 13)
        + make_scenes("maze", 1, 14)
    )
    free = [_free_points(s) for s in scenes]
    scenes.append(_slit_scene())
    layout = layout_of(scenes)
    models = [compile_scene(scene_to_mjcf(s, layout)) for s in scenes]
    rng = np.random.default_rng(0)
    scene, pos, yaw, tilt = [], [], [], []

    def add(k, xy, y, t):
        scene.append(k)
        pos.append([xy[0], xy[1], CAM_Z])
        yaw.append(y)
        tilt.append(t)

    for k, pts in enumerate(free):
        for _ in range(POSES_PER_SCENE):
            add(k, pts[rng.integers(len(pts))], rng.uniform(-np.pi, np.pi), rng.uniform(-0.5, 0.5))
    # One pose free in both house 0 and house 1, rendered in each.
    both = np.array([p for p in free[0] if np.any(np.all(np.abs(free[1] - p) < 1e-6, -1))])
    assert len(both), "houses 0 and 1 share no free cell"
    xy, y, t = both[rng.integers(len(both))], rng.uniform(-np.pi, np.pi), 0.1
    pair = (len(scene), len(scene) + 1)
    add(0, xy, y, t)
    add(1, xy, y, t)
    slit = len(scene)
    add(len(scenes) - 1, *SLIT_POSE)
    return _make_batch(
        models, [s.closed for s in scenes], [s.height for s in scenes], SPEC, scene, pos, yaw, tilt,
        pair=pair, slit=slit,
    )


# The generated batch's cameras without tilt (`render_batch` traces their boxes per
# column and per row when it does not cull), except one camera in the second chunk of
# 16 frames, so that chunk takes the general trace; 51 frames leave a remainder chunk.
TILTED_CHUNK = 1


@pytest.fixture(scope="module")
def level(generated) -> Batch:
    b = generated
    chunk = b.spec.chunk(len(b.scene))
    assert chunk == 16 and len(b.scene) % chunk, "the level batch needs whole chunks and a remainder"
    tilt = np.zeros_like(b.tilt)
    tilt[TILTED_CHUNK * chunk + 5] = 0.3
    refs = _references(b.models, b.datas, b.scene, b.pos, b.yaw, tilt)
    return dataclasses.replace(b, spec=dataclasses.replace(b.spec, candidates=0), tilt=tilt, **refs)


@pytest.fixture(scope="module")
def primitives() -> Batch:
    """The hand-written scene of rotated primitives (not closed), cameras looking
    roughly at its objects."""
    model = compile_scene(PRIMITIVES_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(model.ngeom)]
    targets = [data.geom_xpos[i, :2].copy() for i, n in enumerate(names) if not n.startswith(("floor", "wall"))]
    pts = _free_points(scene_from_mjcf(PRIMITIVES_XML))
    rng = np.random.default_rng(1)
    num = 12
    pos, yaw, tilt = [], [], []
    for _ in range(num):
        xy = pts[rng.integers(len(pts))]
        to = targets[rng.integers(len(targets))] - xy
        pos.append([xy[0], xy[1], CAM_Z])
        yaw.append(np.arctan2(to[1], to[0]) + rng.uniform(-0.4, 0.4))
        tilt.append(rng.uniform(-0.5, 0.5))
    # Few candidates per tile: culling (top-k included) runs for every family, and
    # tiles whose candidates overflow get a tighter bound, often failing its check.
    spec = CameraSpec(H, W, FOVY, candidates=2, chunk_frames=5)
    return _make_batch([model], [False], [2.4], spec, np.zeros(num), pos, yaw, tilt)


@functools.lru_cache(maxsize=None)
def _exact_renderer(spec: CameraSpec):
    return jax.jit(functools.partial(render_batch, spec=spec))


def _mjx_renderer(spec: CameraSpec, batch: Batch):
    """`mjx.render` (MuJoCo Warp) of a batch, one render context from its first scene."""
    renderer = MjxRenderer(batch.models[0], spec)
    fields = fields_of(batch.models)

    def run(geometry, scene, pos, yaw, tilt):
        _, _, cam_mat = agent_pose(jnp.stack([pos[:, 0], pos[:, 1], yaw, tilt], -1), 0.0)
        return renderer.render(fields, geometry.cls, scene, pos, cam_mat, fields.geom_xpos[scene], fields.geom_xmat[scene])

    return jax.jit(run)


@functools.lru_cache(maxsize=None)
def _brute_renderer(spec: CameraSpec):
    one = functools.partial(render, spec=spec, culled=False)

    def run(geometry, scene, pos, yaw, tilt):
        return jax.vmap(one)(take(geometry, scene), pos, yaw, tilt)

    return jax.jit(run)


def _numpy(frame: Frame) -> Frame:
    return Frame(*(np.asarray(a) for a in frame))


@pytest.fixture(scope="module")
def frames(generated, primitives, level):
    """frames(batch name, path) -> numpy Frame, rendered once per module.
    path "exact": render_batch; "brute": render(..., culled=False); "mjx": the mjx backend.
    The level batch's spec does not cull, so its "exact" frames are render_batch's unculled ones."""
    batches = {"generated": generated, "primitives": primitives, "level": level}
    memo = {}

    def get(name: str, path: str) -> Frame:
        if (name, path) not in memo:
            b = batches[name]
            if path == "mjx":
                fn = _mjx_renderer(b.spec, b)
            else:
                fn = _exact_renderer(b.spec) if path == "exact" else _brute_renderer(b.spec)
            memo[name, path] = _numpy(fn(*b.args()))
        return memo[name, path]

    return get


# ----------------------------------------------------------------------------------
# 1. Depth and geom id vs mj_ray.

def _geom_name(m, g) -> str:
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) if g >= 0 else "-"


def _compare_with_mujoco(b: Batch, f: Frame):
    """Failures (strings) and statistics of frame f against b's mj_ray reference."""
    hit = b.ref_geom >= 0
    err = np.abs(f.depth.astype(np.float64) - b.ref_dist)
    bad = np.zeros(hit.shape, bool)
    why = np.full(hit.shape, "", object)
    # Missed by MuJoCo: nothing hit here either.
    miss_bad = ~hit & ((f.geom != -1) | (f.depth != 0))
    bad |= miss_bad
    why[miss_bad] = "mj_ray misses"
    # Hit: same distance, and the same geom unless ours is hit at the same distance.
    depth_bad = hit & ~(err <= TOL)
    bad |= depth_bad
    why[depth_bad] = "depth differs"
    ties = 0
    for bi, i, j in zip(*np.nonzero(hit & ~depth_bad & (f.geom != b.ref_geom))):
        k, g = b.scene[bi], int(f.geom[bi, i, j])
        m, d = b.models[k], b.datas[k]
        t = -1.0
        if g >= 0 and not _geom_name(m, g).startswith("pad_"):
            t = mujoco.mju_rayGeom(
                d.geom_xpos[g], d.geom_xmat[g], m.geom_size[g], b.pos[bi].astype(np.float64),
                b.dirs[bi, i, j], int(m.geom_type[g]), None,
            )
        if t >= 0 and abs(t - b.ref_dist[bi, i, j]) <= TOL:
            ties += 1
        else:
            bad[bi, i, j] = True
            why[bi, i, j] = f"geom differs (mju_rayGeom of ours: {t:.5f})"
    lines = []
    for bi, i, j in zip(*np.nonzero(bad)):
        k = b.scene[bi]
        m = b.models[k]
        lines.append(
            f"frame {bi} (scene {k}, pos {b.pos[bi].tolist()}, yaw {b.yaw[bi]:.4f}, tilt {b.tilt[bi]:.4f}) "
            f"pixel (row {i}, col {j}): {why[bi, i, j]}; ours geom {f.geom[bi, i, j]} "
            f"{_geom_name(m, f.geom[bi, i, j])!r} depth {f.depth[bi, i, j]:.5f}, mj_ray geom "
            f"{b.ref_geom[bi, i, j]} {_geom_name(m, b.ref_geom[bi, i, j])!r} dist {b.ref_dist[bi, i, j]:.5f}"
        )
    max_err = float(np.max(np.where(hit, err, 0.0)))
    return lines, (max_err, hit.shape[0], hit.size, int(hit.sum()), ties)


@pytest.mark.parametrize("name, path", [(n, p) for n in ("generated", "primitives") for p in ("exact", "brute", "mjx")]
                         + [("level", "exact")])
def test_depth_and_geom_match_mj_ray(name, path, frames, request):
    b = request.getfixturevalue(name)
    f = frames(name, path)
    assert f.depth.shape == f.geom.shape == (len(b.scene), H, W)
    # The reference is not degenerate: most rays hit, and in the open scene some miss.
    assert np.mean(b.ref_geom >= 0) > (0.3 if name == "primitives" else 0.99)
    if name == "primitives":
        assert np.any(b.ref_geom < 0)
        hit_types = {int(b.models[0].geom_type[g]) for g in np.unique(b.ref_geom[b.ref_geom >= 0])}
        g = mujoco.mjtGeom
        assert hit_types == {int(g.mjGEOM_BOX), int(g.mjGEOM_SPHERE), int(g.mjGEOM_CAPSULE), int(g.mjGEOM_ELLIPSOID)}
    lines, stats = _compare_with_mujoco(b, f)
    print(f"\n{name}/{path}: max depth error {stats[0]:.3g} m over {stats[3]} hits of {stats[2]} rays "
          f"({stats[1]} frames), {stats[4]} geom-id ties")
    assert not lines, f"{len(lines)} pixels disagree with mj_ray:\n" + "\n".join(lines[:20])


# ----------------------------------------------------------------------------------
# 2. Culling changes nothing.


def test_culling_changes_nothing(generated, frames):
    b = generated
    reference = _numpy(_exact_renderer(dataclasses.replace(SPEC, candidates=0))(*b.args()))
    assert not reference.fallback.any()
    runs = {
        "candidates=24": frames("generated", "exact"),
        # Too few candidates: most frames have tiles that fail their check and are
        # re-traced; chunks of 3 frames leave a remainder chunk.
        "candidates=4, chunks of 3": _numpy(
            _exact_renderer(dataclasses.replace(SPEC, candidates=4, chunk_frames=3))(*b.args())
        ),
    }
    # With 24 candidates a few frames have failing tiles (the slit frame always: see
    # _slit_scene), re-traced among frames that were fine.
    some = runs["candidates=24"].fallback
    assert some[b.slit]
    assert 1 <= some.sum() < len(some) // 2
    many = runs["candidates=4, chunks of 3"].fallback
    assert many.sum() > some.sum(), "candidates=4 should make more frames fall back"
    assert np.all(many >= some)
    for label, f in runs.items():
        np.testing.assert_array_equal(f.geom, reference.geom, err_msg=label)
        np.testing.assert_allclose(f.depth, reference.depth, rtol=0, atol=1e-5, err_msg=label)
        np.testing.assert_array_equal(f.cls, reference.cls, err_msg=label)
        # Colours: the same but for a rounding error's worth of pixels. The shading of a
        # hit is the same function in every program, but how XLA fuses its arithmetic
        # depends on the program and the compiler options (the tests compile with the
        # older loop emitter, tests/conftest.py), and a hit point that moves by one
        # rounding error may cross a texture stripe. Compiled with XLA's fusion emitters
        # (its default) the colours here are bitwise equal.
        differ = (f.rgb != reference.rgb).any(-1)
        assert differ.mean() < 1e-3, f"{label}: {differ.sum()} of {differ.size} pixels differ in colour"


def test_level_cameras_take_the_level_trace(level, monkeypatch):
    """`render_batch` without culling traces a chunk by `trace_level` exactly when all
    its cameras are level: with that function replaced by one that marks every pixel,
    the level chunks (the remainder chunk included) are marked and the chunk with a
    tilted camera is not."""

    def marked(geom, cam_pos, yaw, dirs, spec):
        shape = dirs.shape[:2]
        return jnp.full(shape, 1.0, jnp.float32), jnp.full(shape, -7, jnp.int32)

    monkeypatch.setattr(render_lib, "trace_level", marked)
    b = level
    f = _numpy(jax.jit(functools.partial(render_batch, spec=b.spec))(*b.args()))
    chunk = b.spec.chunk(len(b.scene))
    took = np.all(f.geom == -7, axis=(1, 2))
    tilted = np.arange(len(b.scene)) // chunk == TILTED_CHUNK
    assert np.all(took == ~tilted), np.nonzero(took != ~tilted)
    assert np.all(np.isin(f.geom[tilted], [-7], invert=True))


def test_ray_check_catches_what_culling_misses(generated):
    """In the slit scene culling alone gets the cabinet behind the slit wrong; the
    frame must be flagged (render_batch then re-renders it: test above)."""
    b, k = generated, generated.slit
    cabinet = mujoco.mj_name2id(b.models[b.scene[k]], mujoco.mjtObj.mjOBJ_GEOM, "cabinet_0")
    seen = b.ref_geom[k] == cabinet
    assert seen.any() and np.all(np.nonzero(seen)[1] // SPEC.tile == 16 // SPEC.tile)
    culled = jax.jit(functools.partial(render, spec=SPEC, culled=True))
    f = _numpy(culled(take(b.geometry, int(b.scene[k])), *(jnp.asarray(a[k]) for a in (b.pos, b.yaw, b.tilt))))
    assert not np.any(f.geom == cabinet), "culling no longer drops the cabinet: the scene tests nothing"
    assert f.fallback


# ----------------------------------------------------------------------------------
# 3. Scenes of one batch keep their own geometry.


@pytest.mark.parametrize("path", ["exact", "mjx"])
def test_scenes_in_one_batch_render_their_own_geometry(generated, frames, path):
    """Scenes of one batch (with the mjx backend: one render context, built from
    scene 0) each render their own geometry."""
    b = generated
    f = frames("generated", path)
    p, q = b.pair
    assert (b.scene[p], b.scene[q]) == (0, 1)
    assert np.array_equal(b.pos[p], b.pos[q]) and b.yaw[p] == b.yaw[q] and b.tilt[p] == b.tilt[q]
    # MuJoCo sees different rooms from this pose in the two houses...
    ref_differs = np.abs(b.ref_dist[p] - b.ref_dist[q]) > 0.05
    assert ref_differs.mean() > 0.1
    # ... and so does the renderer: each frame matches its own house, not the other.
    for own, other in ((p, q), (q, p)):
        assert np.all(np.abs(f.depth[own] - b.ref_dist[own]) <= TOL)
        assert np.mean(np.abs(f.depth[own] - b.ref_dist[other]) > 0.05) > 0.1
    assert np.mean(np.abs(f.depth[p] - f.depth[q]) > 0.05) > 0.1
    assert np.any(f.rgb[p] != f.rgb[q])


# ----------------------------------------------------------------------------------
# 4. Segmentation and image formats.


@pytest.mark.parametrize("path", ["exact", "mjx"])
@pytest.mark.parametrize("name", ["generated", "primitives"])
def test_segmentation_and_formats(name, path, frames, request):
    b = request.getfixturevalue(name)
    f = frames(name, path)
    n = len(b.scene)
    assert f.rgb.shape == (n, H, W, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (n, H, W) and f.depth.dtype == np.float32
    assert f.geom.dtype == np.int32 and f.cls.dtype == np.int32
    assert f.fallback.shape == (n,) and f.fallback.dtype == np.bool_
    cls_table = np.asarray(b.geometry.cls)  # [S, G]
    hit = f.geom >= 0
    expected = np.where(hit, cls_table[b.scene[:, None, None], np.maximum(f.geom, 0)], 0)
    np.testing.assert_array_equal(f.cls, expected)
    assert np.all(f.cls[hit] > 0), "every geom hit has a semantic class"
    # The class is the one the geom's MuJoCo name starts with ("bed_3": bed).
    for bi in range(n):
        m = b.models[b.scene[bi]]
        for g in np.unique(f.geom[bi][hit[bi]]):
            name, cls = _geom_name(m, g), CLASS_NAMES[cls_table[b.scene[bi], g]]
            assert name == cls or name.startswith((cls + "_", cls + "/")), (name, cls)
    # Nothing hit: black, depth 0, class 0.
    assert np.all(f.rgb[~hit] == 0) and np.all(f.depth[~hit] == 0) and np.all(f.cls[~hit] == 0)
    assert np.all(f.depth[hit] > 0) and np.all(f.rgb[hit].max(-1) > 0)
    if name == "primitives":
        assert (~hit).any()
        m = b.models[0]
        bed = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "bed_3")
        assert cls_table[0, bed] == CLASS_ID["bed"]
        assert np.any(f.geom == bed), "no camera sees the bed"
        assert np.all(f.cls[f.geom == bed] == CLASS_ID["bed"])
        # Material colours are the geom's colour.
        table = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "table_0")
        np.testing.assert_allclose(np.asarray(b.geometry.rgb)[0, table], [0.55, 0.35, 0.2], atol=1e-6)


# ----------------------------------------------------------------------------------
# 4b. A user's planes, cylinders, meshes and textures (the mjx backend alone).

NATIVE_XML = """
<mujoco model="native">
  <compiler angle="radian"/>
  <asset>
    <texture name="checker" type="2d" builtin="checker" width="64" height="64" rgb1=".2 .3 .4" rgb2=".9 .9 .9"/>
    <material name="tiles" texture="checker" texrepeat="6 4"/>
    <mesh name="wedge" vertex="0 0 0  0.8 0 0  0 0.6 0  0 0 0.9  0.8 0 0.4"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" dir="0.2 0.1 -1" diffuse="0.7 0.7 0.7" castshadow="false"/>
    <geom name="floor" type="plane" size="3 2 0.1" material="tiles"/>
    <geom name="ceiling" type="plane" size="3 2 0.1" pos="0 0 2.4" quat="0 1 0 0"/>
    <geom name="wall_0" type="box" size="0.05 2 1.2" pos="3 0 1.2"/>
    <geom name="wall_1" type="box" size="0.05 2 1.2" pos="-3 0 1.2"/>
    <geom name="wall_2" type="box" size="3 0.05 1.2" pos="0 2 1.2"/>
    <geom name="wall_3" type="box" size="3 0.05 1.2" pos="0 -2 1.2"/>
    <geom name="chair_0" type="mesh" mesh="wedge" pos="1.2 0.6 0" euler="0 0 0.7" rgba="0.8 0.2 0.2 1"/>
    <geom name="table_0" type="cylinder" size="0.35 0.4" pos="-1.2 1.0 0.4" rgba="0.2 0.6 0.2 1"/>
    <geom name="plant_0" type="cylinder" size="0.1 0.5" pos="-1.5 -1.2 0.3" euler="1.2 0 0" rgba="0.1 0.5 0.1 1"/>
    <geom name="sofa_0" type="capsule" size="0.25 0.6" pos="1.0 -1.3 0.3" euler="0 1.5708 0" rgba="0.3 0.3 0.7 1"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def native() -> Batch:
    """NATIVE_XML compiled as the environment compiles a user's scene with plane,
    cylinder and mesh geoms (its own model plus the agent), cameras looking at its objects."""
    scene = scene_from_mjcf(NATIVE_XML)
    assert scene.source == ("xml", NATIVE_XML) and {g.native for g in scene.geoms} == {None, "plane", "cylinder", "mesh"}
    _, model = mjcf_lib.native_model(scene, FOVY)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(model.ngeom)]
    targets = [data.geom_xpos[i, :2].copy() for i, n in enumerate(names) if n.startswith(("chair", "table", "plant"))]
    pts = _free_points(scene)
    rng = np.random.default_rng(2)
    num = 10
    pos, yaw, tilt = [], [], []
    for k in range(num):
        xy = pts[rng.integers(len(pts))]
        to = targets[k % len(targets)] - xy
        pos.append([xy[0], xy[1], CAM_Z])
        yaw.append(np.arctan2(to[1], to[0]) + rng.uniform(-0.3, 0.3))
        tilt.append(rng.uniform(-0.5, 0.2))
    return _make_batch([model], [False], [2.4], SPEC, np.zeros(num), pos, yaw, tilt, skip_unsupported=True)


def test_planes_cylinders_meshes_and_textures_with_mjx(native):
    """With the mjx backend a user's planes (a textured floor), cylinders (one tilted)
    and meshes give mj_ray's depth and geom at every pixel and their own classes; the
    ray caster refuses them (one-line errors: tests/test_scene_errors.py)."""
    b = native
    render_fn = _mjx_renderer(b.spec, b)  # kept while its frames compute: it holds the render context
    f = _numpy(render_fn(*b.args()))
    g = mujoco.mjtGeom
    hit_types = {int(b.models[0].geom_type[x]) for x in np.unique(b.ref_geom[b.ref_geom >= 0])}
    assert {int(g.mjGEOM_PLANE), int(g.mjGEOM_CYLINDER), int(g.mjGEOM_MESH)} <= hit_types
    lines, stats = _compare_with_mujoco(b, f)
    print(f"\nnative/mjx: max depth error {stats[0]:.3g} m over {stats[3]} hits of {stats[2]} rays "
          f"({stats[1]} frames), {stats[4]} geom-id ties")
    assert not lines, f"{len(lines)} pixels disagree with mj_ray:\n" + "\n".join(lines[:20])
    m, cls_table = b.models[0], np.asarray(b.geometry.cls)[0]
    for name in ("floor", "chair_0", "table_0", "plant_0"):
        gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
        assert np.any(f.geom == gid), f"no camera sees {name}"
        assert cls_table[gid] == CLASS_ID[name.split("_")[0]]
        assert np.all(f.cls[f.geom == gid] == CLASS_ID[name.split("_")[0]])
    # The floor's checker texture: its brightness varies several times more than the
    # same floor's without the texture, seen from the same poses.
    plain_xml = NATIVE_XML.replace(' material="tiles"', ' rgba="0.55 0.6 0.65 1"')
    _, plain = mjcf_lib.native_model(scene_from_mjcf(plain_xml), FOVY)
    plain_fn = _mjx_renderer(b.spec, dataclasses.replace(b, models=[plain]))
    untextured = _numpy(plain_fn(*b.args()))
    floor_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    spread = [np.std(frame.rgb[frame.geom == floor_id].astype(float).mean(-1)) for frame in (f, untextured)]
    assert spread[0] > 3 * spread[1], spread
    # Each one's box (what blocks the agent) holds every point mj_ray hits on it, and is
    # tight: the tilted cylinder's box is the extent of points on its two rims.
    scene = scene_from_mjcf(NATIVE_XML)
    boxes = {g.name: (g.pos - g.size, g.pos + g.size) for g in scene.geoms if g.native}
    points = b.pos[:, None, None, :] + b.dirs * b.ref_dist[..., None]
    for name, (lo, hi) in boxes.items():
        on = points[b.ref_geom == mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)]
        assert len(on) and np.all(on >= lo - 1e-4) and np.all(on <= hi + 1e-4), name
    plant = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "plant_0")
    rot, (r, h) = b.datas[0].geom_xmat[plant].reshape(3, 3), m.geom_size[plant][:2]
    assert abs(rot[2, 2]) < 0.5  # tilted by 1.2 rad
    a = np.linspace(0, 2 * np.pi, 3601)
    rim = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], -1)
    ends = np.concatenate([rim + [0, 0, h], rim - [0, 0, h]]) @ rot.T + b.datas[0].geom_xpos[plant]
    np.testing.assert_allclose(boxes["plant_0"][0], ends.min(0), atol=1e-5)
    np.testing.assert_allclose(boxes["plant_0"][1], ends.max(0), atol=1e-5)
    # The ray caster's geometry holds no family member for them.
    members = np.concatenate([np.asarray(fam.gid).ravel() for fam in b.geometry.families.values()])
    native_ids = [i for i in range(m.ngeom) if int(m.geom_type[i]) in mjcf_lib.NATIVE_TYPES]
    assert native_ids and not set(native_ids) & set(members.tolist())


MOVING_XML = (Path(__file__).resolve().parent / "data" / "moving_scene.xml").read_text()


def test_moving_bodies_render_where_their_data_puts_them():
    """A scene with bodies on hinge and slide joints: with joint positions drawn per
    frame, both backends (reading the geom poses from each frame's `mjx.Data`, placed
    by `mjx.kinematics`) give mj_ray's depth and geom id at every pixel, for mj_ray
    run on MuJoCo's own data at the same joint positions. The agent's camera in the
    data is where MuJoCo's kinematics puts the mocap body's camera."""
    scene = scene_from_mjcf(MOVING_XML)
    moving = {g.name for g in scene.geoms if g.moving}
    assert moving == {"door_frame_leaf", "cabinet_0", "cabinet_knob", "lamp_0", "lamp_1"} and scene.source
    _, model = mjcf_lib.native_model(scene, FOVY)
    world = MjxWorld(model, CAM_Z)
    assert world.nq == 4 and len(world.moving) == 5
    fields = fields_of([model])
    geometry = pack([model], [False], [2.4])
    where = slots(take(geometry, 0), world.moving)
    assert all(f != "abox" for f, _ in where)  # moving boxes are oriented boxes
    num = 12
    rng = np.random.default_rng(5)
    qpos = jax.vmap(world.draw_qpos)(jax.random.split(jax.random.PRNGKey(3), num))
    lo, hi = (np.asarray(a) for a in world.qpos_range)
    assert np.all((np.asarray(qpos) >= lo) & (np.asarray(qpos) <= hi)) and np.ptp(np.asarray(qpos), 0).min() > 0.3
    targets = np.array([[0.5, -0.6], [-1.5, 1.0], [1.5, 1.0]])
    pose = []
    for k in range(num):
        # Outside every moving geom's footprint (as the environment keeps the agent).
        d = mujoco.MjData(model)
        d.qpos[:] = np.asarray(qpos[k], np.float64)
        mujoco.mj_forward(model, d)
        while True:
            xy = np.array([rng.uniform(-2.5, 2.5), rng.uniform(-1.7, 1.7)])
            if all(np.linalg.norm(xy - d.geom_xpos[i, :2]) > model.geom_rbound[i] + 0.1 for i in world.moving):
                break
        to = targets[k % 3] - xy
        pose.append([xy[0], xy[1], np.arctan2(to[1], to[0]) + rng.uniform(-0.2, 0.2), rng.uniform(-0.4, 0.3)])
    pose = jnp.asarray(pose, jnp.float32)
    scene_idx = jnp.zeros(num, jnp.int32)
    data = jax.jit(jax.vmap(lambda q, p: world.place_agent(world.data(fields, 0, q), p)))(qpos, pose)
    # The camera in the data is where MuJoCo's own kinematics (mjx) puts the mocap body's.
    kin = jax.jit(jax.vmap(lambda d: mjx.kinematics(world.model, d)))(data)
    np.testing.assert_allclose(np.asarray(kin.cam_xpos[:, world.camera]), np.asarray(data.cam_xpos[:, world.camera]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(kin.cam_xmat[:, world.camera]), np.asarray(data.cam_xmat[:, world.camera]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(kin.xquat[:, world.body]), np.asarray(data.xquat[:, world.body]), atol=1e-5)
    # mj_ray on MuJoCo's data at the same joint positions, from the same rays.
    pos = np.asarray(data.cam_xpos[:, world.camera], np.float64)
    dirs = np.asarray(jax.vmap(lambda y, t: camera.ray_directions(y, t, H, W, FOVY))(pose[:, 2], pose[:, 3]), np.float64)
    ref_geom = np.zeros((num, H * W), np.int32)
    ref_dist = np.zeros((num, H * W))
    datas = []
    for b in range(num):
        d = mujoco.MjData(model)
        d.qpos[:] = np.asarray(qpos[b], np.float64)
        mujoco.mj_forward(model, d)
        np.testing.assert_allclose(np.asarray(data.geom_xpos[b, world.moving]), d.geom_xpos[world.moving], atol=1e-5)
        mujoco.mj_multiRay(model, d, pos[b], dirs[b].reshape(-1).copy(), None, 1, -1, ref_geom[b], ref_dist[b], None,
                           H * W, mujoco.mjMAXVAL)
        datas.append(d)
    seen_moving = set(np.unique(ref_geom).tolist()) & set(world.moving.tolist())
    assert len(seen_moving) >= 4, seen_moving
    b = Batch(models=[model] * num, datas=datas, geometry=geometry, spec=SPEC, scene=np.arange(num), pos=pos.astype(np.float32),
              yaw=np.asarray(pose[:, 2]), tilt=np.asarray(pose[:, 3]), dirs=dirs, ref_geom=ref_geom.reshape(num, H, W),
              ref_dist=ref_dist.reshape(num, H, W))
    renderer = MjxRenderer(model, SPEC)
    outs = {
        "raycast": jax.jit(lambda d: render_batch(geometry, scene_idx, d.cam_xpos[:, world.camera], pose[:, 2], pose[:, 3], SPEC,
                                                  (where, world.moving, d.geom_xpos[:, world.moving], d.geom_xmat[:, world.moving])))(data),
        "mjx": jax.jit(lambda d: renderer.render(fields, geometry.cls, scene_idx, d.cam_xpos[:, world.camera],
                                                 d.cam_xmat[:, world.camera], d.geom_xpos, d.geom_xmat))(data),
    }
    for name, f in outs.items():
        lines, stats = _compare_with_mujoco(b, _numpy(f))
        print(f"\nmoving/{name}: max depth error {stats[0]:.3g} m over {stats[3]} hits of {stats[2]} rays")
        assert not lines, f"{name}: {len(lines)} pixels disagree with mj_ray:\n" + "\n".join(lines[:20])


# ----------------------------------------------------------------------------------
# 5. Camera conventions.


def test_camera_conventions():
    d = np.asarray(camera.ray_directions(0.0, 0.0, H, W, FOVY))
    assert d.shape == (H, W, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
    centre = d[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean((0, 1))
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [1.0, 0.0, 0.0], atol=1e-6)
    assert np.all(d[0, :, 2] > 0) and np.all(d[-1, :, 2] < 0)  # row 0 is the top
    assert np.all(d[:, 0, 1] > 0) and np.all(d[:, -1, 1] < 0)  # column 0 is the left (+y)
    # Vertical field of view: the top and bottom image edges are fovy apart; the
    # horizontal one follows from square pixels.
    half = np.tan(np.deg2rad(FOVY / 2))
    np.testing.assert_allclose(d[0, W // 2, 2] / d[0, W // 2, 0], half * (1 - 1 / H), rtol=1e-5)
    np.testing.assert_allclose(d[H // 2, 0, 1] / d[H // 2, 0, 0], half * W / H * (1 - 1 / W), rtol=1e-5)
    up = np.asarray(camera.ray_directions(0.3, 0.4, H, W, FOVY))
    centre = up[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean((0, 1))
    centre /= np.linalg.norm(centre)
    assert centre[2] > 0
    np.testing.assert_allclose(centre, [np.cos(0.3) * np.cos(0.4), np.sin(0.3) * np.cos(0.4), np.sin(0.4)], atol=1e-6)


@pytest.mark.parametrize("yaw, tilt", [(0.0, 0.0), (0.7, 0.3), (-2.5, -0.45)])
def test_rays_match_mujoco_camera(yaw, tilt):
    """Pixel rays equal those of MuJoCo's camera "agent_cam" (scene_to_mjcf) with the
    agent body turned by yaw about z and then pitched up by tilt."""
    scene = make_scenes("room", 1, 3)[0]
    m = compile_scene(scene_to_mjcf(scene, fovy=FOVY))
    d = mujoco.MjData(m)
    qz = np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
    qy = np.array([np.cos(-tilt / 2), 0, np.sin(-tilt / 2), 0])
    quat = np.zeros(4)
    mujoco.mju_mulQuat(quat, qz, qy)
    d.mocap_quat[0] = quat
    mujoco.mj_forward(m, d)
    cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "agent_cam")
    assert m.cam_fovy[cam] == FOVY
    xmat = d.cam_xmat[cam].reshape(3, 3)  # columns: camera x (right), y (up), z (backwards)
    half = np.tan(np.deg2rad(m.cam_fovy[cam]) / 2)
    x = ((np.arange(W) + 0.5) / W * 2 - 1) * half * W / H
    y = (1 - (np.arange(H) + 0.5) / H * 2) * half
    local = np.stack(np.broadcast_arrays(x[None, :], y[:, None], -1.0), -1)
    expected = local @ xmat.T
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(camera.ray_directions(yaw, tilt, H, W, FOVY)), expected, atol=1e-6)
