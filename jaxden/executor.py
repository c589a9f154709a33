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
- ``'ray'``: ``ray.remote`` tasks on the Ray cluster named by ``ray_address`` (the
  ``--ray-address`` option) or ``RAY_ADDRESS``; ``local`` starts a private Ray on this machine,
  and no address is an error (never a silent private cluster). Every node must see the files
  at the same paths (a shared filesystem; callers pass absolute paths) and run the same Python
  environment. Workers' output stays out of the command's (``log_to_driver=False``); a task's
  exception is re-raised as itself; a task lost with its node is retried elsewhere; a cluster
  with no free CPU for ``JAXDEN_RAY_WAIT_S`` seconds (default 300) is an error instead of a
  silent wait. Needs ``pip install jaxden[ray]``; see docs/scaling.md.

``workers`` caps how many tasks run at once (default: :func:`default_workers`). A task that
raises stops the map: tasks not yet started are cancelled and the exception is re-raised in the
caller; local tasks already running finish in the background and are discarded, Ray tasks are
cancelled (also on Ctrl-C).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import socket
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal, Protocol

from jaxden.errors import JaxdenError

ExecutorKind = Literal["local", "serial", "ray"]
EXECUTOR_KINDS: tuple[str, ...] = ("local", "serial", "ray")

RAY_ADDRESS_ENV = "RAY_ADDRESS"
#: Environment variable: seconds a Ray map may find no free CPU before it gives up.
RAY_WAIT_ENV = "JAXDEN_RAY_WAIT_S"
DEFAULT_RAY_WAIT_S = 300.0
RAY_NOTICE_S = 10.0
RAY_POLL_S = 1.0
RAY_CONNECT_TIMEOUT_S = 5.0
#: Retries of a task whose worker or node died (the task is rerun on another node).
RAY_TASK_RETRIES = 3
RAY_LOCAL_STORE_BYTES = 256 * 2**20

__all__ = [
    "EXECUTOR_KINDS",
    "Executor",
    "ExecutorError",
    "LocalExecutor",
    "RayExecutor",
    "SerialExecutor",
    "default_workers",
    "make_executor",
    "resolve_ray_address",
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
    _import_plugins()


def _import_plugins() -> None:
    """In a spawned worker: the plugins the parent imported (it wrote them into
    ``JAXDEN_PLUGINS``), before any task unpickles a reference to their code. A failure is
    printed as the parent would print it; the task then fails on the missing name."""
    from jaxden.errors import JaxdenError
    from jaxden.plugins import load_ambient

    try:
        load_ambient()
    except JaxdenError as error:
        print(f"jaxden: error: in a worker process: {error}", file=sys.stderr)


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
    """Ray tasks on the cluster at ``address``; at most ``workers`` in flight (default: the
    cluster's CPUs / ``num_cpus_per_task``).

    ``address``: the head node's ``HOST:PORT`` (``ray start --head`` prints it), ``auto`` (the
    cluster started on this machine), a ``ray://`` client address, or ``local`` (a private
    Ray on this machine, stopped at :meth:`close`); None takes ``RAY_ADDRESS``, and neither
    is an :class:`ExecutorError` (never a silent private cluster). Every node must see the
    caller's files at the same paths (a shared filesystem) and have the same Python
    environment; each task runs in the caller's working folder when the node has it.
    ``wait_s``: how long the cluster may have no free CPU while none of these tasks runs
    before the map gives up (default ``JAXDEN_RAY_WAIT_S`` or 300 s; a notice is printed
    after 10 s).
    """

    def __init__(self, workers: int | None = None, *, address: str | None = None,
                 num_cpus_per_task: float = 1.0, wait_s: float | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise ExecutorError(
                "executor 'ray' needs Ray, which is not installed: pip install 'jaxden[ray]'"
            ) from None
        self._ray = ray
        self._owns_ray = False
        self._starts = None
        if ray.is_initialized():  # the caller connected already (a notebook, a test)
            self.address = "(connected)"
        else:
            self.address = resolve_ray_address(address)
            _connect(ray, self.address)
            self._owns_ray = True
        if workers is None:
            cpus = ray.cluster_resources().get("CPU", 0.0)
            workers = max(1, int(cpus // num_cpus_per_task))
        self.workers = int(workers)
        if self.workers < 1:
            raise ExecutorError(f"workers must be >= 1, got {workers}")
        self._num_cpus = float(num_cpus_per_task)
        self._wait_s = _ray_wait_seconds() if wait_s is None else float(wait_s)
        self._remote = ray.remote(num_cpus=self._num_cpus, max_retries=RAY_TASK_RETRIES)(
            _ray_call)

    def _tracker(self):
        """A CPU-less actor on this node that records which tasks have started (Ray does not
        tell a driver whether a submitted task is running or still waits for a CPU)."""
        if self._starts is None:
            ray = self._ray
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            here = ray.get_runtime_context().get_node_id()
            self._starts = ray.remote(num_cpus=0, max_restarts=-1)(_StartLog).options(
                scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=True)).remote()
        return self._starts

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        ray = self._ray
        starts = self._tracker()
        cwd = os.getcwd()
        from jaxden.plugins import worker_payload

        plugins = worker_payload()  # a node without the plugin's file still runs its code
        self._maps = getattr(self, "_maps", 0) + 1
        iterator = (((self._maps, index), item) for index, item in enumerate(items))
        pending: dict[Any, tuple[int, int]] = {}
        exhausted = False
        stall = _Stall(self)
        try:
            while True:
                while not exhausted and len(pending) < self.workers:
                    try:
                        index, item = next(iterator)
                    except StopIteration:
                        exhausted = True
                        break
                    pending[self._remote.remote(fn, item, index, starts, cwd,
                                                plugins)] = index
                if not pending:
                    return
                # A short timeout keeps Ctrl-C responsive and lets a stall be noticed.
                done, _ = ray.wait(list(pending), num_returns=1, timeout=RAY_POLL_S)
                if not done:
                    stall.check(list(pending.values()), starts)
                    continue
                stall.reset()
                for ref in done:
                    pending.pop(ref)
                    yield self._result(ref)
        finally:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)

    def _result(self, ref) -> Any:
        ray = self._ray
        errors = ray.exceptions
        try:
            return ray.get(ref)
        except errors.RayTaskError as error:
            # The task's own exception (a SceneError, a DatasetError, ...) with its message.
            cause = getattr(error, "cause", None)
            raise (cause if isinstance(cause, BaseException) else error) from None
        except errors.TaskCancelledError:
            raise ExecutorError("a Ray task was cancelled (by `ray stop`, or another "
                                "driver?)") from None
        except errors.RayError as error:
            first = (str(error).strip().splitlines() or [""])[0][:300]
            raise ExecutorError(
                f"a Ray task was lost ({type(error).__name__}, after {RAY_TASK_RETRIES} retries "
                f"on other nodes): {first}"
            ) from None

    def close(self) -> None:
        ray = self._ray
        if self._starts is not None:
            with contextlib.suppress(Exception):
                ray.kill(self._starts)
            self._starts = None
        if self._owns_ray and ray.is_initialized():
            ray.shutdown()
            self._owns_ray = False


class _StartLog:
    """The Ray actor behind :meth:`RayExecutor._tracker`."""

    def __init__(self) -> None:
        self.started: set[tuple[int, int]] = set()

    def start(self, index: tuple[int, int]) -> None:
        self.started.add(tuple(index))

    def running(self, indexes: list[tuple[int, int]]) -> list[tuple[int, int]]:
        return [i for i in indexes if tuple(i) in self.started]


def _ray_call(fn: Callable[[Any], Any], item: Any, index: tuple[int, int], starts: Any,
              cwd: str, plugins: list | None = None) -> Any:
    """One task on a Ray worker: say it started, work in the caller's folder (relative paths
    inside configs, e.g. a scene file, then mean what they meant to the caller), import the
    caller's plugins (:func:`jaxden.plugins.load_payload`), run."""
    if starts is not None:
        starts.start.remote(index)
    if cwd and os.path.isdir(cwd) and os.getcwd() != cwd:
        os.chdir(cwd)
    if plugins:
        from jaxden.plugins import load_payload

        load_payload(plugins)
    return fn(item)


class _Stall:
    """Waiting for a CPU: a notice after RAY_NOTICE_S, an ExecutorError after ``wait_s``."""

    def __init__(self, executor: RayExecutor) -> None:
        self.executor = executor
        self.since: float | None = None
        self.noticed = False

    def reset(self) -> None:
        self.since = None

    def check(self, indexes: list[tuple[int, int]], starts: Any) -> None:
        ex = self.executor
        ray = ex._ray
        if ray.available_resources().get("CPU", 0.0) >= ex._num_cpus:
            self.since = None  # a CPU is free: Ray is about to start a task
            return
        with contextlib.suppress(Exception):
            if ray.get(starts.running.remote(indexes), timeout=30):
                self.since = None  # our own tasks hold the CPUs
                return
        now = time.monotonic()
        if self.since is None:
            self.since = now
            return
        waited = now - self.since
        total = ray.cluster_resources().get("CPU", 0.0)
        if waited >= RAY_NOTICE_S and not self.noticed:
            self.noticed = True
            print(f"jaxden: waiting for a free CPU on the Ray cluster at {ex.address} "
                  f"({total:g} CPUs, all busy with other work, for {waited:.0f} s; giving up "
                  f"after {ex._wait_s:g} s, Ctrl-C to stop)", file=sys.stderr, flush=True)
        if waited >= ex._wait_s:
            raise ExecutorError(
                f"the Ray cluster at {ex.address} has had no free CPU for {waited:.0f} s "
                f"({total:g} CPUs in all): none of {len(indexes)} waiting task(s) could start; "
                f"free some CPUs or add nodes (`ray start --address ...`), then rerun "
                f"(JAXDEN_RAY_WAIT_S sets the wait)"
            )


def resolve_ray_address(address: str | None) -> str:
    """The Ray cluster to join: ``address`` (``--ray-address``), else ``RAY_ADDRESS``."""
    address = (address or os.environ.get(RAY_ADDRESS_ENV, "")).strip()
    if not address:
        raise ExecutorError(
            "executor 'ray' needs a Ray cluster to join: pass --ray-address HOST:PORT (the "
            "head node's address that `ray start --head` prints) or set RAY_ADDRESS; "
            "--ray-address local starts a private Ray on this machine instead"
        )
    return address


def _ray_wait_seconds() -> float:
    text = os.environ.get(RAY_WAIT_ENV, "").strip()
    if not text:
        return DEFAULT_RAY_WAIT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value > 0:
        raise ExecutorError(f"{RAY_WAIT_ENV}={text!r}: expected seconds > 0")
    return value


def _quiet_cluster_messages() -> None:
    """Keep the cluster's messages to drivers out of this command's output.

    Even with ``log_to_driver=False`` a Ray driver prints what the cluster publishes to it on
    stdout: a dead node's last 20 raylet log lines, "task failed, retrying" notes. They stay
    in the cluster's logs (``ray logs``); here they go to the ``jaxden.ray`` logger at debug
    level. Ray has no option for it: this wraps ``ray._private.worker.print_to_stdstream``
    (checked with Ray 2.60; with another Ray the messages are simply printed)."""
    import logging

    try:
        from ray._private import worker
    except ImportError:  # pragma: no cover - another Ray layout
        return
    original = getattr(worker, "print_to_stdstream", None)
    if original is None or getattr(original, "jaxden_quiet", False):
        return

    def quiet(data, *args, **kwargs):
        if isinstance(data, dict) and data.get("pid") == "raylet":
            for line in data.get("lines", ()):
                logging.getLogger("jaxden.ray").debug("%s", line)
            return None
        return original(data, *args, **kwargs)

    quiet.jaxden_quiet = True  # type: ignore[attr-defined]
    worker.print_to_stdstream = quiet


def _connect(ray, address: str) -> None:
    """``ray.init`` for ``address`` with the workers' output kept out of this command's, and
    one clear line when the cluster cannot be reached."""
    import logging

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    _quiet_cluster_messages()
    options: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.ERROR}
    if address == "local":
        options.update(include_dashboard=False, object_store_memory=RAY_LOCAL_STORE_BYTES)
    elif "://" not in address and address != "auto":
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit():
            raise ExecutorError(f"--ray-address / RAY_ADDRESS {address!r}: expected HOST:PORT "
                                f"(e.g. 10.0.0.1:6379), 'auto', 'local' or ray://HOST:PORT")
        try:
            socket.create_connection((host, int(port)), timeout=RAY_CONNECT_TIMEOUT_S).close()
        except OSError as error:
            raise ExecutorError(
                f"cannot reach the Ray cluster at {address} (--ray-address / RAY_ADDRESS): "
                f"{error.strerror or error}; start it with `ray start --head --port {port}` on "
                f"{host}, or pass --ray-address local for a private Ray on this machine"
            ) from None
    try:
        ray.init(address=address, **options)
    except Exception as error:  # noqa: BLE001 - ConnectionError, RuntimeError, ValueError
        first = (str(error).strip().splitlines() or [type(error).__name__])[0][:300]
        raise ExecutorError(
            f"cannot join the Ray cluster at {address} (--ray-address / RAY_ADDRESS): {first}"
        ) from None


def make_executor(kind: str = "local", workers: int | None = None, *,
                  ray_address: str | None = None) -> Executor:
    """An executor of the given kind ('local', 'serial' or 'ray') with ``workers`` slots.

    ``workers=None`` takes :func:`default_workers` (local) or the cluster's CPUs (Ray).
    ``ray_address``: the cluster for 'ray' (see :class:`RayExecutor`; None: ``RAY_ADDRESS``).
    """
    if kind == "local":
        return LocalExecutor(workers)
    if kind == "serial":
        return SerialExecutor(workers)
    if kind == "ray":
        return RayExecutor(workers, address=ray_address)
    raise ExecutorError(f"unknown executor {kind!r}; choose one of {', '.join(EXECUTOR_KINDS)}")
