"""Binary (+1/-1) responses: by sign, each response's mean, Otsu's threshold or a fixed value."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import EvtkError

if TYPE_CHECKING:
    import numpy.typing as npt

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


#: How close to its threshold (relative to the response's largest magnitude, or the threshold's if larger) a value
#: counts as exactly at it (:func:`binarize`'s tie rule).
TIE_RTOL = 1e-9


def binarize(values: npt.ArrayLike, method: str | float = "sign") -> np.ndarray:
    """+1 where a response reaches the threshold, -1 elsewhere (int8), per response.

    A value exactly at the threshold is a tie and goes to +1 under "sign", "mean" and a number (it reaches the
    threshold), to -1 under "otsu" (Otsu's threshold is the last value of the lower class). A value within
    :data:`TIE_RTOL` of the threshold, relative to the larger of the response's largest magnitude and the
    threshold's, counts as exactly at it: the same response summed in another order (the whole-run path and the
    batched one, :mod:`evtk.reconstruct._batched`) differs by rounding, which must not flip a tie. Ties are common
    where the responses are net counts (whole numbers, their means often among them).

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
        # Otsu's threshold is the last value of the lower class: strictly above it (beyond a tie) is "high"
        high = flat > (thr + _tie_band(flat, thr))[:, None, None]
        high[const] = True
        return _signs(high, values.shape)
    else:
        try:
            thr = np.full(len(flat), float(method))
        except (TypeError, ValueError):
            raise EvtkError(f"binarize method must be sign, mean, otsu or a number, not {method!r}") from None
        if not np.isfinite(thr).all():
            raise EvtkError(f"binarize threshold must be finite, not {method!r}")
    return _signs(flat >= (thr - _tie_band(flat, thr))[:, None, None], values.shape)


def _tie_band(flat: np.ndarray, thr: np.ndarray) -> np.ndarray:
    """How far from each response's threshold a value still counts as at it (:data:`TIE_RTOL`), no copy of
    ``flat`` made."""
    scale = np.maximum(np.maximum(flat.max(axis=(1, 2)), -flat.min(axis=(1, 2))), np.abs(thr))
    return TIE_RTOL * scale


def _signs(high: np.ndarray, shape: tuple) -> np.ndarray:
    """+1 where ``high``, else -1, as int8 of ``shape``."""
    out = high.astype(np.int8)
    out *= 2
    out -= 1
    return out.reshape(shape)
