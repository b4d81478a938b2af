"""The update runs with the environment axis split over devices and gives the same result.

Runs in a subprocess with two host CPU devices (XLA_FLAGS must be set before JAX starts).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

SCRIPT = textwrap.dedent(
    """
    import os
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh
    from a2catvn_jax.config import load_config
    from a2catvn_jax.agent.networks import make_networks
    from a2catvn_jax.agent.update import make_update, shard
    from a2catvn_jax.env import make_env

    OVERRIDES = ["env.kind=synthetic", "env.num_envs=4", "env.render.image_size=16", "env.scene.num_scenes=1",
        "env.scene.grid=[1,1]", "env.goals_per_scene=2", "train.rollout_length=4", "train.replay_size=8",
        "train.replay_batch=2", "agent.conv_channels=[4,8,8,8]", "agent.dense_size=16", "agent.core_size=16"]
    cfg = load_config(None, OVERRIDES)
    env = make_env(cfg.env)
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    assert len(jax.devices()) == 2
    ts = init(jax.random.PRNGKey(0))
    plain = jax.tree_util.tree_map(jnp.copy, ts)
    sharded = shard(ts, Mesh(np.array(jax.devices()), ("batch",)))
    for _ in range(2):
        sharded, m_sharded = update(sharded)
        plain, m_plain = update(plain)
    assert sharded.env_state.obs.rgb.sharding.spec == jax.sharding.PartitionSpec("batch")
    assert sharded.replay.data.rgb.sharding.spec == jax.sharding.PartitionSpec(None, None, "batch")
    assert len(sharded.env_state.obs.rgb.addressable_shards) == 2
    assert sharded.env_state.obs.rgb.addressable_shards[0].data.shape[0] == 2
    for a, b in zip(jax.tree_util.tree_leaves(sharded.params), jax.tree_util.tree_leaves(plain.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(sharded.env_state.info.pose), np.asarray(plain.env_state.info.pose))
    odd = load_config(None, [*OVERRIDES, "train.replay_envs=3"])
    abstract = jax.eval_shape(make_update(env, make_networks(odd, env.num_actions), odd).init, jax.random.PRNGKey(0))
    try:
        shard(abstract, Mesh(np.array(jax.devices()), ("batch",)))
        raise AssertionError("3 kept environments split over 2 devices")
    except ValueError as e:
        assert "train.replay_envs" in str(e) and "multiple of 2" in str(e), e
    print("OK")
    """
)


def test_update_with_environments_sharded_over_two_devices():
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=root, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("OK"), proc.stderr[-3000:]
