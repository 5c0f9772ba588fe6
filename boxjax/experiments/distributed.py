"""Evaluations across processes and hosts with `jax.distributed`.

Every process runs the same command with its own process id; they meet at a coordinator (JAX's
coordination service, on process 0's host), each evaluates its share of the boxes on its own local
devices (sharded over them as on one host: `boxjax.control.batch`), and the results are gathered on
every process; process 0 writes them. On N hosts, or N processes on one:

    boxjax evaluate --boxes 10000 --coordinator HOST0:12355 --num-processes N --process-id I --out DIR

Which process runs which box (`share`): box j on process j mod N, so that every share gets the same mix
of safe and hazardous boxes. Every box keeps its own episode key wherever it runs: one at a time
(`--one-at-a-time`, `controller.run_episode`) an episode is the same bit for bit on any process (a test
runs two processes on this machine against one); batched, the planner's vmapped call depends on the
batch's width at float32 round-off, so the rows agree in distribution, as for `--slots`
(docs/results/batched-episodes.md).

How the results travel: each process pickles its rows, balance traces and actions and all-gathers the
bytes (`jax.experimental.multihost_utils.process_allgather`, the collective JAX programs use; on CPUs
through gloo, set by `initialize`). Nothing is written by a process other than 0, so no shared file system
is needed.
"""

from __future__ import annotations

import pickle
from typing import Any

import jax
import numpy as np


def check(coordinator: str | None, num_processes: int | None, process_id: int | None) -> None:
    """Raise ValueError naming what is wrong with a distributed run's settings (all three or none)."""
    given = [x is not None for x in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise ValueError(
            "--coordinator, --num-processes and --process-id go together: give all three or none"
        )
    if not any(given):
        return
    host, _, port = str(coordinator).rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--coordinator {coordinator!r} must be HOST:PORT (e.g. node0:12355)")
    if num_processes < 1:
        raise ValueError(f"--num-processes {num_processes} must be >= 1")
    if not 0 <= process_id < num_processes:
        raise ValueError(f"--process-id {process_id} must be in [0, {num_processes - 1}]")


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join the run (before JAX starts its backend, as `jax.distributed.initialize` requires). On CPUs
    the processes exchange results through gloo's collectives."""
    check(coordinator, num_processes, process_id)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)


def share(n: int, index: int | None = None, count: int | None = None) -> list[int]:
    """The boxes (of n) that process `index` of `count` runs (default: this process of this run)."""
    index = jax.process_index() if index is None else index
    count = jax.process_count() if count is None else count
    return list(range(index, n, count))


def gather(obj: Any) -> list[Any]:
    """Every process's `obj` (picklable), in process order, on every process; [obj] for one process."""
    if jax.process_count() == 1:
        return [obj]
    from jax.experimental import multihost_utils

    data = np.frombuffer(pickle.dumps(obj), np.uint8)
    sizes = np.asarray(multihost_utils.process_allgather(np.asarray([data.size], np.int64))).reshape(-1)
    padded = np.zeros(int(sizes.max()), np.uint8)
    padded[: data.size] = data
    every = np.asarray(multihost_utils.process_allgather(padded)).reshape(len(sizes), -1)
    return [pickle.loads(every[i, : int(sizes[i])].tobytes()) for i in range(len(sizes))]
