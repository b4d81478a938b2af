"""A run written by the previous layout of the training state (format 1: observations,
info and replayed rollouts as dicts with one `done` flag) resumes under the current one.

tests/data/format1_run holds such a run of the tiny learner after 3 updates, and the
parameters it reaches after 5. Resumed for 2 more updates, it reaches the same
parameters to float32 rounding (no episode ends in those updates, so the new time-out
handling plays no part). The reference was written by the code that wrote the run,
and written again when the update's sampling of reward-prediction windows changed
(same distribution, other draws): by the current code resumed from the same files.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import make_update
from a2catvn_jax.env import NavEnv
from a2catvn_jax.run.checkpoint import FORMAT, Checkpointer, read_run_config
from a2catvn_jax.run.training import train

DATA = Path(__file__).resolve().parent / "data" / "format1_run"


def test_format1_run_resumes_exactly(tmp_path):
    run = tmp_path / "run"
    shutil.copytree(DATA, run)
    cfg = read_run_config(run)
    ckpt = Checkpointer(run, create=False)
    assert "format" not in json.loads((run / "checkpoints" / "3" / "meta" / "metadata").read_text())
    env = NavEnv(cfg.env)
    init = make_update(env, make_networks(cfg, env.num_actions), cfg).init
    state, meta = ckpt.restore(jax.eval_shape(init, jax.random.PRNGKey(0)), cfg)
    ckpt.close()
    assert meta["update"] == 3 and int(state.update) == 3
    info, obs = state.env_state.info, state.env_state.obs
    np.testing.assert_array_equal(np.asarray(obs.target_index), np.asarray(env.target_index(info.scene, info.goal)))
    np.testing.assert_array_equal(np.asarray(obs.target_rgb), np.asarray(env.target_images()["rgb"])[np.asarray(obs.target_index)])
    assert state.replay.data.terminated.shape == state.replay.data.reward.shape

    _, resumed, _ = train(cfg, run, resume=True, max_updates=2, progress=False, log=lambda *_: None)
    want = np.load(DATA / "params_after_5_updates.npz")
    got = [np.asarray(x) for x in jax.tree_util.tree_leaves(resumed.params)]
    assert len(got) == len(want.files)
    for x, k in zip(got, want.files):  # to float32 rounding: the stored values come from another compile
        np.testing.assert_allclose(x, want[k], rtol=1e-5, atol=1e-7)
    latest = Checkpointer(run, create=False)
    assert latest.latest() == 5
    assert json.loads((run / "checkpoints" / "5" / "meta" / "metadata").read_text())["format"] == FORMAT
