"""Compiled MuJoCo scenes -> batched geometry arrays for the ray-cast renderer.

Each scene of a batch is compiled from its own MJCF by MuJoCo; all share one geom
layout (same count of geoms of each type, in the order boxes, spheres, capsules,
ellipsoids). World poses come from MuJoCo's own forward kinematics (`geom_xpos`,
`geom_xmat`), so the renderer sees exactly the geometry `mujoco.mj_ray` sees.

The renderer groups geoms into intersection families (see `FAMILIES`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from a2catvn_jax.env.scenes.mjcf import PAD_PREFIX
from a2catvn_jax.env.scenes.spec import CLASS_NAMES, class_of_name, half_extents

# Intersection families: world-aligned boxes (a box whose rotation permutes the world
# axes is one), oriented boxes, ellipsoids (spheres included) and capsules.
FAMILIES = ("abox", "obox", "ell", "cap")
_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_ELLIPSOID = int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)
_CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
_TYPE_NAMES = {_BOX: "box", _SPHERE: "sphere", _CAPSULE: "capsule", _ELLIPSOID: "ellipsoid"}
# The MuJoCo type of each family's geoms as `world_half_extents` reads their sizes (spheres are
# ellipsoids of three equal radii in the "ell" family).
_FAMILY_TYPE = {"obox": _BOX, "ell": _ELLIPSOID, "cap": _CAPSULE}

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
class Family:
    """N geoms of one intersection family (with a leading axis S when batched).

    pos [N, 3] world centre; rot [N, 3, 3] world-from-local rotation (identity for
    world-aligned boxes); size [N, 3] (box half-sizes along its own axes, or along the
    world axes for "abox"; ellipsoid radii; capsule (radius, half-length, 0));
    gid [N] MuJoCo geom id; valid [N] False for padding; fp [N, 4] world xy footprint
    (xmin, ymin, xmax, ymax); occluder [N] (world-aligned boxes spanning floor to
    ceiling of a closed scene; always False for other families).
    """

    pos: jnp.ndarray
    rot: jnp.ndarray
    size: jnp.ndarray
    gid: jnp.ndarray
    valid: jnp.ndarray
    fp: jnp.ndarray
    occluder: jnp.ndarray

    @property
    def count(self) -> int:
        return self.valid.shape[-1]


@struct.dataclass
class Geometry:
    """Static geometry of one scene (or, with a leading axis S, of a batch).

    families: {name: Family} for name in FAMILIES.
    Per MuJoCo geom (G of them): rgb [G, 3] in [0, 1], cls [G] semantic class,
    pattern [G] shader pattern, aabb [G, 6] (xmin, ymin, zmin, xmax, ymax, zmax),
    shape_table [G, 16]: world centre (3), world-from-local rotation (9), size (3) and
    shape kind (0 box, 1 ellipsoid, 2 capsule), for normals at hit points.
    """

    families: dict
    shape_table: jnp.ndarray
    rgb: jnp.ndarray
    cls: jnp.ndarray
    pattern: jnp.ndarray
    aabb: jnp.ndarray


def _world_aabb(gtype: int, pos, rot, size) -> np.ndarray:
    half = half_extents(_TYPE_NAMES[gtype], rot, size)
    return np.concatenate([pos - half, pos + half])


def seen(m: mujoco.MjModel, i: int) -> bool:
    """Whether `mujoco.mj_ray` can hit geom i (it skips alpha-0 geoms) and it is not
    layout padding ("pad_" names)."""
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) or ""
    mat = m.geom_matid[i]
    alpha = m.mat_rgba[mat, 3] if mat >= 0 else m.geom_rgba[i, 3]
    return bool(alpha > 0) and not name.startswith(PAD_PREFIX)


def _is_axis_permutation(rot: np.ndarray) -> bool:
    return bool(np.all(np.isclose(np.abs(rot), np.round(np.abs(rot)), atol=1e-9)))


def _scene_geoms(m: mujoco.MjModel, closed: bool, height: float, skip_unsupported: bool = False):
    """Per-geom arrays and per-family member lists of one compiled scene. With
    `skip_unsupported`, geoms of other types (plane, cylinder, mesh: the `mjx` backend's
    alone) keep their class, colour and box but join no family: the ray caster does not
    see them."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    G = m.ngeom
    per_geom = {
        "rgb": np.zeros((G, 3)),
        "cls": np.zeros(G, np.int32),
        "pattern": np.zeros(G, np.int32),
        "aabb": np.zeros((G, 6)),
        "shape_table": np.zeros((G, 16)),
    }
    members = {f: [] for f in FAMILIES}
    for i in range(G):
        t = int(m.geom_type[i])
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) or ""
        if t not in (_BOX, _SPHERE, _CAPSULE, _ELLIPSOID) and skip_unsupported:
            valid = seen(m, i)
            mat = m.geom_matid[i]
            per_geom["rgb"][i] = m.mat_rgba[mat, :3] if mat >= 0 else m.geom_rgba[i, :3]
            per_geom["cls"][i] = class_of_name(name) if valid else 0
            continue
        if t not in (_BOX, _SPHERE, _CAPSULE, _ELLIPSOID):
            raise ValueError(
                f"geom {name or i!r} has type {mujoco.mjtGeom(t).name}; the renderer "
                "supports box, sphere, capsule and ellipsoid"
            )
        pos = d.geom_xpos[i].copy()
        rot = d.geom_xmat[i].reshape(3, 3).copy()
        size = m.geom_size[i].copy()
        aabb = _world_aabb(t, pos, rot, size)
        mat = m.geom_matid[i]
        valid = seen(m, i)
        cls = class_of_name(name) if valid else 0
        per_geom["aabb"][i] = aabb
        per_geom["rgb"][i] = m.mat_rgba[mat, :3] if mat >= 0 else m.geom_rgba[i, :3]
        per_geom["cls"][i] = cls
        per_geom["pattern"][i] = _PATTERN_OF_CLASS.get(CLASS_NAMES[cls], PATTERN_PLAIN)
        moving = m.body_weldid[m.geom_bodyid[i]] != 0  # its pose changes per episode (`place`)
        if t == _BOX and _is_axis_permutation(rot) and not moving:
            fam, rot, size = "abox", np.eye(3), (aabb[3:] - aabb[:3]) / 2
        elif t == _BOX:
            fam = "obox"
        elif t == _CAPSULE:
            fam = "cap"
        else:
            fam = "ell"
            if t == _SPHERE:
                size = np.full(3, size[0])
        # Exact 2D occluders of a closed scene: world-aligned boxes spanning the whole
        # storey. A ray from inside the scene that crosses their footprint has hit
        # something no farther away (them, or the floor/ceiling before leaving).
        occluder = fam == "abox" and not moving and closed and valid and aabb[2] <= 1e-6 and aabb[5] >= height - 1e-6
        kind = {"abox": 0, "obox": 0, "ell": 1, "cap": 2}[fam]
        per_geom["shape_table"][i] = np.concatenate([pos if fam != "abox" else (aabb[:3] + aabb[3:]) / 2, rot.ravel(), size, [kind]])
        members[fam].append((pos, rot, size, i, valid, aabb[[0, 1, 3, 4]], occluder))
    return per_geom, members


def _pad_family(items: list, n: int) -> dict[str, np.ndarray]:
    pad = (np.zeros(3), np.eye(3), np.zeros(3), -1, False, np.zeros(4), False)
    items = items + [pad] * (n - len(items))
    cols = list(zip(*items)) if items else [[]] * 7
    keys = ("pos", "rot", "size", "gid", "valid", "fp", "occluder")
    shapes = ((0, 3), (0, 3, 3), (0, 3), (0,), (0,), (0, 4), (0,))
    out = {}
    for k, col, shp in zip(keys, cols, shapes):
        arr = np.asarray(col) if len(col) else np.zeros(shp)
        out[k] = arr
    out["gid"] = out["gid"].astype(np.int32)
    out["valid"] = out["valid"].astype(bool)
    out["occluder"] = out["occluder"].astype(bool)
    return out


def pack(models: list[mujoco.MjModel], closed: list[bool], heights: list[float],
         skip_unsupported: bool = False) -> Geometry:
    """Stack scenes sharing one geom layout into a batched `Geometry` (leading axis S).
    Geoms of types the ray caster cannot render are an error, or with `skip_unsupported`
    left out of its families (they keep their class, for the `mjx` backend).

    A family's size is the largest count over the scenes; shorter ones are padded with
    invalid entries, so scenes may split their boxes differently between families.
    """
    types0 = models[0].geom_type
    for k, m in enumerate(models[1:], 1):
        if m.ngeom != models[0].ngeom or not np.array_equal(m.geom_type, types0):
            raise ValueError(
                f"scene {k} has a different geom layout from scene 0; scenes batched "
                "together must share one (pad them with scenes.mjcf.layout_of)"
            )
    scenes = [_scene_geoms(m, c, h, skip_unsupported) for m, c, h in zip(models, closed, heights)]

    def f32(a):
        return jnp.asarray(a.astype(np.float32) if a.dtype == np.float64 else a)

    families = {}
    for f in FAMILIES:
        n = max(len(members[f]) for _, members in scenes)
        padded = [_pad_family(members[f], n) for _, members in scenes]
        families[f] = Family(**{k: f32(np.stack([p[k] for p in padded])) for k in padded[0]})
    per_geom = {k: f32(np.stack([pg[k] for pg, _ in scenes])) for k in scenes[0][0]}
    return Geometry(families=families, **per_geom)


def take(geometry: Geometry, index) -> Geometry:
    """Scene `index` of a batched Geometry (index may be traced, or an array of them)."""
    return jax.tree_util.tree_map(lambda a: a[index], geometry)


def slots(geometry: Geometry, gids) -> tuple[tuple[str, int], ...]:
    """(family, member index) of each geom id of `gids` in an unbatched or one-scene
    `geometry` (for `place`)."""
    out = []
    for g in np.asarray(gids).tolist():
        for f in FAMILIES:
            ids = np.asarray(geometry.families[f].gid).reshape(-1)
            hit = np.flatnonzero(ids == g)
            if hit.size:
                out.append((f, int(hit[0])))
                break
        else:
            raise ValueError(f"geom {g} is in no family of the ray caster")
    return tuple(out)


def place(geom: Geometry, where: tuple[tuple[str, int], ...], gids, xpos, xmat) -> Geometry:
    """One scene's (unbatched) `geom` with the geoms `gids` [K] (at `where`, from `slots`)
    moved to world positions xpos [K, 3] and rotations xmat [K, 3, 3]: their family
    entries, footprints, boxes and normals' frames."""
    families = dict(geom.families)
    gids = np.asarray(gids)
    for f in FAMILIES:
        ks = np.array([k for k, (fam, _) in enumerate(where) if fam == f], np.int32)
        if ks.size == 0:
            continue
        idx = np.array([where[k][1] for k in ks], np.int32)
        fam = families[f]
        pos, rot, size = xpos[ks], xmat[ks], fam.size[idx]
        half = world_half_extents(np.full(len(ks), _FAMILY_TYPE[f]), rot, size, jnp.zeros(len(ks)))
        families[f] = fam.replace(pos=fam.pos.at[idx].set(pos), rot=fam.rot.at[idx].set(rot),
                                  fp=fam.fp.at[idx].set(jnp.concatenate([pos[:, :2] - half[:, :2], pos[:, :2] + half[:, :2]], -1)))
        g = gids[ks]
        geom = geom.replace(
            aabb=geom.aabb.at[g].set(jnp.concatenate([pos - half, pos + half], -1)),
            shape_table=geom.shape_table.at[g, :12].set(jnp.concatenate([pos, rot.reshape(-1, 9)], -1)),
        )
    return geom.replace(families=families)


def world_half_extents(gtype, rot, size, rbound):
    """Half-sizes [..., 3] along the world axes of the boxes around geoms of MuJoCo types
    `gtype` [...] (static ints) with rotations [..., 3, 3], sizes [..., 3] and bounding
    radii [...]: exact for boxes, spheres, capsules, ellipsoids, cylinders and planes,
    the bounding sphere for meshes."""
    axis = rot[..., :, 2]
    box = jnp.abs(rot) @ size[..., :, None]
    out = {
        _BOX: box[..., 0],
        _SPHERE: jnp.broadcast_to(size[..., :1], size.shape),
        _CAPSULE: jnp.abs(axis) * size[..., 1:2] + size[..., :1],
        _ELLIPSOID: jnp.sqrt((rot**2) @ (size[..., :, None] ** 2))[..., 0],
        _CYLINDER: size[..., :1] * jnp.sqrt(jnp.clip(1.0 - axis**2, 0.0, 1.0)) + size[..., 1:2] * jnp.abs(axis),
        _PLANE: (jnp.abs(rot[..., :, :2]) @ size[..., :2, None])[..., 0],
    }
    result = jnp.broadcast_to(rbound[..., None], size.shape)
    for t, h in out.items():
        result = jnp.where((gtype == t)[..., None], h, result)
    return result
