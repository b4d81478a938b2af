"""One run in two processes on this machine (JAX's CPU collectives, gloo), as on two
machines: each process steps its half of the environments, the gradients are reduced
across both, process 0 logs, and both write one checkpoint together. The run reaches
the parameters of one process at the same global batch; signals that reach the two a
moment apart stop both after the same update, with a checkpoint; `--resume` with the
same processes goes on exactly.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from a2catvn_jax.run.checkpoint import Checkpointer, read_run_config
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.training import train
from tiny import TINY_SYNTHETIC

ROOT = Path(__file__).resolve().parents[1]
OVERRIDES = TINY_SYNTHETIC + ["train.log_every=1", "train.checkpoint_every=100000"]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _launch(workdir: Path, updates: int, resume: bool = False) -> list:
    """The two processes of one run (each with one CPU device)."""
    port = _port()
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    env["PYTHONUNBUFFERED"] = "1"
    procs = []
    for rank in range(2):
        cmd = [sys.executable, "-m", "a2catvn_jax.train", "--workdir", str(workdir), "--updates", str(updates),
               "--no-progress", "--coordinator-address", f"localhost:{port}", "--num-processes", "2",
               "--process-id", str(rank)]
        cmd += ["--resume"] if resume else ["--set", *OVERRIDES]
        log = open(workdir.parent / f"{workdir.name}_{'resume' if resume else 'run'}_{rank}.log", "w")
        procs.append((subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT), log))
    return procs


def _wait(procs, timeout: float = 600) -> list[str]:
    outs = []
    for proc, log in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            for p, _ in procs:
                p.kill()
            raise
        log.close()
        outs.append(Path(log.name).read_text())
    for (proc, _), out in zip(procs, outs):
        assert proc.returncode == 0, out[-3000:]
    return outs


def _reference(tmp_path: Path, cfg, updates: int):
    """The same run's parameters in this process, on one device."""
    _, state, _ = train(cfg, tmp_path / f"reference_{updates}", max_updates=updates, progress=False,
                        log=lambda *_: None, devices=1)
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state.params))]


def _saved_params(workdir: Path, updates: int):
    """The parameters of the run's checkpoint at `updates`, read in this process."""
    from a2catvn_jax.agent.networks import make_networks
    from a2catvn_jax.agent.update import make_update
    from a2catvn_jax.env import make_env

    cfg = read_run_config(workdir)
    env = make_env(cfg.env)
    init, _ = make_update(env, make_networks(cfg, env.num_actions), cfg)
    ckpt = Checkpointer(workdir, create=False)
    try:
        state, meta = ckpt.restore(jax.eval_shape(init, jax.random.PRNGKey(0)), cfg, updates)
    finally:
        ckpt.close()
    assert meta["update"] == updates
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state.params))]


@pytest.mark.slow
def test_two_processes_train_one_run_stop_together_and_resume(tmp_path):
    workdir = tmp_path / "run"
    procs = _launch(workdir, 100000)
    metrics = workdir / "metrics.jsonl"
    deadline = time.time() + 600
    while time.time() < deadline and not (metrics.exists() and len(read_jsonl(metrics)) >= 3):
        assert all(p.poll() is None for p, _ in procs), "a process ended early"
        time.sleep(0.5)
    procs[0][0].send_signal(signal.SIGTERM)  # a scheduler signals each process on its own
    time.sleep(0.7)
    procs[1][0].send_signal(signal.SIGTERM)
    outs = _wait(procs)
    stopped = max(Checkpointer(workdir, create=False).steps())
    rows = read_jsonl(metrics)
    assert [r["update"] for r in rows] == list(range(1, stopped + 1)), "process 0 logs each update once"
    assert f"checkpoint at update {stopped} " in outs[0] and "checkpoint at update" not in outs[1]
    assert "on 2 cpu devices" in outs[0] and "2 processes" in outs[0]
    for got, want in zip(_saved_params(workdir, stopped), _reference(tmp_path, read_run_config(workdir), stopped)):
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-6)
    _wait(_launch(workdir, 2, resume=True))
    for got, want in zip(_saved_params(workdir, stopped + 2), _reference(tmp_path, read_run_config(workdir), stopped + 2)):
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-6)
    assert [r["update"] for r in read_jsonl(metrics)] == list(range(1, stopped + 3))


def test_importing_the_command_lines_starts_no_backend():
    """`jax.distributed.initialize` must come before any JAX backend starts: importing the
    command lines (and so the package) must not start one."""
    code = ("import jax._src.xla_bridge as xb; import a2catvn_jax.train, a2catvn_jax.evaluate, "
            "a2catvn_jax.experiments, a2catvn_jax.pretrain; assert not xb._backends, 'a backend started'; print('OK')")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.stdout.strip() == "OK", proc.stderr[-2000:]
