"""Prophesee system IDs and the sensors they carry, for RAW files whose header gives no geometry.

Older Prophesee headers (Metavision before 2.x, and the cameras' own recordings
of that time) name the camera board by a ``% system_ID N`` line and give no
``% geometry`` or ``% format ...;width=;height=``. Prophesee's own reader then
takes the sensor from the system ID; evtk does the same, from this table.

Source of every entry: OpenEB (Prophesee's open-source Metavision SDK,
github.com/prophesee-ai/openeb), ``hal_psee_plugins``: the ``SystemId``
enumeration (the IDs) and the RAW header check's ``system_id_map`` (each ID's
sensor generation and geometry), together with ``systemid2version`` for the
generations that map lists no geometry for (a generation's sensor has one
size: Gen3.x VGA 640x480, Gen4.x and the IMX636/637/646/647 1280x720, GenX320
320x320). IDs with the EVK proxy flag (0x80) are the same boards behind an
evaluation kit.
"""

from __future__ import annotations

__all__ = ["SYSTEM_IDS", "sensor_from_system_id"]

_VGA, _HD, _X320 = (640, 480), (1280, 720), (320, 320)

#: system ID -> (board and sensor, (width, height))
SYSTEM_IDS: dict[int, tuple[str, tuple[int, int]]] = {
    0x15: ("CCAM3 Gen3.0", _VGA),
    0x17: ("CCAM4 Gen3.0 (onboard rev A)", _VGA),
    0x97: ("CCAM4 Gen3.0 EVK (onboard rev A)", _VGA),
    0x19: ("CCAM4 Gen3.0 (onboard rev B)", _VGA),
    0x99: ("CCAM4 Gen3.0 EVK (onboard rev B)", _VGA),
    0x1D: ("CCAM4 Gen3.0 rev B EVK bridge", _VGA),
    0x21: ("VisionCam Gen3.0", _VGA),
    0xA1: ("VisionCam Gen3.0 EVK", _VGA),
    0x1C: ("CCAM3 Gen3.1", _VGA),
    0x22: ("VisionCam Gen3.1", _VGA),
    0xA2: ("VisionCam Gen3.1 EVK", _VGA),
    0x23: ("CCAM5 Gen3.1", _VGA),
    0x29: ("EVK2 Gen3.1", _VGA),
    0x28: ("EVK3 Gen3.1 (EVT 3.0)", _VGA),
    0x1A: ("CCAM3 Gen4.0", _HD),
    0x9A: ("CCAM4 Gen4.0 EVK", _HD),
    0x1E: ("CCAM5 Gen4.0", _HD),
    0x2E: ("CCAM5 Gen4.0 fixed frame", _HD),
    0x20: ("CCAM5 Gen4.0 EVK bridge", _HD),
    0x1F: ("EVK2 Gen4.0", _HD),
    0x27: ("EVK2 Gen4.1", _HD),
    0x30: ("EVK3 Gen4.1", _HD),
    0x31: ("EVK3 IMX636", _HD),
    0x32: ("EVK2 IMX636", _HD),
    0x34: ("EVK3 IMX637", _HD),
    0x35: ("EVK3 IMX646", _HD),
    0x36: ("EVK3 IMX647", _HD),
    0x3A: ("RDK2 IMX636", _HD),
    0x42: ("EVK2 IMX636 ESP", _HD),
    0x3B: ("EVK3 GenX320 MP", _X320),
    0x40: ("EVK3 GenX320", _X320),
}


def sensor_from_system_id(lines: list[str]) -> tuple[tuple[int, int], str] | None:
    """The sensor size a header's ``system_ID`` line names, and the board's name.

    Parameters
    ----------
    lines : list of str
        The header's lines without their leading ``%``.

    Returns
    -------
    ((int, int), str) or None
        ``((width, height), board)``; None when there is no system ID line,
        or its ID is not in :data:`SYSTEM_IDS`.
    """
    for line in lines:
        parts = line.split()
        if len(parts) == 2 and parts[0].lower() in ("system_id", "systemid"):
            text = parts[1].strip()
            try:
                value = int(text, 16) if text.lower().startswith("0x") else int(text)
            except ValueError:
                return None
            found = SYSTEM_IDS.get(value)
            return None if found is None else (found[1], found[0])
    return None
