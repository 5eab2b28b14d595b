"""Reading and writing the small TOML/JSON settings files evtk uses (bench, job, calibration)."""

from __future__ import annotations

import json
import math
import os

from .errors import EvtkError

__all__ = ["read_table", "toml_value"]


def read_table(path, what) -> dict:
    """The top-level table of a TOML (``.toml``) or JSON (anything else) file; ``what`` names it in errors."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise EvtkError(f"{path}: cannot read {what} file: {exc.strerror or exc}") from None
    try:
        if path.lower().endswith(".toml"):
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            data = tomllib.loads(raw.decode("utf-8"))
        else:
            data = json.loads(raw.decode("utf-8"))
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise EvtkError(f"{path}: not a valid {what} file: {exc}") from None
    if not isinstance(data, dict):
        raise EvtkError(f"{path}: a {what} file holds a table of parameters")
    return data


def toml_value(v, what="settings") -> str:
    """``v`` (bool, number, string or a list of them) as a TOML value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise EvtkError(f"cannot store {v!r} in a {what} file")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x, what) for x in v) + "]"
    raise EvtkError(f"cannot store {v!r} in a {what} file")
