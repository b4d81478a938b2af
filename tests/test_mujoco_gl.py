"""Tests for the MuJoCo OpenGL reference renderer (a2catvn_jax.bench.mujoco_gl)."""

import os
import types

import numpy as np
import pytest

from a2catvn_jax.bench import mujoco_gl as mgl

_BACKEND = mgl.gl_backend_available()
if _BACKEND is None:
    pytest.skip(
        "no headless OpenGL backend (EGL or OSMesa) works for mujoco.Renderer here; "
        "install one with: " + mgl.APT_HINT.replace("\n", " or "),
        allow_module_level=True,
    )

import mujoco  # noqa: E402  (imported after the backend is selected)

H, W = 24, 32  # non-square on purpose: checks the horizontal field of view

SCENE = """
<mujoco model="tiny">
  <visual>
    <global offwidth="64" offheight="64"/>
    <map znear="0.005"/>
  </visual>
  <asset><material name="m" rgba="1 1 1 1"/></asset>
  <worldbody>
    <light pos="0 0 4" dir="0 0 -1"/>
    <geom name="floor" type="box" size="3 3 0.05" pos="0 0 -0.05" rgba=".6 .6 .5 1"/>
    <geom name="wall_e" type="box" size="0.05 3 1.2" pos="3 0 1.2" rgba=".8 .8 .8 1"/>
    <geom name="wall_n" type="box" size="3 0.05 1.2" pos="0 3 1.2" rgba=".7 .8 .8 1"/>
    <geom name="box_a" type="box" size="0.3 0.4 0.5" pos="1.5 0.3 0.5" euler="0 0 25"
          material="m" rgba="1 0 0 1"/>
    <geom name="box_b" type="box" size="0.2 0.2 0.2" pos="1.0 -0.8 1.1" rgba="0 1 0 1"/>
    <geom name="ball" type="sphere" size="0.3" pos="0.8 1.2 0.9" rgba="0 0 1 1"/>
    <body name="agent" mocap="true" pos="0 0 1">
      <camera name="agent_cam" fovy="60"/>
    </body>
  </worldbody>
</mujoco>
"""

POSES = [
    ((0.0, 0.0, 1.0), 0.0, 0.0),
    ((-0.5, -0.3, 1.2), 0.5, -0.3),
    ((0.2, 0.4, 0.8), 1.2, 0.2),
]


@pytest.fixture(scope="module")
def renderer():
    r = mgl.MujocoRenderer(SCENE, H, W)
    yield r
    r.close()


def test_backend_exported():
    assert os.environ.get("MUJOCO_GL") == _BACKEND


def test_camera_frame_is_rotation():
    for yaw, tilt in [(0.0, 0.0), (0.7, -0.4), (-2.5, 0.3)]:
        R = mgl.camera_frame(yaw, tilt)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        fwd = np.array([np.cos(yaw) * np.cos(tilt), np.sin(yaw) * np.cos(tilt), np.sin(tilt)])
        np.testing.assert_allclose(-R[:, 2], fwd, atol=1e-12)
        assert abs(R[2, 0]) < 1e-12  # right axis stays horizontal
        assert R[2, 1] > 0  # up axis points up


def test_pixel_ray_directions():
    d = mgl.pixel_ray_directions(5, 7, 60.0, 0.3, 0.1)
    assert d.shape == (5, 7, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d[2, 3], -mgl.camera_frame(0.3, 0.1)[:, 2], atol=1e-12)
    assert d[0, 3, 2] > d[4, 3, 2]  # row 0 looks higher than the last row
    # Vertical extent of pixel centres spans fovy minus one pixel.
    cam = mgl.camera_ray_directions(5, 7, 60.0)
    assert np.arctan(cam[0, 3, 1]) == pytest.approx(np.arctan(np.tan(np.pi / 6) * 0.8))


def test_shapes_and_dtypes(renderer):
    out = renderer.render(*POSES[0])
    assert out["rgb"].shape == (H, W, 3) and out["rgb"].dtype == np.uint8
    assert out["depth"].shape == (H, W) and out["depth"].dtype == np.float32
    assert out["zdepth"].shape == (H, W) and out["zdepth"].dtype == np.float32
    seg = out["segmentation"]
    assert seg.shape == (H, W) and seg.dtype == np.int32
    assert seg.min() >= -1 and seg.max() < renderer.model.ngeom
    hit = seg >= 0
    assert hit.any()
    assert np.all(out["depth"][hit] >= out["zdepth"][hit])
    assert np.all(out["depth"][~hit] == 0.0)
    assert out["rgb"].max() > 0


def test_camera_pose_matches_mujoco(renderer):
    for pos, yaw, tilt in POSES:
        renderer.set_pose(pos, yaw, tilt)
        np.testing.assert_allclose(renderer.camera_position(), pos, atol=1e-12)
        np.testing.assert_allclose(
            renderer.camera_matrix(), mgl.camera_frame(yaw, tilt), atol=1e-9
        )


def test_row_zero_is_top(renderer):
    # Horizontal view at 1 m towards -x (no wall): floor at the bottom, sky at the top.
    out = renderer.render((0.0, 0.0, 1.0), np.pi, 0.0)
    floor = mujoco.mj_name2id(renderer.model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert np.all(out["segmentation"][-1] == floor)
    assert np.all(out["segmentation"][0] == -1)


def test_background_is_minus_one(renderer):
    out = renderer.render((0.0, 0.0, 1.0), 0.0, 1.4)  # looking up, no ceiling
    assert np.all(out["segmentation"] == -1)
    assert np.all(out["depth"] == 0.0)
    assert np.all(out["zdepth"] > renderer.zfar * 0.99)


@pytest.mark.parametrize("pose", POSES)
def test_agrees_with_mj_ray(renderer, pose):
    out = renderer.render(*pose)
    dist, gid = renderer.reference_raycast(*pose)
    seg = out["segmentation"]
    assert np.mean(seg == gid) > 0.97  # only silhouette edges may differ
    both = (seg == gid) & (gid >= 0)
    is_box = renderer.model.geom_type[np.maximum(gid, 0)] == mujoco.mjtGeom.mjGEOM_BOX
    rel = np.abs(out["depth"] - dist) / np.maximum(dist, 1e-6)
    # Planar faces: limited only by float32 depth-buffer precision.
    assert rel[both & is_box].max() < 1e-4
    # Tessellated sphere: within a few percent.
    if np.any(both & ~is_box):
        assert rel[both & ~is_box].max() < 0.05
    # zdepth is depth projected on the viewing axis.
    fwd = -mgl.camera_frame(pose[1], pose[2])[:, 2]
    dirs = mgl.pixel_ray_directions(H, W, renderer.fovy, pose[1], pose[2])
    np.testing.assert_allclose(
        out["zdepth"][both & is_box], (dist * (dirs @ fwd))[both & is_box], rtol=1e-4
    )


def test_benchmark_fps_runs(monkeypatch):
    poses = np.array([[0.0, 0.0, 0.0, 0.0], [0.3, -0.2, 1.0, 0.1]])
    clock = iter([10.0, 12.0])  # the 4 timed frames take 2 s
    monkeypatch.setattr(mgl, "time", types.SimpleNamespace(perf_counter=lambda: next(clock)))
    fps = mgl.benchmark_fps(SCENE, 16, 16, n_frames=4, poses=poses, cam_height=1.0, warmup=1)
    assert fps == 2.0
