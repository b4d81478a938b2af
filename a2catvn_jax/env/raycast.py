"""Exact ray-cast camera: RGB, depth and semantic segmentation of a static scene.

One ray per pixel is intersected with the scene's boxes, ellipsoids (spheres are
ellipsoids) and capsules: the same geometry MuJoCo's `mj_ray` sees. Depth is the
distance along the unit pixel ray to the first surface, `geom` the MuJoCo id of the
geom hit. Images are computed column-major ([W, H]) and returned row-major.

Speed comes from four things:
- Fused loops. Each geom family is intersected in a real XLA while loop over its
  members, written per vector component, so one member's whole test is a single
  elementwise pass over the image that keeps the running nearest hit.
- Exact culling. The camera never rolls, so the rays of a tile of adjacent image
  columns project onto a narrow wedge of horizontal directions. A geom whose xy
  footprint misses the wedge cannot be hit by them. In a closed scene (floor and
  ceiling everywhere, walls from floor to ceiling) the nearest floor-to-ceiling box
  along the wedge's edges also bounds how far the tile's rays travel horizontally;
  geoms beyond that are skipped too. Each tile tests at most a few members per
  family, the nearest ones; when more remain, the bound is lowered below the
  nearest one skipped. The result is then verified: every ray's hit must lie within
  its tile's bound. Tiles where a ray fails the check are re-traced against all
  geoms, so the output never depends on culling.
- Chunks. `render_batch` renders a few frames at a time (a loop over chunks) rather
  than the whole batch at once, so that each pass over the images stays in cache.
- Level cameras. Without tilt, a pixel ray's horizontal direction depends on its
  column alone and its height on its row alone, so a world-aligned box's slab test
  splits into a part per column and a part per row, and each pixel only intersects
  the two intervals. The unculled renderer does this for every chunk whose cameras
  all have no tilt (tasks without tilt actions), others take the general test.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.env import camera, rects
from a2catvn_jax.env.camera import CameraSpec, Frame
from a2catvn_jax.env.geometry import (
    FAMILIES,
    PATTERN_CHECKER,
    PATTERN_PLANKS,
    PATTERN_STRIPES,
    Geometry,
    place,
)

INF = 1e10
_WEDGE_EPS = 2e-3  # radians added to each side of a tile's wedge
_DIST_EPS = 1e-3  # metres
_OCCLUSION_SLACK = 0.25  # metres added to a tile's occlusion estimate
_LIGHT = np.array([0.4, 0.6, 1.0], np.float32) / np.linalg.norm([0.4, 0.6, 1.0])


# ----------------------------------------------------------------------------------
# Ray-primitive intersections, written per vector component so that XLA fuses one
# candidate's whole test into a single elementwise loop over the image. `p` holds one
# candidate's camera-relative parameters (arrays broadcastable against the image, or
# scalars), `r` the rays: directions (dx, dy, dz) and their inverses (ix, iy, iz).


def _slab(x1, x2, y1, y2, z1, z2):
    tn = jnp.maximum(jnp.maximum(jnp.minimum(x1, x2), jnp.minimum(y1, y2)), jnp.minimum(z1, z2))
    tf = jnp.minimum(jnp.minimum(jnp.maximum(x1, x2), jnp.maximum(y1, y2)), jnp.maximum(z1, z2))
    return _first_hit(tn, tf)


def _first_hit(tn, tf):
    """First non-negative distance of a ray inside the interval [tn, tf], INF if none."""
    return jnp.where((tn <= tf) & (tf >= 0), jnp.where(tn >= 0, tn, tf), INF)


def _unit_sphere(lx, ly, lz, vx, vy, vz):
    """First non-negative hit of l + t v with the unit sphere (stable form)."""
    a = vx * vx + vy * vy + vz * vz
    tc = -(lx * vx + ly * vy + lz * vz) / a
    px, py, pz = lx + tc * vx, ly + tc * vy, lz + tc * vz
    d2 = px * px + py * py + pz * pz
    dt = jnp.sqrt(jnp.maximum(1.0 - d2, 0.0) / a)
    t0, t1 = tc - dt, tc + dt
    t = jnp.where(t0 >= 0, t0, t1)
    return jnp.where((d2 <= 1.0) & (t >= 0), t, INF)


def _local(p, r):
    """Ray directions in the candidate's frame: v_i = column i of its rotation . d."""
    dx, dy, dz = r[:3]
    return tuple(p[f"r0{i}"] * dx + p[f"r1{i}"] * dy + p[f"r2{i}"] * dz for i in range(3))


def _hit_abox(p, r):
    ix, iy, iz = r[3:]
    return _slab(p["ax"] * ix, p["bx"] * ix, p["ay"] * iy, p["by"] * iy, p["az"] * iz, p["bz"] * iz)


def _hit_obox(p, r):
    v = _local(p, r)
    inv = [rects.safe_inv(c) for c in v]
    t = []
    for i, c in enumerate("xyz"):
        t += [(-p[f"s{c}"] - p[f"l{c}"]) * inv[i], (p[f"s{c}"] - p[f"l{c}"]) * inv[i]]
    return _slab(*t)


def _hit_ell(p, r):
    # Rotation columns are pre-divided by the radii: the ellipsoid becomes a unit sphere.
    return _unit_sphere(p["lx"], p["ly"], p["lz"], *_local(p, r))


def _hit_cap(p, r):
    vx, vy, vz = _local(p, r)
    lx, ly, lz, rad, h = p["lx"], p["ly"], p["lz"], p["sx"], p["sy"]
    # Side: the infinite cylinder x^2 + y^2 = rad^2, kept where |z| <= h.
    a = jnp.maximum(vx * vx + vy * vy, 1e-20)
    tc = -(lx * vx + ly * vy) / a
    px, py = lx + tc * vx, ly + tc * vy
    d2 = px * px + py * py
    dt = jnp.sqrt(jnp.maximum(rad * rad - d2, 0.0) / a)
    best = INF
    for ts in (tc - dt, tc + dt):
        ok = (d2 <= rad * rad) & (ts >= 0) & (jnp.abs(lz + ts * vz) <= h)
        best = jnp.minimum(best, jnp.where(ok, ts, INF))
    # Caps: spheres of radius rad at z = +-h.
    inv_r = 1.0 / rad
    for zc in (h, -h):
        t = _unit_sphere(lx * inv_r, ly * inv_r, (lz - zc) * inv_r, vx * inv_r, vy * inv_r, vz * inv_r)
        best = jnp.minimum(best, t)
    return best


_HIT = {"abox": _hit_abox, "obox": _hit_obox, "ell": _hit_ell, "cap": _hit_cap}


def _prepare(f: str, pos, rot, size, cam_pos) -> dict:
    """Camera-relative per-candidate parameters of family f; arrays [..., 3(,3)] in,
    a dict of [...] arrays out."""
    if f == "abox":
        lo, hi = pos - size - cam_pos, pos + size - cam_pos
        return {"ax": lo[..., 0], "ay": lo[..., 1], "az": lo[..., 2], "bx": hi[..., 0], "by": hi[..., 1], "bz": hi[..., 2]}
    rel = cam_pos - pos
    local = jnp.einsum("...ji,...j->...i", rot, rel)
    if f == "ell":
        rot = rot / size[..., None, :]
        local = local / size
    p = {f"r{j}{i}": rot[..., j, i] for j in range(3) for i in range(3)}
    p.update({f"l{c}": local[..., i] for i, c in enumerate("xyz")})
    p.update({f"s{c}": size[..., i] for i, c in enumerate("xyz")})
    return p


# ----------------------------------------------------------------------------------
# Tile culling. Rays are grouped as [T, C * H]: T tiles of C adjacent columns.


def _rot2(v, angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _tile_wedges(dirs, tile: int):
    """Per tile, unit boundary directions (right, left) [T, 2] of an xy wedge holding
    the horizontal directions of all its rays, and its half-angle [T].

    A ray's unnormalised horizontal direction is affine in its image-plane
    coordinates, so a tile's rays span the cone of its four corner rays."""
    first, last = dirs[0::tile], dirs[tile - 1 :: tile]
    corners = jnp.stack([first[:, 0], first[:, -1], last[:, 0], last[:, -1]], 1)[..., :2]  # [T, 4, 2]
    corners = corners / jnp.linalg.norm(corners, axis=-1, keepdims=True)
    mid = jnp.sum(corners, 1)
    mid = mid / jnp.linalg.norm(mid, axis=-1, keepdims=True)
    ang = jnp.arctan2(_cross2(mid[:, None], corners), jnp.sum(mid[:, None] * corners, -1))
    lo = jnp.min(ang, 1) - _WEDGE_EPS
    hi = jnp.max(ang, 1) + _WEDGE_EPS
    return _rot2(mid, lo), _rot2(mid, hi), 0.5 * (hi - lo)


def _corners(fp):
    x0, y0, x1, y1 = fp[..., 0], fp[..., 1], fp[..., 2], fp[..., 3]
    xs = jnp.stack([x0, x1, x0, x1], -1)
    ys = jnp.stack([y0, y0, y1, y1], -1)
    return jnp.stack([xs, ys], -1)  # [..., 4, 2]


def _in_wedge(fp, c, right, left):
    """Whether footprints fp [N, 4] may meet each tile's wedge: [T, N]. Conservative:
    a footprint is kept unless all its corners lie outside one boundary line."""
    rel = (_corners(fp) - c)[None]  # [1, N, 4, 2]
    ok_r = jnp.max(_cross2(right[:, None, None, :], rel), -1) >= -1e-6
    ok_l = jnp.max(_cross2(rel, left[:, None, None, :]), -1) >= -1e-6
    return ok_r & ok_l


def _entry_2d(fp, c, u):
    """Entry distance of the 2D rays c + s u [T, 2] into rectangles fp [N, 4]: [T, N],
    INF where missed or where c is inside."""
    tn, tf = rects.slab(c, u, fp)
    return jnp.where((tn <= tf) & (tn >= 0), tn, INF)


def _occlusion_estimate(geom: Geometry, c, right, left, half_angle):
    """Per tile, an estimate of how far (horizontally) its rays travel: [T].

    The nearest occluder along each wedge boundary, plus slack for what lies between
    them (the wedge's width there). Only an estimate: `render` verifies each ray."""
    boxes = geom.families["abox"]
    if boxes.count == 0:
        return jnp.full(right.shape[:1], INF)
    occ = boxes.occluder[None, :]
    e_r = jnp.min(jnp.where(occ, _entry_2d(boxes.fp, c, right), INF), -1)
    e_l = jnp.min(jnp.where(occ, _entry_2d(boxes.fp, c, left), INF), -1)
    far = jnp.maximum(e_r, e_l)
    slack = _OCCLUSION_SLACK + 2.0 * far * jnp.tan(half_angle)
    return jnp.where(far < INF, far + slack, INF)


def _tile_candidates(geom: Geometry, cam_pos, dirs, spec: CameraSpec):
    """Per family, the geoms each tile must test, and the distance bound of each tile.

    Geoms are skipped when their footprint misses the tile's wedge, lies beyond the
    occlusion estimate, or (when more than the family's cap remain) is not among the
    cap nearest ones; the bound `far` is then lowered below the nearest skipped one.
    A ray whose hit is no farther than `far` (horizontally) has its true nearest hit.

    Returns ({family: (indices [T, K_f], ok [T, K_f])}, far [T])."""
    c = cam_pos[:2]
    right, left, half = _tile_wedges(dirs, spec.tile)
    far = _occlusion_estimate(geom, c, right, left, half)
    bound = far
    out = {}
    for f in FAMILIES:
        fam = geom.families[f]
        n = fam.count
        if n == 0:
            continue
        dist = rects.distance(c, fam.fp)
        mask = _in_wedge(fam.fp, c, right, left) & (dist[None, :] <= far[:, None] + _DIST_EPS) & fam.valid[None, :]
        k = spec.cap(f)
        if n <= k:
            out[f] = (jnp.broadcast_to(jnp.arange(n), mask.shape), mask)
            continue
        # The k nearest; the (k+1)-th nearest bounds the distance of every skipped one.
        score = jnp.where(mask, -dist[None, :], -INF)
        top, idx = jax.lax.top_k(score, k + 1)
        out[f] = (idx[:, :k], top[:, :k] > -INF)
        bound = jnp.where(top[:, k] > -INF, jnp.minimum(bound, -top[:, k] - 2.0 * _DIST_EPS), bound)
    return out, bound


# ----------------------------------------------------------------------------------
# Tracing and shading.


def _nearest(hit, params: dict, rays, carry):
    """Loop over candidates, updating the nearest hit (t, geom id) per ray; hit(p, rays)
    is the distance to one candidate p (`_HIT`).

    params: {name: [n, ...]} whose trailing shape broadcasts against the rays'.

    The loop is always a real XLA while loop (at least two trips, no remainder): a
    loop XLA unrolls away would let it fuse the whole intersection computation into
    every consumer of the image, recomputing it many times."""
    n = params["ok"].shape[0]
    unroll = 4 if n >= 8 else 1
    padded = max(-(-n // unroll) * unroll, 2)
    if padded != n:
        params = {
            k: jnp.concatenate([v, jnp.zeros((padded - n,) + v.shape[1:], v.dtype)]) for k, v in params.items()
        }

    def body(j, carry):
        best, gid = carry
        for u in range(unroll):
            p = {name: a[j * unroll + u] for name, a in params.items()}
            t = jnp.where(p["ok"], hit(p, rays), INF)
            better = t < best
            best, gid = jnp.where(better, t, best), jnp.where(better, p["gid"], gid)
        return best, gid

    return jax.lax.fori_loop(0, padded // unroll, body, carry)


def trace(geom: Geometry, cam_pos, dirs, cands=None, carry=None, families=FAMILIES):
    """Nearest hit per ray of dirs [T, R, 3] (rays grouped by tile) among the per-tile
    candidates `cands` (from `_tile_candidates`), or among all geoms if None, of the
    geom families `families`, starting from the nearest hits `carry` (default: none).

    Returns (t, geom id), each [T, R]; t is INF and the id -1 where nothing is hit."""
    dx, dy, dz = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    rays = (dx, dy, dz, rects.safe_inv(dx), rects.safe_inv(dy), rects.safe_inv(dz))
    if carry is None:
        carry = (jnp.full(dx.shape, INF, jnp.float32), jnp.full(dx.shape, -1, jnp.int32))
    for f in families:
        fam = geom.families[f]
        if fam.count == 0:
            continue
        if cands is None:
            params = _prepare(f, fam.pos, fam.rot, fam.size, cam_pos)
            params.update(ok=fam.valid, gid=fam.gid)
        else:
            idx, ok = cands[f]  # [T, K]
            params = _prepare(f, fam.pos[idx], fam.rot[idx], fam.size[idx], cam_pos)
            params.update(ok=ok, gid=fam.gid[idx])
            # Candidate-major with a broadcast axis for the tile's rays: [K, T, 1].
            params = {k: jnp.swapaxes(v, 0, 1)[..., None] for k, v in params.items()}
        carry = _nearest(_HIT[f], params, rays, carry)
    return carry


def _level_boxes(fam, cam_pos, yaw, spec: CameraSpec):
    """Nearest hits [W, H] (t along the unit rays, geom id) of a level camera's rays
    (column-major) with the world-aligned boxes `fam`.

    With no tilt the unnormalised ray through pixel (column i, row j) is forward +
    x_i right + y_j up with `up` the world's z: its horizontal part depends on the
    column only and its height on the row only. A box's xy slab interval is then
    computed once per column and its z interval once per row, and each pixel only
    intersects the two. Hits are found in units of the unnormalised ray (the same
    order along a ray) and scaled to unit-ray distances at the end."""
    x, y = (a.astype(np.float32) for a in camera.image_plane(spec.height, spec.width, spec.fovy))
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    ix, iy = rects.safe_inv(cy + x * sy), rects.safe_inv(sy - x * cy)  # [W]
    iz = 1.0 / np.where(np.abs(y) < 1e-12, 1e-12, y)  # [H]
    lo, hi = fam.pos - fam.size - cam_pos, fam.pos + fam.size - cam_pos  # [N, 3]
    tx1, tx2, ty1, ty2 = lo[:, :1] * ix, hi[:, :1] * ix, lo[:, 1:2] * iy, hi[:, 1:2] * iy
    near_col = jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2))  # [N, W]
    far_col = jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2))
    tz1, tz2 = lo[:, 2:] * iz, hi[:, 2:] * iz
    near_row, far_row = jnp.minimum(tz1, tz2), jnp.maximum(tz1, tz2)  # [N, H]
    params = {"nc": near_col[:, :, None], "fc": far_col[:, :, None], "nr": near_row[:, None, :],
              "fr": far_row[:, None, :], "ok": fam.valid, "gid": fam.gid}
    shape = (spec.width, spec.height)
    t, gid = _nearest(_hit_level_box, params, None, (jnp.full(shape, INF, jnp.float32), jnp.full(shape, -1, jnp.int32)))
    norm = np.sqrt(1.0 + x[:, None] ** 2 + y[None, :] ** 2).astype(np.float32)  # |unnormalised ray|
    return jnp.where(t < INF, t * norm, INF), gid


def _hit_level_box(p, _):
    """`_hit_abox` from a box's interval along the pixel's column and along its row."""
    return _first_hit(jnp.maximum(p["nc"], p["nr"]), jnp.minimum(p["fc"], p["fr"]))


def trace_level(geom: Geometry, cam_pos, yaw, dirs, spec: CameraSpec):
    """`trace` against every geom for a camera without tilt (rays dirs [1, W * H, 3],
    column-major), its world-aligned boxes by `_level_boxes`."""
    boxes, rest = geom.families["abox"], tuple(f for f in FAMILIES if f != "abox")
    if not boxes.count:
        return trace(geom, cam_pos, dirs, families=rest)
    carry = tuple(a.reshape(1, -1) for a in _level_boxes(boxes, cam_pos, yaw, spec))
    return trace(geom, cam_pos, dirs, carry=carry, families=rest)


def _pattern_factor(pattern, p):
    """Brightness factor of procedural surface patterns at world points p = (x, y, z)."""
    x, y, z = p
    checker = (jnp.floor(x * 2.0) + jnp.floor(y * 2.0)) % 2  # 0.5 m tiles
    stripes = jnp.floor((x + y) * 4.0) % 2
    planks = (z / 0.3) % 1.0 < 0.12
    skirting = jnp.where(z < 0.1, 0.55, 1.0)
    f = jnp.ones_like(x)
    f = jnp.where(pattern == PATTERN_CHECKER, 0.8 + 0.2 * checker, f)
    f = jnp.where(pattern == PATTERN_STRIPES, (0.9 + 0.1 * stripes) * skirting, f)
    f = jnp.where(pattern == PATTERN_PLANKS, jnp.where(planks, 0.7, 1.0), f)
    return f


def _normals(geom: Geometry, p, gid):
    """Unit outward surface normals (nx, ny, nz) at hit points p = (px, py, pz) on
    geoms gid, all [...] arrays (kept per component: XLA vectorises those best)."""
    safe = jnp.maximum(gid, 0)
    col = lambda k: geom.shape_table[:, k][safe]  # noqa: E731
    rel = [p[j] - col(j) for j in range(3)]
    rot = [[col(3 + 3 * j + i) for i in range(3)] for j in range(3)]  # world-from-local
    size = [col(12 + i) for i in range(3)]
    kind = col(15)
    lx, ly, lz = (sum(rot[j][i] * rel[j] for j in range(3)) for i in range(3))
    # Box: the face whose slab the point lies on; ellipsoid: gradient; capsule: away
    # from the axis segment.
    qx, qy, qz = (jnp.abs(lx) / size[0], jnp.abs(ly) / size[1], jnp.abs(lz) / size[2])
    on_x = (qx >= qy) & (qx >= qz)
    on_y = ~on_x & (qy >= qz)
    on_z = ~on_x & ~on_y
    box = (on_x * jnp.sign(lx), on_y * jnp.sign(ly), on_z * jnp.sign(lz))
    ell = (lx / (size[0] * size[0]), ly / (size[1] * size[1]), lz / (size[2] * size[2]))
    cap = (lx, ly, lz - jnp.clip(lz, -size[1], size[1]))
    local = [jnp.where(kind == 0, box[i], jnp.where(kind == 1, ell[i], cap[i])) for i in range(3)]
    n = [sum(rot[j][i] * local[i] for i in range(3)) for j in range(3)]
    inv = jax.lax.rsqrt(jnp.maximum(n[0] * n[0] + n[1] * n[1] + n[2] * n[2], 1e-18))
    return tuple(c * inv for c in n)


def _shade(geom: Geometry, cam_pos, dirs, t, gid):
    """Colour, depth and class of each ray's nearest hit: [W, H, 3] uint8, [W, H], [W, H]."""
    hit = gid >= 0
    depth = jnp.where(hit, t, 0.0)
    d = [dirs[..., j] for j in range(3)]
    p = [cam_pos[j] + d[j] * depth for j in range(3)]
    n = _normals(geom, p, gid)
    safe = jnp.maximum(gid, 0)
    factor = _pattern_factor(geom.pattern[safe], p)
    light = (
        0.45
        + 0.35 * jnp.maximum(sum(n[j] * float(_LIGHT[j]) for j in range(3)), 0.0)
        + 0.25 * jnp.abs(sum(n[j] * d[j] for j in range(3)))
    )
    shade = jnp.where(hit, factor * light, 0.0)
    rgb = jnp.stack([jnp.clip(geom.rgb[:, c][safe] * shade, 0.0, 1.0) for c in range(3)], -1)
    cls = jnp.where(hit, geom.cls[safe], 0)
    return (rgb * 255.0 + 0.5).astype(jnp.uint8), depth, cls


def _culled_trace(geom: Geometry, cam_pos, tiled, dirs, spec: CameraSpec):
    """Culled nearest hits of the rays tiled [T, R, 3] and which tiles failed the
    check: (t, geom id) [T, R], bad [T]."""
    cands, far = _tile_candidates(geom, cam_pos, dirs, spec)
    t, gid = trace(geom, cam_pos, tiled, cands)
    # Geoms were skipped only beyond `far`: a ray whose hit is no farther than that
    # (horizontally) has found its true nearest hit.
    reach = t * jnp.sqrt(tiled[..., 0] ** 2 + tiled[..., 1] ** 2)
    ok = (far[:, None] >= INF) | ((t < INF) & (reach <= far[:, None] + _DIST_EPS))
    return t, gid, ~jnp.all(ok, -1)


def _retrace_tiles(geom: Geometry, cam_pos, tiled, t, gid, bad):
    """Re-trace the tiles flagged in bad [T] against every geom, one at a time."""

    def cond(carry):
        return jnp.any(carry[2])

    def body(carry):
        t, gid, bad = carry
        k = jnp.argmax(bad)
        tk, gk = trace(geom, cam_pos, tiled[k][None])
        return t.at[k].set(tk[0]), gid.at[k].set(gk[0]), bad.at[k].set(False)

    t, gid, _ = jax.lax.while_loop(cond, body, (t, gid, bad))
    return t, gid


def _rays(yaw, tilt, spec: CameraSpec, culled: bool):
    """A camera's unit ray directions [W, H, 3] and the same grouped by tile [T, R, 3]
    (one tile of every column when not `culled`)."""
    dirs = camera.column_ray_directions(yaw, tilt, spec.height, spec.width, spec.fovy)  # [W, H, 3]
    tile = spec.tile if culled else spec.width
    return dirs, dirs.reshape(spec.width // tile, tile * spec.height, 3)


def _hits(geom: Geometry, cam_pos, yaw, dirs, tiled, spec: CameraSpec, culled: bool, exact: bool = False,
          level: bool = False):
    """One camera's nearest hits (t, geom id) [W, H] and whether culling fell back.
    `level`: the camera has no tilt (the caller checked), so the unculled trace is
    `trace_level`'s."""
    if culled:
        t, gid, bad = _culled_trace(geom, cam_pos, tiled, dirs, spec)
        if exact:
            t, gid = _retrace_tiles(geom, cam_pos, tiled, t, gid, bad)
        fallback = jnp.any(bad)
    else:
        t, gid = trace_level(geom, cam_pos, yaw, tiled, spec) if level else trace(geom, cam_pos, tiled)
        fallback = jnp.bool_(False)
    return t.reshape(spec.width, spec.height), gid.reshape(spec.width, spec.height), fallback


def _frame(geom: Geometry, cam_pos, dirs, t, gid, fallback) -> Frame:
    """The shaded frame, row-major, of one camera's hits."""
    rgb, depth, cls = _shade(geom, cam_pos, dirs, t, gid)
    swap = lambda a: jnp.swapaxes(a, 0, 1)  # noqa: E731  [W, H] -> [H, W]
    return Frame(swap(rgb), swap(depth), swap(gid), swap(cls), fallback)


def render(geom: Geometry, cam_pos, yaw, tilt, spec: CameraSpec, culled: bool = True) -> Frame:
    """Render one camera in one scene (unbatched Geometry); images [H, W].

    With `culled`, `fallback` says whether some tiles failed culling's check, in which
    case this frame is *not* exact: use `render_batch` (which re-renders those tiles),
    or `culled=False`."""
    culled = culled and spec.candidates > 0
    dirs, tiled = _rays(yaw, tilt, spec, culled)
    return _frame(geom, cam_pos, dirs, *_hits(geom, cam_pos, yaw, dirs, tiled, spec, culled))


def render_batch(geometry: Geometry, scene, cam_pos, yaw, tilt, spec: CameraSpec, moving=None) -> Frame:
    """Render B cameras exactly. `geometry` is batched over scenes [S, ...], `scene` [B]
    picks each camera's scene; cam_pos [B, 3], yaw/tilt [B] radians. Images [B, H, W].
    `moving`: None, or (slots, geom ids [K], positions [B, K, 3], rotations [B, K, 3, 3])
    of geoms whose pose differs per camera (`geometry.place`).

    Frames are rendered `spec.chunk(B)` at a time. Tiles of culled frames that fail
    their check are re-traced against every geom (`fallback` flags those frames).
    Unculled chunks whose cameras all have no tilt take `trace_level`."""
    culled = spec.candidates > 0
    where, gids = (moving[0], moving[1]) if moving is not None else ((), ())
    poses = (moving[2], moving[3]) if moving is not None else ()

    def geometry_of(s, *placed):
        g = jax.tree_util.tree_map(lambda a: a[s], geometry)
        return place(g, where, gids, *placed) if placed else g

    def chunk(args):  # a chunk of cameras: their hits (level or not), then their frames
        s, p, y, t, *placed = args
        g = jax.vmap(geometry_of)(s, *placed)
        dirs, tiled = jax.vmap(_rays, in_axes=(0, 0, None, None))(y, t, spec, culled)

        def hits(level: bool):
            one = functools.partial(_hits, spec=spec, culled=culled, exact=True, level=level)
            return jax.vmap(one)(g, p, y, dirs, tiled)

        h = hits(False) if culled else jax.lax.cond(jnp.all(t == 0), lambda: hits(True), lambda: hits(False))
        return jax.vmap(_frame)(g, p, dirs, *h)

    return _map_chunks(chunk, (scene, cam_pos, yaw, tilt, *poses), spec.chunk(cam_pos.shape[0]))


def _map_chunks(f, xs, size: int):
    """f over consecutive chunks of `size` along the leading axis of the pytree xs (a
    loop over whole chunks, then one call on the rest), concatenated: like
    `jax.lax.map(..., batch_size=size)`, with f taking whole chunks."""
    b = jax.tree_util.tree_leaves(xs)[0].shape[0]
    n, rest = divmod(b, size)
    outs = []
    if n:
        whole = jax.tree_util.tree_map(lambda a: a[: n * size].reshape(n, size, *a.shape[1:]), xs)
        out = jax.lax.map(f, whole)
        outs.append(jax.tree_util.tree_map(lambda a: a.reshape(n * size, *a.shape[2:]), out))
    if rest:
        outs.append(f(jax.tree_util.tree_map(lambda a: a[n * size :], xs)))
    return outs[0] if len(outs) == 1 else jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *outs)
