"""Parallel execution of the per-layer stages: the worker count and one process-pool map.

Every stage that works layer by layer (scaffold scans, path planning, trajectory planning)
goes through :func:`parallel_map` (or :func:`parallel_imap`, its streaming form), so the
number of workers is decided in one place (:func:`n_workers`, from ``job.cell.cpus``) and
results come back in input order, whatever the number of workers: the output never
depends on ``cpus``.

May import: ``icefab.config`` (the Job) only.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import math
import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from typing import TYPE_CHECKING, Callable, Iterator, Sequence, TypeVar

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job

T = TypeVar("T")
R = TypeVar("R")


def machine_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else all)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def n_workers(job: "Job") -> int:
    """Worker processes for parallel stages: ``job.cell.cpus`` (0 = all cores), never
    more than the machine's cores (issue 10: ``cpus = 1000000`` forked hundreds of
    workers; more processes than cores only add start-up and memory)."""
    cores = machine_cores()
    return max(1, min(int(job.cell.cpus or cores), cores))


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _die_with_parent(parent: int) -> None:
    """Pool worker initializer: end this worker when the process that started it ends,
    even by ``kill -9`` (which runs no clean-up in the parent). On Linux the kernel sends
    SIGKILL (``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread watches the parent.

    Signals are the parent's to handle: SIGTERM ends a worker as it ends any process
    (the handler it inherited raised the command's Terminated in it, and every worker
    printed a traceback when a stopped build ended its pool), and Ctrl-C, which a
    terminal sends to the whole process group, is ignored (a worker waiting for its
    next item printed a KeyboardInterrupt traceback); the parent ends its pool."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        ok = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        ok = False
    if os.getppid() != parent:  # the parent ended before prctl took effect
        os._exit(1)
    if not ok:  # pragma: no cover - not Linux
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(1.0)
            os._exit(1)
        threading.Thread(target=watch, daemon=True).start()


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A process pool of ``workers`` whose workers die with this process."""
    return ProcessPoolExecutor(max_workers=workers, initializer=_die_with_parent,
                               initargs=(os.getpid(),))


@contextlib.contextmanager
def _pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """:func:`process_pool` for one map: waited for when the map ends, its items not yet
    started dropped when it fails or is interrupted. Leaving a ``with
    ProcessPoolExecutor`` waits for every submitted item: a build stopped (SIGTERM,
    Ctrl-C) while it planned its paths ran the rest of the stage first, over a minute on a
    busy machine (CI)."""
    before = set(multiprocessing.active_children())
    pool = process_pool(workers)
    try:
        yield pool
    except BaseException:
        # the items not started are dropped; the workers finish the chunk each is on (a
        # few layers; terminating them makes the pool's own thread fail on the cancelled
        # items) and die with this process
        manager = getattr(pool, "_executor_manager_thread", None)   # shutdown drops it
        pool.shutdown(wait=False, cancel_futures=True)
        if manager is None or not manager.is_alive():
            # interrupted as the pool started its workers, before its manager thread ran:
            # nothing tells them to end, and multiprocessing joins its children at exit,
            # so a program that caught the interruption never ended (found chasing CI
            # stop 48; the CLI leaves by os._exit). They hold no item yet (only that
            # thread hands them out).
            for p in set(multiprocessing.active_children()) - before:
                p.terminate()
        _forget_wakeup(manager)
        raise
    pool.shutdown(wait=True)


def _forget_wakeup(manager: object) -> None:
    """Take the manager thread of a pool shut down without waiting off concurrent.futures'
    exit hook: the hook
    wakes the pool's manager thread through a pipe the thread may be closing as it ends,
    and CPython 3.11 then prints "Exception ignored ... OSError: [Errno 9] Bad file
    descriptor" after the one-line error of a failed command (a hunt's, 2 runs in 3; fixed
    in CPython 3.12's _ThreadWakeup). The shutdown has woken the thread already, and the
    interpreter joins it at exit as any thread."""
    import concurrent.futures.process as cfp

    wakeups = getattr(cfp, "_threads_wakeups", None)
    if manager is not None and wakeups is not None:
        wakeups.pop(manager, None)


def parallel_map(fn: Callable[[T], R], items: Sequence[T], job: "Job",
                 min_items: int = 40,
                 progress: Callable[[int, int], None] | None = None) -> list[R]:
    """``[fn(x) for x in items]`` on a process pool over contiguous chunks of items.

    fn must be a module-level function (it is pickled to the workers). Runs serially when
    only one worker is configured or there are fewer than ``min_items`` items (process
    start-up would cost more than it saves). Items are cut into about ``8 * workers``
    contiguous chunks; no more workers are started than there are chunks.
    progress: called as ``progress(done, total)`` as items complete (after every item when
    serial, after every chunk otherwise).
    """
    workers = n_workers(job)
    total = len(items)
    if workers <= 1 or total < min_items:
        out = []
        for i, x in enumerate(items):
            out.append(fn(x))
            if progress is not None:
                progress(i + 1, total)
        return out
    n_chunks = workers * 8
    size = max(1, math.ceil(total / n_chunks))
    chunks = [list(items[i:i + size]) for i in range(0, total, size)]
    out = []
    with _pool(min(workers, len(chunks))) as pool:
        for chunk in pool.map(_apply_chunk, [fn] * len(chunks), chunks):
            out.extend(chunk)
            if progress is not None:
                progress(len(out), total)
    return out


def _apply_chunk(fn: Callable[[T], R], chunk: list[T]) -> list[R]:
    return [fn(x) for x in chunk]


def parallel_imap(fn: Callable[[T], R], items: Sequence[T], job: "Job", *,
                  chunk_items: int = 8, window: int = 3, min_items: int = 2,
                  progress: Callable[[int, int], None] | None = None) -> Iterator[R]:
    """``fn(x) for x in items``, yielded in input order as the pool completes them.

    Unlike :func:`parallel_map`, the results are not collected: a consumer that writes
    each one away holds only those in flight, at most ``window`` chunks of
    ``chunk_items`` items per worker (issue 17: a stage that works layer by layer must not
    need the whole build in memory). Chunks are submitted ahead so the workers never wait
    for the consumer, unless it is slower than they are. Serial under the same conditions
    as :func:`parallel_map`; progress as there.
    """
    workers = n_workers(job)
    total = len(items)
    if workers <= 1 or total < min_items:
        for i, x in enumerate(items):
            yield fn(x)
            if progress is not None:
                progress(i + 1, total)
        return
    size = max(1, min(int(chunk_items), math.ceil(total / (workers * 8))))
    starts = range(0, total, size)
    workers = min(workers, len(starts))
    done = 0
    with _pool(workers) as pool:
        pending: collections.deque = collections.deque()
        nxt = iter(starts)

        def submit(a: int) -> None:
            pending.append(pool.submit(_apply_chunk, fn, list(items[a:a + size])))
        try:
            for a in itertools.islice(nxt, workers * window):
                submit(a)
            while pending:
                chunk = pending.popleft().result()
                a = next(nxt, None)
                if a is not None:   # one more in flight for each one done
                    submit(a)
                done += len(chunk)
                if progress is not None:
                    progress(done, total)
                yield from chunk
        finally:  # the consumer stopped early (an error, a generator closed): drop the rest
            for f in pending:
                f.cancel()
