"""Every setting of a reconstruction in one typed value, shared by the library, ``reconstruct`` and ``batch``."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..errors import EvtkError

__all__ = ["ReconstructOptions"]


@dataclass(frozen=True)
class ReconstructOptions:
    """The settings :func:`evtk.reconstruct.reconstruct` takes besides the recording.

    ``window`` is ``"schedule"``, ``"triggers"`` or ``("period", US)``;
    ``binarize_method`` ``"auto"``, ``"sign"``, ``"mean"``, ``"otsu"`` or a
    number; ``region`` (x0, x1, y0, y1) or None; ``deblur`` and ``timing``
    None for the default rule. See :func:`~evtk.reconstruct.reconstruct` for
    each. ``reconstruct(rec, **options.kwargs())`` runs them.

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

    def __post_init__(self):
        if self.crop not in ("valid", "full"):
            raise EvtkError(f"crop must be 'valid' or 'full', not {self.crop!r}")
        if int(self.skip_us) < 0 or (self.length_us is not None and int(self.length_us) < 1):
            raise EvtkError("skip_us must be >= 0 and length_us >= 1")
        if len(tuple(self.size)) != 2 or min(int(v) for v in self.size) < 1:
            raise EvtkError(f"size must be two positive numbers, not {self.size!r}")

    def kwargs(self) -> dict:
        """The keyword arguments of :func:`~evtk.reconstruct.reconstruct`."""
        d = asdict(self)
        d["size"] = tuple(int(v) for v in self.size)
        return d
