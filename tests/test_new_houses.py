"""`train.new_houses_every`: the training houses replaced by newly generated ones during
a run, with the compiled update taking them as data; exact resume across a replacement."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.env.world import new_houses
from a2catvn_jax.configio import ConfigError
from a2catvn_jax.env.scenes.errors import SceneError
from a2catvn_jax.run.training import train
from tiny import TINY_ROOM

# Two rooms, new ones every 2 updates: updates 1-2 in the run's own rooms, 3-4 in the
# first new set, 5 in the second.
EVERY = 2
NEW_HOUSES = TINY_ROOM + ["env.scene.num_scenes=2", "env.new_scene_per_episode=true", "train.log_every=1",
                          "train.checkpoint_every=100", f"train.new_houses_every={EVERY}"]


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(tree))]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """(environment, state, log lines) of 5 updates in one go."""
    lines = []
    env, state, _ = train(load_config(None, NEW_HOUSES), tmp_path_factory.mktemp("straight"), max_updates=5,
                          progress=False, log=lines.append)
    return env, state, lines


def test_each_set_of_new_houses_is_built_once_and_logged(straight):
    _, state, lines = straight
    assert int(state.update) == 5
    assert [line.split(":")[0] for line in lines if line.startswith("new houses ")] == [
        f"new houses every {EVERY} updates (32 frames)", "new houses 1", "new houses 2"]


def test_the_run_ends_in_the_second_new_houses(straight):
    env, state, _ = straight
    own = env.world.arrays
    second, _ = new_houses(env.world, 2)
    obs = state.env_state.obs
    k = obs.target_index

    def targets(world):
        return np.asarray(world.target_rgb).reshape((-1,) + obs.target_rgb.shape[1:])[np.asarray(k)]

    np.testing.assert_array_equal(np.asarray(obs.target_rgb), targets(second))
    assert not np.array_equal(targets(second), targets(own))
    assert not np.array_equal(np.asarray(second.free), np.asarray(own.free))


def test_resume_across_new_houses_is_exact(straight, tmp_path):
    """Stopped inside a set (update 3) and at a replacement (update 4: the checkpoint
    precedes it), the run resumes to the parameters and state of the run in one go."""
    cfg = load_config(None, NEW_HOUSES)
    quiet = lambda *_: None  # noqa: E731
    train(cfg, tmp_path, max_updates=3, progress=False, log=quiet)
    train(cfg, tmp_path, resume=True, max_updates=1, progress=False, log=quiet)
    lines = []
    _, resumed, _ = train(cfg, tmp_path, resume=True, max_updates=1, progress=False, log=lines.append)
    assert any(line.startswith("new houses 2:") for line in lines), lines
    for a, b in zip(_leaves(resumed), _leaves(straight[1])):
        np.testing.assert_array_equal(a, b)


def test_two_updates_per_call_take_the_new_houses_too(straight, tmp_path):
    """The device loop of several updates per call (the default on an accelerator) passes
    the houses to each of its updates: the one-per-call run's parameters, through a resume."""
    cfg = load_config(None, NEW_HOUSES + ["train.log_every=2", "train.updates_per_call=2"])
    quiet = lambda *_: None  # noqa: E731
    train(cfg, tmp_path, max_updates=3, progress=False, log=quiet)
    _, looped, _ = train(cfg, tmp_path, resume=True, max_updates=2, progress=False, log=quiet)
    assert int(looped.update) == 5
    for a, b in zip(_leaves(looped.params), _leaves(straight[1].params)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-6)


def test_new_houses_are_other_houses_the_same_each_time(straight):
    env = straight[0]
    first, drawn = new_houses(env.world, 1)
    assert drawn >= env.num_scenes
    assert not np.array_equal(np.asarray(first.target_rgb), np.asarray(env.world.arrays.target_rgb))
    assert not np.array_equal(np.asarray(first.free), np.asarray(env.world.arrays.free))
    again, _ = new_houses(env.world, 1)  # the same generation is the same houses (so a resume rebuilds them)
    for a, b in zip(_leaves(first), _leaves(again)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(SceneError, match="^new houses 3: only 0 of 0 drawn scenes fit"):
        new_houses(env.world, 3, draws=0)


TWO_DEVICES = textwrap.dedent(
    """
    import os, sys
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    import jax, numpy as np
    sys.path.insert(0, "tests")
    from test_new_houses import NEW_HOUSES
    from a2catvn_jax.config import load_config
    from a2catvn_jax.run.training import train

    lines = []
    _, state, _ = train(load_config(None, NEW_HOUSES), sys.argv[1] + "/run", max_updates=5, progress=False,
                        log=lines.append)
    assert any("4 environments on 2 cpu devices" in line for line in lines), lines
    assert any(line.startswith("new houses 2:") for line in lines), lines
    assert len(state.env_state.obs.rgb.addressable_shards) == 2
    leaves = jax.tree_util.tree_leaves(jax.device_get(state.params))
    np.savez(sys.argv[1] + "/params.npz", *[np.asarray(x) for x in leaves])
    print("OK")
    """
)


def test_new_houses_on_two_devices_give_the_one_device_result(straight, tmp_path):
    """The environments split over two devices, the new houses replicated on both: the
    parameters of the one-device run in one go."""
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", TWO_DEVICES, str(tmp_path)], cwd=root, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("OK"), proc.stderr[-3000:]
    split = np.load(tmp_path / "params.npz")
    whole = _leaves(straight[1].params)
    assert len(split.files) == len(whole)
    for i, b in enumerate(whole):
        np.testing.assert_allclose(split[f"arr_{i}"], b, rtol=2e-4, atol=2e-6)


@pytest.mark.parametrize("setting, message", [
    (["env.kind=synthetic"], "train.new_houses_every: new houses need generated scenes; env.kind is 'synthetic'"),
    (["env.scene.kind=mjcf", "env.scene.mjcf_path=tests/data/moving_scene.xml"], "train.new_houses_every: new houses need generated scenes; env.scene.kind is 'mjcf'"),
    (["env.render.backend=mjx"], "train.new_houses_every: new houses are rendered by the ray caster"),
])
def test_settings_that_cannot_have_new_houses_are_one_line_errors(setting, message):
    with pytest.raises(ConfigError) as e:
        load_config(None, NEW_HOUSES + setting)
    assert str(e.value).startswith(message) and "\n" not in str(e.value)
