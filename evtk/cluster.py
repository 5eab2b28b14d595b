"""Where work runs: serially, on a local Dask cluster, or on a running Dask scheduler.

Every command that fans out takes ``--scheduler``:

* ``serial``: one task after another in this process (the default without Dask);
* ``local`` or ``local:N``: a ``dask.distributed.LocalCluster`` of N worker
  processes (default: one per core), started and stopped by evtk (the
  default with Dask installed, ``pip install 'evtk[cluster]'``);
* ``tcp://HOST:PORT``: an existing ``dask scheduler`` with its workers.

Without ``--scheduler`` the environment variable ``EVTK_SCHEDULER`` decides
(so a lab can point unchanged scripts at its cluster), then the default above.

In the library, functions that fan out take an optional ``client`` (a
``distributed.Client``); :func:`run_tasks` is what they share. Tasks are
module-level functions of explicit arguments, seeded from the run's seed and
the task's index, so results equal a serial run's whatever the worker.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, TypeVar

from ._threads import workers as io_workers
from .errors import EvtkError
from .io import open as open_recording

if TYPE_CHECKING:
    import dask.dataframe as dd
    from distributed import Client

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["dask_available", "default_scheduler", "scheduler", "run_tasks", "to_dask"]

CONNECT_TIMEOUT_S = 5


def dask_available() -> bool:
    """Whether Dask's ``distributed`` package can be imported (``pip install 'evtk[cluster]'``).

    Returns
    -------
    bool
        True when ``distributed`` is installed; it is looked up, not imported.
    """
    import importlib.util

    return importlib.util.find_spec("distributed") is not None


def default_scheduler() -> str:
    """The scheduler a command uses without ``--scheduler``.

    Returns
    -------
    str
        ``$EVTK_SCHEDULER`` if set (and not blank), else ``"local"`` with Dask installed, else ``"serial"``.
    """
    env = os.environ.get("EVTK_SCHEDULER", "").strip()
    if env:
        return env
    return "local" if dask_available() else "serial"


@contextlib.contextmanager
def scheduler(spec: str | None = None) -> Iterator[Client | None]:
    """A ``distributed.Client`` for ``spec`` (None for serial), closed on exit.

    A context manager: a local cluster it starts is stopped, and the environment variables Dask's nanny
    changed in this process are put back, when the ``with`` block ends.

    Parameters
    ----------
    spec : str, optional
        ``"serial"``, ``"local"``, ``"local:N"`` (N worker processes, one thread each) or
        ``"tcp://HOST:PORT"`` (a running ``dask scheduler``); None or empty: :func:`default_scheduler`.

    Yields
    ------
    distributed.Client or None
        The client (None for serial).

    Raises
    ------
    EvtkError
        For a malformed ``spec``, N below 1 or above :func:`max_local_workers`, Dask not installed, no
        scheduler answering at a ``tcp://`` address within 5 s, or a local cluster that cannot start.
    """
    spec = default_scheduler() if spec in (None, "") else str(spec)
    if spec == "serial":
        yield None
        return
    if not (spec == "local" or spec.startswith("local:") or spec.startswith("tcp://")):
        raise EvtkError(f"--scheduler must be serial, local, local:N or tcp://HOST:PORT, not {spec!r}")
    if not dask_available():
        raise EvtkError(f"--scheduler {spec} needs Dask: pip install 'evtk[cluster]' (or use --scheduler serial)")
    from distributed import Client, LocalCluster

    if spec.startswith("tcp://"):
        host, port = _tcp_address(spec)
        try:  # a refused connection answers at once: say so now, not after the client's full time-out
            socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as exc:
            raise EvtkError(f"no Dask scheduler at {spec}: {exc.strerror or exc}") from None
        try:
            client = Client(spec, timeout=f"{CONNECT_TIMEOUT_S}s")
        except Exception as exc:  # noqa: BLE001 - distributed raises OSError, TimeoutError, ValueError, ...
            raise EvtkError(f"no Dask scheduler answered at {spec} within {CONNECT_TIMEOUT_S} s "
                            f"({type(exc).__name__}: {exc})") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = os.cpu_count() or 1
    if spec.startswith("local:"):
        try:
            n = int(spec.split(":", 1)[1])
        except ValueError:
            n = 0
        if n < 1:
            raise EvtkError(f"local:N needs a positive number of workers, not {spec!r}")
        most = max_local_workers()
        if n > most:
            raise EvtkError(f"{spec}: at most {most} local workers on this machine ({os.cpu_count() or 1} cores; "
                            "each is a process); set EVTK_MAX_LOCAL_WORKERS to allow more")
    import dask

    # Dask's nanny applies its pre-spawn environment to this process's os.environ before it starts a
    # worker; what it changes here is put back when the cluster closes
    saved = dict(os.environ)
    try:
        # Dask sets MALLOC_TRIM_THRESHOLD_ in its workers, which also stops glibc from raising its mmap
        # threshold: every large array then comes from fresh pages, and a reconstruction ran at half speed
        # (measured, benchmarks/bench_batch.py). evtk's workers keep the allocator's default.
        # Tasks run on a worker's thread pool, whose thread allocates from a glibc arena of its own; that
        # arena gave its freed pages back after every recording (about 1,300 page faults and 3 ms per
        # recording of 30, measured), the main arena keeps them: one arena per worker (MALLOC_ARENA_MAX).
        # The workers' statistical profiler (a stack sample every 10 ms, for the dashboard) and GIL monitor
        # took about a tenth of each worker's time on evtk's tasks (measured); a local cluster evtk starts and
        # stops around one command has no dashboard to show them on.
        quiet = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                 "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": 1,
                 "distributed.worker.profile.enabled": False,
                 "distributed.admin.system-monitor.gil.enabled": False}
        with dask.config.set(quiet):  # the HTTP server on any free port: a taken 8787 would warn on stderr
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=50)
    except (RuntimeError, OSError, TimeoutError) as exc:
        _restore_environ(saved)
        raise EvtkError(f"could not start a local Dask cluster ({exc}); a script that starts one needs an "
                        "'if __name__ == \"__main__\":' guard, or use --scheduler serial") from None
    client = Client(cluster)
    try:
        # the workers share out the threads the parent would use (decode threads, numba's parallel loops);
        # set inside each worker: the nanny's pre-spawn environment would also change this process's own
        from ._worker_plugin import WorkerThreads

        client.register_plugin(WorkerThreads(max(1, io_workers() // n)))
        yield client
    finally:
        client.close()
        cluster.close()
        _restore_environ(saved)


def max_local_workers() -> int:
    """Most workers ``local:N`` starts: ``$EVTK_MAX_LOCAL_WORKERS``, else four per core (at least 8)."""
    env = os.environ.get("EVTK_MAX_LOCAL_WORKERS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise EvtkError(f"EVTK_MAX_LOCAL_WORKERS must be a whole number, not {env!r}") from None
    return max(8, 4 * (os.cpu_count() or 1))


def _tcp_address(spec):
    """``(host, port)`` of ``tcp://HOST:PORT``, or an EvtkError saying what is wrong with it."""
    rest = spec[len("tcp://"):]
    host, sep, port = rest.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port:
        raise EvtkError(f"--scheduler {spec!r}: expected tcp://HOST:PORT")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise EvtkError(f"--scheduler {spec!r}: the port must be a number from 1 to 65535, not {port!r}")
    return host, int(port)


def _restore_environ(saved):
    for key in set(os.environ) - set(saved):
        del os.environ[key]
    for key, value in saved.items():
        if os.environ.get(key) != value:
            os.environ[key] = value


def run_tasks(fn: Callable[[T], R], items: Iterable[T], client: Client | None = None,
              progress: Callable[[int], object] | None = None, retries: int = 2) -> list[R]:
    """``[fn(item) for item in items]``, on ``client``'s workers when given (in order, retried on worker loss).

    Parameters
    ----------
    fn : callable
        A module-level function of one argument (it is pickled to the workers).
    items : iterable
        Its arguments.
    client : distributed.Client, optional
        Where to run; None runs each in this process, one after another.
    progress : callable, optional
        Called with 1 as each task finishes (in completion order on a cluster).
    retries : int
        How many times Dask reruns a task whose worker was lost.

    Returns
    -------
    list
        ``fn``'s results, in the order of ``items``.
    """
    items = list(items)
    out: list[Any] = []
    if client is None:
        for it in items:
            out.append(fn(it))
            if progress is not None:
                progress(1)
        return out
    from distributed import as_completed

    futures = client.map(fn, items, pure=False, retries=retries)
    index = {f.key: i for i, f in enumerate(futures)}
    out = [None] * len(items)  # each slot filled as its task completes
    for fut in as_completed(futures):
        out[index[fut.key]] = fut.result()
        if progress is not None:
            progress(1)
    return out


def to_dask(path: str | os.PathLike[str], partitions: int | None = None,
            events_per_partition: int = 5_000_000) -> dd.DataFrame:
    """A recording's events as a lazily read ``dask.dataframe`` (columns t, x, y, p), partitioned by time.

    Each partition reads one time range through the recording's index (the
    AEDAT4 data table, the HDF5 time index, Parquet row-group statistics),
    so nothing is read until computed; about ``events_per_partition`` events
    each, or ``partitions`` equal time ranges. Needs ``pip install
    'evtk[cluster]'``.

    Parameters
    ----------
    path : str or os.PathLike
        A recording in any format :func:`evtk.io.open` reads.
    partitions : int, optional
        Number of equal time ranges; default: enough for ``events_per_partition`` events each.
    events_per_partition : int
        Events a partition should hold, about (the recording's event rate is taken as uniform).

    Returns
    -------
    dask.dataframe.DataFrame
        Columns ``t`` (int64, µs), ``x``, ``y`` (uint16, pixels) and ``p`` (uint8, 1 ON, 0 OFF); nothing is
        read until it is computed.

    Raises
    ------
    EvtkError
        When Dask's dataframes are not installed, ``partitions`` is below 1, or the recording cannot be read.
    """
    import math

    try:
        import dask.dataframe as dd
        import pandas as pd
        from dask import delayed
    except ImportError:
        raise EvtkError("to_dask needs Dask's dataframes: pip install 'evtk[cluster]'") from None
    import numpy as np

    path = os.fspath(path)
    with open_recording(path) as rec:
        info = rec.info()
    n = int(info["events"])
    if n == 0 or info["t_start_us"] is None:
        bounds = [0, 1]
    else:
        k = int(partitions) if partitions else max(1, math.ceil(n / int(events_per_partition)))
        if k < 1:
            raise EvtkError(f"partitions must be at least 1, not {partitions!r}")
        t0, t1 = int(info["t_start_us"]), int(info["t_end_us"]) + 1
        bounds = sorted(set(int(v) for v in np.linspace(t0, t1, k + 1)))
    meta = pd.DataFrame({"t": np.zeros(0, np.int64), "x": np.zeros(0, np.uint16), "y": np.zeros(0, np.uint16),
                         "p": np.zeros(0, np.uint8)})
    parts = [delayed(_time_range_frame)(path, a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    return dd.from_delayed(parts, meta=meta, verify_meta=False)


def _time_range_frame(path, t_start_us, t_end_us):
    import pandas as pd

    with open_recording(path) as rec:
        ev = rec.events(t_start_us=t_start_us, t_end_us=t_end_us)
    return pd.DataFrame({"t": ev.t, "x": ev.x, "y": ev.y, "p": ev.p})
