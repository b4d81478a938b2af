"""Scene <-> MJCF.

`scene_to_mjcf` writes a scene as static world-body geoms, ordered by geom type
(all boxes, then spheres, then capsules, then ellipsoids): geom id = offset of its
type + index within the type. With a `layout` every type is padded with invisible,
non-colliding geoms up to a fixed count, so that scenes of a batch compile to models
with identical geom arrays. `scene_from_mjcf` reads a user's MJCF back into a
`Scene`, checking that it only uses what the renderer supports; `scene_from_mjcf_file`
does the same for a file. A scene that cannot be used raises `SceneError`.
"""

from __future__ import annotations

import os
from typing import Optional
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from .errors import SceneError
from .spec import CLASS_NAMES, GEOM_TYPES, Geom, Scene, class_of_name, half_extents

PAD_PREFIX = "pad_"
PAD_DEPTH = -100.0  # padding geom i of a type sits at z = PAD_DEPTH - i
AGENT_BODY = "agent"
AGENT_CAMERA = "agent_cam"

# Classes a geom may carry ("void" means "nothing hit" and is not a geom class).
GEOM_CLASSES: tuple[str, ...] = tuple(c for c in CLASS_NAMES if c != "void")
# Longest first, so that "door_frame_2" is a door_frame and not a "door".

_MJ_TYPE = {
    "box": int(mujoco.mjtGeom.mjGEOM_BOX),
    "sphere": int(mujoco.mjtGeom.mjGEOM_SPHERE),
    "capsule": int(mujoco.mjtGeom.mjGEOM_CAPSULE),
    "ellipsoid": int(mujoco.mjtGeom.mjGEOM_ELLIPSOID),
}
_TYPE_OF_MJ = {v: k for k, v in _MJ_TYPE.items()}
# Geom types of a user's MJCF that only the `mjx` backend renders (`Geom.native`).
NATIVE_TYPES = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_MESH): "mesh",
}
_PAD_SIZE = {"box": "0.01 0.01 0.01", "sphere": "0.01", "capsule": "0.01 0.01", "ellipsoid": "0.01 0.01 0.01"}


def class_from_name(name: Optional[str]) -> Optional[str]:
    """Semantic class encoded in a geom name, or None (see `spec.class_of_name`)."""
    cid = class_of_name(name) if name else 0
    return CLASS_NAMES[cid] if cid else None


def _num(x: float) -> str:
    s = f"{float(x):.10g}"
    return "0" if s == "-0" else s


def _vec(v) -> str:
    return " ".join(_num(x) for x in v)


def geom_counts(scene: Scene) -> dict[str, int]:
    """Number of geoms of each type in a scene."""
    counts = {t: 0 for t in GEOM_TYPES}
    for g in scene.geoms:
        counts[g.type] += 1
    return counts


def layout_of(scenes: list[Scene]) -> dict[str, int]:
    """Per-type geom counts that fit every scene: max over scenes, at least 1 each."""
    layout = {t: 1 for t in GEOM_TYPES}
    for s in scenes:
        for t, n in geom_counts(s).items():
            layout[t] = max(layout[t], n)
    return layout


def ordered_geoms(scene: Scene) -> list[Geom]:
    """The scene's geoms in MJCF order: boxes, spheres, capsules, ellipsoids."""
    return [g for t in GEOM_TYPES for g in scene.geoms if g.type == t]


def _unique_names(geoms: list[Geom]) -> list[str]:
    """Names for the MJCF: the geom's own name when it encodes its class (and is
    not a padding name), else "<class>_<k>"; duplicates get fresh "<class>_<k>"."""
    own = [
        g.name if (g.name and not g.name.startswith(PAD_PREFIX) and class_from_name(g.name) == g.cls) else None
        for g in geoms
    ]
    reserved = {n for n in own if n}
    used: set[str] = set()
    next_k: dict[str, int] = {}
    names = []
    for n, g in zip(own, geoms):
        if n is None or n in used:
            k = next_k.get(g.cls, 0)
            while f"{g.cls}_{k}" in used or f"{g.cls}_{k}" in reserved:
                k += 1
            next_k[g.cls] = k + 1
            n = f"{g.cls}_{k}"
        used.add(n)
        names.append(n)
    return names


def scene_to_mjcf(
    scene: Scene,
    layout: Optional[dict[str, int]] = None,
    *,
    fovy: float = 60.0,
    offscreen: int = 512,
) -> str:
    """MJCF text of a scene (see module docstring for the geom order contract).

    layout: optional geom count per type; each type is padded with invisible geoms
    named "pad_<type>_<i>" (alpha 0, no collisions, parked below the floor) up to
    that count. Raises ValueError if the scene has more geoms of a type than allowed.
    The model also holds a mocap body "agent" at the origin with a fixed camera
    "agent_cam" that looks along the body's +x axis with +z up.
    """
    counts = geom_counts(scene)
    if layout is not None:
        unknown = set(layout) - set(GEOM_TYPES)
        if unknown:
            raise ValueError(f"layout has unknown geom types {sorted(unknown)}; valid: {GEOM_TYPES}")
        for t in GEOM_TYPES:
            if counts[t] > int(layout.get(t, 0)):
                raise ValueError(
                    f"scene {scene.name!r} has {counts[t]} {t} geoms but the layout allows only "
                    f"{int(layout.get(t, 0))}"
                )
    geoms = ordered_geoms(scene)
    names = _unique_names(geoms)
    x0, y0, x1, y1 = scene.bounds
    lines = [
        f"<mujoco model={quoteattr(scene.name)}>",
        '  <compiler angle="radian" autolimits="true"/>',
        '  <option gravity="0 0 0" timestep="0.01"/>',
        "  <visual>",
        f'    <global offwidth="{int(offscreen)}" offheight="{int(offscreen)}"/>',
        '    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0 0 0"/>',
        "  </visual>",
        "  <asset>",
        '    <material name="default" rgba="1 1 1 1"/>',
        "  </asset>",
        "  <worldbody>",
        f'    <light name="sun" directional="true" castshadow="false" pos="{_vec(((x0 + x1) / 2, (y0 + y1) / 2, scene.height))}" '
        'dir="0.3 0.2 -1" diffuse="0.6 0.6 0.6" specular="0 0 0"/>',
    ]
    by_type: dict[str, list[str]] = {t: [] for t in GEOM_TYPES}
    for g, name in zip(geoms, names):
        size = g.size[:3] if g.type in ("box", "ellipsoid") else (g.size[:2] if g.type == "capsule" else g.size[:1])
        attrs = f'name={quoteattr(name)} type="{g.type}" pos="{_vec(g.pos)}" size="{_vec(size)}"'
        if not np.allclose(g.quat, (1.0, 0.0, 0.0, 0.0)):
            attrs += f' quat="{_vec(g.quat)}"'
        attrs += f' rgba="{_vec(g.rgba)}"'
        by_type[g.type].append(f"    <geom {attrs}/>")
    for t in GEOM_TYPES:
        lines += by_type[t]
        if layout is not None:
            for i in range(int(layout.get(t, 0)) - counts[t]):
                lines.append(
                    f'    <geom name="{PAD_PREFIX}{t}_{i}" type="{t}" size="{_PAD_SIZE[t]}" '
                    f'pos="0 0 {_num(PAD_DEPTH - i)}" rgba="0 0 0 0" contype="0" conaffinity="0" group="5"/>'
                )
    lines += [
        f'    <body name="{AGENT_BODY}" mocap="true" pos="0 0 0">',
        f'      <camera name="{AGENT_CAMERA}" mode="fixed" pos="0 0 0" xyaxes="0 -1 0 0 0 1" fovy="{_num(fovy)}"/>',
        "    </body>",
        "  </worldbody>",
        "</mujoco>",
        "",
    ]
    return "\n".join(lines)


def _one_line(message) -> str:
    """`message` with every run of whitespace (newlines included) made one space."""
    return " ".join(str(message).split())


def compile_scene(xml: str) -> mujoco.MjModel:
    """Compile MJCF text with MuJoCo; errors become SceneError("MJCF does not compile: ...")."""
    if not isinstance(xml, str):
        raise ValueError(f"MJCF must be a string, got {type(xml).__name__}")
    try:
        return mujoco.MjModel.from_xml_string(xml)
    except Exception as e:  # mujoco raises ValueError with the parser/compiler message
        raise SceneError(f"MJCF does not compile: {_one_line(e)}") from e


def _type_name(t: int) -> str:
    try:
        return mujoco.mjtGeom(int(t)).name.removeprefix("mjGEOM_").lower()
    except ValueError:
        return f"type {int(t)}"


def geom_aabb(g: Geom) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned bounding box (lo, hi) of a geom, exact for every type."""
    w, x, y, z = g.quat / np.linalg.norm(g.quat)
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    half = half_extents(g.type, rot, g.size)
    return g.pos - half, g.pos + half


def scene_from_mjcf(xml: str, name: str = "user") -> Scene:
    """A Scene from a user's MJCF.

    Every visible geom must be static (in the world body or a body welded to it) or
    on a body that moves on hinge joints or slide joints with a range (`Geom.moving`:
    each episode draws the joint positions uniformly within their ranges), of type
    box/sphere/capsule/ellipsoid (or plane/cylinder/mesh, which only the `mjx`
    backend renders). A scene with moving or plane/cylinder/mesh geoms keeps its
    source and is compiled from it as it is (`native_model`). Every geom is named after its semantic class
    ("<class>", "<class>_<anything>" or "<class>/<anything>"). Padding geoms ("pad_"
    names) and invisible geoms (alpha 0, no material) are skipped. At least one geom
    must be of class floor. bounds: xy union of the floor geoms' boxes; height: lowest
    ceiling bottom if there is a ceiling, else highest geom top. The result has no
    rooms and closed=False. Raises `SceneError` saying which geom is at fault and why.
    """
    return _scene_of_model(compile_scene(xml), name, where="", source=("xml", xml))


def scene_from_mjcf_file(path: str | os.PathLike, name: Optional[str] = None) -> Scene:
    """A Scene from a user's MJCF file (see `scene_from_mjcf`); name: the path unless given.

    The file is compiled from its path, so meshes, textures and includes it names
    resolve relative to it. Every `SceneError` message starts with the path.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise SceneError(f"{path}: cannot read the MJCF file: {e.strerror}") from None
    try:
        model = mujoco.MjModel.from_xml_path(path)
    except Exception as e:  # mujoco raises ValueError with the parser/compiler message
        raise SceneError(f"{path}: MJCF does not compile: {_one_line(e)}") from e
    return _scene_of_model(model, path if name is None else name, where=f"{path}: ", source=("file", os.path.abspath(path)))


def _native_box(m: mujoco.MjModel, d: mujoco.MjData, i: int, where: str, label: str) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half-sizes) of the world bounding box of a plane, cylinder or mesh geom."""
    rot, pos, size = d.geom_xmat[i].reshape(3, 3), d.geom_xpos[i], m.geom_size[i]
    gtype = int(m.geom_type[i])
    if gtype == int(mujoco.mjtGeom.mjGEOM_PLANE):
        if size[0] <= 0 or size[1] <= 0:
            raise SceneError(f"{where}{label} is an infinite plane (size 0); give it a finite size "
                             "(half-lengths along x and y), the scene's extent")
        return pos, np.abs(rot) @ np.array([size[0], size[1], 0.0])
    if gtype == int(mujoco.mjtGeom.mjGEOM_CYLINDER):  # exact: the two end discs' extents
        axis = rot[:, 2]
        return pos, size[0] * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0)) + size[1] * np.abs(axis)
    mesh = int(m.geom_dataid[i])  # exact: the extent of the mesh's vertices, placed
    start, count = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
    world = m.mesh_vert[start : start + count].astype(np.float64) @ rot.T + pos
    lo, hi = world.min(axis=0), world.max(axis=0)
    return (lo + hi) / 2, (hi - lo) / 2


def _on_mocap(m: mujoco.MjModel, body: int) -> bool:
    """Whether `body` is a mocap body or hangs from one."""
    while body > 0:
        if m.body_mocapid[body] >= 0:
            return True
        body = int(m.body_parentid[body])
    return False


def _check_joints(m: mujoco.MjModel, where: str) -> None:
    """Joints must be hinges (any range) or slides with a range: the environment draws
    each episode's joint positions uniformly within them (`mjx_world.MjxWorld`)."""
    for j in range(m.njnt):
        label = f"joint {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f'#{j}'!r}"
        jtype = int(m.jnt_type[j])
        if jtype not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise SceneError(f"{where}{label} has type {mujoco.mjtJoint(jtype).name.removeprefix('mjJNT_').lower()}; "
                             "scene bodies may move on hinge and slide joints only")
        if jtype == int(mujoco.mjtJoint.mjJNT_SLIDE) and not m.jnt_limited[j]:
            raise SceneError(f"{where}{label} is a slide joint without a range; give it one (range=\"lo hi\" in "
                             "metres): each episode places it uniformly within it")


def _scene_of_model(m: mujoco.MjModel, name: str, where: str, source: Optional[tuple[str, str]] = None) -> Scene:
    """The Scene of a compiled user model; `where` starts every error message. A scene
    with plane, cylinder or mesh geoms keeps `source` (its model is compiled from it)."""
    _check_joints(m, where)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    geoms: list[Geom] = []
    for i in range(m.ngeom):
        gname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) or ""
        label = f"geom {gname!r}" if gname else f"unnamed geom #{i}"
        matid = int(m.geom_matid[i])
        rgba = np.array(m.mat_rgba[matid] if matid >= 0 else m.geom_rgba[i], np.float64)
        if gname.startswith(PAD_PREFIX):
            continue
        if matid < 0 and m.geom_rgba[i][3] == 0:
            continue
        body = int(m.geom_bodyid[i])
        if _on_mocap(m, body):
            bname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body) or f"#{body}"
            raise SceneError(
                f"{where}{label} is on a mocap body ({bname!r}); scene geoms must be static or move on "
                "hinge and slide joints (the agent is the environment's only mocap body)"
            )
        moving = int(m.body_weldid[body]) != 0
        gtype = int(m.geom_type[i])
        if gtype not in _TYPE_OF_MJ and gtype not in NATIVE_TYPES:
            raise SceneError(
                f"{where}{label} has unsupported type {_type_name(gtype)!r}; supported geom types: "
                f"{', '.join(GEOM_TYPES)} (both render backends) and {', '.join(NATIVE_TYPES.values())} "
                "(env.render.backend mjx)"
            )
        if not gname:
            raise SceneError(
                f"{where}{label} has no name; name every geom after its semantic class, e.g. 'wall_3' "
                f"or 'bed/frame', with class one of: {', '.join(GEOM_CLASSES)}"
            )
        cls = class_from_name(gname)
        if cls is None:
            raise SceneError(
                f"{where}{label} does not name a known semantic class (its name must be '<class>', "
                f"'<class>_...' or '<class>/...'); valid classes: {', '.join(GEOM_CLASSES)}"
            )
        if gtype in NATIVE_TYPES:
            centre, half = _native_box(m, d, i, where, label)
            geoms.append(Geom(type="box", pos=centre, size=half, rgba=rgba, cls=cls, name=gname,
                              native=NATIVE_TYPES[gtype], moving=moving))
            continue
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.geom_xmat[i])
        if quat[0] < 0:
            quat = -quat
        geoms.append(
            Geom(
                type=_TYPE_OF_MJ[gtype],
                pos=np.array(d.geom_xpos[i], np.float64),
                size=np.array(m.geom_size[i], np.float64),
                rgba=rgba,
                cls=cls,
                quat=quat,
                name=gname,
                moving=moving,
            )
        )
    floors = [g for g in geoms if g.cls == "floor"]
    if not floors:
        raise SceneError(
            f"{where}MJCF has no geom of class floor; name the floor geom(s) 'floor' or 'floor_<k>' "
            "(a thin box whose top face is the walkable surface at z=0)"
        )
    boxes = [geom_aabb(g) for g in floors]
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    ceilings = [geom_aabb(g)[0][2] for g in geoms if g.cls == "ceiling"]
    height = float(min(ceilings)) if ceilings else float(max(geom_aabb(g)[1][2] for g in geoms))
    native = source if any(g.native or g.moving for g in geoms) else None
    return Scene(name=name, geoms=geoms, rooms=[], bounds=bounds, height=height, closed=False, source=native)


def native_model(scene: Scene, fovy: float) -> tuple[str, mujoco.MjModel]:
    """(MJCF text, compiled model) of a scene with a `source`: the user's model as it is,
    with the mocap body "agent" and its camera "agent_cam" added (as `scene_to_mjcf`
    adds them). Meshes and textures resolve relative to the source file."""
    kind, value = scene.source
    where = f"{value}: " if kind == "file" else ""
    try:
        spec = mujoco.MjSpec.from_file(value) if kind == "file" else mujoco.MjSpec.from_string(value)
        if kind == "file":  # asset folders made absolute: the MJCF text compiles from anywhere
            folder = os.path.dirname(os.path.abspath(value))
            spec.meshdir = os.path.join(folder, spec.meshdir)
            spec.texturedir = os.path.join(folder, spec.texturedir)
        if spec.body(AGENT_BODY) is not None or spec.camera(AGENT_CAMERA) is not None:
            raise SceneError(f"{where}the MJCF already has a body {AGENT_BODY!r} or a camera {AGENT_CAMERA!r}; "
                             "the environment adds its agent under those names: rename them")
        body = spec.worldbody.add_body(name=AGENT_BODY, mocap=True)
        # Looking along the body's +x axis with +z up (xyaxes "0 -1 0 0 0 1").
        body.add_camera(name=AGENT_CAMERA, fovy=float(fovy), quat=[-0.5, -0.5, 0.5, 0.5])
        model = spec.compile()
    except SceneError:
        raise
    except Exception as e:  # mujoco raises ValueError with the parser/compiler message
        raise SceneError(f"{where}MJCF does not compile: {_one_line(e)}") from e
    return spec.to_xml(), model


__all__ = [
    "AGENT_BODY",
    "AGENT_CAMERA",
    "GEOM_CLASSES",
    "NATIVE_TYPES",
    "PAD_PREFIX",
    "class_from_name",
    "compile_scene",
    "geom_aabb",
    "geom_counts",
    "layout_of",
    "native_model",
    "ordered_geoms",
    "scene_from_mjcf",
    "scene_from_mjcf_file",
    "scene_to_mjcf",
]

