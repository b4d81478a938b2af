"""One writer per work directory: a lock held while a command writes there.

    with hold(workdir, "train", log=print):   # WorkdirLocked if another run writes there
        ...

Every command that writes a work directory (training, pre-training, and so the
experiment runner's runs, which call them) holds its lock from start to end; readers
(evaluation, plots, notebooks) take none: they read the newest complete checkpoint.

The lock is the file `LOCK` in the work directory, a JSON record of its holder (host,
process id, the process's start time and the machine's boot id, a run id, the command,
when it started). While it is held:

- the holder keeps an exclusive `flock` on it, which the kernel drops when the process
  ends, however it ends (kill -9 included), and touches the file every `HEARTBEAT_S`
  seconds (its modification time is the heartbeat);
- a second writer finds the `flock` taken and stops with one line naming the holder's
  host and process id and how to go on (`WorkdirLocked`).

A lock whose holder ended without releasing it (kill -9, a crash, power loss) is stale
and is taken over, with a line saying so. Whether it is stale:

- holder on this host: its process id is not alive, is a zombie, or is a process that
  started at another time, or the machine has rebooted since (boot id);
- holder on another host: its process cannot be checked from here, so the heartbeat
  decides: a lock not touched for `STALE_S` seconds is stale (the hosts' clocks must
  agree to within minutes); a younger one is refused with a line that says to delete
  `LOCK` if that run is not running.

On a filesystem without `flock` the same record checks are all there is. The holder
removes `LOCK` when it is done. Holding is re-entrant in one thread of one process (a
function that holds it may call another that takes it).

Multi-process runs (`jax.distributed`, one process per host writing one orbax checkpoint
together) are one writer: only process 0 (`process_index`, default
`jax.process_index()`) takes the lock, on behalf of the run; the others hold nothing.
A multi-process launcher should let the other processes go on only once process 0 holds
the lock (e.g. by a `multihost_utils.sync_global_devices` after `hold`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import inspect
import json
import os
import socket
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Callable, Iterator, Optional

from a2catvn_jax.errors import UserError

LOCK_FILE = "LOCK"
HEARTBEAT_S = 30.0  # how often the holder touches the lock
STALE_S = 600.0  # a lock of another host not touched for this long is stale
_NO_FLOCK = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)

_held: dict[str, "_Lock"] = {}  # the locks this process holds, by the work directory's real path
_held_guard = threading.Lock()


class WorkdirLocked(UserError, RuntimeError):
    """Another run writes the work directory, or its lock cannot be taken."""


def hold(workdir, command: str = "", *, log: Optional[Callable[[str], None]] = None,
         process_index: Optional[int] = None) -> contextlib.AbstractContextManager:
    """A context manager that holds the lock of `workdir` (created if missing) for the
    block; `WorkdirLocked` if another run holds it. `log` gets the line about a stale
    lock taken over (default: print to stderr). `process_index`: this process's index in
    a multi-process run (default `jax.process_index()`); only process 0 takes the lock."""
    return _hold(Path(workdir), command, log, process_index)


def locked(command: str) -> Callable:
    """A decorator: the function holds the lock of its `workdir` argument while it runs
    (and passes its `log` argument, if any, to `hold`)."""

    def wrap(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            log = bound.arguments.get("log")
            with hold(bound.arguments["workdir"], command, log=log):
                return fn(*args, **kwargs)

        return call

    return wrap


def holder(workdir) -> Optional[dict]:
    """The record of the lock in `workdir` (None when there is none or it cannot be read)."""
    return _read_record(Path(workdir) / LOCK_FILE)


@contextlib.contextmanager
def _hold(workdir: Path, command: str, log, process_index) -> Iterator[None]:
    if (process_index if process_index is not None else _process_index()) != 0:
        yield  # process 0 holds the lock for the whole run
        return
    try:
        workdir.mkdir(parents=True, exist_ok=True)
        key = str(workdir.resolve())
    except OSError as e:
        raise WorkdirLocked(f"{workdir}: cannot create the work directory ({e.strerror or e})") from None
    with _held_guard:
        mine = _held.get(key)
        if mine is not None and mine.thread != threading.get_ident():
            raise WorkdirLocked(f"{workdir} is in use by another thread of this process ({mine.record['command']})")
        if mine is None:
            mine = _held[key] = _Lock.acquire(workdir, command, log or _stderr)
        mine.depth += 1
    try:
        yield
    finally:
        with _held_guard:
            mine.depth -= 1
            if mine.depth == 0:
                del _held[key]
                mine.release()


class _Lock:
    """The lock file of one work directory, held by this process."""

    def __init__(self, path: Path, fd: int, record: dict):
        self.path, self.fd, self.record = path, fd, record
        self.thread = threading.get_ident()
        self.depth = 0
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, name=f"lock heartbeat {path}", daemon=True)
        self._beat.start()

    @classmethod
    def acquire(cls, workdir: Path, command: str, log) -> "_Lock":
        path = workdir / LOCK_FILE
        for _ in range(20):  # the holder may remove the file between our open and our flock
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as e:
                raise WorkdirLocked(f"{workdir}: cannot create its lock {path} ({e.strerror or e})") from None
            try:
                lock = cls._take(workdir, path, fd, command, log)
            except BaseException:
                os.close(fd)
                raise
            if lock is not None:
                return lock
            os.close(fd)
        raise WorkdirLocked(f"{workdir}: its lock {path} keeps changing; is another run starting there?")

    @classmethod
    def _take(cls, workdir: Path, path: Path, fd: int, command: str, log) -> Optional["_Lock"]:
        """The lock, or None when `fd` is no longer the file at `path` (try again)."""
        flocked = True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise WorkdirLocked(_busy_message(workdir, path, _read_record(path, wait=True))) from None
        except OSError as e:
            if e.errno not in _NO_FLOCK:
                raise WorkdirLocked(f"{workdir}: cannot lock {path} ({e.strerror or e})") from None
            flocked = False  # this filesystem has no flock: the record alone decides
        try:
            if os.fstat(fd).st_ino != os.stat(path).st_ino:
                return None
        except FileNotFoundError:
            return None
        previous = _read_record(path)
        if previous is not None:
            stale = _stale_because(previous, path)
            if stale is None:  # a live holder that this filesystem's flock does not see
                raise WorkdirLocked(_busy_message(workdir, path, previous))
            log(f"{workdir}: took over the lock of process {previous.get('pid')} on host {previous.get('host')} "
                f"({previous.get('command') or 'a run'}, started {previous.get('started', '?')}): {stale}")
        elif not flocked and _age(path) < STALE_S and path.stat().st_size:
            raise WorkdirLocked(f"{workdir}: its lock {path} cannot be read; if no run writes there, delete it")
        record = _own_record(command)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
            os.fsync(fd)
        except OSError as e:
            raise WorkdirLocked(f"{workdir}: cannot write its lock {path} ({e.strerror or e})") from None
        return cls(path, fd, record)

    def _heartbeat(self):
        while not self._stop.wait(HEARTBEAT_S):
            with contextlib.suppress(OSError):
                os.utime(self.fd)

    def release(self):
        self._stop.set()
        self._beat.join(timeout=5)
        try:
            if os.stat(self.path).st_ino == os.fstat(self.fd).st_ino:
                os.unlink(self.path)
        except OSError:
            pass  # gone already, or a read-only or full filesystem: the flock still goes below
        finally:
            with contextlib.suppress(OSError):
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)


def _busy_message(workdir: Path, path: Path, record: Optional[dict]) -> str:
    if record is None:
        return (f"{workdir} is in use by another run (its lock {path} is held); wait for it to finish or stop it, "
                f"or choose another --workdir")
    who = f"process {record.get('pid')} on host {record.get('host')}"
    what = f"{record.get('command') or 'a run'}, started {record.get('started', '?')}"
    if record.get("host") == socket.gethostname():
        how = f"wait for it to finish or stop it (kill {record.get('pid')}), or choose another --workdir"
    else:
        how = (f"wait for it to finish or stop it on {record.get('host')}, or choose another --workdir; "
               f"if that run is not running, delete {path}")
    return f"{workdir} is in use by another run: {who} ({what}) holds {path}; {how}"


def _stale_because(record: dict, path: Path) -> Optional[str]:
    """Why the lock of `record` is stale, or None while its holder may be running."""
    if record.get("host") == socket.gethostname():
        if record.get("boot_id") and record["boot_id"] != _boot_id():
            return "the machine has restarted since"
        pid = record.get("pid")
        if not isinstance(pid, int) or not _alive(pid, record.get("pid_start")):
            return "that process is no longer running"
        if pid == os.getpid():
            return "this process took it and did not release it"
        return None
    age = _age(path)
    if age >= STALE_S:
        return (f"its heartbeat stopped {age / 60:.0f} min ago (a process on another host cannot be checked; "
                f"a lock not touched for {STALE_S / 60:.0f} min is stale)")
    return None


def _alive(pid: int, start: Optional[int]) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: alive
    stat = _proc_stat(pid)
    if stat is None:
        return True  # no /proc: the process id alone says
    state, started = stat
    return state not in ("Z", "X") and (start is None or started == start)


def _proc_stat(pid: int) -> Optional[tuple[str, int]]:
    """(state, start time in clock ticks after boot) of process `pid` from /proc."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return fields[0], int(fields[19])


def _boot_id() -> Optional[str]:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def _age(path: Path) -> float:
    try:
        return max(0.0, time.time() - path.stat().st_mtime)
    except OSError:
        return 0.0


def _own_record(command: str) -> dict:
    stat = _proc_stat(os.getpid())
    return {"host": socket.gethostname(), "pid": os.getpid(), "pid_start": None if stat is None else stat[1],
            "boot_id": _boot_id(), "run_id": uuid.uuid4().hex, "command": command or " ".join(sys.argv[:1]),
            "processes": _process_count(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}


def _read_record(path: Path, wait: bool = False) -> Optional[dict]:
    """The holder's record; with `wait`, give a holder that is writing it a moment."""
    for attempt in range(10 if wait else 1):
        try:
            record = json.loads(path.read_text())
            if isinstance(record, dict):
                return record
        except (OSError, ValueError):
            pass
        if wait:
            time.sleep(0.05 * (attempt + 1))
    return None


def _process_index() -> int:
    jax = sys.modules.get("jax")  # a process that has not imported JAX runs alone
    return 0 if jax is None else jax.process_index()


def _process_count() -> int:
    jax = sys.modules.get("jax")
    return 1 if jax is None else jax.process_count()


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
