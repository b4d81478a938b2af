"""Several training processes at once, each on its own share of the CPU cores.

On a CPU with few cores one small training run does not keep every core busy: its
operations are too small for XLA's intra-op threads to split well. Independent runs
(the seeds and variants of an experiment, or copies of a benchmark) then finish sooner
in all when they run side by side, each pinned to its own cores (`python -m a2catvn_jax.benchmark train --processes 1 2`
measures it; docs/benchmarks.md). On one GPU, run one process at a time.

`core_groups(n)` splits the cores this process may use into n groups, `worker_env`
gives a process the XLA flags of its group, and `run_pool` runs a list of commands, at
most one per group at a time, each pinned to a free group (Linux: `sched_setaffinity`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

from a2catvn_jax.errors import Interrupted, UserError


class WorkerError(UserError, ValueError):
    """A pool that cannot be set up (more processes than cores, no affinity support)."""


class PoolInterrupted(Interrupted):
    """The pool was stopped by Ctrl-C, SIGTERM or SIGHUP; its running processes were asked to stop."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def available_cores() -> list[int]:
    """The CPU cores this process may run on, sorted."""
    if not hasattr(os, "sched_getaffinity"):
        raise WorkerError("running several processes pinned to cores needs Linux (os.sched_getaffinity)")
    return sorted(os.sched_getaffinity(0))


def core_groups(n: int, cores: Optional[Sequence[int]] = None) -> list[list[int]]:
    """`cores` (default: `available_cores()`) in `n` groups of consecutive cores whose
    sizes differ by at most one."""
    cores = list(available_cores() if cores is None else cores)
    if n < 1:
        raise WorkerError(f"the number of processes must be >= 1, got {n}")
    if n > len(cores):
        raise WorkerError(f"{n} processes need at least {n} CPU cores; this process may use {len(cores)} "
                          f"({', '.join(map(str, cores))})")
    size, extra = divmod(len(cores), n)
    groups, start = [], 0
    for i in range(n):
        end = start + size + (i < extra)
        groups.append(cores[start:end])
        start = end
    return groups


def worker_env(cores: Sequence[int], base: Optional[dict] = None) -> dict:
    """Environment variables of a process pinned to `cores`: `base` (default: this
    process's), with XLA's multi-threaded Eigen kernels off when it has one core (XLA
    sizes its thread pools from the cores a process may use), other XLA_FLAGS kept."""
    env = dict(os.environ if base is None else base)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith("--xla_cpu_multi_thread_eigen=")]
    if len(cores) == 1:
        flags.append("--xla_cpu_multi_thread_eigen=false")
    if flags:
        env["XLA_FLAGS"] = " ".join(flags)
    else:
        env.pop("XLA_FLAGS", None)
    return env


def pinned(command: Sequence[str], cores: Sequence[int]) -> list[str]:
    """`command` run by a small Python process that pins itself to `cores` and then
    replaces itself with `command` (which keeps the pinning)."""
    return [sys.executable, "-m", "a2catvn_jax.study.workers", ",".join(map(str, cores)), *command]


def run_pool(commands: Sequence[Sequence[str]], jobs: int, logs: Sequence[Path], *,
             on_start: Optional[Callable[[int, list[int]], None]] = None,
             on_end: Optional[Callable[[int, int], None]] = None, poll_s: float = 0.5) -> list[int]:
    """Run `commands` (argument lists), at most `jobs` at once, each pinned to one of
    `core_groups(jobs)` that no running command holds, its stdout and stderr written to
    the matching path of `logs`. Calls `on_start(i, cores)` and `on_end(i, exit code)`;
    returns the exit codes in the order of `commands`.

    Ctrl-C, SIGTERM or SIGHUP to the pool (called from the main thread) starts no further
    command, sends each running process one SIGTERM (a training run checkpoints and
    stops on it), waits for them and raises `PoolInterrupted`; a second signal kills
    them. Each process runs in a session of its own, so a terminal's Ctrl-C or hang-up
    reaches the pool alone (a second signal would abort a training run without its
    checkpoint). From another thread the signals are not the pool's to take, and the
    processes stay in the caller's session."""
    if len(logs) != len(commands):
        raise WorkerError(f"{len(commands)} commands but {len(logs)} log paths")
    free = core_groups(jobs)
    waiting = list(range(len(commands)))
    running: dict[int, tuple[subprocess.Popen, list[int], object]] = {}
    codes: list[int] = [0] * len(commands)
    signals: list[str] = []  # the stop signals received, in order
    main_thread = threading.current_thread() is threading.main_thread()
    previous = {}
    if main_thread:
        for sig in STOP_SIGNALS:
            previous[sig] = signal.signal(sig, lambda signum, frame: signals.append(signal.Signals(signum).name))
    try:
        while (waiting or running) and not signals:
            while waiting and free and not signals:
                i, cores = waiting.pop(0), free.pop(0)
                Path(logs[i]).parent.mkdir(parents=True, exist_ok=True)
                out = open(logs[i], "w")
                try:
                    proc = subprocess.Popen(pinned(commands[i], cores), stdout=out, stderr=subprocess.STDOUT,
                                            env=worker_env(cores), start_new_session=main_thread)
                except BaseException:
                    out.close()
                    raise
                running[i] = (proc, cores, out)
                if on_start:
                    on_start(i, cores)
            time.sleep(poll_s)
            for i, (proc, cores, out) in list(running.items()):
                code = proc.poll()
                if code is None:
                    continue
                out.close()
                del running[i]
                free.append(cores)
                codes[i] = code
                if on_end:
                    on_end(i, code)
        if signals:
            alive = sum(proc.poll() is None for proc, _, _ in running.values())
            raise PoolInterrupted(f"interrupted ({signals[0]}): asked the {alive} running process(es) to stop, "
                                  f"{len(waiting)} command(s) not started; the same command resumes them")
    finally:  # let the running processes stop (training checkpoints on SIGTERM); a second signal kills them
        for proc, _, _ in running.values():
            if proc.poll() is None:
                proc.terminate()
        stopping = len(signals)
        deadline = time.monotonic() + 120
        for proc, _, out in running.values():
            while proc.poll() is None:
                if len(signals) > max(stopping, 1) or time.monotonic() > deadline:
                    proc.kill()
                try:
                    proc.wait(timeout=0.2)
                except subprocess.TimeoutExpired:
                    pass
            out.close()
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
    return codes


def last_line(log: Path) -> str:
    """The last non-empty line a process wrote to `log` (what names its error), or "(no output)"."""
    lines = Path(log).read_text().strip().splitlines() if Path(log).exists() else []
    return lines[-1] if lines else "(no output)"


def _exec_pinned(argv: Sequence[str]) -> None:
    """`python -m a2catvn_jax.study.workers CORES COMMAND...`: pin this process to CORES
    (comma-separated) and replace it with COMMAND."""
    cores, command = argv[0], list(argv[1:])
    os.sched_setaffinity(0, [int(c) for c in cores.split(",")])
    os.execvp(command[0], command)


if __name__ == "__main__":
    _exec_pinned(sys.argv[1:])
