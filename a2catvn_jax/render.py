"""Exact ray-cast camera: RGB, depth and semantic segmentation of a static scene.

One ray per pixel is intersected with the scene's boxes, ellipsoids (and spheres)
and capsules, with the same geometry MuJoCo's `mj_ray` uses: depth is the distance
along the unit pixel ray to the first surface and `geom` the id of the geom hit.

Acceleration (exact): the rays of one image column all project onto a narrow wedge
of horizontal directions (the camera never rolls). Per column, a geom can only be
hit if its xy footprint meets that wedge. In a closed scene, an axis-aligned box
that spans floor to ceiling and covers the whole wedge bounds how far (horizontally)
any ray of the column can travel, so geoms whose footprint lies farther away are
skipped too. Each column then tests at most `K` candidates per geom family instead
of every geom. Columns with more candidates than fit set an overflow flag; batched
rendering re-renders those frames by brute force, so results never depend on `K`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax import camera
from a2catvn_jax.geometry import (
    FAMILIES,
    PATTERN_CHECKER,
    PATTERN_PLANKS,
    PATTERN_STRIPES,
    Geometry,
)

INF = jnp.float32(1e10)
_WEDGE_EPS = 2e-3  # radians added to each side of a column's wedge
_DIST_EPS = 1e-3  # metres
_OCCLUSION_SLACK = 0.5  # metres added to a column's occlusion estimate
_LIGHT = np.array([0.4, 0.6, 1.0], np.float32) / np.linalg.norm([0.4, 0.6, 1.0])


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Static camera settings (they fix array shapes)."""

    height: int
    width: int
    fovy: float = 60.0
    candidates: int = 24  # per column and family; <= 0 disables culling

    def __post_init__(self):
        if self.height < 1 or self.width < 1:
            raise ValueError(f"image size must be positive, got {self.height}x{self.width}")


class Frame(NamedTuple):
    """Rendered outputs, row-major images [..., H, W]."""

    rgb: jnp.ndarray  # uint8 [..., H, W, 3]
    depth: jnp.ndarray  # float32 metres along the ray, 0 where nothing is hit
    geom: jnp.ndarray  # int32 MuJoCo geom id, -1 where nothing is hit
    cls: jnp.ndarray  # int32 semantic class, 0 where nothing is hit
    overflow: jnp.ndarray  # bool [...]: some column exceeded its candidate cap


# ----------------------------------------------------------------------------------
# Ray-primitive intersections, written per vector component so that XLA fuses one
# candidate's whole test into a single elementwise loop over the image. `p` holds one
# candidate's camera-relative parameters (arrays broadcastable against the image, or
# scalars), `r` the rays: directions (dx, dy, dz) and their inverses (ix, iy, iz).


def _safe_inv(v):
    return 1.0 / jnp.where(jnp.abs(v) < 1e-12, jnp.where(v < 0, -1e-12, 1e-12), v)


def _slab(x1, x2, y1, y2, z1, z2):
    tn = jnp.maximum(jnp.maximum(jnp.minimum(x1, x2), jnp.minimum(y1, y2)), jnp.minimum(z1, z2))
    tf = jnp.minimum(jnp.minimum(jnp.maximum(x1, x2), jnp.maximum(y1, y2)), jnp.maximum(z1, z2))
    t = jnp.where(tn >= 0, tn, tf)
    return jnp.where((tn <= tf) & (tf >= 0), t, INF)


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
    inv = [_safe_inv(c) for c in v]
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
# Column culling.


def _rot2(v, angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _column_wedges(dirs):
    """Per column, unit boundary directions (right, left) of a widened xy wedge that
    contains the horizontal directions of all its rays. dirs: [W, H, 3]."""
    a = dirs[:, 0, :2]
    b = dirs[:, -1, :2]
    a = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    b = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    mid = a + b
    mid = mid / jnp.linalg.norm(mid, axis=-1, keepdims=True)
    half = 0.5 * jnp.arccos(jnp.clip(jnp.sum(a * b, -1), -1.0, 1.0)) + _WEDGE_EPS
    return _rot2(mid, -half), _rot2(mid, half)


def _corners(fp):
    x0, y0, x1, y1 = fp[..., 0], fp[..., 1], fp[..., 2], fp[..., 3]
    return jnp.stack(
        [jnp.stack([x0, y0], -1), jnp.stack([x1, y0], -1), jnp.stack([x0, y1], -1), jnp.stack([x1, y1], -1)],
        -2,
    )  # [..., 4, 2]


def _in_wedge(fp, c, right, left):
    """Whether footprints fp [N, 4] may meet each column's wedge: [W, N]."""
    rel = _corners(fp) - c  # [N, 4, 2]
    r = right[:, None, None, :]
    lft = left[:, None, None, :]
    ok_r = jnp.max(_cross2(r, rel[None]), -1) >= -1e-6
    ok_l = jnp.max(_cross2(rel[None], lft), -1) >= -1e-6
    return ok_r & ok_l


def _footprint_distance(fp, c):
    dx = jnp.maximum(jnp.maximum(fp[..., 0] - c[0], c[0] - fp[..., 2]), 0.0)
    dy = jnp.maximum(jnp.maximum(fp[..., 1] - c[1], c[1] - fp[..., 3]), 0.0)
    return jnp.sqrt(dx * dx + dy * dy)


def _entry_2d(fp, c, u):
    """2D slab: entry distance of rays c + s u into rectangles, INF if missed. u [W,2]."""
    lo = fp[None, :, :2] - c
    hi = fp[None, :, 2:] - c
    inv = _safe_inv(u)[:, None, :]
    t1, t2 = lo * inv, hi * inv
    tn = jnp.max(jnp.minimum(t1, t2), -1)
    tf = jnp.min(jnp.maximum(t1, t2), -1)
    return jnp.where((tn <= tf) & (tn >= 0), tn, INF)


def _occlusion_estimate(geom: Geometry, c, right, left):
    """Per column, an estimate of how far (horizontally) its rays travel: [W].

    The nearest occluder along each wedge boundary, plus slack for corners between
    them. It is only an estimate; `render` verifies every ray against it."""
    boxes = geom.families["abox"]
    if boxes.count == 0:
        return jnp.full(right.shape[:1], INF)
    occ = boxes.occluder[None, :]
    e_r = jnp.min(jnp.where(occ, _entry_2d(boxes.fp, c, right), INF), -1)
    e_l = jnp.min(jnp.where(occ, _entry_2d(boxes.fp, c, left), INF), -1)
    far = jnp.maximum(e_r, e_l)
    return jnp.where(far < INF, far + _OCCLUSION_SLACK, INF)


def _column_candidates(geom: Geometry, cam_pos, dirs, cap: int):
    """Per family, the geoms each column must test.

    Returns ({family: (indices [W, K_f], ok [W, K_f])}, far [W], overflow)."""
    c = cam_pos[:2]
    right, left = _column_wedges(dirs)
    far = _occlusion_estimate(geom, c, right, left)
    out, overflow = {}, jnp.bool_(False)
    for f in FAMILIES:
        fam = geom.families[f]
        n = fam.count
        if n == 0:
            continue
        mask = (
            _in_wedge(fam.fp, c, right, left)
            & (_footprint_distance(fam.fp, c)[None, :] <= far[:, None] + _DIST_EPS)
            & fam.valid[None, :]
        )
        if n <= cap:
            out[f] = (jnp.broadcast_to(jnp.arange(n), mask.shape), mask)
            continue
        score = jnp.where(mask, (n - jnp.arange(n)).astype(jnp.float32), 0.0)
        top, idx = jax.lax.top_k(score, cap)
        out[f] = (idx, top > 0)
        overflow = overflow | jnp.any(jnp.sum(mask, -1) > cap)
    return out, far, overflow


# ----------------------------------------------------------------------------------
# Tracing and shading.


def _nearest(f: str, params: dict, rays, carry):
    """Loop over candidates, updating the nearest hit (t, geom id) per ray.

    params: {name: [n, ...]} whose trailing shape broadcasts against the rays'.

    The loop is always a real XLA while loop (at least two trips, no remainder): a
    loop XLA unrolls away would let it fuse the whole intersection computation into
    every consumer of the image (e.g. each shifted copy), recomputing it many times."""
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
            t = jnp.where(p["ok"], _HIT[f](p, rays), INF)
            better = t < best
            best, gid = jnp.where(better, t, best), jnp.where(better, p["gid"], gid)
        return best, gid

    return jax.lax.fori_loop(0, padded // unroll, body, carry)


def _trace(geom: Geometry, cam_pos, dirs, cands=None):
    """Nearest hit per ray of dirs [W, H, 3] among the per-column candidates `cands`
    (from `_column_candidates`), or among all geoms when `cands` is None.

    Returns (t, geom id), each [W, H]; t is INF and the id -1 where nothing is hit."""
    dx, dy, dz = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    rays = (dx, dy, dz, _safe_inv(dx), _safe_inv(dy), _safe_inv(dz))
    carry = (jnp.full(dx.shape, INF), jnp.full(dx.shape, -1, jnp.int32))
    for f in FAMILIES:
        fam = geom.families[f]
        if fam.count == 0:
            continue
        if cands is None:
            params = _prepare(f, fam.pos, fam.rot, fam.size, cam_pos)
            params.update(ok=fam.valid, gid=fam.gid)
            carry = _nearest(f, params, rays, carry)
        else:
            idx, ok = cands[f]  # [W, K]
            params = _prepare(f, fam.pos[idx], fam.rot[idx], fam.size[idx], cam_pos)
            params.update(ok=ok, gid=fam.gid[idx])
            # Candidate-major with a broadcast axis for the rows: [K, W, 1].
            params = {k: jnp.swapaxes(v, 0, 1)[..., None] for k, v in params.items()}
            carry = _nearest(f, params, rays, carry)
    return carry


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


def render(geom: Geometry, cam_pos, yaw, tilt, spec: CameraSpec, culled: bool = True) -> Frame:
    """Render one camera in one scene (unbatched Geometry). Images are [H, W]."""
    dirs = camera.column_ray_directions(yaw, tilt, spec.height, spec.width, spec.fovy)
    if culled and spec.candidates > 0:
        cands, far, overflow = _column_candidates(geom, cam_pos, dirs, spec.candidates)
    else:
        cands, far, overflow = None, None, jnp.bool_(False)
    t, gid = _trace(geom, cam_pos, dirs, cands)
    if far is not None:
        # Geoms were skipped only beyond `far`: a ray whose hit is no farther than that
        # (horizontally) has found its true first hit; any other ray makes the frame
        # fall back to the full geom set.
        reach = t * jnp.linalg.norm(dirs[..., :2], axis=-1)
        ok = (far[:, None] >= INF) | ((t < INF) & (reach <= far[:, None] + _DIST_EPS))
        overflow = overflow | ~jnp.all(ok)
    rgb, depth, cls = _shade(geom, cam_pos, dirs, t, gid)
    swap = lambda a: jnp.swapaxes(a, 0, 1)  # noqa: E731  [W, H] -> [H, W]
    return Frame(swap(rgb), swap(depth), swap(gid), swap(cls), overflow)


def render_batch(geometry: Geometry, scene, cam_pos, yaw, tilt, spec: CameraSpec) -> Frame:
    """Render B cameras; `geometry` is batched over scenes [S, ...], `scene` [B] picks
    each camera's scene; cam_pos [B, 3], yaw/tilt [B] radians.

    Frames whose culled render overflowed a candidate cap are re-rendered against all
    geoms (a real branch here; under an outer vmap it becomes a select that always
    runs both)."""
    geo = jax.tree_util.tree_map(lambda a: a[scene], geometry)
    frames = jax.vmap(lambda g, p, y, t: render(g, p, y, t, spec, culled=True))(geo, cam_pos, yaw, tilt)
    if spec.candidates <= 0:
        return frames

    def brute(frames):
        full = jax.vmap(lambda g, p, y, t: render(g, p, y, t, spec, culled=False))(geo, cam_pos, yaw, tilt)

        def pick(a, b):
            m = frames.overflow.reshape(frames.overflow.shape + (1,) * (a.ndim - 1))
            return jnp.where(m, a, b)

        return Frame(*(pick(a, b) for a, b in zip(full[:4], frames[:4])), frames.overflow)

    return jax.lax.cond(jnp.any(frames.overflow), brute, lambda f: f, frames)
