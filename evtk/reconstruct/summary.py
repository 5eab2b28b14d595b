"""What a reconstruction reports about itself: :class:`ReconstructionSummary`, typed, readable as a dict."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, MutableMapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["ReconstructionSummary"]


@dataclass(eq=False)
class ReconstructionSummary(MutableMapping):
    """The summary of a reconstruction: captures, windows, events used and dropped, settings, errors, warnings.

    Every entry is a typed attribute; the summary also reads and writes as the dict it used to be
    (``summary["windows"]``, ``summary.get("error")``, ``dict(summary)``, ``summary.update(...)``), and
    :meth:`to_dict` gives the JSON-ready form a reconstruction file stores. An entry a route did not set (the
    trigger ``match`` of a reconstruction by the recording's own schedule, say) is not in the dict: reading it by
    key raises ``KeyError``, as before, and its attribute is None. Entries that are not attributes (the file's
    ``metadata`` a loaded reconstruction carries, a caller's own) are kept in :attr:`extra`.

    Parameters
    ----------
    captures : int or None
        Captures of the schedule (None without one).
    windows : int
        Windows counted.
    window_source : str
        Where the windows came from (the schedule, the trigger edges, a period, ...).
    windows_dropped : dict
        What the windows left out, by reason: edge name to count.
    events_used : int
        Events counted in the windows over the region.
    region : list of int
        ``[x0, x1, y0, y1]``: the sensor pixels counted (half-open).
    responses : int
        Responses produced.
    size : list of int
        ``[rows, cols]`` of each resampled response.
    linear : bool
        Whether counts were linearised to light (else net counts ON - OFF).
    theta_on : float
        The ON contrast threshold the linearisation took (log units).
    binarize : str
        The binarisation rule applied.
    skip_us : int
        How far every window was delayed (µs).
    length_us : int or None
        Every window's length when shortened (µs), else None.
    deblurred : bool
        Whether the footprint and defocus were solved out (:mod:`evtk.reconstruct.deblur`).
    level_light_ratio : list of float or None
        Each level capture's light read back (median over the interior) over the light it had: 1 when the
        linearisation is right.
    deblur_regularisation : float or None
        The deblur's Tikhonov regularisation, relative to the sampling matrix's largest singular value.
    flat_field_captures : int
        Flat-field captures that calibrated the pixels' thresholds (0: none).
    decimation : int
        The bench's decimation (every decimation-th sensor pixel, eq. 6).
    linearization : str
        How counts became light: "counts", "exp(n theta)", "pixel model", "pixel model and event times", or
        "the level captures' table".
    timed_share : float or None
        The share of pixel-windows whose light the event times set.
    timing_skipped : str or None
        Why event times were not used where the default would have read them.
    error : dict or None
        ``correlation``, ``nrmse``, ``nrmse_range`` against the ideal (:func:`~evtk.reconstruct.response_error`).
    empty_windows : int or None
        Windows with no event over the region (:func:`~evtk.reconstruct.pipeline.silent_failures`).
    vanished_responses : int or None
        Responses that are zero everywhere.
    kernels_without_response : list of int or None
        Kernels the job holds that have no capture.
    warnings : list of str or None
        One sentence for each thing that would otherwise pass unseen.
    response_origin_px : list of float or None
        ``[x, y]``: the sensor pixel of the full response's cell (0, 0) the bench routes took.
    match : dict or None
        How the trigger windows matched the schedule (:func:`~evtk.reconstruct.match_windows`'s report).
    pairs_left_out : list or None
        (kernel, features, repeat) pairs left out because a pass had no window.
    scale_to_ideal : float or None
        The best scale from the responses to the ideal (relative intensity, scored after it).
    pixel_model : dict or None
        The fitted pixel model (:meth:`~evtk.reconstruct.PixelFit.to_dict`) a calibrated route used.
    pixel_model_from : str or None
        Where that model came from (the run's own level captures, the calibration).
    pixel_model_note : str or None
        Why no model or another linearisation was used.
    pixel_model_rejected : bool or None
        Whether a fitted model was given up.
    refused_pixel_model : dict or None
        A model refused as no camera's (outside the physical ranges).
    level_table_error : float or None
        How well the level captures' own table reads a level left out of it (median ``|log(read / true)|``).
    pixel_model_level_error : float or None
        How far the fitted model misread the level captures (median ``|log(read / true)|``).
    level_captures : int or None
        Level captures the run held.
    windows_after_edges_us : int or None
        How long after the trigger edges the windows were taken (the light's fitted delay, µs).
    route : str or None
        The route :func:`evtk.workflow.reconstruct_recording` took.
    oracle : bool or None
        Whether it was the oracle (the simulation record's own pixel model and placement).
    placement : str or None
        What placed the response on the sensor.
    extra : dict
        Every other entry (a loaded file's ``metadata``, ``sensor_size``, ``layout_version``, a caller's own).
    """

    captures: int | None = None
    windows: int | None = None
    window_source: str | None = None
    windows_dropped: dict | None = None
    events_used: int | None = None
    region: list | None = None
    responses: int | None = None
    size: list | None = None
    linear: bool | None = None
    theta_on: float | None = None
    binarize: str | None = None
    skip_us: int | None = None
    length_us: int | None = None
    deblurred: bool | None = None
    level_light_ratio: list | None = None
    deblur_regularisation: float | None = None
    flat_field_captures: int | None = None
    decimation: int | None = None
    linearization: str | None = None
    timed_share: float | None = None
    timing_skipped: str | None = None
    error: dict | None = None
    empty_windows: int | None = None
    vanished_responses: int | None = None
    kernels_without_response: list | None = None
    warnings: list | None = None
    response_origin_px: list | None = None
    match: dict | None = None
    pairs_left_out: list | None = None
    scale_to_ideal: float | None = None
    pixel_model: dict | None = None
    pixel_model_from: str | None = None
    pixel_model_note: str | None = None
    pixel_model_rejected: bool | None = None
    refused_pixel_model: dict | None = None
    level_table_error: float | None = None
    pixel_model_level_error: float | None = None
    level_captures: int | None = None
    windows_after_edges_us: int | None = None
    route: str | None = None
    oracle: bool | None = None
    placement: str | None = None
    extra: dict = field(default_factory=dict)
    #: the entries set: those given a value here, or any value (None included) by key or attribute since
    _given: set[str] = field(default_factory=set, init=False, repr=False)

    def __post_init__(self) -> None:
        self._given = {n for n in _ENTRIES if getattr(self, n) is not None}

    def __setattr__(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)
        given = self.__dict__.get("_given")
        if given is not None and name in _ENTRIES:
            given.add(name)

    def __getitem__(self, key: str) -> Any:
        if key in _ENTRIES:
            if key in self._given:
                return getattr(self, key)
            raise KeyError(key)
        return self.extra[key]

    def __setitem__(self, key: str, value: Any) -> None:
        if key in _ENTRIES:
            setattr(self, key, value)
        else:
            self.extra[key] = value

    def __delitem__(self, key: str) -> None:
        if key in _ENTRIES:
            if key not in self._given:
                raise KeyError(key)
            object.__setattr__(self, key, None)
            self._given.discard(key)
        else:
            del self.extra[key]

    def __iter__(self) -> Iterator[str]:
        yield from (n for n in _ENTRIES if n in self._given)
        yield from self.extra

    def __len__(self) -> int:
        return len(self._given) + len(self.extra)

    def __repr__(self) -> str:
        return f"ReconstructionSummary({dict(self)!r})"

    def to_dict(self) -> dict:
        """The summary as a plain dict (the entries set, then :attr:`extra`'s), as a reconstruction file stores it.

        Returns
        -------
        dict
            Entry name to value; values are JSON types (lists, dicts, numbers, strings, None).
        """
        return dict(self)

    @classmethod
    def from_dict(cls, d: Mapping) -> ReconstructionSummary:
        """The summary of its dict form (:meth:`to_dict`, or a reconstruction file's ``summary``).

        Parameters
        ----------
        d : Mapping
            Entry name to value; names that are not attributes go to :attr:`extra`. Values are taken as they
            are (a file's are JSON types).

        Returns
        -------
        ReconstructionSummary
            Its entries are exactly ``d``'s.
        """
        out = cls()
        for key, value in d.items():
            out[key] = value
        return out


#: The entries that are attributes, in the order a summary lists them.
_ENTRIES = tuple(f.name for f in dataclasses.fields(ReconstructionSummary) if f.name not in ("extra", "_given"))
