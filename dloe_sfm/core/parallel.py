"""Independent solves (events of one capture) in parallel worker processes on one machine.

Workers are spawned with one BLAS / OpenMP thread each (set in their environment before they
import numpy), so that W workers use W cores and never oversubscribe them. A solve gives the
same numbers in a worker as in the calling process when both run one BLAS thread. What a task
logs to ``dloe_sfm``'s logger is logged again in the calling process, after its result. Inside
:func:`kept_workers` the workers started stay for the next tasks.
"""

from __future__ import annotations

import logging
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


_kept: dict[int, ProcessPoolExecutor] | None = None
"""The pools of :func:`kept_workers` by their number of processes (None: outside it)."""


@contextmanager
def kept_workers() -> Iterator[None]:
    """Inside, :func:`map_in_processes` keeps the processes it starts for its next calls (a
    spawned worker takes about a second to start), and they end on leaving."""
    global _kept
    if _kept is not None:  # already inside: the outer one keeps them
        yield
        return
    _kept = {}
    try:
        yield
    finally:
        pools, _kept = _kept, None
        for pool in pools.values():
            pool.shutdown(cancel_futures=True)


def map_in_processes(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """``fn`` over ``items`` in ``workers`` spawned single-threaded processes (results in order;
    ``fn`` a module-level function and items picklable), or here with fewer than two. The first
    exception raised by a task is raised here."""
    if workers < 2:
        yield from map(fn, items)
        return
    level = logging.getLogger("dloe_sfm").getEffectiveLevel()
    kept = _kept is not None
    pool = _kept.get(workers) if kept else None
    if pool is None:
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"))
        if kept:
            _kept[workers] = pool
    try:
        with single_threaded_children():  # processes start as tasks are submitted
            done = pool.map(_logged, [(fn, item, level) for item in items])
        for result, records in done:
            for record in records:
                logging.getLogger(record.name).handle(record)
            yield result
    finally:
        if not kept:
            pool.shutdown(cancel_futures=True)


class _Records(logging.Handler):
    """The records a task logs, their messages formatted (their arguments may not pickle)."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        record.msg, record.args, record.exc_info = record.getMessage(), None, None
        self.records.append(record)


def _logged(task: tuple[Callable[[T], R], T, int]) -> tuple[R, list[logging.LogRecord]]:
    """``fn(item)`` in a worker, with what it logs at ``level`` or above to ``dloe_sfm``'s
    logger: (result, records)."""
    fn, item, level = task
    logger, records = logging.getLogger("dloe_sfm"), _Records()
    logger.setLevel(level)
    logger.addHandler(records)
    logger.propagate = False
    try:
        return fn(item), records.records
    finally:
        logger.removeHandler(records)
