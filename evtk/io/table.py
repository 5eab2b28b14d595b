"""Events as an Arrow table (the columns, the schema metadata evtk writes, the header checks shared by readers).

The code lives in ``evtk/_table.py``, below both the event container (:class:`evtk.Events` builds its Arrow
conversions on it) and the file formats, so that neither imports the other; this module is its public name.
"""

from __future__ import annotations

from .._table import MAX_SENSOR_SIDE, columns_to_table, load_json, sensor_dims, table_to_columns

__all__ = ["columns_to_table", "table_to_columns", "sensor_dims", "load_json", "MAX_SENSOR_SIDE"]
