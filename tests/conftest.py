import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

import evtk

# CI explores a fixed set of examples (reproducible verdicts); local runs
# draw new ones every time.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"

# commands that fan out run serially in the tests unless a test asks for a cluster (test_cluster.py)
os.environ.setdefault("EVTK_SCHEDULER", "serial")


def random_events(n, seed=0, sensor_size=(320, 240), t0=0, span_us=1_000_000, sort=True):
    rng = np.random.default_rng(seed)
    t = rng.integers(t0, t0 + span_us, n, dtype=np.int64)
    if sort:
        t = np.sort(t)
    w, h = sensor_size
    return evtk.Events(
        t,
        rng.integers(0, w, n, dtype=np.uint16),
        rng.integers(0, h, n, dtype=np.uint16),
        rng.integers(0, 2, n, dtype=np.uint8),
        sensor_size,
    )


@pytest.fixture
def fixtures_dir():
    return FIXTURES


class Hang(Exception):
    """What :func:`no_hang` raises when its block runs past the limit."""


def no_hang(seconds=10.0):
    """A context manager that stops its block with :class:`Hang` after ``seconds`` (SIGALRM): a guard
    against parsers that hang or take minutes, not a speed assertion (the limit is generous)."""
    import contextlib
    import signal

    @contextlib.contextmanager
    def guard():
        def fire(signum, frame):
            raise Hang(f"still running after {seconds} s")

        old = signal.signal(signal.SIGALRM, fire)
        signal.setitimer(signal.ITIMER_REAL, seconds)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)

    return guard()
