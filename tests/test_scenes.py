"""Tests of the scene generators and the MJCF conversion (fast, CPU only)."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import mujoco
import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from a2catvn_jax.env.scenes import (  # noqa: E402
    AGENT_BODY,
    AGENT_CAMERA,
    CLASS_NAMES,
    GEOM_TYPES,
    HOUSE_ROOM_TYPES,
    ROOM_TYPES,
    STRUCTURAL_CLASSES,
    class_from_name,
    compile_scene,
    geom_aabb,
    geom_counts,
    house,
    layout_of,
    make_scenes,
    maze,
    scene_from_mjcf,
    scene_to_mjcf,
    single_room,
)
from a2catvn_jax.env.scenes.spec import CLASS_ID, class_colors  # noqa: E402
from a2catvn_jax.run.topdown import save_topdown  # noqa: E402

TYPE_RANK = {
    int(mujoco.mjtGeom.mjGEOM_BOX): 0,
    int(mujoco.mjtGeom.mjGEOM_SPHERE): 1,
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): 2,
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): 3,
}
SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def houses():
    return [house(s) for s in SEEDS]


@pytest.fixture(scope="module")
def all_scenes(houses):
    return houses + [single_room(s) for s in SEEDS] + [maze(s) for s in SEEDS]


def _furniture(scene):
    return [g for g in scene.geoms if g.cls not in STRUCTURAL_CLASSES]


# ----------------------------------------------------------------------------------
# generators
# ----------------------------------------------------------------------------------


def test_scenes_compile(all_scenes):
    for s in all_scenes:
        m = compile_scene(scene_to_mjcf(s))
        assert m.ngeom == len(s.geoms)
        assert m.nmat >= 1
        assert mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, AGENT_CAMERA) >= 0
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, AGENT_BODY)
        assert body >= 0 and m.body_mocapid[body] == 0
        assert m.vis.global_.offwidth >= 512 and m.vis.global_.offheight >= 512
        assert np.all(m.geom_rgba[:, 3] == 1.0)
        assert s.closed


def test_same_seed_same_mjcf_and_different_seeds_differ():
    for fn in (house, single_room, maze):
        a, b, c = scene_to_mjcf(fn(11)), scene_to_mjcf(fn(11)), scene_to_mjcf(fn(12))
        assert a == b
        assert a != c


def test_make_scenes():
    scenes = make_scenes("house", 3, seed=4)
    again = make_scenes("house", 3, seed=4)
    xmls = [scene_to_mjcf(s) for s in scenes]
    assert xmls == [scene_to_mjcf(s) for s in again]
    assert len(set(xmls)) == 3
    assert len({s.name for s in scenes}) == 3
    assert make_scenes("house", 2, seed=5)[0].name != scenes[0].name
    assert len(make_scenes("maze", 2, seed=0, cells=(4, 3))) == 2
    assert all(len(s.rooms) == 1 for s in make_scenes("room", 2, seed=0))
    with pytest.raises(ValueError, match="valid kinds.*house.*maze.*room"):
        make_scenes("castle", 1, seed=0)


def test_geom_budget_and_names(houses):
    for s in houses:
        assert 60 <= len(s.geoms) <= 150
        names = [g.name for g in s.geoms]
        assert len(set(names)) == len(names)
        for g in s.geoms:
            assert class_from_name(g.name) == g.cls
            assert g.rgba[3] == 1.0


def test_semantic_class_variety():
    classes = set()
    for seed in range(4):
        classes |= {g.cls for g in house(seed).geoms}
    assert len(classes) >= 12, classes
    assert {"wall", "floor", "ceiling", "door_frame"} <= classes
    assert classes <= set(CLASS_NAMES[1:])


def test_room_types():
    repeated = 0
    for seed in range(8):
        s = house(seed)
        assert len(s.rooms) == 6
        types = [r.type for r in s.rooms]
        assert all(t in HOUSE_ROOM_TYPES for t in types)
        repeated += len(set(types)) < len(types)
        for i, room in enumerate(s.rooms):
            assert any(g.room == i and g.cls == "floor" for g in s.geoms)
    assert repeated >= 1  # some houses have two rooms of one type
    assert [r.type for r in maze(0).rooms] == ["maze"]
    assert single_room(0, room_type="kitchen").rooms[0].type == "kitchen"
    with pytest.raises(ValueError, match="room type"):
        single_room(0, room_type="garage")
    assert set(HOUSE_ROOM_TYPES) == set(ROOM_TYPES) - {"maze"}


def test_furniture_inside_rooms(all_scenes):
    for s in all_scenes:
        for g in _furniture(s):
            assert 0 <= g.room < len(s.rooms), g.name
            x0, y0, x1, y1 = s.rooms[g.room].rect
            lo, hi = geom_aabb(g)
            eps = 1e-6
            assert lo[0] >= x0 + 0.05 - eps and lo[1] >= y0 + 0.05 - eps, (s.name, g.name)
            assert hi[0] <= x1 - 0.05 + eps and hi[1] <= y1 - 0.05 + eps, (s.name, g.name)
            assert lo[2] >= -eps and hi[2] < s.height, (s.name, g.name)
            # boxes/ellipsoids are axis-aligned; capsules vertical or horizontal
            if g.type != "capsule":
                assert np.allclose(g.quat, [1, 0, 0, 0])


def test_furniture_keeps_doorways_clear(houses):
    for s in houses:
        lintels = [g for g in s.geoms if g.cls == "door_frame"]
        assert lintels
        for d in lintels:
            lo, hi = geom_aabb(d)
            thin = int(np.argmin(hi[:2] - lo[:2]))  # axis across the wall
            zone_lo, zone_hi = lo[:2].copy(), hi[:2].copy()
            zone_lo[thin] -= 0.8
            zone_hi[thin] += 0.8
            for g in _furniture(s):
                glo, ghi = geom_aabb(g)
                overlap = np.all(glo[:2] < zone_hi - 1e-6) and np.all(ghi[:2] > zone_lo + 1e-6)
                assert not overlap, (s.name, d.name, g.name)


def test_structure_floor_to_ceiling(all_scenes):
    for s in all_scenes:
        h = s.height
        walls = [g for g in s.geoms if g.cls == "wall"]
        assert walls
        for g in walls:
            assert g.type == "box" and np.allclose(g.quat, [1, 0, 0, 0])
            lo, hi = geom_aabb(g)
            assert lo[2] <= 1e-9 and hi[2] >= h - 1e-9, g.name
            assert 0.05 <= min(hi[:2] - lo[:2]) <= 0.16, g.name
        floors = [geom_aabb(g) for g in s.geoms if g.cls == "floor"]
        ceilings = [geom_aabb(g) for g in s.geoms if g.cls == "ceiling"]
        assert all(abs(hi[2]) < 1e-9 for lo, hi in floors)
        assert all(abs(lo[2] - h) < 1e-9 for lo, hi in ceilings)
        # floors tile the footprint: no area overlap, union covers bounds
        rects = [(lo[0], lo[1], hi[0], hi[1]) for lo, hi in floors]
        for i in range(len(rects)):
            for j in range(i + 1, len(rects)):
                a, b = rects[i], rects[j]
                ox = min(a[2], b[2]) - max(a[0], b[0])
                oy = min(a[3], b[3]) - max(a[1], b[1])
                assert ox <= 1e-9 or oy <= 1e-9, (s.name, i, j)
        x0, y0, x1, y1 = s.bounds
        area = sum((r[2] - r[0]) * (r[3] - r[1]) for r in rects)
        ux0, uy0 = min(r[0] for r in rects), min(r[1] for r in rects)
        ux1, uy1 = max(r[2] for r in rects), max(r[3] for r in rects)
        assert abs(area - (ux1 - ux0) * (uy1 - uy0)) < 1e-6
        assert ux0 <= x0 and uy0 <= y0 and ux1 >= x1 and uy1 >= y1


def _collinear_overlaps(scene):
    """Pairs of wall boxes on the same line and side whose extents overlap along it."""
    boxes = [(g.name, *geom_aabb(g)) for g in scene.geoms if g.cls == "wall"]
    bad = []
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            n1, lo1, hi1 = boxes[i]
            n2, lo2, hi2 = boxes[j]
            for across in (0, 1):
                along = 1 - across
                same = abs(lo1[across] - lo2[across]) < 1e-9 and abs(hi1[across] - hi2[across]) < 1e-9
                runs_along = (hi1[along] - lo1[along]) > (hi1[across] - lo1[across])
                if same and runs_along and min(hi1[along], hi2[along]) - max(lo1[along], lo2[along]) > 1e-9:
                    bad.append((n1, n2))
    return bad


def test_collinear_walls_do_not_overlap(all_scenes):
    for s in all_scenes:
        assert _collinear_overlaps(s) == [], s.name


def test_maze_structure():
    s = maze(3, cells=(6, 4), cell_size=1.5)
    x0, y0, x1, y1 = s.bounds
    assert x1 - x0 == pytest.approx(6 * 1.5 - 0.1) and y1 - y0 == pytest.approx(4 * 1.5 - 0.1)
    walls = [g for g in s.geoms if g.cls == "wall"]
    # a perfect maze has nx*ny-1 openings; merging keeps the number of boxes small
    assert len(walls) < 6 * 4 + 10
    objects = [g for g in s.geoms if g.cls == "object"]
    assert 2 <= len(objects) <= 6
    assert len({tuple(g.rgba[:3]) for g in walls}) >= 2


def _free_grid(scene, res=0.1, radius=0.2):
    """Free cells for a disc agent: footprints of geoms below 1.5 m (not floor/ceiling)."""
    x0, y0, x1, y1 = scene.bounds
    xs = np.arange(x0 + res / 2, x1, res)
    ys = np.arange(y0 + res / 2, y1, res)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    free = np.ones(px.shape, bool)
    for g in scene.geoms:
        if g.cls in ("floor", "ceiling"):
            continue
        lo, hi = geom_aabb(g)
        if lo[2] > 1.5:  # lintels above doorways
            continue
        dx = np.maximum(np.maximum(lo[0] - px, px - hi[0]), 0.0)
        dy = np.maximum(np.maximum(lo[1] - py, py - hi[1]), 0.0)
        free &= dx * dx + dy * dy >= radius * radius
    return free, xs, ys


@pytest.mark.parametrize("make", [lambda: house(21), lambda: house(22, grid=(3, 3)), lambda: single_room(5), lambda: maze(6)])
def test_free_space_connected(make):
    s = make()
    free, xs, ys = _free_grid(s)
    labels, n = ndimage.label(free)
    assert n == 1, np.bincount(labels.ravel())[1:]
    for room in s.rooms:  # every room has free floor (all in the single component)
        inside = (xs[:, None] > room.rect[0]) & (xs[:, None] < room.rect[2])
        inside = inside & (ys[None, :] > room.rect[1]) & (ys[None, :] < room.rect[3])
        assert free[inside].sum() > 20


# ----------------------------------------------------------------------------------
# MJCF
# ----------------------------------------------------------------------------------


def test_mjcf_geom_order_by_type(all_scenes):
    for s in all_scenes[:4]:
        for layout in (None, layout_of([s])):
            m = compile_scene(scene_to_mjcf(s, layout))
            ranks = [TYPE_RANK[int(t)] for t in m.geom_type]
            assert ranks == sorted(ranks)


def test_padding_layout(houses):
    scenes = houses + [maze(0)]
    layout = layout_of(scenes)
    assert set(layout) == set(GEOM_TYPES) and all(v >= 1 for v in layout.values())
    for t in GEOM_TYPES:
        assert layout[t] == max(max(geom_counts(s)[t] for s in scenes), 1)
    layout = {t: n + 2 for t, n in layout.items()}
    models = [compile_scene(scene_to_mjcf(s, layout)) for s in scenes]
    for s, m in zip(scenes, models):
        assert m.ngeom == sum(layout.values())
        np.testing.assert_array_equal(m.geom_type, models[0].geom_type)
        counts = geom_counts(s)
        offset = 0
        for t in GEOM_TYPES:
            ids = range(offset, offset + layout[t])
            for k, gid in enumerate(ids):
                name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, gid)
                if k < counts[t]:
                    assert not name.startswith("pad_") and m.geom_rgba[gid, 3] == 1
                else:
                    assert name == f"pad_{t}_{k - counts[t]}"
                    assert m.geom_rgba[gid, 3] == 0 and m.geom_matid[gid] == -1
                    assert m.geom_contype[gid] == 0 and m.geom_conaffinity[gid] == 0
                    assert m.geom_pos[gid, 2] <= -100
            offset += layout[t]
    small = dict(layout_of(scenes), box=geom_counts(houses[0])["box"] - 1)
    with pytest.raises(ValueError, match=r"box geoms but the layout allows only"):
        scene_to_mjcf(houses[0], small)


def test_round_trip(houses):
    s = houses[1]
    xml = scene_to_mjcf(s, {t: n + 3 for t, n in layout_of([s]).items()})
    back = scene_from_mjcf(xml, name="back")
    assert back.name == "back" and not back.closed and back.rooms == []
    assert len(back.geoms) == len(s.geoms)
    assert Counter(g.cls for g in back.geoms) == Counter(g.cls for g in s.geoms)
    orig = {g.name: g for g in s.geoms}
    for g in back.geoms:
        o = orig[g.name]
        assert g.type == o.type and g.cls == o.cls
        np.testing.assert_allclose(g.pos, o.pos, atol=1e-6)
        np.testing.assert_allclose(g.size[: len(o.size)], o.size, atol=1e-6)
        np.testing.assert_allclose(g.rgba, o.rgba, atol=1e-6)
        np.testing.assert_allclose(np.abs(np.dot(g.quat, o.quat)), 1.0, atol=1e-6)
    assert back.height == pytest.approx(s.height)
    bx0, by0, bx1, by1 = back.bounds
    x0, y0, x1, y1 = s.bounds
    assert bx0 <= x0 and by0 <= y0 and bx1 >= x1 and by1 >= y1
    assert bx1 - bx0 == pytest.approx(x1 - x0 + 0.12)  # floors reach under the outer walls


USER_OK = """
<mujoco>
  <asset><material name="red" rgba="1 0 0 1"/></asset>
  <worldbody>
    <geom name="floor" type="box" size="3 2 0.05" pos="0 0 -0.05"/>
    <geom name="wall_north" type="box" size="3 0.05 1.2" pos="0 2 1.2"/>
    <geom name="door_frame_1" type="box" size="0.5 0.05 0.1" pos="1 -2 2.2"/>
    <geom name="invisible" type="box" size="1 1 1" rgba="0 0 0 0"/>
    <body name="furniture" pos="1 0.5 0" euler="0 0 90">
      <geom name="bed/frame" type="box" size="1 0.5 0.2" pos="0.5 0 0.2" material="red"/>
      <geom name="lamp" type="capsule" size="0.03 0.5" pos="0 0 0.6"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_user_mjcf_ok():
    s = scene_from_mjcf(USER_OK)
    assert [g.cls for g in s.geoms] == ["floor", "wall", "door_frame", "bed", "lamp"]
    bed = s.geoms[3]
    np.testing.assert_allclose(bed.pos, [1.0, 1.0, 0.2], atol=1e-9)  # body rotated by 90 degrees
    np.testing.assert_allclose(bed.rgba, [1, 0, 0, 1])
    lo, hi = geom_aabb(bed)
    np.testing.assert_allclose(hi - lo, [1.0, 2.0, 0.4], atol=1e-9)
    assert s.bounds == pytest.approx((-3.0, -2.0, 3.0, 2.0))
    assert s.height == pytest.approx(2.4)  # no ceiling: highest top
    # and it goes back to MJCF
    assert compile_scene(scene_to_mjcf(s)).ngeom == 5


def _user(body: str) -> str:
    return f"""<mujoco><worldbody>
      <geom name="floor_0" type="box" size="2 2 0.05" pos="0 0 -0.05"/>
      {body}
    </worldbody></mujoco>"""


@pytest.mark.parametrize(
    "xml, pattern",
    [
        (_user('<geom name="rug_1" type="hfield" hfield="h"/>').replace("<worldbody>", '<asset><hfield name="h" nrow="2" ncol="2" size="1 1 0.1 0.1"/></asset><worldbody>'),
         r"geom 'rug_1' has unsupported type 'hfield'"),
        (_user('<geom name="floor_2" type="plane" size="0 0 0.1"/>'), r"geom 'floor_2' is an infinite plane"),
        (_user('<geom type="box" size="0.4 0.3 0.2"/>'), r"unnamed geom #1 has no name"),
        (_user('<geom name="couch_1" type="box" size="0.4 0.3 0.2"/>'), r"geom 'couch_1' does not name a known semantic class.*valid classes: wall, floor"),
        (_user('<body name="crate"><freejoint/><geom name="object_1" type="box" size=".1 .1 .1"/></body>'), r"joint '#0' has type free; scene bodies may move on hinge and slide joints only"),
        (_user('<body name="cart" mocap="true"><geom name="object_2" type="sphere" size=".1"/></body>'), r"geom 'object_2' is on a mocap body \('cart'\); scene geoms must be static or move on hinge and slide joints"),
        ('<mujoco><worldbody><geom name="wall_1" type="box" size="1 1 1"/></worldbody></mujoco>', r"no geom of class floor"),
        ("<mujoco><worldbody><geom name='floor' type='box' size='1 1 1'></worldbody>", r"MJCF does not compile: "),
        (_user('<geom name="wall_1" type="box" size="1 1"/>'), r"MJCF does not compile: "),
    ],
)
def test_user_mjcf_errors(xml, pattern):
    with pytest.raises(ValueError, match=pattern):
        scene_from_mjcf(xml)


def test_class_from_name():
    assert class_from_name("door_frame_3") == "door_frame"
    assert class_from_name("bed/left") == "bed"
    assert class_from_name("bed") == "bed"
    assert class_from_name("bedside") is None
    assert class_from_name("void") is None
    assert class_from_name("") is None


def test_plot_topdown(tmp_path, houses):
    """The drawing shows the classes of the house in their class colours (the floor a third
    of the picture or more, the walls, most furniture) and never the ceiling."""
    from matplotlib.image import imread

    out = save_topdown(houses[0], str(tmp_path / "top.png"), color_by="class", dpi=40)
    pixels = np.round(imread(out)[..., :3] * 255).astype(int)
    table = class_colors()

    def share(cls):
        return float(np.mean(np.all(pixels == table[CLASS_ID[cls]], axis=-1)))

    assert share("floor") > 0.3 and share("wall") > 0.003
    assert share("ceiling") == 0.0
    drawn = {g.cls for g in houses[0].geoms if g.cls not in ("ceiling", "floor", "wall")}
    assert sum(share(c) > 0 for c in drawn) >= len(drawn) // 2  # small furniture may hide under labels
