"""The train command: logs, checkpoints, exact resume, and its errors.

Runs use a tiny configuration (16x16 images, 4 environments, 4-step rollouts). The
reference run of 6 updates is trained once per module; everything else resumes,
interrupts or corrupts copies of such runs.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import make_update
from a2catvn_jax.config import load_config
from a2catvn_jax.env import make_env
from a2catvn_jax.run import inspection
from a2catvn_jax.run.checkpoint import Checkpointer, CheckpointError
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.training import TrainingError, train
from a2catvn_jax.train import main
from tiny import TINY_RUN

TINY = TINY_RUN
N = 3


def _cfg(*extra):
    return load_config(None, TINY + list(extra))


def _leaves(state):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state))]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """2N updates in one go."""
    workdir = tmp_path_factory.mktemp("straight")
    _, state, _ = train(_cfg(), workdir, max_updates=2 * N, progress=False, log=lambda *_: None)
    return workdir, _leaves(state)


def test_resume_is_exact(tmp_path, straight):
    _, reference = straight
    train(_cfg(), tmp_path, max_updates=N, progress=False, log=lambda *_: None)
    _, state, _ = train(_cfg(), tmp_path, resume=True, max_updates=N, progress=False, log=lambda *_: None)
    resumed = _leaves(state)
    assert len(resumed) == len(reference)
    for a, b in zip(resumed, reference):
        np.testing.assert_array_equal(a, b)


def test_logs_and_checkpoints(straight):
    workdir, _ = straight
    rows = read_jsonl(workdir / "metrics.jsonl")
    assert [r["update"] for r in rows] == list(range(1, 2 * N + 1))
    assert rows[-1]["frames"] == 2 * N * 4 * 4
    for key in ("loss/total", "loss/actor", "loss/pixel_control", "loss/depth", "success_rate", "fps", "learning_rate"):
        assert key in rows[0]
    assert rows[1]["learning_rate"] < rows[0]["learning_rate"]  # linear decay
    csv_lines = (workdir / "metrics.csv").read_text().splitlines()
    assert len(csv_lines) == 2 * N + 1 and csv_lines[0].startswith("update,frames,fps")
    assert list((workdir / "tb").iterdir()), "no TensorBoard events"
    assert sorted(Checkpointer(workdir, create=False).steps())[-1] == 2 * N
    assert load_config(workdir / "config.yaml") == _cfg()


def test_fresh_run_refuses_existing_checkpoints(straight):
    workdir, _ = straight
    with pytest.raises(CheckpointError, match="--resume"):
        train(_cfg(), workdir, max_updates=1, progress=False)


def test_resume_with_other_config_is_an_error(tmp_path, straight, capsys):
    workdir, _ = straight
    run = tmp_path / "run"
    shutil.copytree(workdir, run)
    with pytest.raises(SystemExit) as e:
        main(["--workdir", str(run), "--resume", "--set", "train.gamma=0.9"])
    assert e.value.code == 2
    assert "train.gamma: 0.99 != 0.9" in capsys.readouterr().err
    with pytest.raises(CheckpointError, match="different configuration"):
        Checkpointer(run, create=False).restore(None, _cfg("train.gamma=0.9"))


def test_missing_and_corrupt_checkpoints(tmp_path, straight, capsys):
    workdir, _ = straight
    with pytest.raises(SystemExit) as e:
        main(["--workdir", str(tmp_path / "nothing"), "--resume"])
    assert e.value.code == 2 and "holds no checkpoints" in capsys.readouterr().err
    run = tmp_path / "run"
    shutil.copytree(workdir, run)
    ckpt = Checkpointer(run, create=False)
    with pytest.raises(CheckpointError, match="no checkpoint at update 99"):
        ckpt.restore(None, step=99)
    latest = run / "checkpoints" / str(ckpt.latest()) / "state"
    for f in latest.rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "metadata" not in f.name:
            f.write_bytes(b"\0" * 7)
    with pytest.raises(SystemExit) as e:
        main(["--workdir", str(run), "--resume", "--updates", "1", "--no-progress"])
    assert e.value.code == 1
    assert "corrupt" in capsys.readouterr().err


def test_silenced_reports_are_only_those_of_abandoned_orbax_reads():
    import logging
    import sys
    import warnings

    from a2catvn_jax.run.checkpoint import silence_abandoned_reads

    def task_record(filename):
        code = {}
        exec(compile("def read():\n    raise ValueError('corrupt')\n", filename, "exec"), code)
        try:
            code["read"]()
        except ValueError:
            exc_info = sys.exc_info()
        return logging.LogRecord("asyncio", logging.ERROR, __file__, 1, "Task exception was never retrieved\nfuture: ...",
                                 None, exc_info)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        silence_abandoned_reads()
        silence_abandoned_reads()
        warnings.warn("coroutine 'Store._get_array_metadatas' was never awaited", RuntimeWarning)
        warnings.warn("something else", RuntimeWarning)
    assert [str(w.message) for w in caught] == ["something else"]
    log = logging.getLogger("asyncio")
    assert sum(type(f).__name__ == "_AbandonedOrbaxTasks" for f in log.filters) == 1
    assert not log.filter(task_record("/site-packages/orbax/checkpoint/_src/serialization/serialization.py"))
    assert log.filter(task_record("/site-packages/somelib/io.py"))
    # A task whose traceback has no orbax frame, but whose repr names the file of orbax's coroutine.
    orbax_task = ("Task exception was never retrieved\nfuture: <Task finished name='Task-9' coro=<read() done, "
                  "defined at /site-packages/orbax/checkpoint/_src/serialization/tensorstore_utils.py:40> "
                  "exception=ValueError('corrupt')>")
    assert not log.filter(logging.LogRecord("asyncio", logging.ERROR, __file__, 1, orbax_task, None, None))
    assert log.filter(logging.LogRecord("asyncio", logging.ERROR, __file__, 1, "Unclosed event loop", None, None))


def test_nonfinite_loss_stops_and_keeps_last_checkpoint(tmp_path):
    cfg = _cfg("train.learning_rate=1e38", "train.lr_schedule=constant")
    with pytest.raises(TrainingError, match="non-finite"):
        train(cfg, tmp_path, max_updates=20, progress=False, log=lambda *_: None)
    ckpt = Checkpointer(tmp_path, create=False)
    env = make_env(cfg.env)
    net = make_networks(cfg, env.num_actions)
    state, meta = ckpt.restore(jax.eval_shape(make_update(env, net, cfg).init, jax.random.PRNGKey(0)), cfg)
    assert all(np.all(np.isfinite(x)) for x in _leaves(state.params))
    # The parameters alone, as evaluation reads them, are the same arrays.
    params, meta_p = Checkpointer(tmp_path, create=False).restore_params(
        jax.eval_shape(net.init, jax.random.PRNGKey(0)), cfg)
    assert meta_p == meta
    assert all(np.array_equal(a, b) for a, b in zip(_leaves(params), _leaves(state.params)))
    rows = read_jsonl(tmp_path / "metrics.jsonl")
    assert all(np.isfinite(r["loss/total"]) for r in rows)
    assert json.dumps(meta)  # the record is plain JSON


def test_ctrl_c_saves_a_checkpoint(tmp_path):
    """SIGINT (Ctrl-C) stops the command after the current update, with a checkpoint of it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    cmd = [sys.executable, "-m", "a2catvn_jax.train", "--workdir", str(tmp_path), "--no-progress", "--updates", "100000",
           "--set", *TINY, "train.checkpoint_every=100000"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    metrics = tmp_path / "metrics.jsonl"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 3:
            break
        time.sleep(0.5)
    assert proc.poll() is None, proc.communicate()[1][-2000:]
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-2000:]
    last = read_jsonl(metrics)[-1]["update"]
    steps = Checkpointer(tmp_path, create=False).steps()
    assert max(steps) >= last and max(steps) > 0
    assert "checkpoint at update" in out
    assert os.path.exists(tmp_path / "config.yaml")


def test_runs_of_one_configuration_share_its_build_and_keep_their_seeds(tmp_path):
    """`train` keeps the last configuration's environment and compiled functions: runs of
    it that differ only in their seed build once, still start from their own seed, and a
    run is the same before and after another has used the kept functions."""
    from a2catvn_jax.run import training

    quiet = dict(max_updates=2, progress=False)
    training._build.cache_clear()
    training.COMPILED.clear()
    logs = {name: [] for name in ("first", "other", "again")}
    _, first, _ = train(_cfg("seed=1"), tmp_path / "first", log=logs["first"].append, **quiet)
    _, other, _ = train(_cfg(), tmp_path / "other", log=logs["other"].append, **quiet)
    _, again, _ = train(_cfg("seed=1"), tmp_path / "again", log=logs["again"].append, **quiet)
    assert training._build.cache_info().misses == 1 and training._build.cache_info().hits == 2
    assert len(training.COMPILED) == 1  # one compiled update loop served the three runs
    assert any(line.startswith("compiled the update in") for line in logs["first"])
    for name in ("other", "again"):
        assert any("compiled by an earlier run of this configuration in this process is reused" in line
                   for line in logs[name]), logs[name]
    assert all(np.array_equal(a, b) for a, b in zip(_leaves(first), _leaves(again)))
    assert not all(np.array_equal(a, b) for a, b in zip(_leaves(first.params), _leaves(other.params)))


def test_sigterm_stops_training_after_the_update_with_a_checkpoint(tmp_path):
    """`train` itself, in this process (Ctrl-C's SIGINT goes to a process of its own above):
    SIGTERM arrives twice while update 3 is logged (as `timeout` sends it, to the command and
    to its process group); the run stops after that update, checkpoints it and puts the
    previous handler back."""
    import os
    import signal

    sig = signal.SIGTERM
    before = signal.getsignal(sig)
    lines = []

    def log(line):
        lines.append(line)
        if line.startswith("update 3 "):
            os.kill(os.getpid(), sig)
            os.kill(os.getpid(), sig)

    _, state, _ = train(_cfg("train.checkpoint_every=100000"), tmp_path, max_updates=100000, progress=False, log=log)
    assert int(state.update) == 3 and read_jsonl(tmp_path / "metrics.jsonl")[-1]["update"] == 3
    assert max(Checkpointer(tmp_path, create=False).steps()) == 3
    assert any(line.startswith("checkpoint at update 3 ") for line in lines), lines
    assert signal.getsignal(sig) is before


def test_second_ctrl_c_aborts_with_one_line(monkeypatch, tmp_path, capsys):
    """The stop flag: a repeated SIGTERM stays a request to stop, a second Ctrl-C interrupts;
    the command line turns that interruption into one line and exit status 130."""
    import signal

    import a2catvn_jax.train as train_cli
    from a2catvn_jax.run import training

    flag = training.StopFlag()
    flag(signal.SIGTERM, None)
    flag(signal.SIGTERM, None)
    assert flag.stop
    with pytest.raises(KeyboardInterrupt):
        flag(signal.SIGINT, None)
    assert capsys.readouterr().err.strip() == "stopping after the updates in progress"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_cli, "train", interrupted)
    with pytest.raises(SystemExit) as exit_:
        train_cli.main(["--workdir", str(tmp_path)])
    assert exit_.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"aborted without a checkpoint; `--workdir {tmp_path} --resume` goes on from the last one"]


def test_a_ctrl_c_after_the_command_is_over_is_ignored(monkeypatch):
    """`python -m a2catvn_jax.train` and `.experiments` run under `cli.run_stoppable`: once
    the command is over (here with exit status 130), a Ctrl-C or SIGTERM while the process
    exits is ignored instead of ending in a traceback from an exit handler."""
    import signal

    from a2catvn_jax import cli

    calls = []
    monkeypatch.setattr(signal, "signal", lambda sig, handler: calls.append((sig, handler)))

    def stopped():
        raise SystemExit(130)

    with pytest.raises(SystemExit):
        cli.run_stoppable(stopped)
    assert calls == [(signal.SIGINT, signal.SIG_IGN), (signal.SIGTERM, signal.SIG_IGN)]


def test_grad_norm_diagnostic_is_logged_and_changes_nothing(tmp_path, straight):
    """`train.grad_norm_every=2`: every second log row has each loss term's gradient norm
    on the shared conv layers; the run's parameters are those of the run without it."""
    _, reference = straight
    _, state, _ = train(_cfg("train.grad_norm_every=2"), tmp_path, max_updates=2 * N, progress=False,
                        log=lambda *_: None)
    for a, b in zip(_leaves(state), reference):
        np.testing.assert_array_equal(a, b)
    rows = read_jsonl(tmp_path / "metrics.jsonl")
    terms = ("actor", "critic", "entropy", "off_policy_critic", "pixel_control", "reward_prediction", "depth",
             "segmentation", "target_segmentation", "total_shared")
    for r in rows:
        logged = sorted(k[len("grad_norm/"):] for k in r if k.startswith("grad_norm/"))
        if r["update"] % 2:
            assert logged == []
        else:
            assert logged == sorted(terms)
            assert all(np.isfinite(r[f"grad_norm/{t}"]) and r[f"grad_norm/{t}"] > 0 for t in terms)
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "grad_norm/reward_prediction" in header and len((tmp_path / "metrics.csv").read_text().splitlines()) == 2 * N + 1
    # The same norms from the checkpoint at update 4, then from other batches of that state.
    norms = inspection.gradient_norms(tmp_path, step=4, batches=3)
    logged = next(r for r in rows if r["update"] == 4)
    assert norms["step"] == 4 and len(norms["batches"]) == 3
    for key, value in norms["batches"][0].items():
        np.testing.assert_allclose(value, logged[key], rtol=1e-5, err_msg=key)
    others = [b["grad_norm/total_shared"] for b in norms["batches"][1:]]
    assert all(v != norms["batches"][0]["grad_norm/total_shared"] for v in others)
    np.testing.assert_allclose(norms["mean"]["grad_norm/actor"], np.mean([b["grad_norm/actor"] for b in norms["batches"]]))
