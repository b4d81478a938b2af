"""Tests for the typed YAML configuration system (a2catvn_jax.config)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest
import yaml

from a2catvn_jax.cli import add_config_args, config_from_args
from a2catvn_jax.config import (
    Config,
    ConfigError,
    EnvConfig,
    RenderConfig,
    SceneConfig,
    apply_overrides,
    config_keys,
    from_dict,
    load_config,
    save_config,
    to_dict,
)

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


def _write(tmp_path: Path, text: str, name: str = "cfg.yaml") -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _flat_keys(d: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        out.extend(_flat_keys(v, key) if isinstance(v, dict) else [key])
    return out


# ----------------------------------------------------------------------------- defaults


def test_defaults_load():
    cfg = load_config(None)
    assert cfg == Config()
    assert cfg.env.num_envs == 16
    assert cfg.env.scene.grid == (2, 2)
    assert isinstance(cfg.env.scene.room_size, tuple)
    assert cfg.env.render.culling is True
    assert ConfigError.__mro__[1] is ValueError


def test_config_is_frozen():
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3  # type: ignore[misc]


def test_default_yaml_lists_every_key_with_default():
    data = yaml.safe_load(DEFAULT_YAML.read_text())
    assert _flat_keys(data) == config_keys()
    assert load_config(str(DEFAULT_YAML)) == Config()


def test_empty_file_gives_defaults(tmp_path):
    assert load_config(_write(tmp_path, "# nothing\n")) == Config()


# ----------------------------------------------------------------------- file merging


def test_partial_yaml_merges(tmp_path):
    path = _write(
        tmp_path,
        "seed: 7\nenv:\n  num_envs: 4\n  render:\n    image_size: 84\n  scene:\n",
    )
    cfg = load_config(path)
    assert cfg.seed == 7
    assert cfg.env.num_envs == 4
    assert cfg.env.render.image_size == 84
    assert cfg.env.render.fovy == 60.0  # untouched sibling keeps default
    assert cfg.env.scene == SceneConfig()  # empty section means defaults
    assert cfg.env.goal == "image"


def test_overrides_apply_on_top_of_file(tmp_path):
    path = _write(tmp_path, "env:\n  num_envs: 4\n  goals_per_scene: 3\n")
    cfg = load_config(path, ["env.num_envs=8"])
    assert cfg.env.num_envs == 8
    assert cfg.env.goals_per_scene == 3


# --------------------------------------------------------------------------- overrides


def test_override_types():
    cfg = load_config(
        None,
        [
            "seed=5",
            "env.render.image_size=84",  # int
            "env.success_distance=1",  # float accepts an int
            "env.complexity=0.25",  # float
            "env.grid_resolution=5e-2",  # float with exponent, no dot
            "env.render.culling=false",  # bool
            "env.scene.grid=[3, 4]",  # tuple from list
            "env.scene.room_size=[2, 5.5]",  # tuple of floats accepts ints
            "env.action_set=no_tilt",  # literal
            "env.scene.kind=mjcf",  # literal ...
            "env.scene.mjcf_path=scenes/my house.xml",  # ... with optional str
        ],
    )
    assert cfg.seed == 5
    assert cfg.env.render.image_size == 84
    assert cfg.env.success_distance == 1.0 and isinstance(cfg.env.success_distance, float)
    assert cfg.env.complexity == 0.25
    assert cfg.env.grid_resolution == pytest.approx(0.05)
    assert cfg.env.render.culling is False
    assert cfg.env.scene.grid == (3, 4)
    assert cfg.env.scene.room_size == (2.0, 5.5)
    assert all(isinstance(v, float) for v in cfg.env.scene.room_size)
    assert cfg.env.action_set == "no_tilt"
    assert cfg.env.scene.kind == "mjcf"
    assert cfg.env.scene.mjcf_path == "scenes/my house.xml"


def test_override_optional_back_to_none(tmp_path):
    path = _write(tmp_path, "env:\n  scene:\n    kind: mjcf\n    mjcf_path: a.xml\n")
    assert load_config(path).env.scene.mjcf_path == "a.xml"
    cfg = load_config(path, ["env.scene.kind=house", "env.scene.mjcf_path=null"])
    assert cfg.env.scene.mjcf_path is None


def test_string_key_takes_raw_text():
    cfg = load_config(None, ["env.scene.kind=mjcf", "env.scene.mjcf_path=1e5"])
    assert cfg.env.scene.mjcf_path == "1e5"


def test_last_override_wins():
    assert load_config(None, ["env.num_envs=2", "env.num_envs=3"]).env.num_envs == 3


def test_apply_overrides_on_instance():
    cfg = apply_overrides(Config(), ["env.num_envs=2"])
    assert cfg.env.num_envs == 2
    assert dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, num_envs=16)) == Config()
    with pytest.raises(ConfigError, match="env.num_envs"):
        apply_overrides(Config(), ["env.num_envs=0"])


# ------------------------------------------------------------------------ unknown keys


def test_unknown_top_level_key_override():
    with pytest.raises(ConfigError) as ei:
        load_config(None, ["sed=1"])
    msg = str(ei.value)
    assert "'sed'" in msg and "did you mean 'seed'" in msg
    assert "seed, env" in msg  # valid keys listed
    assert ei.value.key == "sed"


def test_unknown_nested_key_override():
    with pytest.raises(ConfigError) as ei:
        load_config(None, ["env.nm_envs=3"])
    msg = str(ei.value)
    assert "env.nm_envs" in msg and "did you mean 'env.num_envs'" in msg
    assert "num_envs" in msg and "max_tilt_deg" in msg


def test_unknown_key_suggests_key_in_other_section():
    with pytest.raises(ConfigError, match=r"env\.image_size.*did you mean 'env\.render\.image_size'"):
        load_config(None, ["env.image_size=84"])


def test_unknown_keys_in_file(tmp_path):
    with pytest.raises(ConfigError, match=r"'colour'.*Valid keys at the top level"):
        load_config(_write(tmp_path, "colour: 3\n"))
    path = _write(tmp_path, "env:\n  render:\n    imagesize: 32\n", "b.yaml")
    with pytest.raises(ConfigError, match=r"env\.render\.imagesize.*did you mean 'env\.render\.image_size'"):
        load_config(path)


def test_from_dict_direct():
    r = from_dict(RenderConfig, {"image_size": 32})
    assert r == RenderConfig(image_size=32)
    with pytest.raises(ConfigError, match=r"env\.render\.fovvy"):
        from_dict(RenderConfig, {"fovvy": 3.0}, path="env.render")
    assert from_dict(RenderConfig, {"culling": "false"}).culling is False
    assert to_dict(Config())["env"]["scene"]["grid"] == [2, 2]


# ------------------------------------------------------------------ types and values


@pytest.mark.parametrize(
    "override, key, fragment",
    [
        ("env.num_envs=abc", "env.num_envs", "expected an integer"),
        ("env.num_envs=2.5", "env.num_envs", "expected an integer"),
        ("env.num_envs=true", "env.num_envs", "expected an integer"),
        ("env.complexity=high", "env.complexity", "expected a number"),
        ("env.complexity=.nan", "env.complexity", "finite"),
        ("env.render.culling=yes", "env.render.culling", "expected true or false"),
        ("env.render.culling=1", "env.render.culling", "expected true or false"),
        ("env.scene.grid=3", "env.scene.grid", "expected a list of 2 integers"),
        ("env.scene.grid=[1, 2, 3]", "env.scene.grid", "expected a list of 2 integers"),
        ("env.scene.grid=[1, x]", "env.scene.grid[1]", "expected an integer"),
        ("train.replay_warmup=yes", "train.replay_warmup", "expected true or false"),
        ("train.reward_prediction_zero_fraction=half", "train.reward_prediction_zero_fraction", "expected a number"),
    ],
)
def test_wrong_type(override, key, fragment):
    with pytest.raises(ConfigError) as ei:
        load_config(None, [override])
    assert str(ei.value).startswith(key + ":")
    assert fragment in str(ei.value)


@pytest.mark.parametrize(
    "override, key, fragment",
    [
        ("seed=-1", "seed", "[0, 2**31)"),
        ("env.num_envs=0", "env.num_envs", ">= 1"),
        ("env.goals_per_scene=0", "env.goals_per_scene", ">= 1"),
        ("env.max_episode_steps=0", "env.max_episode_steps", ">= 1"),
        ("env.success_distance=0", "env.success_distance", "> 0"),
        ("env.agent_radius=1.0", "env.agent_radius", "(0, 1)"),
        ("env.camera_height=-1", "env.camera_height", "> 0"),
        ("env.grid_resolution=0", "env.grid_resolution", "(0, 1]"),
        ("env.complexity=1.5", "env.complexity", "[0, 1]"),
        ("env.position_noise=-0.1", "env.position_noise", ">= 0"),
        ("env.heading_noise_deg=-1", "env.heading_noise_deg", ">= 0"),
        ("env.max_tilt_deg=61", "env.max_tilt_deg", "[0, 60]"),
        ("env.scene.num_scenes=0", "env.scene.num_scenes", ">= 1"),
        ("env.scene.grid=[0, 2]", "env.scene.grid", ">= 1"),
        ("env.scene.room_size=[1.0, 4.0]", "env.scene.room_size", ">= 1.5"),
        ("env.scene.room_size=[4.0, 3.0]", "env.scene.room_size", "exceeds maximum"),
        ("env.render.image_size=8", "env.render.image_size", "too small for the network"),
        ("env.render.image_size=1024", "env.render.image_size", "too large"),
        ("env.render.fovy=10", "env.render.fovy", "(10, 120)"),
        ("env.render.column_candidates=0", "env.render.column_candidates", ">= 1"),
        ("train.reward_prediction_zero_fraction=1.5", "train.reward_prediction_zero_fraction", "[0, 1]"),
        ("train.reward_prediction_zero_fraction=-0.1", "train.reward_prediction_zero_fraction", "[0, 1]"),
    ],
)
def test_out_of_range(override, key, fragment):
    with pytest.raises(ConfigError) as ei:
        load_config(None, [override])
    assert str(ei.value).startswith(key + ":")
    assert fragment in str(ei.value)
    assert ei.value.key == key


def test_bad_literal_lists_choices():
    with pytest.raises(ConfigError) as ei:
        load_config(None, ["env.scene.kind=castle"])
    msg = str(ei.value)
    assert msg.startswith("env.scene.kind:") and "'castle'" in msg
    for choice in ("house", "room", "maze", "mjcf"):
        assert repr(choice) in msg


@pytest.mark.parametrize("key, bad, choices", [
    ("train.reward_prediction_loss", "hinge", ("softmax", "sigmoid")),
    ("train.reward_prediction_target", "third_frame", ("last_frame", "next_frame")),
    ("train.pixel_control_reward", "depth", ("luminance", "rgb")),
])
def test_method_choices(key, bad, choices):
    """The method settings of docs/method.md: each bad value is a one-line error naming the
    key and the choices."""
    with pytest.raises(ConfigError) as ei:
        load_config(None, [f"{key}={bad}"])
    msg = str(ei.value)
    assert msg.startswith(f"{key}:") and repr(bad) in msg and "\n" not in msg
    for choice in choices:
        assert repr(choice) in msg
        assert getattr(load_config(None, [f"{key}={choice}"]).train, key.split(".")[1]) == choice


def test_cross_field_checks():
    with pytest.raises(ConfigError) as ei:
        load_config(None, ["env.scene.height=1.05"])
    assert "env.scene.height" in str(ei.value) and "env.camera_height" in str(ei.value)

    with pytest.raises(ConfigError, match=r"env\.render\.fovy / 2 \+ env\.max_tilt_deg"):
        load_config(None, ["env.render.fovy=110", "env.max_tilt_deg=30"])
    load_config(None, ["env.render.fovy=100", "env.max_tilt_deg=30"])  # 80 < 85 is fine

    with pytest.raises(ConfigError, match="room-type goals need houses with rooms"):
        load_config(None, ["env.goal=room", "env.scene.kind=maze"])
    assert load_config(None, ["env.goal=room"]).env.goal == "room"

    with pytest.raises(ConfigError, match=r"^env\.stop_action: the synthetic test bench has no stop action: "
                                          r"env\.stop_action=true needs env\.kind='mujoco'$"):
        load_config(None, ["env.kind=synthetic", "env.stop_action=true"])
    assert load_config(None, ["env.stop_action=true"]).env.stop_action

    with pytest.raises(ConfigError, match=r"^train\.rollout_length: reward prediction .* must be >= 4, got 3$"):
        load_config(None, ["train.rollout_length=3", "train.replay_size=30", "train.reward_prediction_target=next_frame"])
    load_config(None, ["train.rollout_length=3", "train.replay_size=30"])  # 3 frames fit
    load_config(None, ["train.rollout_length=2", "train.replay_size=30", "train.loss_weights.reward_prediction=0"])

    with pytest.raises(ConfigError, match=r"env\.scene\.mjcf_path: required"):
        load_config(None, ["env.scene.kind=mjcf"])
    with pytest.raises(ConfigError, match=r"env\.scene\.mjcf_path: only allowed"):
        load_config(None, ["env.scene.mjcf_path=a.xml"])


# ------------------------------------------------------------ malformed overrides


def test_section_override_is_error():
    with pytest.raises(ConfigError, match=r"env\.scene: is a section"):
        load_config(None, ["env.scene=house"])
    with pytest.raises(ConfigError, match=r"env: is a section"):
        load_config(None, ["env={num_envs: 3}"])


def test_path_through_leaf_is_error():
    with pytest.raises(ConfigError, match=r"env\.num_envs: is a value, not a section"):
        load_config(None, ["env.num_envs.x=1"])


@pytest.mark.parametrize("override", ["env.num_envs", "=3", "env..num_envs=3", ".seed=1"])
def test_malformed_override(override):
    with pytest.raises(ConfigError, match="malformed override"):
        load_config(None, [override])


def test_unparsable_override_value():
    with pytest.raises(ConfigError, match=r"env\.scene\.grid: cannot parse"):
        load_config(None, ["env.scene.grid=[1, 2"])


# -------------------------------------------------------------------------- files


def test_missing_file(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="not found") as ei:
        load_config(str(missing))
    assert str(missing) in str(ei.value)


def test_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(_write(tmp_path, "env:\n  num_envs: [1, 2\n"))


def test_duplicate_key_is_invalid(tmp_path):
    with pytest.raises(ConfigError, match="duplicate key 'seed'"):
        load_config(_write(tmp_path, "seed: 1\nseed: 2\n"))


def test_top_level_not_mapping(tmp_path):
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load_config(_write(tmp_path, "- 1\n- 2\n"))


def test_section_not_mapping_in_file(tmp_path):
    with pytest.raises(ConfigError, match=r"env\.render: is a section"):
        load_config(_write(tmp_path, "env:\n  render: 64\n"))


def test_several_files_merge_in_order(tmp_path):
    first = _write(tmp_path, "seed: 1\nenv:\n  num_envs: 4\n  render:\n    image_size: 32\n    fovy: 70\n"
                             "  scene:\n    grid: [2, 3]\n", "a.yaml")
    second = _write(tmp_path, "env:\n  num_envs: 8\n  render:\n    image_size: 48\n  scene:\n    grid: [1, 1]\n",
                    "b.yaml")
    cfg = load_config([first, second], ["env.num_envs=2"])
    assert (cfg.seed, cfg.env.render.fovy) == (1, 70.0)  # only in the first file
    assert (cfg.env.render.image_size, cfg.env.scene.grid) == (48, (1, 1))  # the later file wins, lists whole
    assert cfg.env.num_envs == 2  # overrides win over every file
    assert load_config([second, first]).env.render.image_size == 32
    assert load_config([first]) == load_config(first) == load_config(Path(first))
    assert load_config([]) == Config()


def test_missing_second_file(tmp_path):
    first = _write(tmp_path, "seed: 1\n")
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="config file not found") as ei:
        load_config([first, missing])
    assert str(missing) in str(ei.value)


def test_authors_network_preset_lists_only_agent_keys():
    preset = Path(__file__).resolve().parents[1] / "configs" / "presets" / "authors_network.yaml"
    assert list(yaml.safe_load(preset.read_text())) == ["agent"]
    quickstart = DEFAULT_YAML.parent / "quickstart.yaml"
    cfg = load_config([quickstart, preset], ["env.render.image_size=48"])
    assert cfg.agent.conv_kernels == (7, 4, 4, 1) and cfg.env.scene.kind == "room"


# ------------------------------------------------------------------ save and load


def test_save_load_round_trip(tmp_path):
    cfg = load_config(
        None,
        [
            "seed=11",
            "env.goal=object",
            "env.grid_resolution=0.05",
            "env.render.culling=false",
            "env.scene.kind=mjcf",
            "env.scene.mjcf_path=1e5",  # string that looks like a float
            "env.scene.room_size=[2.5, 6.0]",
        ],
    )
    path = tmp_path / "sub" / "saved.yaml"
    save_config(cfg, str(path))
    assert load_config(str(path)) == cfg
    save_config(Config(), path)
    assert load_config(path) == Config()


# ------------------------------------------------------------------------ argparse


def test_argparse_integration(tmp_path):
    path = _write(tmp_path, "env:\n  num_envs: 4\n  render:\n    image_size: 32\n")
    parser = argparse.ArgumentParser()
    add_config_args(parser)
    args = parser.parse_args(
        ["--config", path, "--set", "seed=1", "env.num_envs=2", "--set", "env.render.culling=false"]
    )
    cfg = config_from_args(args)
    assert cfg.seed == 1
    assert cfg.env.num_envs == 2
    assert cfg.env.render.image_size == 32
    assert cfg.env.render.culling is False


def test_argparse_several_config_files(tmp_path):
    first = _write(tmp_path, "env:\n  num_envs: 4\n  render:\n    image_size: 32\n", "a.yaml")
    second = _write(tmp_path, "env:\n  num_envs: 6\n", "b.yaml")
    parser = add_config_args(argparse.ArgumentParser())
    args = parser.parse_args(["--config", first, second, "--set", "seed=3"])
    assert args.config == [first, second]
    cfg = config_from_args(args)
    assert (cfg.env.num_envs, cfg.env.render.image_size, cfg.seed) == (6, 32, 3)
    assert config_from_args(parser.parse_args(["--config", second, first])).env.num_envs == 4
    with pytest.raises(ConfigError, match="config file not found"):
        config_from_args(parser.parse_args(["--config", first, str(tmp_path / "missing.yaml")]))


def test_argparse_defaults():
    parser = add_config_args(argparse.ArgumentParser())
    assert config_from_args(parser.parse_args([])) == Config()


def test_env_config_defaults_are_valid():
    EnvConfig().validate("env")
    SceneConfig().validate("env.scene")
    RenderConfig().validate("env.render")
    Config().validate()


def test_paper_config_has_table_one():
    """configs/paper.yaml carries every value of the paper's Table I."""
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "paper.yaml")
    t, w = cfg.train, cfg.train.loss_weights
    assert (t.gamma, cfg.env.max_episode_steps, t.rollout_length, t.total_frames, cfg.env.num_envs, t.replay_size) == (
        0.99, 900, 20, 40_000_000, 16, 2000)
    assert (t.rmsprop_decay, t.rmsprop_eps, t.learning_rate, t.lr_schedule, t.max_grad_norm) == (
        0.99, 1e-5, 7e-4, "linear", 0.5)
    assert (w.entropy, w.actor, w.critic, w.off_policy_critic, w.pixel_control, w.reward_prediction) == (
        0.001, 1.0, 0.5, 1.0, 0.05, 1.0)
    assert (w.depth, w.segmentation, w.target_segmentation) == (0.1, 0.1, 0.1)
    assert (t.pixel_control_gamma, t.pixel_control_cell, t.aux_downsize) == (0.9, 4, 4)
    assert t.curriculum and t.curriculum_complexity == (0.3, 1.0) and t.curriculum_frames == (5_000_000, 10_000_000)
    assert cfg.env.render.image_size == 174


def test_evaluation_during_training_settings():
    """`train.eval`: house sets and policies are lists of the known names (one name alone
    is a list of one), none twice; it needs the MuJoCo world, and held-out houses need
    generated ones. Each bad value is one line naming its key."""
    ec = load_config(None, ["train.eval.every=10", "train.eval.houses=[held-out, train]",
                            "train.eval.policies=greedy"]).train.eval
    assert (ec.every, ec.houses, ec.policies, ec.episodes, ec.seed) == (10, ("held-out", "train"), ("greedy",), 100, 1000)
    assert load_config(None).train.eval.every == 0  # off by default
    for overrides, key, fragment in [
        (["train.eval.houses=[mars]"], "train.eval.houses[0]", "'held-out'"),
        (["train.eval.houses=[]"], "train.eval.houses", "one or more of 'train', 'held-out', 'new-targets'"),
        (["train.eval.policies=[greedy, greedy]"], "train.eval.policies", "lists a value twice"),
        (["train.eval.policies=[oracle]"], "train.eval.policies[0]", "'sample' or 'greedy'"),
        (["train.eval.every=-1"], "train.eval.every", ">= 0"),
        (["train.eval.every=5", "env.kind=synthetic"], "train.eval.every", "needs the MuJoCo world"),
        (["train.eval.every=5", "env.scene.kind=mjcf", "env.scene.mjcf_path=x.xml"], "train.eval.houses",
         "held-out houses need generated scenes"),
    ]:
        with pytest.raises(ConfigError) as ei:
            load_config(None, overrides)
        msg = str(ei.value)
        assert msg.startswith(key + ":") and fragment in msg and "\n" not in msg, msg
    # Without evaluation the same settings are not checked against the environment.
    load_config(None, ["env.kind=synthetic", "train.eval.houses=[held-out]"])
