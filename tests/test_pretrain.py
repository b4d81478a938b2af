"""Supervised pre-training and starting a run from it (`--init-from`)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import make_update
from a2catvn_jax.config import load_config
from a2catvn_jax.env import NavEnv
from a2catvn_jax.run.checkpoint import Checkpointer
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.pretraining import PRETRAINED_DIR, PretrainError, load_matching, make_dataset, pretrain
from a2catvn_jax.run.training import train
from tiny import TINY_LEARNER

TINY = TINY_LEARNER + [
    "env.scene.kind=room",
    "env.scene.num_scenes=2",
    "pretrain.dataset_size=256",
    "pretrain.epochs=4",
    "pretrain.batch_size=32",
]
quiet = lambda *_: None  # noqa: E731


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("pretrain")
    params = pretrain(load_config(None, TINY), workdir, log=quiet)
    return workdir, params


def test_pretraining_lowers_the_losses(pretrained):
    workdir, _ = pretrained
    rows = read_jsonl(workdir / "pretrain_metrics.jsonl")
    assert [r["epoch"] for r in rows] == [1, 2, 3, 4]
    for term in ("depth", "segmentation", "target_segmentation", "total"):
        assert rows[-1][f"loss/{term}"] < 0.8 * rows[0][f"loss/{term}"], term
    assert (workdir / PRETRAINED_DIR).is_dir() and (workdir / "config.yaml").exists()


def test_dataset_frames_are_rendered_from_free_poses():
    cfg = load_config(None, TINY)
    env = NavEnv(cfg.env)
    data = make_dataset(cfg, env, 70, jax.random.PRNGKey(1))
    assert data["rgb"].shape == (70, 16, 16, 3) and data["rgb"].dtype == np.uint8
    assert data["depth_gt"].shape == (70, 4, 4) and np.all(data["depth_gt"] > 0)  # closed rooms: every ray hits
    assert data["seg_gt"].shape == (70, 4, 4, 3)
    scene = np.arange(70) % 2
    assert np.all(data["target"] // cfg.env.goals_per_scene == scene)
    assert len({d.tobytes() for d in data["rgb"]}) == 70  # distinct views


def test_init_from_loads_the_pretrained_layers(pretrained, tmp_path):
    pre_dir, pre_params = pretrained
    lines = []
    train(load_config(None, TINY), tmp_path, max_updates=1, progress=False, log=lines.append, init_from=pre_dir)
    assert any("conv1, conv2, conv3, conv4, vn" in line and "lstm" in line for line in lines)
    cfg = load_config(None, TINY)
    env = NavEnv(cfg.env)
    init = make_update(env, make_networks(cfg, env.num_actions), cfg).init
    fresh = init(jax.random.PRNGKey(0))
    state, _ = Checkpointer(tmp_path, create=False).restore(jax.eval_shape(init, jax.random.PRNGKey(0)), step=0)
    got, want = state.params["params"], pre_params["params"]
    np.testing.assert_array_equal(np.asarray(got["conv1"]["kernel"]), np.asarray(want["conv1"]["kernel"]))
    assert not np.allclose(np.asarray(got["conv1"]["kernel"]), np.asarray(fresh.params["params"]["conv1"]["kernel"]))
    np.testing.assert_array_equal(np.asarray(got["policy"]["kernel"]), np.asarray(fresh.params["params"]["policy"]["kernel"]))


def test_pretraining_errors(pretrained, tmp_path):
    workdir, _ = pretrained
    with pytest.raises(PretrainError, match="already exists"):
        pretrain(load_config(None, TINY), workdir, log=quiet)
    off = ["train.loss_weights.depth=0", "train.loss_weights.segmentation=0", "train.loss_weights.target_segmentation=0"]
    with pytest.raises(PretrainError, match="non-zero"):
        pretrain(load_config(None, TINY + off), tmp_path / "none", log=quiet)
    with pytest.raises(PretrainError, match="no pre-trained parameters"):
        load_matching({}, tmp_path)
