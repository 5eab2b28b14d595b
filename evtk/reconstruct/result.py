"""What a reconstruction gives: :class:`Reconstruction` (a light module: numpy alone)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .summary import ReconstructionSummary
from .windows import WindowCounts

__all__ = ["Reconstruction"]


@dataclass
class Reconstruction:
    """What :func:`reconstruct` found.

    Parameters
    ----------
    responses : ndarray (n, rows, cols)
        One signed response per (kernel, features, repeat) of the schedule, or
        per window when the recording has none, resampled to ``size``.
    binary : ndarray (n, rows, cols) of int8 (+1/-1)
        The responses binarised.
    pairs : ndarray (n, 3) or None
        (kernel_id, features_id, repeat) of each response.
    cells : ndarray (n, h, w)
        The responses on the response's own cell grid, before resampling.
    ideal : ndarray or None
        Ground truth on the same cell grid (simulated recordings only).
    counts : WindowCounts
        The windows and their ON/OFF counts.
    summary : ReconstructionSummary
        Captures, windows, events used and dropped, parameters, errors (a dict given here is read into one).
    thresholds : ndarray (rows, cols) or None
        Each pixel's ON threshold (log units) as the linearisation used it:
        from the flat fields' event times where they fit the model, else
        the nominal one scaled by the flat-field gain (None when the event
        times were not used).
    """

    responses: np.ndarray
    binary: np.ndarray
    pairs: np.ndarray | None
    cells: np.ndarray
    ideal: np.ndarray | None
    counts: WindowCounts
    summary: ReconstructionSummary
    thresholds: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.summary, ReconstructionSummary):
            self.summary = ReconstructionSummary.from_dict(self.summary)

    def groups(self) -> dict:
        """Indices of the responses of each scene, over its repeats.

        Returns
        -------
        dict
            ``{(kernel_id, features_id): ndarray of indices}``; without a schedule every window counts as a
            repeat of one scene, keyed ``(-1, -1)``.
        """
        if self.pairs is None:
            return {(-1, -1): np.arange(self.cells.shape[0])}
        out: dict = {}
        for i, (k, f, _) in enumerate(self.pairs.tolist()):
            out.setdefault((k, f), []).append(i)
        return {key: np.asarray(v) for key, v in out.items()}
