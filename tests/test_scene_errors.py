"""Unusable MJCF scene files raise `SceneError` with a one-line message, and every
command line prints that line (`error: ...`) and exits non-zero without a traceback.

The library tests build the `World` (read the file, the occupancy grid, the render
backend), which stops before anything compiles. The command-line tests call each module's `main` with a
tiny configuration (one of them also in a process of its own); the bad file stops it
before anything compiles.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from a2catvn_jax.config import load_config, save_config
from a2catvn_jax.env import navgrid
from a2catvn_jax.env.scenes import SceneError
from a2catvn_jax.env.world import BODY_MARGIN, World, make_scenes
from a2catvn_jax.errors import UserError
from tiny import TINY_LEARNER

ROOT = Path(__file__).resolve().parents[1]

ROOM = """<mujoco model="user_room">
  {asset}
  <worldbody>
    {floor}
    <geom name="wall_n" type="box" pos="0 1.45 1.25" size="1.5 0.05 1.25"/>
    <geom name="wall_s" type="box" pos="0 -1.45 1.25" size="1.5 0.05 1.25"/>
    <geom name="wall_e" type="box" pos="1.45 0 1.25" size="0.05 1.4 1.25"/>
    <geom name="wall_w" type="box" pos="-1.45 0 1.25" size="0.05 1.4 1.25"/>
    {item}
  </worldbody>
</mujoco>
"""
FLOOR = '<geom name="floor_0" type="box" pos="0 0 -0.05" size="1.5 1.5 0.05"/>'
TABLE = '<geom name="table_0" type="box" pos="0.5 0.4 0.4" size="0.4 0.3 0.4"/>'
# A tetrahedron in Wavefront OBJ, the mesh asset of the mesh case (next to its MJCF file).
CHAIR_OBJ = "v 0 0 0\nv 0.5 0 0\nv 0 0.5 0\nv 0 0 0.5\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _room(item: str = TABLE, floor: str = FLOOR, asset: str = "") -> str:
    return ROOM.format(item=item, floor=floor, asset=asset)


# case: (file text, or None for a file that does not exist; what the message must say)
CASES = {
    # Cylinders and meshes render with env.render.backend mjx only; the default is raycast.
    "cylinder": (
        _room('<geom name="table_0" type="cylinder" pos="0.5 0.4 0.4" size="0.4 0.4"/>'),
        r"cylinder\.xml: geom 'table_0' has type cylinder, which only the mjx backend renders: "
        r"set env\.render\.backend=mjx",
    ),
    "mesh": (
        _room('<geom name="chair_0" type="mesh" mesh="chair_mesh" pos="0.5 0.4 0"/>',
              asset='<asset><mesh name="chair_mesh" file="chair.obj"/></asset>'),
        r"mesh\.xml: geom 'chair_0' has type mesh, which only the mjx backend renders",
    ),
    "hfield": (
        _room('<geom name="rug_0" type="hfield" hfield="bumps" pos="0.5 0.4 0"/>',
              asset='<asset><hfield name="bumps" nrow="2" ncol="2" size="0.3 0.3 0.02 0.01"/></asset>'),
        r"hfield\.xml: geom 'rug_0' has unsupported type 'hfield'; supported geom types: box, sphere, capsule, "
        r"ellipsoid \(both render backends\) and plane, cylinder, mesh \(env\.render\.backend mjx\)",
    ),
    "infinite_plane": (
        _room(floor='<geom name="floor_0" type="plane" size="0 0 1"/>'),
        r"infinite_plane\.xml: geom 'floor_0' is an infinite plane \(size 0\); give it a finite size",
    ),
    "truncated": (
        _room()[:400],
        r"truncated\.xml: MJCF does not compile: XML parse error",
    ),
    "no_floor": (
        _room(floor=""),
        r"no_floor\.xml: MJCF has no geom of class floor",
    ),
    "freejoint": (
        _room('<body name="crate" pos="0.5 0.4 0.4"><freejoint/>'
              '<geom name="object_0" type="box" size="0.2 0.2 0.2"/></body>'),
        r"freejoint\.xml: joint '#0' has type free; scene bodies may move on hinge and slide joints only",
    ),
    "free_slide": (
        _room('<body name="drawer" pos="0.5 0.4 0.4"><joint name="runner" type="slide" axis="1 0 0"/>'
              '<geom name="cabinet_0" type="box" size="0.2 0.2 0.2"/></body>'),
        r"free_slide\.xml: joint 'runner' is a slide joint without a range; give it one",
    ),
    "small_floor": (
        '<mujoco><worldbody><geom name="floor" type="box" pos="0 0 -0.05" size="0.15 0.15 0.05"/></worldbody></mujoco>',
        r"small_floor\.xml: no free floor for an agent of radius 0\.2 m",
    ),
    "missing": (
        None,
        r"missing\.xml: cannot read the MJCF file: No such file or directory",
    ),
}


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    """A folder with one file per case (none for "missing") and the mesh asset."""
    folder = tmp_path_factory.mktemp("scenes")
    for case, (text, _) in CASES.items():
        if text is not None:
            (folder / f"{case}.xml").write_text(text)
    (folder / "chair.obj").write_text(CHAIR_OBJ)
    return folder


def _scene_overrides(path: Path) -> list[str]:
    return ["env.scene.kind=mjcf", f"env.scene.mjcf_path={path}"]


def test_scene_error_is_a_user_error():
    assert issubclass(SceneError, UserError) and issubclass(SceneError, ValueError)


def test_the_room_itself_is_usable(scene_dir):
    """The cases are one fault each: the room they start from builds."""
    path = scene_dir / "ok.xml"
    path.write_text(_room())
    cfg = load_config(None, _scene_overrides(path)).env
    (scene,) = make_scenes(cfg)
    assert navgrid.build(scene, cfg.grid_resolution, cfg.agent_radius, cfg.camera_height + BODY_MARGIN).free.any()


@pytest.mark.parametrize("case", list(CASES))
def test_library_raises_scene_error(scene_dir, case):
    """Each fault is a one-line SceneError when the world is built."""
    path = scene_dir / f"{case}.xml"
    cfg = load_config(None, _scene_overrides(path)).env
    with pytest.raises(SceneError, match=CASES[case][1]) as e:
        World(cfg, make_scenes(cfg))
    assert "\n" not in str(e.value)
    assert str(e.value).startswith(str(path))


def test_model_settings_mjx_refuses_are_one_line(scene_dir):
    """A native scene (compiled from the user's file) whose options MJX cannot use."""
    path = scene_dir / "pgs.xml"
    path.write_text(CASES["cylinder"][0].replace("<mujoco model=\"user_room\">",
                                                 "<mujoco model=\"user_room\"><option solver=\"PGS\"/>"))
    cfg = load_config(None, _scene_overrides(path) + ["env.render.backend=mjx"]).env
    with pytest.raises(SceneError, match=r"pgs\.xml: the mjx backend cannot use this model: NotImplementedError") as e:
        World(cfg, make_scenes(cfg))
    assert "\n" not in str(e.value)
    # The environment's own MJX model ignores the solver (its bodies are placed, not
    # simulated): with the ray caster the same scene minus its cylinder builds.
    path.write_text(_room().replace("<mujoco model=\"user_room\">", "<mujoco model=\"user_room\"><option solver=\"PGS\"/>"))
    cfg = load_config(None, _scene_overrides(path) + ["env.render.backend=raycast"]).env
    assert World(cfg, make_scenes(cfg)).backend == "raycast"


def test_evaluation_environment_raises_scene_error(scene_dir):
    from a2catvn_jax.run.restore import house_env

    cfg = load_config(None, _scene_overrides(scene_dir / "cylinder.xml")).env
    for houses in ("train", "new-targets"):
        with pytest.raises(SceneError, match=CASES["cylinder"][1]):
            house_env(cfg, houses)


def _evaluate_workdir(folder: Path, path: Path) -> Path:
    """A run directory whose configuration names `path`. The evaluation builds its
    environment before it reads any parameters, so an empty checkpoint folder is
    enough to reach the scene."""
    workdir = folder / "run"
    (workdir / "checkpoints" / "0").mkdir(parents=True)
    save_config(load_config(None, TINY_LEARNER + _scene_overrides(path)), workdir / "config.yaml")
    return workdir


def _command(cli: str, path: Path, folder: Path) -> list[str]:
    scene = _scene_overrides(path)
    if cli == "train":
        return ["a2catvn_jax.train", "--workdir", str(folder / "run"), "--no-progress", "--updates", "1",
                "--set", *TINY_LEARNER, *scene]
    if cli == "pretrain":
        return ["a2catvn_jax.pretrain", "--workdir", str(folder / "pre"), "--set", *TINY_LEARNER, *scene]
    if cli == "evaluate":
        return ["a2catvn_jax.evaluate", "--workdir", str(_evaluate_workdir(folder, path)), "--episodes", "1"]
    if cli == "experiments":
        return ["a2catvn_jax.experiments", "aux", "--seeds", "0", "--episodes", "1", "--root", str(folder / "exp"),
                "--docs", str(folder / "docs"), "--store", str(folder / "store"), "--set", *TINY_LEARNER, *scene]
    if cli == "benchmark":
        return ["a2catvn_jax.benchmark", "env", "--batch-sizes", "2", "--resolutions", "16", "--steps", "1",
                "--no-gl", "--set", *scene]
    assert cli == "random_agent"
    return ["a2catvn_jax.random_agent", "--steps", "1", "--out", str(folder / "random.gif"), "--set", *scene]


COMMANDS = [
    ("train", "cylinder"),
    ("train", "missing"),
    ("pretrain", "mesh"),
    ("train", "hfield"),
    ("evaluate", "freejoint"),
    ("experiments", "small_floor"),
    ("benchmark", "no_floor"),
    ("random_agent", "truncated"),
]


def _check_one_error_line(stderr: str, path: Path, case: str) -> None:
    assert "Traceback" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, stderr
    assert errors[0].startswith(f"error: {path}: "), errors[0]
    assert re.search(CASES[case][1], errors[0]), errors[0]


def test_command_line_prints_one_error_line(scene_dir, tmp_path):
    """`python -m a2catvn_jax.train` in a process of its own: one line, a non-zero exit."""
    path = scene_dir / "cylinder.xml"
    proc = subprocess.run([sys.executable, "-m", *_command("train", path, tmp_path)], cwd=tmp_path,
                          env=dict(os.environ), capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    _check_one_error_line(proc.stderr, path, "cylinder")


@pytest.mark.parametrize("cli, case", COMMANDS)
def test_every_command_prints_one_error_line(scene_dir, tmp_path, monkeypatch, capsys, cli, case):
    """Each module's `main`, as `python -m` calls it (in this process: the test above runs
    one of them in its own), exits non-zero with one error line."""
    import importlib

    path = scene_dir / f"{case}.xml"
    monkeypatch.chdir(tmp_path)
    module, *argv = _command(cli, path, tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(module).main(argv)
    assert exit_info.value.code not in (0, None)
    _check_one_error_line(capsys.readouterr().err, path, case)
