"""Beyond one JAX device: every CPU core as a device, and jobs of several processes.

Every core by default
    XLA's CPU backend exposes one device, and one device keeps about one core busy on batched
    convolutions; splitting the batch over one device per core is 1.5-1.9x faster on 2 cores
    (docs/PLATFORM-NOTES). :func:`use_all_cores` adds
    ``--xla_force_host_platform_device_count=N`` (N = the cores this process may use) to
    ``XLA_FLAGS``; the ``jaxden`` command calls it for ``train``, ``sweep`` and ``bench``
    before JAX starts its backend. It leaves ``XLA_FLAGS`` alone when the option is already
    there; ``JAXDEN_CPU_DEVICES=N`` chooses N (``1``: one device, the plain JAX default).
    The option only concerns the CPU backend: on a GPU machine it changes nothing.

Several processes (hosts)
    :func:`initialize` joins a ``jax.distributed`` job: a coordinator address (``HOST:PORT``
    of process 0), the number of processes and this process's id, given as arguments or by
    the environment variables ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and
    ``JAX_PROCESS_ID`` (on Slurm or Open MPI JAX finds the last two itself). On CPUs the
    processes exchange gradients with JAX's gloo collectives over TCP. Then ``jax.devices()``
    lists the devices of every process and :mod:`jaxden.train.loop` splits the global batch
    over all of them (each process loads only its rows; process 0 alone writes the workdir).
"""

from __future__ import annotations

import os
import sys

from jaxden.errors import ConfigError, JaxdenError

__all__ = [
    "CPU_DEVICES_ENV",
    "DistributedError",
    "cpu_count",
    "initialize",
    "is_initialized",
    "is_primary",
    "use_all_cores",
]

#: Environment variable: how many CPU devices to expose (default: one per core).
CPU_DEVICES_ENV = "JAXDEN_CPU_DEVICES"
FORCE_DEVICES_OPTION = "--xla_force_host_platform_device_count"
COORDINATOR_ENV = "JAX_COORDINATOR_ADDRESS"
NUM_PROCESSES_ENV = "JAX_NUM_PROCESSES"
PROCESS_ID_ENV = "JAX_PROCESS_ID"
#: Seconds to wait for every process to join (JAX's default is 300).
DEFAULT_TIMEOUT_S = 300

_initialized = False


class DistributedError(JaxdenError, RuntimeError):
    """A multi-process job cannot start (bad address or ids, coordinator unreachable) or lost
    one of its processes."""


def cpu_count() -> int:
    """The cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def use_all_cores(environ: dict | None = None) -> int | None:
    """Expose one XLA CPU device per core (``XLA_FLAGS``), unless the user chose already.

    Must run before JAX creates its CPU backend (importing jax is fine; the first
    ``jax.devices()`` or computation is too late). Returns the device count it set, or None
    when it left ``XLA_FLAGS`` as it was (the option already present, or one device wanted).
    Raises ConfigError for a ``JAXDEN_CPU_DEVICES`` that is not a whole number >= 1.
    """
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if FORCE_DEVICES_OPTION in flags:
        return None
    wanted = environ.get(CPU_DEVICES_ENV, "").strip()
    if wanted:
        try:
            count = int(wanted)
        except ValueError:
            count = 0
        if count < 1:
            raise ConfigError(f"{CPU_DEVICES_ENV}={wanted!r}: expected a whole number >= 1 "
                              f"(CPU devices for JAX; 1 = JAX's default of one device)")
    else:
        count = cpu_count()
    if count <= 1:
        return None
    environ["XLA_FLAGS"] = f"{flags} {FORCE_DEVICES_OPTION}={count}".strip()
    return count


def _int_from(value: int | None, env: str, what: str, low: int) -> int | None:
    if value is None:
        text = os.environ.get(env, "").strip()
        if not text:
            return None
        try:
            value = int(text)
        except ValueError:
            raise ConfigError(f"{env}={text!r}: {what} must be a whole number") from None
    if value < low:
        raise ConfigError(f"{what} must be >= {low}, got {value}")
    return value


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, timeout_s: int = DEFAULT_TIMEOUT_S) -> bool:
    """Join a ``jax.distributed`` job; returns False (and does nothing) when no coordinator is
    given (argument or ``JAX_COORDINATOR_ADDRESS``): a single-process run.

    Call before JAX starts its backend. On CPUs the gloo collectives are selected first (JAX
    needs them to run a computation over the devices of several processes). Raises
    DistributedError with one line when the job cannot start (e.g. the coordinator is not
    reachable within ``timeout_s``), ConfigError for inconsistent arguments.
    """
    global _initialized
    coordinator = coordinator or os.environ.get(COORDINATOR_ENV, "").strip() or None
    if coordinator is None:
        if num_processes is not None or process_id is not None:
            raise ConfigError("--num-processes / --process-id need --coordinator HOST:PORT (or "
                              f"{COORDINATOR_ENV}): the address of process 0")
        return False
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--coordinator {coordinator!r}: expected HOST:PORT, e.g. "
                          f"10.0.0.1:12355 (process 0's address and a free port)")
    num_processes = _int_from(num_processes, NUM_PROCESSES_ENV, "--num-processes", 1)
    process_id = _int_from(process_id, PROCESS_ID_ENV, "--process-id", 0)
    if num_processes is not None and process_id is not None and process_id >= num_processes:
        raise ConfigError(f"--process-id {process_id} must be below --num-processes "
                          f"{num_processes} (ids are 0 .. {num_processes - 1})")
    import jax

    if _initialized or jax.distributed.is_initialized():
        return True
    # gloo (TCP) is what lets the CPU backend run collectives across processes; set it
    # before the backend exists (jax >= 0.4.3x; the default in 0.10, explicit here).
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except (AttributeError, ValueError):  # pragma: no cover - an older or newer jax
        pass
    try:
        jax.distributed.initialize(coordinator, num_processes, process_id,
                                   initialization_timeout=int(timeout_s))
    except Exception as error:  # noqa: BLE001 - jax raises RuntimeError/ValueError/XlaRuntimeError
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise DistributedError(
            f"cannot join the distributed job at --coordinator {coordinator} as process "
            f"{process_id} of {num_processes}: {first[:300]} (start every process with the "
            f"same --coordinator and --num-processes, ids 0 .. N-1, within {timeout_s} s)"
        ) from None
    _initialized = True
    return True


def is_initialized() -> bool:
    """Whether this process joined a multi-process job through :func:`initialize`."""
    return _initialized


def is_primary() -> bool:
    """Process 0 (or a single process): the one that writes files and prints progress."""
    if not _initialized:
        return True
    import jax

    return jax.process_index() == 0


def exit_now(code: int) -> None:
    """Leave a multi-process job at once: JAX's exit handler would wait at a shutdown barrier
    for processes that may be gone, and then abort with pages of C++ logs."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
