"""The accidents users have, each ending in one line and a status, nothing lost or repeated.

Two writers in one work directory, a lock left by a killed run, a damaged latest
checkpoint, a half-written checkpoint, a failed write (checkpoint, metrics, TensorBoard)
and a batch too large for the memory. One reference run of 2N updates is trained once
per module; every case works on a copy of it cut back to an earlier point, and a run
that goes on must end with the reference's state (parameters, optimiser, environments,
replay, key) and with each update's metrics row once.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.run import memory, training, workdir as wd
from a2catvn_jax.run.checkpoint import CheckpointError, Checkpointer
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.train import main
from tiny import TINY_RUN

TINY = TINY_RUN
N = 3
ROOT = Path(__file__).resolve().parents[1]


def _cfg(*extra):
    return load_config(None, TINY + list(extra))


def _leaves(state):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(state))]


def _saved(workdir, step):
    """The leaves of the whole train state saved at `step` in `workdir`."""
    cfg = _cfg()
    _, _, (init, _), _, _ = training._build(dataclasses.replace(cfg, seed=0))
    ckpt = Checkpointer(workdir, create=False)
    try:
        state, _ = ckpt.restore(jax.eval_shape(init, jax.random.PRNGKey(cfg.seed)), cfg, step)
    finally:
        ckpt.close()
    return _leaves(state)


def _updates(workdir):
    return [r["update"] for r in read_jsonl(Path(workdir) / "metrics.jsonl")]


def _csv_updates(workdir):
    lines = (Path(workdir) / "metrics.csv").read_text().splitlines()
    return [int(line.split(",")[0]) for line in lines[1:]]


def _steps(workdir):
    return sorted(Checkpointer(workdir, create=False).steps())


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err[-3000:]
    assert lines[0].startswith("error: "), lines[0]
    return lines[0]


def _cli(argv, capsys):
    """(exit status, stdout, stderr) of the train command."""
    capsys.readouterr()
    try:
        main(argv)
        code = 0
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


def _resume(run, capsys, *extra):
    return _cli(["--workdir", str(run), "--resume", "--updates", "2", "--no-progress", *extra], capsys)


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """2N updates in one go: checkpoints at 2, 4 and 6, metrics rows 1-6, and the final state."""
    workdir = tmp_path_factory.mktemp("straight")
    _, state, _ = training.train(_cfg(), workdir, max_updates=2 * N, progress=False, log=lambda *_: None)
    assert _steps(workdir) == [2, 4, 6] and _updates(workdir) == [1, 2, 3, 4, 5, 6]
    return workdir, _leaves(state)


@pytest.fixture
def at_4(tmp_path, straight):
    """A copy of the reference run stopped after its metrics row 6 but before checkpoint 6
    (killed): checkpoints 2 and 4, rows 1-6."""
    run = tmp_path / "run"
    shutil.copytree(straight[0], run)
    shutil.rmtree(run / "checkpoints" / "6")
    return run


def _goes_on_to_6(run, straight, capsys, *extra):
    """Resume `run` for 2 updates: it ends with the reference's state, rows 1-6 once."""
    code, out, err = _resume(run, capsys, *extra)
    assert code == 0, err[-3000:]
    assert _steps(run)[-1] == 6
    for a, b in zip(_saved(run, 6), straight[1], strict=True):
        np.testing.assert_array_equal(a, b)
    assert _updates(run) == [1, 2, 3, 4, 5, 6]
    assert _csv_updates(run) == [1, 2, 3, 4, 5, 6]
    return out, err


def _holder(workdir, then="sleep"):
    """A process that takes the lock of `workdir`, says so, then sleeps or is killed (kill -9)."""
    code = (
        "import os, sys, time\n"
        "from a2catvn_jax.run.workdir import hold\n"
        f"with hold({str(workdir)!r}, 'train'):\n"
        "    print('held', flush=True)\n"
        + ("    time.sleep(120)\n" if then == "sleep" else "    os.kill(os.getpid(), 9)\n")
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_with_the_holder(tmp_path, straight, capsys):
    run = tmp_path / "run"
    shutil.copytree(straight[0], run)
    before = ((run / "metrics.jsonl").read_bytes(), _steps(run))
    proc = _holder(run)
    try:
        code, _, err = _resume(run, capsys)
    finally:
        proc.kill()
        proc.wait()
    line = _one_line(err)
    assert code == 1
    assert f"{run} is in use by another run: process {proc.pid} on host {socket.gethostname()}" in line
    assert f"kill {proc.pid}" in line and "another --workdir" in line
    assert ((run / "metrics.jsonl").read_bytes(), _steps(run)) == before
    # Pre-training is a writer too.
    from a2catvn_jax.pretrain import main as pretrain_main

    proc = _holder(tmp_path / "pre")
    try:
        with pytest.raises(SystemExit) as e:
            pretrain_main(["--workdir", str(tmp_path / "pre"), "--set", *TINY])
    finally:
        proc.kill()
        proc.wait()
    assert e.value.code == 1 and f"process {proc.pid}" in _one_line(capsys.readouterr().err)


def test_a_lock_left_by_a_killed_run_is_taken_over(at_4, straight, capsys):
    proc = _holder(at_4, then="kill")
    assert proc.wait() == -signal.SIGKILL
    assert wd.holder(at_4)["pid"] == proc.pid
    out, err = _goes_on_to_6(at_4, straight, capsys)
    assert (f"{at_4}: took over the lock of process {proc.pid} on host {socket.gethostname()}" in err
            and "that process is no longer running" in err), err
    assert "removed 2 row(s) after update 4" in out
    assert not (at_4 / wd.LOCK_FILE).exists()


def test_a_lock_of_another_host_waits_for_its_heartbeat(tmp_path):
    """Another host's process cannot be checked: a lock with a recent heartbeat is refused
    (saying how to remove it), one whose heartbeat stopped `STALE_S` ago is taken over."""
    lock = tmp_path / wd.LOCK_FILE
    lock.write_text(json.dumps({"host": "elsewhere", "pid": 123, "command": "train", "started": "then"}))
    with pytest.raises(wd.WorkdirLocked, match=f"process 123 on host elsewhere .*delete {lock}"):
        with wd.hold(tmp_path, "train"):
            pass
    past = time.time() - wd.STALE_S - 60
    os.utime(lock, (past, past))
    lines = []
    with wd.hold(tmp_path, "train", log=lines.append):
        assert wd.holder(tmp_path)["pid"] == os.getpid()
        with wd.hold(tmp_path, "train"):  # re-entrant in one thread
            pass
        assert lock.exists()
    assert len(lines) == 1 and "took over the lock of process 123 on host elsewhere" in lines[0]
    assert "heartbeat stopped" in lines[0] and not lock.exists()
    # Process 0 of a multi-process run holds the lock for the others.
    with wd.hold(tmp_path, "train", process_index=1):
        assert not lock.exists()


def test_a_damaged_latest_checkpoint_names_the_intact_ones(tmp_path, straight, capsys):
    run = tmp_path / "run"
    shutil.copytree(straight[0], run)
    data = sorted((run / "checkpoints" / "6" / "state").rglob("ocdbt.process_0/d/*"), key=lambda f: f.stat().st_size)
    data[-1].write_bytes(b"")  # one file of the latest checkpoint emptied
    code, _, err = _resume(run, capsys)
    line = _one_line(err)
    assert code == 1
    assert line.startswith(f"error: {run / 'checkpoints' / '6'}: the checkpoint is corrupt")
    assert "the intact checkpoints are updates 2, 4: --step 4 uses the newest of them" in line
    assert _steps(run) == [2, 4, 6] and _updates(run) == [1, 2, 3, 4, 5, 6]
    out, _ = _goes_on_to_6(run, straight, capsys, "--step", "4")
    assert "removed the checkpoints after update 4 (update 6)" in out
    code, _, err = _cli(["--workdir", str(run), "--step", "4"], capsys)
    assert code == 2 and "--step N chooses the checkpoint to resume from: it needs --resume" in err


def test_evaluation_names_the_intact_checkpoints(tmp_path, straight):
    """What `evaluate` reads the parameters with (`restore.restore`); its command line
    turns the `CheckpointError` into one line (tests/test_evaluate.py)."""
    from a2catvn_jax.run.restore import restore

    run = tmp_path / "run"
    shutil.copytree(straight[0], run)
    for f in (run / "checkpoints" / "6" / "state").rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "metadata" not in f.name:
            f.write_bytes(b"\0" * 7)
    with pytest.raises(CheckpointError) as e:
        restore(run)
    line = str(e.value)
    assert "\n" not in line
    assert "checkpoints/6" in line and "the intact checkpoints are updates 2, 4: --step 4" in line
    assert restore(run, step=4).step == 4


def test_a_half_written_checkpoint_is_removed(at_4, straight, capsys):
    partial = at_4 / "checkpoints" / "6.orbax-checkpoint-tmp-1765000000"
    shutil.copytree(straight[0] / "checkpoints" / "6", partial)
    (partial / "state" / "manifest.ocdbt").unlink()
    assert _steps(at_4) == [2, 4]  # readers do not see it
    out, _ = _goes_on_to_6(at_4, straight, capsys)
    assert f"removed {partial}, a checkpoint whose write did not finish" in out
    assert not partial.exists()


def _disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_failed_checkpoint_write_is_one_line(at_4, straight, capsys, monkeypatch):
    import orbax.checkpoint as ocp

    def half_written(self, step, *args, **kwargs):  # what a full disk leaves: a partial directory, an OSError
        (Path(self.directory) / f"{step}.orbax-checkpoint-tmp-1765000000" / "state").mkdir(parents=True)
        _disk_full()

    with monkeypatch.context() as m:
        m.setattr(ocp.CheckpointManager, "save", half_written)
        code, _, err = _resume(at_4, capsys)
    line = _one_line(err)
    assert code == 1
    assert line == (f"error: cannot write the checkpoint of update 6 to {at_4 / 'checkpoints'}: No space left on device "
                    f"(the disk is full); the last complete checkpoint is update 4 ({at_4 / 'checkpoints' / '4'})")
    assert sorted(p.name for p in (at_4 / "checkpoints").iterdir()) == ["2", "4"]
    assert _updates(at_4) == [1, 2, 3, 4, 5, 6]  # logged before the checkpoint; dropped when it resumes
    _goes_on_to_6(at_4, straight, capsys)


def test_a_disk_too_full_for_a_checkpoint_is_refused_before_the_write(tmp_path, straight, capsys, monkeypatch):
    from a2catvn_jax.run import checkpoint

    run = tmp_path / "run"
    shutil.copytree(straight[0], run)
    full = types.SimpleNamespace(total=2**30, used=2**30 - 1000, free=1000)
    monkeypatch.setattr(checkpoint.shutil, "disk_usage", lambda _: full)
    code, _, err = _resume(run, capsys)
    line = _one_line(err)
    assert code == 1 and "cannot write the checkpoint of update 8" in line and "No space left on device (it needs about" in line
    assert "the last complete checkpoint is update 6" in line and _steps(run) == [2, 4, 6]


@pytest.mark.parametrize("failing", ["csv", "tensorboard"])
def test_a_failed_metrics_write_is_one_line(failing, at_4, straight, capsys, monkeypatch):
    from a2catvn_jax.run import logger

    with monkeypatch.context() as m:
        if failing == "csv":
            m.setattr(logger.MetricsWriter, "_write_csv", _disk_full)
            where = at_4 / "metrics.csv"
            what = "the metrics"
        else:
            m.setattr(logger._EventFile, "scalars", _disk_full)
            where = at_4 / "tb"
            what = "the TensorBoard events"
        code, _, err = _resume(at_4, capsys)
    line = _one_line(err)
    assert code == 1
    assert line.startswith(f"error: cannot write {what} to {where}")
    assert line.endswith(f": No space left on device (the disk is full); the last complete checkpoint is update 4 "
                         f"({at_4 / 'checkpoints' / '4'})")
    assert _updates(at_4) == [1, 2, 3, 4] and _csv_updates(at_4) == [1, 2, 3, 4]  # row 5 taken back from every file
    _goes_on_to_6(at_4, straight, capsys)


def _fake_memory(monkeypatch, available):
    monkeypatch.setattr(memory, "available_bytes", lambda devices: (available, f"{memory.fmt_bytes(available)} of test memory"))


def test_a_run_that_does_not_fit_stops_before_it_allocates(tmp_path, capsys, monkeypatch):
    """The check's two ways, with the memory made small: the state fits but the update does
    not (the run's compile and a smaller one), the state alone does not (no compile of the run)."""
    import re

    _fake_memory(monkeypatch, 3 * 2**19)
    code, _, err = _cli(["--workdir", str(tmp_path / "a"), "--no-progress", "--set", *TINY], capsys)
    line = _one_line(err)
    assert code == 1
    assert re.match(r"error: env.num_envs=4 does not fit in memory: the run needs about 1\.\d MiB \(training state "
                    r"\d+\.\d KiB, update 1\.\d MiB\), and there is 1\.5 MiB of test memory; at most about [123] "
                    r"environments? fits? \(\d+\.\d KiB each\): lower env.num_envs", line), line
    _fake_memory(monkeypatch, 2**18)  # less than the state: the run's update is not compiled
    code, out, err = _cli(["--workdir", str(tmp_path / "b"), "--no-progress", "--set", *TINY], capsys)
    line = _one_line(err)
    assert code == 1
    assert "estimated from a compile at 2 environments" in line and "not even 1 environment fits" in line
    for run in ("a", "b"):
        assert not list((tmp_path / run / "checkpoints").iterdir())


def test_an_enormous_batch_is_refused_in_seconds(tmp_path, capsys):
    """`env.num_envs=100000000` on the real memory: refused before `init` allocates hundreds of GiB."""
    t0 = time.perf_counter()
    code, out, err = _cli(["--workdir", str(tmp_path), "--no-progress", "--set", *TINY, "env.num_envs=100000000"],
                          capsys)
    line = _one_line(err)
    assert code == 1 and time.perf_counter() - t0 < 60
    assert line.startswith("error: env.num_envs=100,000,000 does not fit in memory: the run needs about ")
    assert re.search(r"\(training state \d+\.\d GiB, update \d+\.\d TiB", line), line
    assert "at most about " in line and "estimated from a compile at" in line
    assert not list((tmp_path / "checkpoints").iterdir()) and not (tmp_path / wd.LOCK_FILE).exists()


def test_available_memory_of_each_kind_of_device():
    class Accelerator:
        platform = "gpu"

        def memory_stats(self):
            return {"bytes_limit": 80 * 2**30, "bytes_in_use": 2**30}

    assert memory.available_bytes([Accelerator()]) == (79 * 2**30, "79.0 GiB free on the gpu device")
    host, where = memory.available_bytes(jax.local_devices()[:1])
    assert host > 0 and where.endswith("of available host memory")


def test_evaluate_refuses_a_synthetic_run_in_one_line(straight, capsys):
    """The tests' runs train on the synthetic environment; evaluating one is a one-line error."""
    from a2catvn_jax.evaluate import main as evaluate_main

    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        evaluate_main(["--workdir", str(straight[0]), "--episodes", "1"])
    line = _one_line(capsys.readouterr().err)
    assert e.value.code != 0
    assert line.startswith("error: evaluation needs the MuJoCo environment") and "'synthetic'" in line
