"""One run over several processes (one per machine, or per accelerator) through JAX's own
engine, `jax.distributed`: every process builds the same world, steps and renders its
share of the environments on its local devices, and the update's gradients are reduced
over one global mesh. Process 0 logs; checkpoints are written by all of them together.

`initialize` takes `jax.distributed.initialize`'s arguments (coordinator address, number
of processes, this process's id); left out, JAX reads them from SLURM or Open MPI. On the
CPU the processes exchange arrays through gloo (JAX's CPU collectives).
"""

from __future__ import annotations

import os
from typing import Optional

import jax
import numpy as np

from a2catvn_jax.errors import UserError

# Variables that say a scheduler started this process as one of several (SLURM, Open MPI).
_CLUSTER_SIZES = ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE")


class DistributedError(UserError, RuntimeError):
    """The processes of a run cannot start together."""


class DevicesError(UserError, ValueError):
    """The environments cannot be split over the devices asked for."""


def devices_for(num_envs: int, devices: Optional[int] = None, what: Optional[str] = None) -> list:
    """The devices `num_envs` environments (or the `what` of that count, e.g.
    "pretrain.batch_size=64 samples") are split over: all local ones, or the first
    `devices`; with several processes every device of every process. They must split
    evenly over them (`DevicesError`, one line naming both numbers)."""
    what = what or f"env.num_envs={num_envs} environments"
    if jax.process_count() > 1:
        if devices is not None:
            raise DevicesError(f"--devices {devices}: a run of several processes uses every device of each")
        every = jax.devices()
        if num_envs % len(every):
            raise DevicesError(f"{what} cannot be split evenly over the {len(every)} "
                               f"devices of {jax.process_count()} processes: make it a multiple of {len(every)}")
        return every
    local = jax.local_devices()
    n = len(local) if devices is None else int(devices)
    if not 1 <= n <= len(local):
        raise DevicesError(f"--devices {n}: this machine has {len(local)} {local[0].platform} device(s)")
    if num_envs % n:
        raise DevicesError(f"{what} cannot be split evenly over {n} devices: make it a multiple of {n} or pass --devices")
    return local[:n]


def requested(address: Optional[str] = None, num_processes: Optional[int] = None,
              process_id: Optional[int] = None) -> bool:
    """Whether this process is one of several: an argument is given, or a scheduler
    started more than one task."""
    if any(v is not None for v in (address, num_processes, process_id)):
        return True
    return any(int(os.environ.get(name, "1") or 1) > 1 for name in _CLUSTER_SIZES)


def initialize(address: Optional[str] = None, num_processes: Optional[int] = None,
               process_id: Optional[int] = None, timeout_s: int = 300) -> bool:
    """Join the run's processes (before anything else uses JAX); False when this process
    runs alone. Raises `DistributedError` with one line when they cannot meet."""
    if not requested(address, num_processes, process_id):
        return False
    if num_processes is not None and num_processes < 1:
        raise DistributedError(f"--num-processes must be >= 1, got {num_processes}")
    if process_id is not None and num_processes is not None and not 0 <= process_id < num_processes:
        raise DistributedError(f"--process-id must be in [0, {num_processes}), got {process_id}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # used only where the devices are CPUs
    try:
        jax.distributed.initialize(coordinator_address=address, num_processes=num_processes, process_id=process_id,
                                   initialization_timeout=timeout_s)
    except (RuntimeError, ValueError) as e:
        raise DistributedError(f"could not join the run's processes (coordinator {address or 'from the scheduler'}): "
                               + " ".join(str(e).split())[:300]) from e
    # What each process builds for itself (its world, MJX's data) stays on its own devices.
    jax.config.update("jax_default_device", jax.local_devices()[0])
    return True


def is_main() -> bool:
    """Whether this process logs and owns the work directory (process 0)."""
    return jax.process_index() == 0


def any_process(flag: bool) -> bool:
    """`flag` of any process (every process calls it at the same point): a stop asked of
    one process by a signal stops all of them after the same update."""
    if jax.process_count() == 1:
        return bool(flag)
    from jax.experimental import multihost_utils

    return bool(np.any(multihost_utils.process_allgather(np.asarray(flag, np.int32))))
