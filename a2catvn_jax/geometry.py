"""Compiled MuJoCo scenes -> batched geometry arrays for the ray-cast renderer.

Each scene of a batch is compiled from its own MJCF by MuJoCo; all share one geom
layout (same count of geoms of each type, in the order boxes, spheres, capsules,
ellipsoids). World poses come from MuJoCo's own forward kinematics (`geom_xpos`,
`geom_xmat`), so the renderer sees exactly the geometry `mujoco.mj_ray` sees.

The renderer groups geoms into three intersection families: boxes, ellipsoids
(spheres are ellipsoids with equal radii) and capsules.
"""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from a2catvn_jax.scenes.spec import CLASS_NAMES, class_of_name

FAMILIES = ("box", "ell", "cap")
_FAMILY_OF_TYPE = {
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "ell",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ell",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "cap",
}

# Surface patterns used by the shader, chosen per semantic class.
PATTERN_PLAIN, PATTERN_CHECKER, PATTERN_STRIPES, PATTERN_PLANKS = 0, 1, 2, 3
_PATTERN_OF_CLASS = {
    "floor": PATTERN_CHECKER,
    "wall": PATTERN_STRIPES,
    "rug": PATTERN_STRIPES,
    "wardrobe": PATTERN_PLANKS,
    "shelf": PATTERN_PLANKS,
    "cabinet": PATTERN_PLANKS,
    "door_frame": PATTERN_PLANKS,
    "bed": PATTERN_CHECKER,
}


@struct.dataclass
class Geometry:
    """Static geometry of one scene (or, with a leading axis S, of a batch).

    Per family f in (box, ell, cap), N_f geoms:
      {f}_pos [N_f, 3] world centre; {f}_rot [N_f, 3, 3] world-from-local rotation;
      {f}_size [N_f, 3] (box half-sizes; ellipsoid radii; capsule (radius, half-length, 0));
      {f}_gid [N_f] MuJoCo geom id; {f}_valid [N_f] False for padding;
      {f}_fp [N_f, 4] world xy footprint bounds (xmin, ymin, xmax, ymax).
    box_occluder [N_b]: axis-aligned boxes spanning floor to ceiling of a closed scene.
    Per MuJoCo geom (G of them): rgb [G, 3] in [0, 1], cls [G] semantic class,
      pattern [G] shader pattern, aabb [G, 6] (xmin, ymin, zmin, xmax, ymax, zmax).
    """

    box_pos: jnp.ndarray
    box_rot: jnp.ndarray
    box_size: jnp.ndarray
    box_gid: jnp.ndarray
    box_valid: jnp.ndarray
    box_fp: jnp.ndarray
    box_occluder: jnp.ndarray
    ell_pos: jnp.ndarray
    ell_rot: jnp.ndarray
    ell_size: jnp.ndarray
    ell_gid: jnp.ndarray
    ell_valid: jnp.ndarray
    ell_fp: jnp.ndarray
    cap_pos: jnp.ndarray
    cap_rot: jnp.ndarray
    cap_size: jnp.ndarray
    cap_gid: jnp.ndarray
    cap_valid: jnp.ndarray
    cap_fp: jnp.ndarray
    rgb: jnp.ndarray
    cls: jnp.ndarray
    pattern: jnp.ndarray
    aabb: jnp.ndarray

    def family(self, f: str):
        return tuple(getattr(self, f"{f}_{k}") for k in ("pos", "rot", "size", "gid", "valid", "fp"))


def _world_aabb(gtype: int, pos, rot, size) -> np.ndarray:
    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        half = np.abs(rot) @ size
    elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        half = np.full(3, size[0])
    elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        half = np.sqrt((rot**2) @ (size**2))
    else:  # capsule along local z
        half = np.abs(rot[:, 2]) * size[1] + size[0]
    return np.concatenate([pos - half, pos + half])


def _visible(m: mujoco.MjModel, i: int) -> bool:
    """Whether mj_ray considers geom i (it skips alpha-0 geoms)."""
    mat = m.geom_matid[i]
    alpha = m.mat_rgba[mat, 3] if mat >= 0 else m.geom_rgba[i, 3]
    return bool(alpha > 0)


def scene_arrays(m: mujoco.MjModel, closed: bool, height: float) -> dict[str, np.ndarray]:
    """Geometry arrays (numpy, unbatched) of one compiled scene."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    fam_idx = {f: [] for f in FAMILIES}
    for i in range(m.ngeom):
        t = int(m.geom_type[i])
        if t not in _FAMILY_OF_TYPE:
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) or f"#{i}"
            raise ValueError(
                f"geom {name!r} has type {mujoco.mjtGeom(t).name}; the renderer supports "
                "box, sphere, capsule and ellipsoid"
            )
        fam_idx[_FAMILY_OF_TYPE[t]].append(i)

    G = m.ngeom
    aabb = np.zeros((G, 6))
    rgb = np.zeros((G, 3))
    cls = np.zeros(G, np.int32)
    pattern = np.zeros(G, np.int32)
    valid = np.zeros(G, bool)
    for i in range(G):
        rot = d.geom_xmat[i].reshape(3, 3)
        aabb[i] = _world_aabb(int(m.geom_type[i]), d.geom_xpos[i], rot, m.geom_size[i])
        mat = m.geom_matid[i]
        rgb[i] = m.mat_rgba[mat, :3] if mat >= 0 else m.geom_rgba[i, :3]
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) or ""
        valid[i] = _visible(m, i) and not name.startswith("pad_")
        cls[i] = class_of_name(name) if valid[i] else 0
        pattern[i] = _PATTERN_OF_CLASS.get(CLASS_NAMES[int(cls[i])], PATTERN_PLAIN)

    out = {"rgb": rgb, "cls": cls, "pattern": pattern, "aabb": aabb}
    for f, idx in fam_idx.items():
        idx = np.asarray(idx, np.int64)
        size = m.geom_size[idx].copy() if len(idx) else np.zeros((0, 3))
        if f == "ell":
            is_sphere = m.geom_type[idx] == mujoco.mjtGeom.mjGEOM_SPHERE
            size[is_sphere] = size[is_sphere][:, :1]
        out[f"{f}_pos"] = d.geom_xpos[idx].copy()
        out[f"{f}_rot"] = d.geom_xmat[idx].reshape(-1, 3, 3).copy()
        out[f"{f}_size"] = size
        out[f"{f}_gid"] = idx.astype(np.int32)
        out[f"{f}_valid"] = valid[idx]
        out[f"{f}_fp"] = aabb[idx][:, [0, 1, 3, 4]]
    # Exact 2D occluders: axis-aligned (in xy) boxes spanning the whole storey of a
    # closed scene. Any ray from inside the scene that crosses their footprint has hit
    # something no farther away (them, or the floor/ceiling before leaving the storey).
    brot = out["box_rot"]
    axis_aligned = np.all(np.isclose(np.abs(brot), np.round(np.abs(brot)), atol=1e-9), axis=(1, 2))
    baabb = aabb[fam_idx["box"]] if fam_idx["box"] else np.zeros((0, 6))
    spans = (baabb[:, 2] <= 1e-6) & (baabb[:, 5] >= height - 1e-6)
    out["box_occluder"] = closed & axis_aligned & spans & out["box_valid"]
    return out


def pack(models: list[mujoco.MjModel], closed: list[bool], heights: list[float]) -> Geometry:
    """Stack scenes sharing one geom layout into a batched `Geometry` (leading axis S)."""
    per = [scene_arrays(m, c, h) for m, c, h in zip(models, closed, heights)]
    types0 = models[0].geom_type
    for k, m in enumerate(models[1:], 1):
        if m.ngeom != models[0].ngeom or not np.array_equal(m.geom_type, types0):
            raise ValueError(
                f"scene {k} has a different geom layout from scene 0; scenes batched "
                "together must share one (pad them with scenes.mjcf.layout_of)"
            )
    stacked = {}
    for key in per[0]:
        arr = np.stack([p[key] for p in per])
        if arr.dtype == np.float64:
            arr = arr.astype(np.float32)
        stacked[key] = jnp.asarray(arr)
    return Geometry(**stacked)


def take(geometry: Geometry, index) -> Geometry:
    """One scene of a batched Geometry (works on traced indices)."""
    import jax

    return jax.tree_util.tree_map(lambda a: a[index], geometry)
