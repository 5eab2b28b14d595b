"""Reconstruction files read back as a :class:`~evtk.reconstruct.Reconstruction`.

The file format is :mod:`evtk.io.reconstruction`'s (``docs/formats/reconstruction.md``): io reads and checks the
arrays and the summary; this module makes the reconstruction's objects of them, so that io never imports the
reconstruction.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import EvtkError, FormatError
from ..io.reconstruction import read_reconstruction, save_reconstruction
from .result import Reconstruction
from .summary import ReconstructionSummary
from .windows import WindowCounts, Windows

__all__ = ["load_reconstruction", "save_reconstruction"]


def load_reconstruction(path: str | os.PathLike, trust_external: bool | None = None) -> Reconstruction:
    """Read a file written by :func:`~evtk.io.reconstruction.save_reconstruction` (or ``evtk reconstruct``) back.

    The arrays and the summary are read and checked by :func:`evtk.io.reconstruction.read_reconstruction` (the
    file policy, the memory budget, shapes and ranges); the window times are checked here as
    :class:`~evtk.reconstruct.Windows` checks them.

    Parameters
    ----------
    path : str or os.PathLike
        An ``.npz``, ``.h5`` or ``.hdf5`` reconstruction file; an HDF5 recording that also holds a
        ``/reconstruction`` group gives that group.
    trust_external : bool, optional
        Let an HDF5 file read other files; None takes ``$EVTK_TRUST_EXTERNAL`` (``evtk --trust-external``).

    Returns
    -------
    Reconstruction
        Its ``counts`` hold the windows and ON/OFF counts; its ``summary`` also carries the file's
        ``metadata`` (``source``, ``sensor_size``).

    Raises
    ------
    FormatError
        When arrays are missing, inconsistent, of a type that is not numeric, or refused by the policy.
    EvtkError
        When the arrays would need more memory than the budget allows.

    Examples
    --------
    >>> import evtk, tempfile, os
    >>> from evtk.reconstruct import reconstruct
    >>> from evtk.simulate import Simulation
    >>> d = tempfile.mkdtemp()
    >>> _ = Simulation([[1, 0], [0, 1]], [[0, 1, 1], [1, 0, 1], [1, 1, 0]], repeat=2).write(os.path.join(d, "r.h5"))
    >>> with evtk.open(os.path.join(d, "r.h5")) as rec:
    ...     result = reconstruct(rec)
    >>> save_reconstruction(os.path.join(d, "out.npz"), result, (346, 260))
    >>> back = load_reconstruction(os.path.join(d, "out.npz"))
    >>> bool((back.responses == result.responses).all()), back.summary["sensor_size"]
    (True, [346, 260])
    """
    path = os.fspath(path)
    arrays, summary, region, events_used = read_reconstruction(path, trust_external)
    start, end = arrays["window_start_us"], arrays["window_end_us"]
    try:
        windows = Windows(start, end, np.arange(start.shape[0]), str(summary.get("window_source", "file")))
    except EvtkError as exc:
        raise FormatError(path, None, f"window times: {exc}") from None
    counts = WindowCounts(arrays["on"].astype(np.int32, copy=False), arrays["off"].astype(np.int32, copy=False),
                          windows, region, events_used)
    return Reconstruction(arrays["responses"].astype(np.float64, copy=False),
                          arrays["binary"].astype(np.int8, copy=False), arrays.get("pairs"),
                          arrays["cells"].astype(np.float64, copy=False), arrays.get("ideal"), counts,
                          ReconstructionSummary.from_dict(summary))
