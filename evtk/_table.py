"""Events as an Arrow table: the columns, the schema metadata evtk writes, and the header checks shared by readers.

This module imports nothing of evtk's event classes (:class:`evtk.Events`
builds on it), so the event container and the file formats do not import
each other.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ._version import __version__
from .errors import MAX_SENSOR_SIDE, EvtkError, FormatError, load_json, sensor_dims  # noqa: F401  (this module's API)

if TYPE_CHECKING:
    import pyarrow as pa

    from .events import Triggers

__all__ = ["columns_to_table", "table_to_columns", "sensor_dims", "load_json", "MAX_SENSOR_SIDE"]

KEY_SENSOR = b"evtk.sensor_size"
KEY_META = b"evtk.metadata"
KEY_TRIGGERS = b"evtk.triggers"
KEY_VERSION = b"evtk.version"

def pyarrow_module():
    import pyarrow as pa

    return pa


def _schema_metadata(sensor_size, metadata=None, triggers=None) -> dict:
    import json

    out = {KEY_SENSOR: json.dumps(list(sensor_size)).encode(), KEY_VERSION: __version__.encode()}
    if metadata:
        try:
            out[KEY_META] = json.dumps(metadata, sort_keys=True).encode()
        except (TypeError, ValueError) as exc:
            raise EvtkError(f"metadata must be JSON-serialisable: {exc}") from None
    if triggers is not None:
        d = {"t": triggers.t.tolist(), "kind": triggers.kind.tolist()}
        if triggers.channel.any():  # channel 0 throughout: no key, as files before channels were kept
            d["channel"] = triggers.channel.tolist()
        out[KEY_TRIGGERS] = json.dumps(d).encode()
    return out


def events_schema(sensor_size, metadata=None, triggers=None):
    pa = pyarrow_module()
    return pa.schema(
        [("t", pa.int64()), ("x", pa.uint16()), ("y", pa.uint16()), ("p", pa.uint8())],
        metadata=_schema_metadata(sensor_size, metadata, triggers),
    )


def columns_to_table(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, sensor_size: Sequence[int],
                     metadata: Mapping[str, Any] | None = None, triggers: Triggers | None = None) -> pa.Table:
    """A ``pyarrow.Table`` of the event columns t, x, y, p (no copy), the sensor size in its schema metadata.

    Parameters
    ----------
    t, x, y, p : numpy.ndarray
        The columns: int64 µs, uint16 pixels, uint16 pixels, uint8 polarity (1 ON); other dtypes are cast
        by the schema.
    sensor_size : sequence of two int
        ``(width, height)`` in pixels, stored as ``evtk.sensor_size`` in the schema metadata.
    metadata : Mapping of str to object, optional
        Stored as JSON (``evtk.metadata``).
    triggers : Triggers, optional
        Stored as JSON lists (``evtk.triggers``): times, kinds, and channels where any is not 0.

    Returns
    -------
    pyarrow.Table
        Columns ``t``, ``x``, ``y``, ``p``; the schema metadata also holds ``evtk.version``.

    Raises
    ------
    EvtkError
        When ``metadata`` is not JSON-serialisable.
    """
    pa = pyarrow_module()
    return pa.Table.from_arrays([pa.array(t), pa.array(x), pa.array(y), pa.array(p)],
                                schema=events_schema(sensor_size, metadata, triggers))


def sensor_from(meta, path=None):
    raw = (meta or {}).get(KEY_SENSOR)
    if raw is None:
        return None
    value = load_json(raw, path, f"schema metadata {KEY_SENSOR.decode()}")
    if not isinstance(value, list) or len(value) != 2:
        raise FormatError(path, None, f"schema metadata {KEY_SENSOR.decode()} is not [width, height]: {raw[:100]!r}")
    return sensor_dims(value[0], value[1], path, f"schema metadata {KEY_SENSOR.decode()}")


def numpy_of(col) -> np.ndarray:
    """The values of a pyarrow column (an Array or ChunkedArray without nulls) as one numpy array: integer
    columns straight from their data buffers (one chunk viewed, several copied into one array), as pyarrow's own
    ``to_numpy`` imports pandas (0.2-0.3 s of a fresh process); other types through ``to_numpy``."""
    try:
        dtype = np.dtype(str(col.type))
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in "iu":
        return col.to_numpy()
    chunks = [c for c in (col.chunks if hasattr(col, "chunks") else [col]) if len(c)]
    views = [np.frombuffer(c.buffers()[1], dtype, count=len(c), offset=c.offset * dtype.itemsize) for c in chunks]
    if len(views) == 1:
        return views[0]
    out = np.empty(sum(len(v) for v in views), dtype)
    pos = 0
    for v in views:
        out[pos:pos + len(v)] = v
        pos += len(v)
    return out


def arrow_columns(table, path=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    names = table.schema.names if hasattr(table, "schema") else table.names
    missing = [c for c in ("t", "x", "y", "p") if c not in names]
    if missing:
        raise FormatError(path, None, f"columns {missing} missing; found {list(names)}; expected t, x, y, p")
    t, x, y, p = (arrow_column(table, name, path) for name in ("t", "x", "y", "p"))
    return t, x, y, p


def arrow_column(table: pa.Table, name: str, path: str | os.PathLike[str] | None = None) -> np.ndarray:
    """The integer column ``name`` of a ``pyarrow.Table`` as a numpy array (a view of its buffer where it
    has one chunk); a FormatError naming ``path`` when it holds nulls or is not of an integer type."""
    col = table.column(name)
    if col.null_count:
        raise FormatError(path, None, f"column {name!r} holds {col.null_count} null values")
    arr = numpy_of(col)
    if arr.dtype.kind not in "iub":
        raise FormatError(path, None, f"column {name!r} has type {col.type}, expected an integer type")
    return arr


def table_to_columns(table: pa.Table, sensor_size: Sequence[int] | None = None,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, ...]]:
    """``(t, x, y, p, sensor_size)`` of a ``pyarrow.Table`` (or anything with columns t, x, y, p).

    The sensor size comes from ``sensor_size`` or from the schema metadata
    evtk writes.

    Parameters
    ----------
    table : pyarrow.Table
        Integer columns t, x, y, p without nulls (others are ignored).
    sensor_size : sequence of two int, optional
        ``(width, height)``; default: the table's ``evtk.sensor_size`` metadata.

    Returns
    -------
    t, x, y, p : numpy.ndarray
        The columns as Arrow gives them (no copy where it can; dtypes not converted).
    sensor_size : tuple of int
        ``(width, height)``.

    Raises
    ------
    EvtkError
        When no sensor size is given or stored.
    FormatError
        When a column is missing, holds nulls or is not of an integer type, or the stored size is not two
        whole numbers from 1 to 65536.
    """
    size = sensor_size or sensor_from(table.schema.metadata)
    if size is None:
        raise EvtkError("the table carries no evtk.sensor_size metadata; pass sensor_size=(width, height)")
    t, x, y, p = arrow_columns(table)
    return t, x, y, p, tuple(size)
