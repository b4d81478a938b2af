"""Memory checked before a run allocates anything big.

`checked_compile` compiles the run's update on the abstract training state
(`jax.eval_shape(init, key)`: shapes and dtypes, nothing allocated) and compares what
the run needs with what its devices have, before `init` or a restore allocates the state:

- needed, per device: the training state plus the compiled update's own buffers, from
  XLA's memory analysis (`compiled.memory_analysis()`: arguments + temporaries +
  outputs - the donated arguments the outputs reuse);
- available, per device: on the CPU the host's available memory (`MemAvailable` of
  /proc/meminfo, or the cgroup's limit less its use when lower) shared by the devices;
  on an accelerator `memory_stats()['bytes_limit'] - ['bytes_in_use']`.

A run that does not fit stops with one line (`BatchTooLarge`) giving both numbers and
the largest `env.num_envs` that would fit, estimated linearly from the cost per
environment: from the run's compiled update and that of a smaller batch. When the
training state alone is larger than the memory, the run's update is not even compiled
(XLA's compile of a huge batch takes minutes and gigabytes itself): the update's cost
per environment then comes from a compile at a small batch (`probe_batch`).

`A2CATVN_SKIP_MEMORY_CHECK=1` in the environment skips the check.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable, Optional

import jax
import numpy as np

from a2catvn_jax.errors import UserError

SKIP_VARIABLE = "A2CATVN_SKIP_MEMORY_CHECK"
MAX_PROBE = 4096  # environments of the small compile that estimates the cost per environment


class BatchTooLarge(UserError, RuntimeError):
    """The run's state and update do not fit in the memory of its devices."""


def tree_bytes(tree) -> int:
    """Bytes of the arrays (or `ShapeDtypeStruct`s) of `tree`."""
    return sum(int(np.prod(x.shape, dtype=np.int64)) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(tree))


def update_bytes(compiled) -> Optional[tuple[int, int]]:
    """(arguments, the update's own buffers) of a compiled update per device, from XLA's
    memory analysis; None where the backend gives none."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not implemented on some backends
        return None
    if m is None:
        return None
    return int(m.argument_size_in_bytes), int(m.temp_size_in_bytes + m.output_size_in_bytes - m.alias_size_in_bytes)


def host_available() -> Optional[int]:
    """Bytes of memory this process can still allocate on the host: /proc/meminfo's
    MemAvailable (or free pages), lowered to what the cgroup's limit leaves."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    if not found:
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            pass
    cgroup = _cgroup_available()
    if cgroup is not None:
        found.append(cgroup)
    return min(found) if found else None


def _cgroup_available() -> Optional[int]:
    def read(path):
        try:
            return Path(path).read_text().strip()
        except OSError:
            return None

    for limit_file, usage_file, stat_file, inactive in (
            ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current", "/sys/fs/cgroup/memory.stat", "inactive_file"),
            ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes",
             "/sys/fs/cgroup/memory/memory.stat", "total_inactive_file")):
        limit, usage = read(limit_file), read(usage_file)
        if limit is None or usage is None or not limit.isdigit() or int(limit) >= 2**60:
            continue
        reclaimable = 0
        for line in (read(stat_file) or "").splitlines():
            name, _, value = line.partition(" ")
            if name == inactive and value.isdigit():
                reclaimable = int(value)
        return max(0, int(limit) - int(usage) + reclaimable)
    return None


def available_bytes(devices) -> tuple[Optional[int], str]:
    """(bytes available to each of `devices`, what that is in words)."""
    platform = devices[0].platform
    if platform == "cpu":
        host = host_available()
        if host is None:
            return None, "unknown host memory"
        shared = f" shared by {len(devices)} devices" if len(devices) > 1 else ""
        return host // len(devices), f"{fmt_bytes(host)} of available host memory{shared}"
    free = []
    for d in devices:
        try:
            stats = d.memory_stats() or {}
        except Exception:  # noqa: BLE001 - not every backend reports
            stats = {}
        if "bytes_limit" in stats:
            free.append(int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)))
    if len(free) != len(devices):
        return None, f"unknown {platform} memory"
    each = " each" if len(devices) > 1 else ""
    return min(free), f"{fmt_bytes(min(free))} free on the {platform} device{'s' if len(devices) > 1 else ''}{each}"


def fmt_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:,.1f} TiB"


def probe_batch(cfg, per_device: int) -> int:
    """The small batch whose compile estimates the update's cost per environment: the
    replay's environments per rollout (beyond which the replay no longer grows), at most
    `MAX_PROBE`, below the run's batch per device."""
    return max(1, min(max(cfg.train.replay_envs, 16), MAX_PROBE, per_device // 2))


def probe_cost(cfg, env, batch: int) -> tuple[int, Optional[int]]:
    """(training state bytes, the update's own bytes) of `cfg` at `batch` environments on
    one device, compiled on abstract shapes in the world of `env` (nothing allocated)."""
    from a2catvn_jax.agent.networks import make_networks
    from a2catvn_jax.agent.update import make_update, repeated
    from a2catvn_jax.env import make_env

    small = dataclasses.replace(cfg, seed=0, env=dataclasses.replace(cfg.env, num_envs=batch))
    small_env = make_env(small.env, world=getattr(env, "world", None))
    init, update = make_update(small_env, make_networks(small, small_env.num_actions), small)
    abstract = jax.eval_shape(init, jax.random.PRNGKey(0))
    sizes = update_bytes(repeated(update).lower(abstract, np.int32(1)).compile())
    return tree_bytes(abstract), None if sizes is None else sizes[1]


def checked_compile(cfg, env, compile_fn: Callable, template, devices) -> tuple[object, str]:
    """(the compiled update, a line saying what it needs of what memory).

    `compile_fn(template)` compiles the run's update for the abstract train state
    `template`; `BatchTooLarge` when the state and the update would not fit in the
    memory of `devices` (see the module docstring)."""
    if os.environ.get(SKIP_VARIABLE, "") not in ("", "0"):
        return compile_fn(template), f"memory: not checked ({SKIP_VARIABLE} is set)"
    n = len(devices)
    batch = cfg.env.num_envs
    per_device = max(1, batch // n)
    available, where = available_bytes(devices)
    state = tree_bytes(template)
    if available is not None and state / n > available:  # hopeless: estimate from a small compile only
        p = probe_batch(cfg, per_device)
        state_p, update_p = probe_cost(cfg, env, p)
        per_env = (state - state_p) / max(batch - p, 1) + (update_p or 0) / p
        fixed = state_p - (state - state_p) / max(batch - p, 1) * p
        need = fixed + per_env * per_device
        raise BatchTooLarge(_too_large(batch, n, need, state / n, need - state / n, available, where, fixed, per_env,
                                       f"estimated from a compile at {p} environments"))
    compiled = compile_fn(template)
    sizes = update_bytes(compiled)
    if sizes is None:
        return compiled, f"memory: the training state needs {fmt_bytes(state)}; the update's memory is unknown"
    arguments, own = sizes
    need = arguments + own
    each = f" on each of {n} devices" if n > 1 else ""
    line = (f"memory: the run needs {fmt_bytes(need)}{each} (training state {fmt_bytes(arguments)}, "
            f"update {fmt_bytes(own)}) of {where}")
    if available is None or need <= available:
        return compiled, line
    if per_device < 2:
        raise BatchTooLarge(_too_large(batch, n, need, arguments, own, available, where, need, 0.0, ""))
    p = max(1, per_device // 2)
    state_p, update_p = probe_cost(cfg, env, p)
    per_env = (need - state_p - (update_p or 0)) / (per_device - p)
    fixed = need - per_env * per_device
    raise BatchTooLarge(_too_large(batch, n, need, arguments, own, available, where, fixed, per_env, ""))


def _too_large(batch, n, need, state, own, available, where, fixed, per_env, how) -> str:
    """The one line of a run that does not fit (all sizes per device)."""
    fit = int((available - fixed) // per_env) * n if per_env > 0 else 0
    if fit >= n:
        fits = "environment fits" if fit == 1 else "environments fit"
        advice = (f"at most about {fit:,} {fits} ({fmt_bytes(per_env)} each{'; ' + how if how else ''}): "
                  f"lower env.num_envs" + (f" to a multiple of {n}" if n > 1 else ""))
    else:
        advice = (f"not even {n} environment{'s' if n > 1 else ''} fit{'' if n > 1 else 's'}"
                  f"{' (' + how + ')' if how else ''}: use a smaller configuration")
    devices = f" on each of {n} devices" if n > 1 else ""
    return (f"env.num_envs={batch:,} does not fit in memory: the run needs about {fmt_bytes(need)}{devices} "
            f"(training state {fmt_bytes(state)}, update {fmt_bytes(own)}), and there is {where}; {advice} "
            f"({SKIP_VARIABLE}=1 skips this check)")
