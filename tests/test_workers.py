"""Processes pinned to shares of the CPU cores (`run/workers.py`): how the cores are
split, the XLA flags each process gets, and a pool of real processes that never runs
more commands at once than it has groups, pins each to a free group and reports every
exit status and output."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from a2catvn_jax.study import workers


def test_core_groups_split_evenly_and_refuse_too_many():
    assert workers.core_groups(2, [0, 1, 2, 3, 4]) == [[0, 1, 2], [3, 4]]
    assert workers.core_groups(1, [3, 5]) == [[3, 5]]
    assert workers.core_groups(3, [0, 1, 2]) == [[0], [1], [2]]
    with pytest.raises(workers.WorkerError, match="3 processes need at least 3 CPU cores; this process may use 2"):
        workers.core_groups(3, [0, 1])
    with pytest.raises(workers.WorkerError, match=">= 1"):
        workers.core_groups(0, [0, 1])
    assert sum(map(len, workers.core_groups(1))) == len(workers.available_cores())


def test_worker_env_turns_eigen_threads_off_for_one_core_and_keeps_other_flags():
    base = {"XLA_FLAGS": "--xla_dump_to=/tmp/x --xla_cpu_multi_thread_eigen=true", "HOME": "/h"}
    one = workers.worker_env([1], base)
    assert one["HOME"] == "/h"
    assert one["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/x", "--xla_cpu_multi_thread_eigen=false"]
    assert workers.worker_env([0, 1], base)["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"
    assert "XLA_FLAGS" not in workers.worker_env([0, 1], {"HOME": "/h"})
    assert base["XLA_FLAGS"].endswith("=true")  # not changed in place


PROBE = """
import json, os, sys, time
start = time.time()
time.sleep(0.4)
print(json.dumps({"cores": sorted(os.sched_getaffinity(0)), "flags": os.environ.get("XLA_FLAGS", ""), "start": start,
                  "end": time.time()}))
sys.exit(int(sys.argv[1]))
"""


def test_pool_pins_each_process_and_runs_at_most_jobs_at_once(tmp_path):
    jobs = min(2, len(workers.available_cores()))
    groups = workers.core_groups(jobs)
    codes_in = [0, 3, 0, 0, 5]
    logs = [tmp_path / "logs" / f"{i}.log" for i in range(len(codes_in))]
    started, ended = [], []
    codes = workers.run_pool([[sys.executable, "-c", PROBE, str(c)] for c in codes_in], jobs, logs,
                             on_start=lambda i, cores: started.append((i, cores)),
                             on_end=lambda i, code: ended.append((i, code)), poll_s=0.05)
    assert codes == codes_in
    assert sorted(i for i, _ in started) == sorted(i for i, _ in ended) == list(range(len(codes_in)))
    assert [i for i, _ in started] == list(range(len(codes_in)))  # in the order given
    runs = [json.loads(path.read_text()) for path in logs]
    for (i, cores), run in zip(started, runs):
        assert run["cores"] == cores and cores in groups
        assert ("--xla_cpu_multi_thread_eigen=false" in run["flags"]) == (len(cores) == 1)
    # never more than `jobs` processes alive at once, and no two on the same cores at once
    for t in sorted(r["start"] for r in runs):
        alive = [r for r in runs if r["start"] <= t < r["end"]]
        assert len(alive) <= jobs
        assert len({tuple(r["cores"]) for r in alive}) == len(alive)


def test_pool_checks_its_arguments(tmp_path):
    with pytest.raises(workers.WorkerError, match="2 commands but 1 log paths"):
        workers.run_pool([["true"], ["true"]], 1, [tmp_path / "a.log"])


CHILD = """
import pathlib, signal, sys, time
out = pathlib.Path(sys.argv[1])
signal.signal(signal.SIGTERM, lambda *_: (out.write_text(out.read_text() + "stopped"), sys.exit(0)))
out.write_text("started ")
time.sleep(60)
"""

POOL = """
import sys
from pathlib import Path
from a2catvn_jax.study import workers
tmp = Path(sys.argv[1])
try:
    workers.run_pool([[sys.executable, "-c", sys.argv[2], str(tmp / f"child{i}")] for i in range(3)], 1,
                     [tmp / f"{i}.log" for i in range(3)], poll_s=0.05)
except workers.PoolInterrupted as e:
    print(e)
"""


def _pool_with_a_running_child(tmp_path, child_code):
    """The POOL script in a session of its own, once its first child has started."""
    pool = subprocess.Popen([sys.executable, "-c", POOL, str(tmp_path), child_code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    child = tmp_path / "child0"
    deadline = time.time() + 60
    while not (child.exists() and child.read_text()) and time.time() < deadline:
        time.sleep(0.05)
    return pool, child


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=["SIGTERM", "Ctrl-C", "hang-up"])
def test_a_signal_to_the_pool_stops_its_running_processes_once_each(tmp_path, sig):
    """SIGTERM to the pool, or Ctrl-C or a hang-up to its whole process group (as a
    terminal sends them): each running process gets one SIGTERM and no other signal (it
    has a session of its own; a child that also got SIGINT or SIGHUP would die without
    writing "stopped"), the pool waits for it, starts no further command, and raises
    `PoolInterrupted` with what it stopped."""
    pool, child = _pool_with_a_running_child(tmp_path, CHILD)
    if sig == signal.SIGTERM:
        pool.send_signal(sig)
    else:
        os.killpg(pool.pid, sig)
    out, err = pool.communicate(timeout=60)
    assert pool.returncode == 0, err
    assert child.read_text() == "started stopped"
    assert not (tmp_path / "child1").exists()
    assert out.strip() == (f"interrupted ({sig.name}): asked the 1 running process(es) to stop, 2 command(s) not "
                           f"started; the same command resumes them")


def test_a_second_signal_kills_the_running_processes(tmp_path):
    """A process that does not stop on its SIGTERM is killed by a second signal to the pool."""
    pool, child = _pool_with_a_running_child(tmp_path, CHILD.replace('sys.exit(0)', 'None'))
    deadline = time.time() + 60
    pool.send_signal(signal.SIGTERM)
    while child.read_text() != "started stopped" and time.time() < deadline:
        time.sleep(0.05)
    t0 = time.time()
    pool.send_signal(signal.SIGTERM)
    out, _ = pool.communicate(timeout=60)
    assert time.time() - t0 < 30 and out.startswith("interrupted (SIGTERM)")


def test_last_line_of_a_log(tmp_path):
    log = tmp_path / "a.log"
    assert workers.last_line(log) == "(no output)"  # never written
    log.write_text("\n  \n")
    assert workers.last_line(log) == "(no output)"
    log.write_text("Traceback ...\nValueError: bad\n\n")
    assert workers.last_line(log) == "ValueError: bad"
