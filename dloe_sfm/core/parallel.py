"""Independent solves (events of one capture) in parallel worker processes on one machine.

Workers are spawned with one BLAS / OpenMP thread each (set in their environment before they
import numpy), so that W workers use W cores and never oversubscribe them. A solve gives the
same numbers in a worker as in the calling process when both run one BLAS thread.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
MIN_PARALLEL_SLOTS = 25_000
"""With ``workers`` = auto, events are solved in parallel from this many (image, point) slots in
all, 1000 images of 25 points (a spawned worker takes about a second to start; a solve's time
grows with its images times its points: docs/method.md, "Speed")."""


@contextmanager
def single_threaded_children() -> Iterator[None]:
    """Processes spawned inside inherit one BLAS / OpenMP thread each."""
    old = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    os.environ.update({k: "1" for k in THREAD_VARIABLES})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def worker_count(workers: int | str, tasks: int, slots: int) -> int:
    """Processes to use for ``tasks`` independent solves of ``slots`` (image, point) slots in
    all: 1 (in this process) for a single task; ``auto``: one per core, up to one per task, from
    :data:`MIN_PARALLEL_SLOTS` slots."""
    if tasks < 2:
        return 1
    if workers == "auto":
        return min(os.cpu_count() or 1, tasks) if slots >= MIN_PARALLEL_SLOTS else 1
    return min(int(workers), tasks)


def map_in_processes(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """``fn`` over ``items`` in ``workers`` spawned single-threaded processes (results in order;
    ``fn`` a module-level function and items picklable). The first exception raised by a task
    is raised here."""
    with single_threaded_children(), ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn")) as pool:
        yield from pool.map(fn, items)
