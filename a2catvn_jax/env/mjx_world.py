"""The environment's world model in MJX: one `mjx.Data` per environment.

Every scene is a MuJoCo model, and each environment's state holds an `mjx.Data` of
its scene (impl "jax"). The agent is the model's mocap body "agent" with its camera
"agent_cam": a move writes the agent's pose into the data (`MjxWorld.place_agent`:
the mocap pose, the body's pose and the camera's, as MuJoCo's kinematics would place
them), and both render backends read the camera and every geom's pose from the data.

Scenes of generated houses are static. A user's scene may have bodies on hinge and
slide joints (a door, a drawer): each episode draws their joint positions uniformly
within the joints' ranges (a hinge without a range: any angle), and `mjx.kinematics`
places their geoms. Their geoms block the agent where they are (`footprints`); the
occupancy grid, the geodesic distances and the shortest-path oracle know the static
geoms only.

Geoms that `mujoco.mj_ray` does not see (layout padding, alpha 0) are parked far below
the scene in the data's `geom_xpos` (`fields_of`), so no renderer hits them.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from a2catvn_jax.env import camera
from a2catvn_jax.env.geometry import seen, world_half_extents
from a2catvn_jax.env.scenes.mjcf import AGENT_BODY, AGENT_CAMERA

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
FLOOR_CLEARANCE = 0.02  # metres: geoms entirely below this height never block the agent
AWAY = (0.0, 0.0, -1e6)  # metres: where unseen geoms are put, shrunk to AWAY_SIZE
AWAY_SIZE = 1e-6


@struct.dataclass
class MjxFields:
    """Per-scene model and pose arrays the `mjx` backend renders, leading axis S.

    geom_size [S, G, 3], geom_rgba [S, G, 4], geom_xpos [S, G, 3] and geom_xmat
    [S, G, 3, 3]: MuJoCo's own arrays of each scene's compiled model after forward
    kinematics, with the geoms that `mujoco.mj_ray` does not see (layout padding,
    alpha 0) shrunk and moved far below the scene. All scenes share one geom layout
    (count and type of every geom)."""

    geom_size: jnp.ndarray
    geom_rgba: jnp.ndarray
    geom_xpos: jnp.ndarray
    geom_xmat: jnp.ndarray


def fields_of(models: list[mujoco.MjModel]) -> MjxFields:
    """The `MjxFields` of compiled scenes that share one geom layout."""
    rows = []
    for m in models:
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        size, pos = m.geom_size.copy(), d.geom_xpos.copy()
        unseen = np.array([not seen(m, i) for i in range(m.ngeom)], bool)
        size[unseen], pos[unseen] = AWAY_SIZE, AWAY
        rows.append((size, m.geom_rgba, pos, d.geom_xmat.reshape(-1, 3, 3)))
    return MjxFields(*(jnp.asarray(np.stack(col), jnp.float32) for col in zip(*rows)))


def moving_geoms(m: mujoco.MjModel) -> np.ndarray:
    """Ids of the geoms that move: on a body that has, or hangs from one that has,
    joints (the agent's mocap body has no geoms)."""
    return np.array([i for i in range(m.ngeom) if m.body_weldid[m.geom_bodyid[i]] != 0 and seen(m, i)], np.int32)


def agent_pose(pose, camera_height: float):
    """(mocap position [..., 3], mocap quaternion [..., 4], camera rotation [..., 3, 3]) of
    agent poses [..., 4] (x, y, yaw, tilt): the body turned by yaw about z and pitched
    up by tilt, its camera looking along the body's x axis with z up."""
    x, y, yaw, tilt = (pose[..., i] for i in range(4))
    pos = jnp.stack([x, y, jnp.full_like(x, camera_height)], -1)
    cy, sy, ct, st = jnp.cos(yaw / 2), jnp.sin(yaw / 2), jnp.cos(-tilt / 2), jnp.sin(-tilt / 2)
    quat = jnp.stack([cy * ct, -sy * st, cy * st, sy * ct], -1)  # q_z(yaw) q_y(-tilt)
    right, up, forward = camera.camera_basis(yaw, tilt)
    return pos, quat, jnp.stack([right, up, -forward], -1)  # MuJoCo cameras look along -z


class MjxWorld:
    """The MJX model of a world's scenes and the per-environment data built from it.

    `model` is the first scene's; the scenes of one world share its layout (every
    geom's type and body), so one data structure fits them all, and each scene's geom
    poses come from `MjxFields` (the scenes of generated houses are static). A scene
    with joints is a world of its own (one scene, compiled from the user's MJCF)."""

    def __init__(self, model: mujoco.MjModel, camera_height: float):
        self.mjm = model
        self.camera_height = float(camera_height)
        self.body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, AGENT_BODY)
        self.camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, AGENT_CAMERA)
        self.mocap = int(model.body_mocapid[self.body])
        # Bodies are placed, never simulated: no collision pairs, and the default solver
        # and integrator options (a model's own may be ones MJX's JAX implementation refuses).
        kinematic = copy.copy(model)
        kinematic.geom_contype[:] = 0
        kinematic.geom_conaffinity[:] = 0
        defaults = mujoco.MjModel.from_xml_string("<mujoco/>").opt
        for name in ("integrator", "cone", "jacobian", "solver"):
            setattr(kinematic.opt, name, getattr(defaults, name))
        device = jax.local_devices()[0]  # MJX would pick jax.devices()[0], another process's in a run of several
        self.model = mjx.put_model(kinematic, impl="jax", device=device)
        self._template = mjx.make_data(self.model, impl="jax", device=device)
        self.nq = int(model.nq)
        lo = np.zeros(self.nq, np.float32)
        hi = np.zeros(self.nq, np.float32)
        for j in range(model.njnt):
            a = int(model.jnt_qposadr[j])
            limited = bool(model.jnt_limited[j])
            if int(model.jnt_type[j]) == _HINGE and not limited:
                lo[a], hi[a] = -np.pi, np.pi
            else:
                lo[a], hi[a] = model.jnt_range[j]
        self.qpos_range = (jnp.asarray(lo), jnp.asarray(hi))
        self.moving = moving_geoms(model)
        self._unseen = jnp.asarray([not seen(model, i) for i in range(model.ngeom)])
        mv = self.moving
        self._moving_type = model.geom_type[mv].astype(np.int32)
        self._moving_size = jnp.asarray(model.geom_size[mv], jnp.float32)
        self._moving_rbound = jnp.asarray(model.geom_rbound[mv], jnp.float32)

    @property
    def has_joints(self) -> bool:
        return self.nq > 0

    def draw_qpos(self, key):
        """Joint positions [nq] drawn uniformly within the joints' ranges."""
        lo, hi = self.qpos_range
        return jax.random.uniform(key, (self.nq,), minval=lo, maxval=hi)

    def data(self, fields: MjxFields, scene, qpos=None) -> mjx.Data:
        """The data (unbatched; vmap for a batch) of scene `scene` of `fields` with joint
        positions `qpos` [nq] (default: the model's reference configuration). The agent
        is placed by `place_agent`."""
        d = self._template.replace(geom_xpos=fields.geom_xpos[scene], geom_xmat=fields.geom_xmat[scene])
        if not self.has_joints:
            return d
        d = d.replace(qpos=self.model.qpos0 if qpos is None else qpos)
        d = mjx.kinematics(self.model, d)
        return d.replace(geom_xpos=jnp.where(self._unseen[:, None], jnp.asarray(AWAY, jnp.float32), d.geom_xpos))

    def place_agent(self, d: mjx.Data, pose) -> mjx.Data:
        """`d` (unbatched) with the agent at pose [4] (x, y, yaw, tilt): its mocap body,
        the body's world pose and its camera's."""
        pos, quat, cam = agent_pose(pose, self.camera_height)
        b, c = self.body, self.camera
        body_mat = jnp.stack([cam[:, 2] * -1.0, cam[:, 0] * -1.0, cam[:, 1]], -1)  # body x = forward, y = left, z = up
        return d.replace(
            mocap_pos=d.mocap_pos.at[self.mocap].set(pos),
            mocap_quat=d.mocap_quat.at[self.mocap].set(quat),
            xpos=d.xpos.at[b].set(pos),
            xquat=d.xquat.at[b].set(quat),
            xmat=d.xmat.at[b].set(body_mat),
            cam_xpos=d.cam_xpos.at[c].set(pos),
            cam_xmat=d.cam_xmat.at[c].set(cam),
        )

    def camera_pose(self, d: mjx.Data):
        """(position [..., 3], rotation [..., 3, 3]) of the agent's camera in data `d`."""
        return d.cam_xpos[..., self.camera, :], d.cam_xmat[..., self.camera, :, :]

    def footprints(self, d: mjx.Data, body_height: float):
        """World xy boxes [..., K, 4] (xmin, ymin, xmax, ymax) of the K moving geoms where
        `d` places them; a geom entirely above the agent's body or below the floor
        clearance lies far away (it never blocks)."""
        xpos = d.geom_xpos[..., self.moving, :]
        xmat = d.geom_xmat[..., self.moving, :, :]
        half = world_half_extents(self._moving_type, xmat, self._moving_size, self._moving_rbound)
        lo, hi = xpos - half, xpos + half
        blocks = (hi[..., 2] > FLOOR_CLEARANCE) & (lo[..., 2] < body_height)
        fp = jnp.concatenate([lo[..., :2], hi[..., :2]], -1)
        return jnp.where(blocks[..., None], fp, jnp.asarray([1e6, 1e6, 1e6 + 1, 1e6 + 1], jnp.float32))
