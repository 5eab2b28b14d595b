"""Binary (+1/-1) responses: by sign, each response's mean, Otsu's threshold or a fixed value."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ..errors import EvtkError

if TYPE_CHECKING:
    from ..plan import Plan, SimulationRecord

__all__ = ["binarize_rule", "binarize"]


def binarize_rule(sim: Plan | SimulationRecord | dict | None) -> str:
    """The binarisation ``"auto"`` stands for: ``"sign"`` for signed responses, ``"mean"`` for the rest.

    A response is signed when the recording's schedule shows a kernel or
    features holding -1 (its captures are combined from + and - passes, so
    zero is the natural threshold). An unsigned kernel on 0/1 features gives
    a response that is positive wherever light falls (the sign would be +1
    almost everywhere), and a recording without a schedule has no sign to
    go by: both are split at each response's mean.

    Parameters
    ----------
    sim : Plan, SimulationRecord, dict or None
        The run's plan, or the recording's simulation record (or its dict form), if any.

    Returns
    -------
    str
        "sign" or "mean".
    """
    if sim is None:
        return "mean"
    from ..plan import Plan, SimulationRecord

    if (sim if isinstance(sim, Plan) else SimulationRecord.from_dict(sim)).signed:
        return "sign"
    return "mean"


def binarize(values: npt.ArrayLike, method: str | float = "sign") -> np.ndarray:
    """+1 where a response reaches the threshold, -1 elsewhere (int8), per response.

    Parameters
    ----------
    values : array_like (n, ...)
        The responses.
    method : str or float
        "sign" (threshold 0), "mean" (each response's mean), "otsu" (Otsu's threshold of each response,
        scikit-image), or a number. A constant response is all +1 under "mean" and "otsu".

    Returns
    -------
    ndarray of int8
        +1/-1, the shape of ``values``.

    Examples
    --------
    >>> binarize(np.array([[-1.0, 0.0], [2.0, 0.5]]), "mean").tolist()
    [[-1, -1], [1, 1]]
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim < 2:
        raise EvtkError("binarize needs responses of at least 2 dimensions")
    if not np.all(np.isfinite(values)):
        raise EvtkError("cannot binarize responses holding NaN or infinity")
    flat = values.reshape((-1,) + values.shape[-2:])
    if method == "sign":
        thr = np.zeros(len(flat))
    elif method == "mean":
        thr = flat.mean(axis=(1, 2))
    elif method == "otsu":
        from skimage.filters import threshold_otsu

        const = np.array([np.ptp(r) == 0 for r in flat], bool)
        thr = np.array([r.flat[0] if c else threshold_otsu(r) for r, c in zip(flat, const)])
        # Otsu's threshold is the last value of the lower class: strictly above it is "high"
        high = flat > thr[:, None, None]
        high[const] = True
        return np.where(high, 1, -1).astype(np.int8).reshape(values.shape)
    else:
        try:
            thr = np.full(len(flat), float(method))
        except (TypeError, ValueError):
            raise EvtkError(f"binarize method must be sign, mean, otsu or a number, not {method!r}") from None
        if not np.isfinite(thr).all():
            raise EvtkError(f"binarize threshold must be finite, not {method!r}")
    return np.where(flat >= thr[:, None, None], 1, -1).astype(np.int8).reshape(values.shape)
