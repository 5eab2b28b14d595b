"""Prophesee RAW (EVT 2.0, 2.1 and 3.0) and DAT (CD, version 2) recordings, read by content.

Both start with a text header of lines beginning with ``%``. EVT 2.0 then
holds little-endian 32-bit words whose top four bits give their type:
CD_OFF (0) and CD_ON (1) carry the six low bits of the time stamp, x (11
bits) and y (11 bits); EV_TIME_HIGH (8) carries the 28 high bits of the time
stamp; EXT_TRIGGER (10) carries the six low bits, a channel (5 bits) and the
edge (bit 0). DAT files follow the header with two bytes (event type 0x0C,
event size 8) and then 8-byte events: a 32-bit time stamp and a 32-bit word
with x (14 bits), y (14 bits) and the polarity (4 bits). EVT 2.1 holds 64-bit
words: 32 bits laid out as an EVT 2.0 word (a CD word's x the base of 32
pixels) and a 32-bit mask of those pixels; by default one little-endian 64-bit
value (the mask in its low half), or, where the format line says
``endianness=legacy`` (the IMX636's output), the half with the type first.
EVT 3.0 holds 16-bit
words (type in the top four bits): y (0), a single x with its polarity (2),
the base x and polarity of a vector (3), 12- and 8-pixel vector masks (4, 5),
the low and high twelve bits of a 24-bit time stamp (6, 8) and triggers (10),
following Prophesee's documentation; the 24-bit time is unwrapped (public
decoders differ on some files' stamps: evtk follows the documented format). Time stamps are
microseconds as stored (faery also writes a ``% t0`` line and adds it back
when reading; Prophesee's tools and expelliarmus do not: evtk reports it in
``metadata`` and keeps the stamps as stored). Counters that wrap (EVT 2.0's
34-bit time, DAT's 32-bit one) are unwrapped.

A full read decodes the file block by block into one set of columns (EVT
3.0's blocks on the reader's threads, each from the state a counting pass
gives it). For windows the reader makes its own block index in one counting
pass, so a window decodes only the blocks it overlaps, and streaming holds
one block at a time; nothing in the index comes from the file's claims.
"""

from __future__ import annotations

from .decoders import sniff
from .recording import EventStreamRecording, PropheseeRecording

__all__ = ["PropheseeRecording", "EventStreamRecording", "sniff"]
