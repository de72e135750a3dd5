"""Running independent jobs on the machine's cores: `ordered_map` gives the results in job order,
so what a stage writes never depends on how many worker processes computed it.

Workers are fresh interpreters (`spawn`): nothing is inherited from the stage's process but the
jobs and the initializer's arguments, so no lock or thread pool (BLAS, OpenMP) is copied mid-use.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

J = TypeVar("J")
R = TypeVar("R")


def usable_cpus() -> int:
    """The CPUs this process may run on (a container's or `taskset`'s limit, not the machine's)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity else os.cpu_count() or 1


# The project's machines have 2 cores; more workers than cores only adds start-up time.
WORKERS = min(2, usable_cpus())
WORKERS_ENV = "NEEDLECUE_WORKERS"  # a number: worker processes whatever the work (never above WORKERS)


def workers_for(work: float, worth: float, workers: int = WORKERS) -> int:
    """`workers` when `work` (the jobs' size, in the caller's own measure) reaches `worth`, else 1: a
    worker is a fresh interpreter, seconds of imports before it does anything, which small jobs do not
    repay (the project's tests run the stages on a few trials). `NEEDLECUE_WORKERS=N` decides instead
    (at most `workers`): the tests run the worker processes on small data that way."""
    forced = os.environ.get(WORKERS_ENV, "").strip()
    if forced:
        return max(1, min(int(forced), workers))
    return workers if work >= worth else 1


def ordered_map(
    fn: Callable[[J], R],
    jobs: Sequence[J],
    workers: int = WORKERS,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
) -> list[R]:
    """`[fn(job) for job in jobs]`, on up to `workers` processes when there is more than one job.
    `fn` and `initializer` must be module-level functions (they are pickled by name)."""
    return list(ordered_imap(fn, jobs, workers, initializer, initargs))


def ordered_imap(
    fn: Callable[[J], R],
    jobs: Sequence[J],
    workers: int = WORKERS,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
) -> Iterator[R]:
    """`ordered_map`, each result given as soon as it and those before it are done (for progress)."""
    if workers < 2 or len(jobs) < 2:
        if initializer is not None:
            initializer(*initargs)
        yield from (fn(job) for job in jobs)
        return
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(
        min(workers, len(jobs)), mp_context=context, initializer=initializer, initargs=initargs
    ) as pool:
        yield from pool.map(fn, jobs)
