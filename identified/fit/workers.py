"""Independent fits side by side: this process and ``jobs - 1`` forked worker processes.

The effect search (:mod:`identified.fit.pipeline`) refits the model once per candidate effect in
every round.  The fits are independent, so with ``jobs > 1`` a :class:`TaskPool` runs them in this
process and in ``jobs - 1`` workers at once, longest first, by list scheduling: a task goes to a
worker that is free, and whenever every worker is busy this process takes the next task itself,
so no task waits in a queue behind a slow one and a round takes about the longest of its fits or
its total over ``jobs``, whichever is more.

The workers are *forked* from this process: they inherit its data and imported modules, so they
start in milliseconds, and the caller's script is never re-run (as ``spawn`` would re-import
``__main__``).  While the pool is open every process, this one included, runs torch on ONE
intra-op thread: ``jobs`` processes then ask for ``jobs`` cores (torch's idle threads spin and
fight each other for cores), and a forked child must not use OpenMP threads when its parent has
(GNU libgomp's pool does not survive fork: the child hangs; ``tests/test_workers.py``).

Where fork is not available (not Linux) or ``jobs`` is 1, every task runs in this process; so do
they inside a daemonic process (a ``multiprocessing.Pool`` worker may have no children).  The
results do not depend on ``jobs``: each task is the same deterministic computation wherever it
runs (``tests/test_workers.py`` compares the effect search with one job and two).
"""

from __future__ import annotations

import multiprocessing
import numbers
import os
import signal
import sys
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import ExitStack
from typing import Any, Generic, TypeVar

import torch

from identified.threads import torch_threads

__all__ = ["TaskPool", "resolve_jobs"]

C = TypeVar("C")
T = TypeVar("T")

#: the context of the worker's tasks, set once when the worker starts (inherited through fork)
_CONTEXT: Any = None


def resolve_jobs(jobs: int | str | None) -> int:
    """``"auto"`` or ``None``: the cores this process may run on; an int >= 1 as given."""
    if jobs is None or jobs == "auto":
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # not Linux
            return max(1, os.cpu_count() or 1)
    if isinstance(jobs, bool) or not isinstance(jobs, numbers.Integral) or jobs < 1:
        raise ValueError(f"jobs must be 'auto' or an integer >= 1, got {jobs!r}")
    return int(jobs)


def _start_worker(context: Any, threads: int) -> None:
    global _CONTEXT
    _CONTEXT = context
    torch.set_num_threads(threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it stops the workers


def _run(fn: Callable[[Any, Any], Any], task: Any) -> Any:
    return fn(_CONTEXT, task)


class TaskPool(Generic[C]):
    """Runs ``fn(context, task)`` over lists of tasks in this process and ``jobs - 1`` workers.

    ``fn`` must be a module-level function (it is sent to the workers by name); ``context`` is the
    read-only data every task shares (the workers inherit it at fork).  Use as a context manager:
    the workers start with the first task given to them and stop when the block ends.
    """

    def __init__(self, fn: Callable[[C, Any], Any], context: C, jobs: int | str | None = 1) -> None:
        self.fn, self.context = fn, context
        self.jobs = resolve_jobs(jobs)
        if not sys.platform.startswith("linux") or multiprocessing.current_process().daemon:
            self.jobs = 1  # no fork; or inside a daemonic worker (a multiprocessing.Pool's), which may not fork
        self.threads = 1  # see the module docstring: libgomp after fork, and one core a process
        self._pool: ProcessPoolExecutor | None = None
        self._stack = ExitStack()

    def __enter__(self) -> TaskPool[C]:
        if self.jobs > 1:
            self._pool = ProcessPoolExecutor(self.jobs - 1, mp_context=multiprocessing.get_context("fork"),
                                             initializer=_start_worker, initargs=(self.context, self.threads))
            self._stack.enter_context(torch_threads(self.threads))
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if self._pool is not None:
            if exc_type is not None:  # an error or Ctrl-C here: the workers' fits are not wanted
                for p in list((getattr(self._pool, "_processes", None) or {}).values()):  # no public API < 3.14
                    p.terminate()
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._stack.close()

    def map(self, tasks: Sequence[T], on_done: Callable[[], None] | None = None) -> list[Any]:
        """``fn(context, task)`` for every task, results in the tasks' order; give the longest
        tasks first (they are started in that order).  ``on_done`` is called after each task."""
        results: list[Any] = [None] * len(tasks)
        todo = deque(range(len(tasks)))
        running: dict[Future, int] = {}

        def finish(i: int, value: Any) -> None:
            results[i] = value
            if on_done is not None:
                on_done()

        while todo or running:
            for f in [f for f in running if f.done()]:
                i = running.pop(f)
                try:
                    finish(i, f.result())
                except BrokenProcessPool:  # a worker died (killed, out of memory): go on without them
                    warnings.warn("a worker process died; its tasks run in this process",
                                  RuntimeWarning, stacklevel=2)
                    todo.appendleft(i)
                    if self._pool is not None:
                        self._pool.shutdown(wait=False, cancel_futures=True)
                        self._pool = None
            while todo and self._pool is not None and len(running) < self.jobs - 1:
                i = todo.popleft()
                running[self._pool.submit(_run, self.fn, tasks[i])] = i
            if todo:
                i = todo.popleft()
                finish(i, self.fn(self.context, tasks[i]))
            elif running:
                wait(running, return_when=FIRST_COMPLETED)
        return results
