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
# Ray-primitive intersections. Origins are in the primitive's local frame and shared
# by all rays (one camera), directions are per ray. Return distance or INF.


def _safe_inv(v):
    return 1.0 / jnp.where(jnp.abs(v) < 1e-12, jnp.where(v < 0, -1e-12, 1e-12), v)


def _hit_box(l, v, size):
    inv = _safe_inv(v)
    t1 = (-size - l) * inv
    t2 = (size - l) * inv
    tn = jnp.max(jnp.minimum(t1, t2), axis=-1)
    tf = jnp.min(jnp.maximum(t1, t2), axis=-1)
    t = jnp.where(tn >= 0, tn, tf)
    return jnp.where((tn <= tf) & (tf >= 0), t, INF)


def _hit_unit_sphere(l, v):
    """First non-negative hit of l + t v with the unit sphere (numerically stable)."""
    a = jnp.sum(v * v, -1)
    tc = -jnp.sum(l * v, -1) / a
    p = l + tc[..., None] * v
    d2 = jnp.sum(p * p, -1)
    dt = jnp.sqrt(jnp.maximum(1.0 - d2, 0.0) / a)
    t0, t1 = tc - dt, tc + dt
    t = jnp.where(t0 >= 0, t0, t1)
    return jnp.where((d2 <= 1.0) & (t >= 0), t, INF)


def _hit_ellipsoid(l, v, size):
    return _hit_unit_sphere(l / size, v / size)


def _hit_capsule(l, v, size):
    r, h = size[..., 0], size[..., 1]
    # Side: the infinite cylinder x^2 + y^2 = r^2, kept where |z| <= h.
    lxy, vxy = l[..., :2], v[..., :2]
    a = jnp.maximum(jnp.sum(vxy * vxy, -1), 1e-20)
    tc = -jnp.sum(lxy * vxy, -1) / a
    p = lxy + tc[..., None] * vxy
    d2 = jnp.sum(p * p, -1)
    dt = jnp.sqrt(jnp.maximum(r * r - d2, 0.0) / a)
    side = INF
    for ts in (tc - dt, tc + dt):
        z = l[..., 2] + ts * v[..., 2]
        ok = (d2 <= r * r) & (ts >= 0) & (jnp.abs(z) <= h)
        side = jnp.minimum(side, jnp.where(ok, ts, INF))
    # Caps: spheres of radius r at z = +-h.
    rr = r[..., None]
    caps = INF
    for sgn in (-1.0, 1.0):
        centre = jnp.stack([jnp.zeros_like(h), jnp.zeros_like(h), sgn * h], -1)
        caps = jnp.minimum(caps, _hit_unit_sphere((l - centre) / rr, v / rr))
    return jnp.minimum(side, caps)


_HIT = {"box": _hit_box, "ell": _hit_ellipsoid, "cap": _hit_capsule}


def _normal(family, local_hit, size):
    if family == "box":
        q = jnp.abs(local_hit) / jnp.maximum(size, 1e-9)
        axis = jnp.argmax(q, -1)
        n = jax.nn.one_hot(axis, 3) * jnp.sign(local_hit)
    elif family == "ell":
        n = local_hit / jnp.maximum(size, 1e-9) ** 2
    else:
        z = jnp.clip(local_hit[..., 2], -size[..., 1], size[..., 1])
        n = local_hit - jnp.stack([jnp.zeros_like(z), jnp.zeros_like(z), z], -1)
    return n / jnp.maximum(jnp.linalg.norm(n, axis=-1, keepdims=True), 1e-9)


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
    fp = geom.box_fp
    occ = geom.box_occluder[None, :]
    e_r = jnp.min(jnp.where(occ, _entry_2d(fp, c, right), INF), -1)
    e_l = jnp.min(jnp.where(occ, _entry_2d(fp, c, left), INF), -1)
    far = jnp.maximum(e_r, e_l)
    return jnp.where(far < INF, far + _OCCLUSION_SLACK, INF)


def _candidates(geom: Geometry, cam_pos, dirs, cap: int):
    """Per family: (indices [W, K_f], valid [W, K_f]) and an overflow flag."""
    c = cam_pos[:2]
    right, left = _column_wedges(dirs)
    far = _occlusion_estimate(geom, c, right, left)
    out, overflow = {}, jnp.bool_(False)
    for f in FAMILIES:
        _, _, _, _, valid, fp = geom.family(f)
        n = valid.shape[0]
        mask = (
            _in_wedge(fp, c, right, left)
            & (_footprint_distance(fp, c)[None, :] <= far[:, None] + _DIST_EPS)
            & valid[None, :]
        )
        if n <= cap:
            out[f] = (jnp.broadcast_to(jnp.arange(n), mask.shape), mask)
            continue
        score = jnp.where(mask, (n - jnp.arange(n)).astype(jnp.float32), 0.0)
        top, idx = jax.lax.top_k(score, cap)
        out[f] = (idx, top > 0)
        overflow = overflow | jnp.any(jnp.sum(mask, -1) > cap)
    return out, far, overflow


def _all_geoms(geom: Geometry, width: int):
    out = {}
    for f in FAMILIES:
        valid = geom.family(f)[4]
        n = valid.shape[0]
        out[f] = (jnp.broadcast_to(jnp.arange(n), (width, n)), jnp.broadcast_to(valid, (width, n)))
    return out


# ----------------------------------------------------------------------------------
# Tracing and shading.


def _trace(geom: Geometry, cam_pos, dirs, cands):
    """Nearest hit per ray. dirs [W, H, 3]; returns (t, family index, local index)."""
    best_t = jnp.full(dirs.shape[:2], INF)
    best_f = jnp.zeros(dirs.shape[:2], jnp.int32)
    best_i = jnp.zeros(dirs.shape[:2], jnp.int32)
    for fi, f in enumerate(FAMILIES):
        idx, ok = cands[f]
        if idx.shape[-1] == 0:
            continue
        pos, rot, size, _, _, _ = geom.family(f)
        pos, rot, size = pos[idx], rot[idx], size[idx]  # [W, K, ...]
        l = jnp.einsum("wkji,wkj->wki", rot, cam_pos - pos)  # local origin
        v = jnp.einsum("wkji,whj->whki", rot, dirs)  # local directions [W, H, K, 3]
        t = _HIT[f](l[:, None], v, size[:, None])
        t = jnp.where(ok[:, None, :], t, INF)
        k = jnp.argmin(t, -1)
        tk = jnp.min(t, -1)
        better = tk < best_t
        best_t = jnp.where(better, tk, best_t)
        best_f = jnp.where(better, fi, best_f)
        best_i = jnp.where(better, jnp.take_along_axis(idx, k, -1), best_i)
    return best_t, best_f, best_i


def _pattern_factor(pattern, p):
    checker = (jnp.floor(p[..., 0] / 0.5) + jnp.floor(p[..., 1] / 0.5)) % 2
    stripes = jnp.floor((p[..., 0] + p[..., 1]) / 0.25) % 2
    planks = (p[..., 2] / 0.3) % 1.0 < 0.12
    base = jnp.where(p[..., 2] < 0.1, 0.55, 1.0)  # dark skirting at the foot of surfaces
    f = jnp.ones_like(p[..., 0])
    f = jnp.where(pattern == PATTERN_CHECKER, 0.8 + 0.2 * checker, f)
    f = jnp.where(pattern == PATTERN_STRIPES, (0.9 + 0.1 * stripes) * base, f)
    f = jnp.where(pattern == PATTERN_PLANKS, jnp.where(planks, 0.7, 1.0), f)
    return f


def _shade(geom: Geometry, cam_pos, dirs, t, fam, idx):
    hit = t < INF
    p = cam_pos + dirs * jnp.where(hit, t, 0.0)[..., None]
    normal = jnp.zeros_like(dirs)
    gid = jnp.full(t.shape, -1, jnp.int32)
    for fi, f in enumerate(FAMILIES):
        pos, rot, size, fgid, _, _ = geom.family(f)
        if pos.shape[0] == 0:
            continue
        i = jnp.where(fam == fi, idx, 0)
        r = rot[i]
        local = jnp.einsum("...ji,...j->...i", r, p - pos[i])
        n = jnp.einsum("...ij,...j->...i", r, _normal(f, local, size[i]))
        sel = hit & (fam == fi)
        normal = jnp.where(sel[..., None], n, normal)
        gid = jnp.where(sel, fgid[i], gid)
    safe = jnp.maximum(gid, 0)
    base = geom.rgb[safe] * _pattern_factor(geom.pattern[safe], p)[..., None]
    light = (
        0.45
        + 0.35 * jnp.maximum(jnp.sum(normal * _LIGHT, -1), 0.0)
        + 0.25 * jnp.abs(jnp.sum(normal * dirs, -1))
    )
    rgb = jnp.clip(base * light[..., None], 0.0, 1.0)
    rgb = jnp.where(hit[..., None], rgb, 0.0)
    depth = jnp.where(hit, t, 0.0)
    cls = jnp.where(hit, geom.cls[safe], 0)
    return (rgb * 255.0 + 0.5).astype(jnp.uint8), depth, gid, cls


def render(geom: Geometry, cam_pos, yaw, tilt, spec: CameraSpec, culled: bool = True) -> Frame:
    """Render one camera in one scene (unbatched Geometry). Images are [H, W]."""
    dirs = camera.column_ray_directions(yaw, tilt, spec.height, spec.width, spec.fovy)
    if culled and spec.candidates > 0:
        cands, far, overflow = _candidates(geom, cam_pos, dirs, spec.candidates)
    else:
        cands, far, overflow = _all_geoms(geom, spec.width), None, jnp.bool_(False)
    t, fam, idx = _trace(geom, cam_pos, dirs, cands)
    if far is not None:
        # Geoms were skipped only beyond `far`: a ray whose hit is no farther than that
        # (horizontally) has found its true first hit; any other ray makes the frame
        # fall back to the full geom set.
        reach = t * jnp.linalg.norm(dirs[..., :2], axis=-1)
        ok = (far[:, None] >= INF) | ((t < INF) & (reach <= far[:, None] + _DIST_EPS))
        overflow = overflow | ~jnp.all(ok)
    rgb, depth, gid, cls = _shade(geom, cam_pos, dirs, t, fam, idx)
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
