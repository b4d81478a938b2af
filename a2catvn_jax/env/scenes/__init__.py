"""Scenes: data model, procedural generators and MJCF conversion."""

from .builder import AGENT_RADIUS
from .errors import SceneError
from .generate import GENERATORS, make_scenes
from .houses import HOUSE_ROOM_TYPES, house
from .mazes import maze
from .mjcf import (
    AGENT_BODY,
    AGENT_CAMERA,
    GEOM_CLASSES,
    PAD_PREFIX,
    class_from_name,
    compile_scene,
    geom_aabb,
    geom_counts,
    layout_of,
    ordered_geoms,
    scene_from_mjcf,
    scene_from_mjcf_file,
    scene_to_mjcf,
)
from .placement import free_space_ok
from .rooms import single_room
from .spec import (
    CLASS_ID,
    CLASS_NAMES,
    GEOM_TYPES,
    NUM_CLASSES,
    ROOM_TYPE_ID,
    ROOM_TYPES,
    STRUCTURAL_CLASSES,
    Geom,
    Room,
    Scene,
    class_colors,
)

__all__ = [
    "AGENT_BODY",
    "AGENT_CAMERA",
    "AGENT_RADIUS",
    "CLASS_ID",
    "CLASS_NAMES",
    "GENERATORS",
    "GEOM_CLASSES",
    "GEOM_TYPES",
    "Geom",
    "HOUSE_ROOM_TYPES",
    "NUM_CLASSES",
    "PAD_PREFIX",
    "ROOM_TYPES",
    "ROOM_TYPE_ID",
    "Room",
    "STRUCTURAL_CLASSES",
    "Scene",
    "SceneError",
    "class_colors",
    "class_from_name",
    "compile_scene",
    "free_space_ok",
    "geom_aabb",
    "geom_counts",
    "house",
    "layout_of",
    "make_scenes",
    "maze",
    "ordered_geoms",
    "scene_from_mjcf",
    "scene_from_mjcf_file",
    "scene_to_mjcf",
    "single_room",
]
