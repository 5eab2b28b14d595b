"""Flip rates of repeated binarised captures (the paper's Fig. 3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EvtkError
from ..limits import require_memory
from .sinad import _as_repeats

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["FlipReport", "flip_rates", "flip_rates_bytes"]


@dataclass
class FlipReport:
    """What :func:`flip_rates` measured (percentages of pixels).

    Parameters
    ----------
    pairwise_pct : float
        Mean over all pairs of repeats of the share of pixels that differ, percent.
    majority_pct : float
        Share of (repeat, pixel) values that differ from the pixel's majority vote, percent (ties count as +1,
        as :func:`evtk.reconstruct.binarize` maps 0 to +1).
    repeats : int
        Repeated captures compared.
    pixels : int
        Values in each capture.
    per_pixel : numpy.ndarray
        float64, shaped like one capture: each pixel's share (0 to 1) of repeats that disagree with its majority.
    """

    pairwise_pct: float
    majority_pct: float
    repeats: int
    pixels: int
    per_pixel: np.ndarray

    def to_dict(self) -> dict:
        """The scalar figures as a dict (``per_pixel`` left out), for JSON.

        Returns
        -------
        dict
            ``pairwise_pct``, ``majority_pct``, ``repeats`` and ``pixels``.
        """
        return {"pairwise_pct": self.pairwise_pct, "majority_pct": self.majority_pct,
                "repeats": self.repeats, "pixels": self.pixels}


def flip_rates_bytes(repeats: int, pixels: int, itemsize: int = 1) -> int:
    """Memory :func:`flip_rates` needs beyond its input.

    Parameters
    ----------
    repeats : int
        Repeated captures.
    pixels : int
        Values in each capture.
    itemsize : int
        Bytes of one input value (int8: 1).

    Returns
    -------
    int
        Bytes: a sorted copy and a mask of the captures, and five per-pixel
        float64 or int64 arrays.
    """
    return int(repeats) * int(pixels) * (int(itemsize) + 1) + 40 * int(pixels)


def flip_rates(binary: npt.ArrayLike) -> FlipReport:
    """Flip rates of repeated binarised captures of one scene.

    Parameters
    ----------
    binary : array_like, shape (repeats, ...)
        Values in {-1, +1}, {0, 1} or bool.

    Returns
    -------
    FlipReport
        Pairwise and majority flip rates, and each pixel's share of
        disagreeing repeats.

    Raises
    ------
    EvtkError
        Fewer than two repeats, values that are not binary, or more memory
        than the budget (:func:`evtk.limits.require_memory`).

    Examples
    --------
    >>> r = flip_rates([[1, 1, -1, -1], [1, -1, -1, -1], [1, 1, -1, 1]])
    >>> round(r.pairwise_pct, 4), round(r.majority_pct, 4)   # 4 of 12 pair-pixels; 2 of 12 values
    (33.3333, 16.6667)
    """
    b = _as_repeats(binary, "flip rates")
    require_memory(flip_rates_bytes(b.shape[0], b.size // b.shape[0], b.itemsize),
                   f"flip rates of {b.shape[0]:,} captures of {b.size // b.shape[0]:,} pixels")
    one = b == 1
    if not (np.all(one | (b == -1)) or np.all(one | (b == 0))):  # (np.unique would load numpy.ma: 30 ms)
        vals = np.unique(b)
        raise EvtkError(f"flip rates need binary values (-1/+1, 0/1 or bool), found {vals[:6].tolist()}")
    ones = (b > 0).reshape(b.shape[0], -1)
    r, p = ones.shape
    k = ones.sum(axis=0, dtype=np.int64)
    pairwise = float((k * (r - k)).sum()) / (p * r * (r - 1) / 2)
    majority_one = 2 * k >= r
    disagree = np.where(majority_one, r - k, k)
    return FlipReport(100.0 * pairwise, 100.0 * float(disagree.sum()) / (r * p), r, p,
                      (disagree / r).reshape(b.shape[1:]))
