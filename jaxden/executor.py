"""Run many independent tasks (renders, sweep runs) in parallel, locally or on a Ray cluster.

``make_executor(kind, workers)`` returns an object with ``map_unordered(fn, items)``, which
yields ``fn(item)`` for every item, in completion order, and ``close()`` (it is also a context
manager). Kinds:

- ``'local'`` (default): a ``concurrent.futures.ProcessPoolExecutor`` with the ``'spawn'``
  start method, because forking a process that has started Mitsuba's or JAX's thread pools can
  deadlock. ``fn`` and the items must be picklable (module-level functions); worker processes
  are reused across items, so each imports Mitsuba/JAX once. A worker exits within about a
  second of its parent's death (``kill PID`` of a build, not only Ctrl-C): an orphaned worker
  would otherwise finish its tasks unseen and render the same items as the rerun.
- ``'serial'``: in this process, one item at a time (no pickling; for tests, debugging, and
  for jobs that already use every core per task).
- ``'ray'``: ``ray.remote`` tasks on the cluster that ``ray.init()`` connects to (the
  ``RAY_ADDRESS`` environment variable, or a local one). Needs ``pip install jaxden[ray]``.

``workers`` caps how many tasks run at once (default: :func:`default_workers`). A task that
raises stops the map: tasks not yet started are cancelled and the exception is re-raised in the
caller; tasks already running finish in the background and are discarded.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal, Protocol

from jaxden.errors import JaxdenError

ExecutorKind = Literal["local", "serial", "ray"]
EXECUTOR_KINDS: tuple[str, ...] = ("local", "serial", "ray")

__all__ = [
    "EXECUTOR_KINDS",
    "Executor",
    "ExecutorError",
    "LocalExecutor",
    "RayExecutor",
    "SerialExecutor",
    "default_workers",
    "make_executor",
]


class ExecutorError(JaxdenError, RuntimeError):
    """An executor cannot be created (unknown kind, Ray missing) or lost a worker process."""


class Executor(Protocol):
    workers: int

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...


def default_workers() -> int:
    """A modest default: one process per 8 CPUs, at least 1 (1 on the 2-core project machine).

    Each Mitsuba ``llvm`` render (and each JAX training run) already uses every core, so more
    processes mostly add memory and contention; a second process only helps to hide the
    single-threaded kernel compilation. On 2 cores, building the tiny dataset with 2 worker
    processes was slower than with 1 (see ``jaxden.data.builder``); the 1-per-8 rule for
    bigger machines is a guess, not a measurement.
    """
    return max(1, (os.cpu_count() or 1) // 8)


class _Base:
    workers: int = 1

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:  # pragma: no cover - overridden where needed
        pass


class SerialExecutor(_Base):
    """Runs every task in this process, in order."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = 1

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        for item in items:
            yield fn(item)


PARENT_POLL_SECONDS = 1.0


def _exit_with_parent(parent: int) -> None:
    """Worker initializer: a daemon thread that ends this process once ``parent`` is gone
    (the worker is then re-parented, so ``os.getppid()`` changes)."""
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="jaxden-parent-watch", daemon=True).start()


class LocalExecutor(_Base):
    """A pool of ``workers`` spawned processes (created on first use, reused until close)."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = default_workers() if workers is None else int(workers)
        if self.workers < 1:
            raise ExecutorError(f"workers must be >= 1, got {workers}")
        self._pool: cf.ProcessPoolExecutor | None = None

    def _get_pool(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(
                max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_exit_with_parent, initargs=(os.getpid(),),
            )
        return self._pool

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        pool = self._get_pool()
        pending: set[cf.Future] = set()
        iterator = iter(items)
        # A bounded window (2 per worker) keeps every worker busy without queueing the whole
        # job, so an error or Ctrl-C stops quickly and little work is thrown away.
        window = 2 * self.workers
        exhausted = False
        try:
            while True:
                while not exhausted and len(pending) < window:
                    try:
                        item = next(iterator)
                    except StopIteration:
                        exhausted = True
                        break
                    pending.add(pool.submit(fn, item))
                if not pending:
                    return
                done, pending = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
                for future in done:
                    try:
                        result = future.result()
                    except BrokenProcessPool as error:
                        self._pool = None
                        raise ExecutorError(
                            "a worker process died (killed, out of memory, or a crash in native "
                            f"code such as Mitsuba's LLVM backend): {error}"
                        ) from None
                    yield result
        finally:
            for future in pending:
                future.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class RayExecutor(_Base):
    """Ray tasks; at most ``workers`` in flight (default: the cluster's CPU count)."""

    def __init__(self, workers: int | None = None, *, num_cpus_per_task: float = 1.0) -> None:
        try:
            import ray
        except ImportError:
            raise ExecutorError(
                "executor 'ray' needs Ray, which is not installed: pip install 'jaxden[ray]'"
            ) from None
        self._ray = ray
        if not ray.is_initialized():
            ray.init(ignore_reinit_error=True, log_to_driver=False)
        if workers is None:
            workers = max(1, int(ray.cluster_resources().get("CPU", 1) // num_cpus_per_task))
        self.workers = int(workers)
        if self.workers < 1:
            raise ExecutorError(f"workers must be >= 1, got {workers}")
        self._num_cpus = num_cpus_per_task
        self._remote_cache: dict[Callable, Any] = {}

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        ray = self._ray
        remote = self._remote_cache.get(fn)
        if remote is None:
            remote = self._remote_cache[fn] = ray.remote(num_cpus=self._num_cpus)(fn)
        iterator = iter(items)
        pending: list = []
        exhausted = False
        try:
            while True:
                while not exhausted and len(pending) < self.workers:
                    try:
                        pending.append(remote.remote(next(iterator)))
                    except StopIteration:
                        exhausted = True
                if not pending:
                    return
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayTaskError as error:
                        # Re-raise the task's own exception (e.g. a SceneError) when Ray kept it.
                        cause = getattr(error, "cause", None)
                        raise (cause if isinstance(cause, BaseException) else error) from None
                    yield result
        finally:
            for ref in pending:
                ray.cancel(ref)


def make_executor(kind: str = "local", workers: int | None = None) -> Executor:
    """An executor of the given kind ('local', 'serial' or 'ray') with ``workers`` slots.

    ``workers=None`` takes :func:`default_workers` (local) or the cluster's CPUs (Ray).
    """
    if kind == "local":
        return LocalExecutor(workers)
    if kind == "serial":
        return SerialExecutor(workers)
    if kind == "ray":
        return RayExecutor(workers)
    raise ExecutorError(f"unknown executor {kind!r}; choose one of {', '.join(EXECUTOR_KINDS)}")
