"""The Dask worker plugin evtk's local clusters install (imported only where Dask is)."""

from __future__ import annotations

import os

from distributed import WorkerPlugin


class WorkerThreads(WorkerPlugin):
    """Give each worker process its share of the machine's threads (``EVTK_THREADS``, which bounds
    evtk's decode threads and its numba parallel loops), set inside the worker when it starts or
    restarts, so the parent process's environment is left alone; then warm the worker (:func:`warm`), so
    that no task pays for loading evtk's modules and numba's cached kernels (issue 32 item 4)."""

    name = "evtk-worker-threads"

    def __init__(self, threads: int, warm: bool = True):
        self.threads = int(threads)
        self.warm = bool(warm)

    def setup(self, worker):
        from ._threads import ALIAS, ENV

        os.environ[ENV] = os.environ[ALIAS] = str(self.threads)
        if self.warm:
            warm()


def warm() -> float:
    """Load in this process what a batch task loads, by reconstructing a tiny simulated recording (3x3 kernel,
    16x16 features, one repeat) into a temporary folder: evtk's reader, reconstruction and writer modules and
    numba's cached kernels of the schedule route. Best effort: a failure here is left for the tasks to meet
    and report.

    Returns
    -------
    float
        Seconds it took (0.0 when it failed).
    """
    import tempfile
    import time

    t0 = time.perf_counter()
    try:
        import numpy as np

        from .batch import batch_reconstruct
        from .simulate import Simulation

        with tempfile.TemporaryDirectory(prefix="evtk-warm-") as folder:
            path = os.path.join(folder, "warm.aedat4")
            kernel = np.array([[1, -1, 1], [-1, 1, -1], [1, -1, 1]])
            Simulation(kernel, np.ones((16, 16)), repeat=1, seed=0).write(path)
            batch_reconstruct([path], os.path.join(folder, "out"), force=True)
    except Exception:  # noqa: BLE001 - warming is an optimisation: the tasks report what fails for them
        return 0.0
    return time.perf_counter() - t0
