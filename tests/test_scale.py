"""Training at scale: many updates per call of the compiled loop, and the environments
split over every local device. Both give the results of one update per call on one
device, to float rounding.

The two-device run is a subprocess with two host CPU devices (XLA_FLAGS must be set
before JAX starts).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.configio import ConfigError
from a2catvn_jax.run.distributed import DevicesError, devices_for
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.training import next_stop, train, updates_per_call
from tiny import TINY_ROOM, TINY_SYNTHETIC

QUIET = dict(progress=False, log=lambda *_: None)


def _leaves(state):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state))]


def test_calls_stop_at_log_checkpoint_and_call_boundaries():
    cfg = load_config(None, TINY_SYNTHETIC + ["train.log_every=4", "train.checkpoint_every=6", "train.updates_per_call=3"])
    assert updates_per_call(cfg, "cpu") == updates_per_call(cfg, "gpu") == 3
    stops, update = [], 0
    while update < 13:
        update = next_stop(update, 13, cfg, 3)
        stops.append(update)
    assert stops == [3, 4, 6, 8, 9, 12, 13]
    default = load_config(None, TINY_SYNTHETIC + ["train.log_every=5", "train.checkpoint_every=500"])
    assert updates_per_call(default, "cpu") == 1 and updates_per_call(default, "gpu") == 5
    assert next_stop(0, 100, default, 5) == 5 and next_stop(7, 100, default, 5) == 10
    assert next_stop(7, 100, default, 1) == 8
    evaluated = load_config(None, TINY_ROOM + ["train.log_every=5", "train.checkpoint_every=500", "train.eval.every=7"])
    assert [next_stop(u, 100, evaluated, 5) for u in (0, 5, 7, 10, 14)] == [5, 7, 10, 14, 15]


def test_many_updates_per_call_match_one_per_call_and_resume_exactly(tmp_path):
    """Six updates as two calls of three (`train.updates_per_call`), with a
    stop and a resume between them, against six calls of one: the same parameters and the
    same logged losses, to float rounding; the per-call run's log rows are the means of
    the one-per-call run's."""
    one = load_config(None, TINY_SYNTHETIC + ["train.log_every=1", "train.checkpoint_every=3", "train.updates_per_call=1"])
    _, single, _ = train(one, tmp_path / "one", max_updates=6, **QUIET)
    three = load_config(None, TINY_SYNTHETIC + ["train.log_every=3", "train.checkpoint_every=3", "train.updates_per_call=3"])
    train(three, tmp_path / "three", max_updates=3, **QUIET)
    _, looped, _ = train(three, tmp_path / "three", resume=True, max_updates=3, **QUIET)
    assert int(looped.update) == 6
    for a, b in zip(_leaves(looped.params), _leaves(single.params)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-6)
    for a, b in zip(_leaves(looped.env_state.info), _leaves(single.env_state.info)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    per_update = read_jsonl(tmp_path / "one" / "metrics.jsonl")
    per_call = read_jsonl(tmp_path / "three" / "metrics.jsonl")
    assert [r["update"] for r in per_call] == [3, 6]
    for row, part in zip(per_call, (per_update[:3], per_update[3:])):
        for key in ("loss/total", "loss/actor", "loss/depth", "learning_rate", "grad_norm"):
            np.testing.assert_allclose(row[key], np.mean([r[key] for r in part]), rtol=2e-3, err_msg=key)
        assert row["episodes"] == sum(r["episodes"] for r in part)


def test_a_batch_that_does_not_split_over_the_devices_is_one_line():
    devices = jax.local_devices()
    with pytest.raises(DevicesError, match=rf"^--devices {len(devices) + 1}: this machine has {len(devices)} "):
        devices_for(4, len(devices) + 1)
    assert devices_for(4, None) == devices


TWO_DEVICES = textwrap.dedent(
    """
    import os, sys
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    import jax, numpy as np
    sys.path.insert(0, "tests")
    from tiny import TINY_SYNTHETIC
    from a2catvn_jax.config import load_config
    from a2catvn_jax.run.training import train
    from a2catvn_jax.train import main

    assert len(jax.local_devices()) == 2
    tmp = sys.argv[1]
    cfg = load_config(None, TINY_SYNTHETIC + ["train.log_every=2"])
    lines = []
    _, split, _ = train(cfg, tmp + "/split", max_updates=4, progress=False, log=lines.append)
    assert any("4 environments on 2 cpu devices" in line for line in lines), lines
    assert len(split.env_state.obs.rgb.addressable_shards) == 2
    assert split.env_state.obs.rgb.sharding.spec == jax.sharding.PartitionSpec("batch")
    _, whole, _ = train(cfg, tmp + "/whole", max_updates=4, progress=False, log=lambda *_: None, devices=1)
    assert len(whole.env_state.obs.rgb.addressable_shards) == 1
    for a, b in zip(jax.tree_util.tree_leaves(jax.device_get(split.params)),
                    jax.tree_util.tree_leaves(jax.device_get(whole.params))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=2e-6)
    np.testing.assert_allclose(np.asarray(split.env_state.info.pose), np.asarray(whole.env_state.info.pose),
                               rtol=1e-4, atol=1e-5)
    # Two gradient steps per rollout, each on every other environment: both devices hold a
    # share of each step's environments, and the result is still one device's.
    halves = load_config(None, TINY_SYNTHETIC + ["env.num_envs=8", "train.minibatches=2", "train.log_every=2"])
    quiet = lambda *_: None  # noqa: E731
    _, split, _ = train(halves, tmp + "/halves_split", max_updates=2, progress=False, log=quiet)
    _, whole, _ = train(halves, tmp + "/halves_whole", max_updates=2, progress=False, log=quiet, devices=1)
    for a, b in zip(jax.tree_util.tree_leaves(jax.device_get(split.params)),
                    jax.tree_util.tree_leaves(jax.device_get(whole.params))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=2e-6)
    # The sharded run resumes from its checkpoint on the devices it ran on.
    _, resumed, _ = train(cfg, tmp + "/split", resume=True, max_updates=2, progress=False, log=lambda *_: None)
    assert int(resumed.update) == 6 and len(resumed.env_state.obs.rgb.addressable_shards) == 2
    try:
        main(["--set", *TINY_SYNTHETIC, "env.num_envs=3", "--workdir", tmp + "/odd", "--updates", "1", "--no-progress"])
        raise AssertionError("3 environments over 2 devices")
    except SystemExit as e:
        assert e.code == 1
    print("OK")
    """
)


def test_environments_split_over_two_devices_give_the_one_device_result(tmp_path):
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", TWO_DEVICES, str(tmp_path)], cwd=root, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("OK"), proc.stderr[-3000:]
    assert "error: env.num_envs=3 environments cannot be split evenly over 2 devices" in proc.stderr
    assert proc.stderr.count("\n") >= 1 and "Traceback" not in proc.stderr


def test_learning_rate_scales_with_the_batch():
    from a2catvn_jax.agent.update import learning_rate

    def lr(envs, scaling):
        return learning_rate(load_config(None, [f"env.num_envs={envs}", f"train.lr_scaling={scaling}"]))

    assert lr(256, "none") == pytest.approx(7e-4)
    assert lr(256, "linear") == pytest.approx(7e-4 * 16) and lr(256, "sqrt") == pytest.approx(7e-4 * 4)
    assert lr(16, "linear") == pytest.approx(7e-4) and lr(4, "sqrt") == pytest.approx(7e-4 / 2)


def test_learning_rate_warms_up_then_follows_its_schedule():
    """`train.lr_warmup_frames`: a linear rise over ceil(W / frames per update) updates
    (here 16 environments x 20 steps = 320 frames: 1,000 frames are 4 updates), then the
    paper's linear decay; without it the schedule is the decay alone."""
    from a2catvn_jax.agent.update import learning_rate_schedule

    keys = ["train.total_frames=32000", "train.lr_scaling=linear", "env.num_envs=16"]  # 100 updates, lr 7e-4
    plain = learning_rate_schedule(load_config(None, keys))
    warm = learning_rate_schedule(load_config(None, keys + ["train.lr_warmup_frames=1000"]))
    decay = [7e-4 * (100 - n) / 100 for n in range(8)]
    np.testing.assert_allclose([float(plain(n)) for n in range(8)], decay, rtol=1e-6)
    want = [decay[n] * min(1.0, (n + 1) / 4) for n in range(8)]
    np.testing.assert_allclose([float(warm(n)) for n in range(8)], want, rtol=1e-6)
    with pytest.raises(ConfigError, match="lr_warmup_frames"):
        load_config(None, ["train.lr_warmup_frames=-1"])


def test_minibatches_take_one_step_per_share_of_the_environments(monkeypatch):
    """`train.minibatches=2` on 4 environments: the update collects one rollout of all 4,
    then takes two gradient steps in turn, the first on environments 0 and 2, the second
    on 1 and 3 from the first's parameters, each with its own loss key and the schedule
    counting steps; the same steps taken by hand give the same parameters, with the
    steps written out in the program (the CPU's choice) and in a loop (elsewhere)."""
    import optax

    from a2catvn_jax.agent import update as update_lib
    from a2catvn_jax.agent.networks import make_networks
    from a2catvn_jax.env import make_env

    cfg = load_config(None, TINY_SYNTHETIC + ["train.minibatches=2", "train.total_frames=160"])  # 10 updates, 20 steps
    env = make_env(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    assert update_lib.steps_written_out() == (jax.default_backend() == "cpu")
    init, _ = update_lib.make_update(env, networks, cfg)  # the initial state does not depend on the steps' form
    state = jax.device_get(init(jax.random.PRNGKey(0)))
    state = state.replace(update=np.int32(3))  # the 4th update: gradient steps 6 and 7
    results = {}
    for written_out in (True, False):
        monkeypatch.setattr(update_lib, "steps_written_out", lambda w=written_out: w)
        _, update = update_lib.make_update(env, networks, cfg)
        results[written_out] = update(jax.device_put(state))
    new, metrics = results[True]

    spec = update_lib.learner(cfg)
    targets = update_lib.targets_of(spec, env)
    batch = jax.jit(lambda s: update_lib.collect(spec, env, networks, targets, s))(jax.device_put(state))
    parts = update_lib.minibatches(2, batch.traj, batch.truth, batch.carry0)
    np.testing.assert_array_equal(parts[0].action[1], np.asarray(batch.traj.action)[:, 1::2])
    np.testing.assert_array_equal(parts[0].rgb[0], np.asarray(batch.traj.rgb)[:, 0::2])
    optimizer = update_lib.make_optimizer(cfg)
    grad = jax.jit(jax.grad(lambda p, *a: update_lib.loss(spec, networks, targets, p, *a)[0]))  # compiled once, for both steps
    params, opt_state = state.params, state.opt_state
    for m, key in enumerate(jax.random.split(batch.loss_key, 2)):
        share = jax.tree_util.tree_map(lambda x: x[m], parts)
        g = grad(params, *share, batch.replay, key)
        step, opt_state = optimizer.update(g, opt_state, params)
        params = optax.apply_updates(params, step)
    for written_out, (got, _) in results.items():
        for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(got.params)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6,
                                       err_msg=f"steps written out: {written_out}")
    # The rate of step 6 of 20 under the linear decay; lr_scaling counts the 2 environments of a step.
    assert float(metrics["learning_rate"]) == pytest.approx(7e-4 * (20 - 6) / 20)
    scaled = load_config(None, ["env.num_envs=256", "train.minibatches=4", "train.lr_scaling=linear"])
    assert update_lib.learning_rate(scaled) == pytest.approx(7e-4 * 4)
    with pytest.raises(ConfigError, match=r"train.minibatches: 3 does not divide env.num_envs = 4"):
        load_config(None, TINY_SYNTHETIC + ["train.minibatches=3"])


@pytest.mark.parametrize("optimizer", ["rmsprop", "adam", "lamb"])
def test_each_optimizer_takes_its_own_first_step(optimizer):
    """The first step of each optimiser after the clip, on every parameter array: RMSprop
    (decay 0.99) moves each weight by lr * g / sqrt(0.01 g^2), i.e. 10 lr; Adam by lr;
    LAMB by a step whose norm is lr times the array's norm (its trust ratio). The
    learning rate is scaled with the batch (4 environments, linear: a quarter)."""
    from a2catvn_jax.agent.networks import make_networks
    from a2catvn_jax.agent.update import make_update
    from a2catvn_jax.env import make_env

    cfg = load_config(None, TINY_SYNTHETIC + [f"train.optimizer={optimizer}", "train.lr_scaling=linear"])
    env = make_env(cfg.env)
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    state = init(jax.random.PRNGKey(0))
    before = jax.device_get(state.params)
    after = jax.device_get(update(state)[0].params)
    lr = 7e-4 / 4
    kernel = lambda p: np.asarray(p["params"]["conv1"]["kernel"])  # noqa: E731
    step = kernel(after) - kernel(before)
    if optimizer == "rmsprop":
        assert np.max(np.abs(step)) == pytest.approx(10 * lr, rel=1e-2)
    elif optimizer == "adam":
        assert np.max(np.abs(step)) == pytest.approx(lr, rel=1e-2)
    else:
        assert np.linalg.norm(step) == pytest.approx(lr * np.linalg.norm(kernel(before)), rel=1e-2)


def test_render_passes_follow_the_platform():
    """The ray caster renders a few frames per pass on the CPU (each pass in cache) and the
    whole batch on an accelerator."""
    from a2catvn_jax.env.camera import CameraSpec
    from a2catvn_jax.env.world import render_chunk

    cpu = CameraSpec(32, 32, chunk_frames=render_chunk("cpu"))
    gpu = CameraSpec(32, 32, chunk_frames=render_chunk("gpu"))
    assert cpu.chunk(4096) == 16 and CameraSpec(84, 84, chunk_frames=render_chunk("cpu")).chunk(4096) == 16
    assert CameraSpec(174, 174, chunk_frames=render_chunk("cpu")).chunk(4096) == 9
    assert gpu.chunk(4096) == 4096 and gpu.chunk(16) == 16


TWO_DEVICE_EVALUATION = textwrap.dedent(
    """
    import os, sys
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    import jax
    sys.path.insert(0, "tests")
    from tiny import TINY_LEARNER, TINY_ROOM
    from a2catvn_jax.config import load_config
    from a2catvn_jax.run.evaluation import evaluate, evaluate_baseline
    from a2catvn_jax.run.training import train

    tmp = sys.argv[1]
    cfg = load_config(None, TINY_ROOM)
    train(cfg, tmp + "/run", max_updates=1, progress=False, log=lambda *_: None, devices=1)
    quiet = lambda *_: None
    for policy in ("sample", "greedy"):
        split = evaluate(tmp + "/run", 8, policy=policy, log=quiet)
        whole = evaluate(tmp + "/run", 8, policy=policy, log=quiet, devices=1)
        assert split["per_episode"] == whole["per_episode"], (policy, split["per_episode"], whole["per_episode"])
    split = evaluate_baseline(cfg, 8, policy="oracle", log=quiet)
    assert split["per_episode"] == evaluate_baseline(cfg, 8, policy="oracle", log=quiet, devices=1)["per_episode"]
    odd = load_config(None, TINY_LEARNER + ["env.scene.kind=room", "env.scene.num_scenes=1", "env.num_envs=3"])
    try:
        evaluate_baseline(odd, 3, policy="random", log=quiet)
        raise AssertionError("3 environments over 2 devices")
    except ValueError as e:
        assert "env.num_envs=3 environments cannot be split evenly over 2 devices" in str(e), e
    # Pre-training splits each batch over the devices: the parameters of one device.
    import numpy as np
    from a2catvn_jax.run.distributed import DevicesError
    from a2catvn_jax.run.pretraining import pretrain
    small = ["pretrain.dataset_size=64", "pretrain.epochs=2", "pretrain.batch_size=16"]
    pre = load_config(None, TINY_ROOM + small)
    lines = []
    split = pretrain(pre, tmp + "/pre_split", log=lines.append)
    assert any("each batch of 16 is split over 2 cpu devices" in line for line in lines), lines
    whole = pretrain(pre, tmp + "/pre_whole", log=quiet, devices=1)
    for a, b in zip(jax.tree_util.tree_leaves(jax.device_get(split)), jax.tree_util.tree_leaves(jax.device_get(whole))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=2e-6)
    try:
        pretrain(load_config(None, TINY_ROOM + small[:2] + ["pretrain.batch_size=15"]), tmp + "/pre_odd", log=quiet)
        raise AssertionError("15 samples over 2 devices")
    except DevicesError as e:
        assert "pretrain.batch_size=15 samples cannot be split evenly over 2 devices" in str(e), e
    print("OK")
    """
)


def test_evaluation_and_pretraining_split_over_two_devices_with_the_one_device_result(tmp_path):
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", TWO_DEVICE_EVALUATION, str(tmp_path)], cwd=root, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("OK"), proc.stderr[-3000:]
