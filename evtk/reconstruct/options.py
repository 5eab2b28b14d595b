"""Every setting of a reconstruction in one typed value, shared by the library, ``reconstruct`` and ``batch``."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..errors import EvtkError, check_positive

__all__ = ["ReconstructOptions"]


@dataclass(frozen=True)
class ReconstructOptions:
    """The settings :func:`evtk.reconstruct.reconstruct` takes besides the recording.

    ``reconstruct(rec, options=options)`` runs them (``reconstruct(rec, **options.kwargs())`` too); the
    ``reconstruct``, ``batch`` and ``enob`` commands build one from their options of the same names. The value
    is frozen: :func:`dataclasses.replace` gives a changed copy.

    Parameters
    ----------
    window : str or tuple
        How the recording is cut into capture windows: ``"schedule"`` (default; the simulation record's or the
        bench plan's schedule of captures), ``"triggers"`` (from each rising trigger edge to the next falling
        one) or ``("period", period_us)`` (back-to-back windows of ``period_us`` microseconds); without a
        schedule every window is a repeat of one scene.
    skip_us : int
        Microseconds left out at the start of every window (the pixels' settling after a pattern change), at
        least 0; default 0.
    length_us : int, optional
        Keep at most this many microseconds of every window (after ``skip_us``), >= 1; None (default) keeps
        the whole window.
    size : tuple of int
        ``(rows, cols)`` of each resampled response, both >= 1; default ``(16, 16)``.
    binarize_method : str or float
        How each response becomes a binary map: ``"auto"`` (default; sign for signed responses, else each
        response's mean), ``"sign"``, ``"mean"``, ``"otsu"`` or a fixed threshold in the response's units.
    linear : bool
        Linearise counts to light (default), or keep net counts ON - OFF (``False``).
    theta : float, optional
        A fixed contrast threshold (log-intensity units) linearising by ``exp(n theta)``; None (default) inverts
        the plan's pixel model where there is one; without one, fixed windows keep net counts ON - OFF and a
        bench plan's ``linearization="exp(n theta)"`` takes 0.2.
    crop : {"valid", "full"}
        Which part of the correlation each response keeps: ``"valid"`` (default; where the kernel lies wholly
        on the features) or ``"full"``.
    region : tuple of int, optional
        Sensor pixels ``(x0, x1, y0, y1)`` (half-open) to use; None (default): the plan's response region, else
        the whole sensor.
    deblur : bool, optional
        Undo the known optical footprint blur by solving the sampling model (:mod:`evtk.reconstruct.deblur`);
        None (default): deblur when the pixels are flat-field calibrated.
    flat_field : bool
        Calibrate each pixel's contrast threshold on the recording's flat-field captures, where it has any
        (default ``True``).
    timing : bool, optional
        Read the light below one threshold from each window's first and last ON-event times; None (default):
        wherever the pixel model allows it; ``True``: required; ``False``: never.

    Raises
    ------
    EvtkError
        When ``crop`` is neither "valid" nor "full", ``skip_us`` < 0, ``length_us`` < 1, ``size`` is not two
        positive numbers, or ``theta`` is not a positive finite number.

    Examples
    --------
    >>> ReconstructOptions(window=("period", 1000), size=(8, 8)).kwargs()["window"]
    ('period', 1000)
    """

    window: object = "schedule"
    skip_us: int = 0
    length_us: int | None = None
    size: tuple = (16, 16)
    binarize_method: object = "auto"
    linear: bool = True
    theta: float | None = None
    crop: str = "valid"
    region: tuple | None = None
    deblur: bool | None = None
    flat_field: bool = True
    timing: bool | None = None

    def __post_init__(self) -> None:
        if self.crop not in ("valid", "full"):
            raise EvtkError(f"crop must be 'valid' or 'full', not {self.crop!r}")
        if int(self.skip_us) < 0 or (self.length_us is not None and int(self.length_us) < 1):
            raise EvtkError("skip_us must be >= 0 and length_us >= 1")
        if len(tuple(self.size)) != 2 or min(int(v) for v in self.size) < 1:
            raise EvtkError(f"size must be two positive numbers, not {self.size!r}")
        if self.theta is not None:
            check_positive(theta=self.theta)

    def kwargs(self) -> dict:
        """The settings as keyword arguments (the field names), ``size`` as a tuple of ints.

        Returns
        -------
        dict
            One entry per field, for :func:`~evtk.reconstruct.reconstruct` (``reconstruct(rec, **kwargs)``).
        """
        d = asdict(self)
        d["size"] = tuple(int(v) for v in self.size)
        return d
