"""The kinds of trigger an AEDAT4 file records (:class:`evtk.events.TriggerKind`, loaded on first use)."""

from __future__ import annotations

import enum
import inspect


class TriggerKind(enum.IntEnum):
    """Trigger type codes, numbered as in the AEDAT4 ``Trigger`` table.

    Parameters
    ----------
    value : int
        The code (0 to 9): ``TriggerKind(1)`` is ``EXTERNAL_SIGNAL_RISING_EDGE``; any other value raises
        ``ValueError``.
    """

    # what calling the class takes (a code), for the signature help and the API reference shows
    __signature__ = inspect.Signature([inspect.Parameter("value", inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                                         annotation=int)])

    def __init__(self, value: int) -> None:  # each member is made with its code; nothing more to set
        super().__init__()

    TIMESTAMP_RESET = 0
    EXTERNAL_SIGNAL_RISING_EDGE = 1
    EXTERNAL_SIGNAL_FALLING_EDGE = 2
    EXTERNAL_SIGNAL_PULSE = 3
    EXTERNAL_GENERATOR_RISING_EDGE = 4
    EXTERNAL_GENERATOR_FALLING_EDGE = 5
    APS_FRAME_START = 6
    APS_FRAME_END = 7
    APS_EXPOSURE_START = 8
    APS_EXPOSURE_END = 9
