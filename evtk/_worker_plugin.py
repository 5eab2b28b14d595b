"""The Dask worker plugin evtk's local clusters install (imported only where Dask is)."""

from __future__ import annotations

import os

from distributed import WorkerPlugin


class WorkerThreads(WorkerPlugin):
    """Give each worker process its share of the machine's threads (``EVTK_THREADS``, which bounds
    evtk's decode threads and its numba parallel loops), set inside the worker when it starts or
    restarts, so the parent process's environment is left alone."""

    name = "evtk-worker-threads"

    def __init__(self, threads: int):
        self.threads = int(threads)

    def setup(self, worker):
        from ._threads import ALIAS, ENV

        os.environ[ENV] = os.environ[ALIAS] = str(self.threads)
