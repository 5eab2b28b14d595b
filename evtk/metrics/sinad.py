"""SINAD and effective bits of repeated captures (eq. 8), with intervals of honest coverage."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, overload

import numpy as np

from .._parallel import parts, run
from .._threads import workers
from ..errors import EvtkError
from ..limits import require_memory

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["SinadReport", "sinad", "SinadAccumulator", "enob_bits"]


def _json_float(v):
    """inf/-inf/NaN as JSON null; everything else a plain float."""
    return float(v) if v is not None and np.isfinite(v) else None


@overload
def enob_bits(sinad_db: float) -> float: ...


@overload
def enob_bits(sinad_db: npt.ArrayLike) -> float | np.ndarray: ...


def enob_bits(sinad_db: npt.ArrayLike) -> float | np.ndarray:
    """Effective number of bits from SINAD in dB (eq. 8): ``(SINAD - 1.76) / 6.02``.

    ``+inf`` (noise-free) stays ``+inf``.

    Parameters
    ----------
    sinad_db : float or array_like
        SINAD in dB (may be infinite, not NaN).

    Returns
    -------
    float or numpy.ndarray
        ENOB in bits: a float for a scalar, else float64 shaped like ``sinad_db``.

    Raises
    ------
    EvtkError
        If any value is NaN.

    Examples
    --------
    >>> round(enob_bits(6.02 * 8 + 1.76), 12)
    8.0
    """
    s = np.asarray(sinad_db, dtype=np.float64)
    if np.any(np.isnan(s)):
        raise EvtkError("SINAD is NaN")
    out = (s - 1.76) / 6.02
    return float(out) if out.ndim == 0 else out


@dataclass
class SinadReport:
    """What :func:`sinad` measured.

    Parameters
    ----------
    sinad_db : float
        SINAD of eq. 8 in dB, pooled over pixels; ``+inf`` when no pixel varies between repeats.
    enob_bits : float
        Effective number of bits from ``sinad_db`` (eq. 8); ``+inf`` likewise.
    noise_free : bool
        True when the pooled noise is exactly zero.
    signal_rms : float
        ``RMS`` over all captures and pixels, in the captures' units.
    noise_std : float
        The pooled per-pixel standard deviation over repeats (ddof 1), in the captures' units.
    repeats : int
        Repeated captures measured.
    pixels : int
        Values in one capture.
    ci_db : (low, high) or None
        Confidence interval of ``sinad_db`` over repeats, dB (may reach ``+inf``); None when not formed.
    ci_enob : (low, high) or None
        The same interval in bits.
    confidence : float
        Nominal coverage of the interval.
    per_pixel_db : numpy.ma.MaskedArray or None
        Per-pixel SINAD, dB (shape of one capture), masked where a pixel has no
        signal at all; ``+inf`` where it has signal but no noise.
    interval : str or None
        How the interval was formed (``"jackknife"`` or ``"bootstrap"``).
    """

    sinad_db: float
    enob_bits: float
    noise_free: bool
    signal_rms: float
    noise_std: float
    repeats: int
    pixels: int
    ci_db: tuple | None = None
    ci_enob: tuple | None = None
    confidence: float = 0.95
    per_pixel_db: np.ma.MaskedArray | None = None
    interval: str | None = None

    def to_dict(self) -> dict:
        """The report as a JSON-safe dict: infinities become ``null`` (see ``noise_free``).

        Returns
        -------
        dict
            Every field; intervals as lists, ``per_pixel_db`` (when measured) as nested lists with ``null``
            where masked or infinite.
        """
        d = {
            "sinad_db": _json_float(self.sinad_db),
            "enob_bits": _json_float(self.enob_bits),
            "noise_free": bool(self.noise_free),
            "signal_rms": float(self.signal_rms),
            "noise_std": float(self.noise_std),
            "repeats": int(self.repeats),
            "pixels": int(self.pixels),
            "confidence": float(self.confidence),
            "ci_db": None if self.ci_db is None else [_json_float(v) for v in self.ci_db],
            "ci_enob": None if self.ci_enob is None else [_json_float(v) for v in self.ci_enob],
            "interval": self.interval,
        }
        if self.per_pixel_db is not None:
            pp = self.per_pixel_db
            values = pp.filled(0.0)
            missing = np.asarray(pp.mask | ~np.isfinite(values))
            d["per_pixel_db"] = np.where(missing, np.nan, values).astype(object)
            d["per_pixel_db"][missing] = None
            d["per_pixel_db"] = d["per_pixel_db"].tolist()
        return d


def _as_repeats(captures, what):
    x = np.asarray(captures)
    if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
        raise EvtkError(f"{what} must be numeric, not {x.dtype}")
    if x.ndim < 1 or x.shape[0] < 2:
        raise EvtkError(f"{what} needs at least two repeated captures along the first axis, "
                        f"got shape {x.shape}")
    if x.size == 0:
        raise EvtkError(f"{what} holds no pixels")
    return x


#: Most groups of repeats an interval resamples: more repeats are grouped in contiguous blocks.
MAX_BOOTSTRAP_GROUPS = 64

#: Interval methods of :func:`sinad`.
INTERVALS = ("jackknife", "bootstrap", None)


def _pixel_parts(block: np.ndarray) -> list[tuple[int, int]]:
    """Runs of a block's pixels (columns), one a counting thread (:func:`evtk._parallel.parts`)."""
    p = block.shape[1]
    n = min(parts(block.size), p)  # (never an empty run)
    return [(p * r // n, p * (r + 1) // n) for r in range(n)]


def _magnitude(x: np.ndarray, runs: list[tuple[int, int]]) -> int:
    """The largest magnitude of whole numbers ``x`` (rows x pixels), as a Python int (no wrap); ``runs`` of pixels
    (:func:`_pixel_parts`) on the counting threads."""
    def part(a: int, b: int) -> int:
        v = x[:, a:b]
        return max(abs(int(v.max())), abs(int(v.min())))

    return max(run(part, runs))


def _sums_exact(k: int, big: int) -> bool:
    """Whether ``k`` whole-number repeats of magnitudes at most ``big`` keep ``k * S2`` and ``S1 ** 2`` in int64 (the
    exact integer route); beyond it the float route measures them."""
    return k * k * big * big < 2**62


def _whole_sums(block: np.ndarray, big: int, runs: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-pixel sum and sum of squares (exact) of a block of whole-number repeats whose magnitudes are at most
    ``big``, in the narrowest signed type of the block's own, int32 and int64 that holds them; None where ``k * S2``
    or ``S1 ** 2`` could leave int64 (then the float route measures it). ``runs`` of pixels (:func:`_pixel_parts`)
    go to the counting threads (each pixel's sums are its own: the same whatever the runs)."""
    k = block.shape[0]
    if not _sums_exact(k, big):
        return None
    # einsum sums in its inputs' type: in the block's own signed type where neither sum can leave it (int16 net
    # counts: no copy), else in int32 where they cannot overflow it, else in int64; the sums stay in that type
    # (no int64 copy of them: the merge widens what it must, one step at a time)
    if block.dtype.kind == "i" and block.dtype.itemsize <= 4 and k * big * big <= np.iinfo(block.dtype).max:
        kind = block.dtype
    elif block.dtype.itemsize <= 4 and block.dtype != np.uint32 and k * big * big < 2**31:
        kind = np.dtype(np.int32)
    else:
        kind = np.dtype(np.int64)
    s1 = np.empty(block.shape[1], kind)
    s2 = np.empty(block.shape[1], kind)

    def part(a: int, z: int) -> None:
        b = block[:, a:z].astype(kind, copy=False)
        np.einsum("rp->p", b, out=s1[a:z])
        np.einsum("rp,rp->p", b, b, out=s2[a:z])

    run(part, runs)
    return s1, s2


#: The report centres the groups' means a run of pixels at a time, on at most this many threads, each with a
#: groups x run float64 buffer of one per-pixel array's worth (or of 32 pixels a group, where more).
_REPORT_RUN = 2

#: Most sizes of groups whose whole-number sums the accumulator keeps apart at once (:meth:`SinadAccumulator._pool`):
#: equal groups of repeats have at most two sizes.
_SIZES_KEPT = 2


class SinadAccumulator:
    """SINAD (eq. 8) of repeated captures of one scene, fed a block of repeats at a time.

    Keeps, per contiguous group of repeats (a repeat a group up to
    :data:`MAX_BOOTSTRAP_GROUPS` repeats, contiguous blocks beyond), the
    group's per-pixel mean, its summed squared deviation and its summed
    squares, merged block by block with Chan's pairwise update (exact for
    large means with tiny noise); a group of whole numbers (counts) is kept
    as its exact integer sums instead. Memory is groups x pixels whatever the
    number of repeats, so a minute of 10 ms windows is measured in one pass;
    :func:`sinad` is one accumulator given every repeat at once.

    Parameters
    ----------
    repeats : int
        How many repeats will be added in all (at least two).
    shape : int or tuple of int
        Shape of one capture.
    per_pixel : bool
        Keep each pixel's own sums for :meth:`report`'s per-pixel SINAD (default). False leaves them out (two
        int64 or float64 passes over the pixels a group, which ``evtk enob`` spares when no per-pixel figure is
        asked for); :meth:`report` then refuses ``per_pixel=True``.

    Raises
    ------
    EvtkError
        Fewer than two repeats, a capture of no pixels, or more memory than the budget
        (:func:`evtk.limits.require_memory`).

    Examples
    --------
    >>> acc = SinadAccumulator(4, (2,))
    >>> acc.add([[3.0, 1.0], [5.0, 1.0]])
    >>> acc.add([[3.0, 1.0], [5.0, 1.0]])
    >>> a = acc.report(interval=None).sinad_db
    >>> b = sinad([[3.0, 1.0], [5.0, 1.0]] * 2, interval=None).sinad_db
    >>> abs(a - b) < 1e-12
    True
    """

    def __init__(self, repeats: int, shape: int | tuple[int, ...], per_pixel: bool = True) -> None:
        repeats = int(repeats)
        if repeats < 2:
            raise EvtkError(f"SINAD needs at least two repeated captures, got {repeats}")
        self.shape = tuple(int(s) for s in np.atleast_1d(shape)) if len(tuple(np.atleast_1d(shape))) else (1,)
        p = math.prod(self.shape)  # a Python int: a hostile shape cannot wrap int64
        if p == 0:
            raise EvtkError("SINAD: the captures hold no pixels")
        require_memory(self.bytes_needed(repeats, p), f"SINAD of {repeats:,} captures of {p:,} pixels")
        self.repeats = repeats
        self.per_pixel = bool(per_pixel)
        g = min(repeats, MAX_BOOTSTRAP_GROUPS)
        self._bounds = np.linspace(0, repeats, g + 1).round().astype(np.int64)
        self._n = np.zeros(g)
        self._mean = np.zeros((g, p))  # the groups' means (pages touched only by groups merged in floats)
        # the per-pixel sums of the groups merged from whole numbers (int16 or int32: a quarter or half of their
        # float means' pages), the group's mean their quotient by its size (:meth:`_mean_of`)
        self._s1: np.ndarray | None = None
        self._whole = np.zeros(g, bool)
        self._m2 = np.zeros(g)  # squared deviations from the group's mean, summed over its repeats and pixels
        self._m2_px = np.zeros(p)  # the same per pixel, summed over groups
        self._sq = np.zeros(g)  # squares of the group's values, summed
        self._sq_px = np.zeros(p)
        self._pending: list | None = None  # a group's integer sums not yet merged (:meth:`_stash`)
        # per size k of group: the per-pixel sums over its whole-number groups of S2 and of S1^2 (int64, exact),
        # and bounds of the two (:meth:`_pool`; into _m2_px and _sq_px by :meth:`_spill`)
        self._sizes: dict[int, list] = {}
        # per group merged from exact integer sums and holding them still (its row of _s1): (sum of S2, sum of
        # S1^2) over its pixels, Python ints, for the jackknife's exact leave-one-outs; None for the others
        self._exact_sums: list[tuple[int, int] | None] = [None] * g
        self.added = 0

    @staticmethod
    def bytes_needed(repeats: int, pixels: int) -> int:
        """Peak memory of an accumulator and its report, before any is allocated.

        Parameters
        ----------
        repeats : int
            Repeats it will be given.
        pixels : int
            Values in one capture.

        Returns
        -------
        int
            Bytes: one groups x pixels float64 array (the groups' means; a
            group merged from whole numbers leaves its pages untouched and
            keeps its int16 or int32 sums instead), the int16 and int32
            arrays of those sums (both while the first is widened, beside
            the means where floats and counts mix), eight per-pixel float64
            ones, two int64 per-pixel sums for each size of group kept apart,
            the report's groups x run-of-pixels buffers, and each run's
            squared norms (a float64 a group; runs of 32 pixels at least).
        """
        groups = min(max(int(repeats), 0), MAX_BOOTSTRAP_GROUPS)
        return (8 * int(pixels) * (groups + 8 + _REPORT_RUN + 2 * _SIZES_KEPT) + 6 * int(pixels) * groups
                + 8 * 32 * _REPORT_RUN * groups + 8 * groups * -(-int(pixels) // 32))

    @property
    def group_starts(self) -> np.ndarray:
        """The first repeat of each group of repeats: blocks of :meth:`add` that keep within one group are
        merged once per group.

        Returns
        -------
        numpy.ndarray
            int64, increasing, from 0 (a copy).
        """
        return self._bounds[:-1].copy()

    def add(self, captures: npt.ArrayLike) -> int | None:
        """Add the next repeats, shape ``(k, *shape)``, in their order.

        Integer captures (counts) are summed exactly in integers, a group of
        repeats at a time: its per-pixel sum and sum of squares give the
        group's mean and squared deviation without rounding, and a block whose
        squares could overflow int64 goes the float route (Chan's update from a
        shift near the data), as float captures do.

        Parameters
        ----------
        captures : array_like
            ``k`` repeats, numeric (any shape whose size is ``k`` times the pixels of one capture).

        Returns
        -------
        int or None
            The largest magnitude among whole-number captures (integers or booleans; what the exact sums were
            checked against), None for other captures or none at all.

        Raises
        ------
        EvtkError
            Values not numeric, NaN or infinite, captures of the wrong size, or more repeats than announced.
        """
        x = np.asarray(captures)
        if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
            raise EvtkError(f"SINAD: the captures must be numeric, not {x.dtype}")
        p = self._mean.shape[1]
        if x.ndim < 1 or x.size != x.shape[0] * p:
            raise EvtkError(f"SINAD: each capture must hold {p} values, got shape {x.shape}")
        x = x.reshape(x.shape[0], p)
        if self.added + x.shape[0] > self.repeats:
            raise EvtkError(f"SINAD: more than the {self.repeats} repeats announced")
        whole = np.issubdtype(x.dtype, np.integer) or x.dtype == bool
        runs = _pixel_parts(x) if whole and x.size else []
        # the largest magnitude of whole numbers (a Python int: no wrap), for the exact sums' overflow check
        big = _magnitude(x, runs) if runs else None
        if not whole:
            x = x.astype(np.float64, copy=False)
            if not np.all(np.isfinite(x)):
                raise EvtkError("SINAD: the captures hold NaN or infinite values")
        i = 0
        while i < x.shape[0]:
            at = self.added + i
            g = int(np.searchsorted(self._bounds, at, side="right")) - 1
            block = x[i:i + int(self._bounds[g + 1]) - at]
            k = block.shape[0]
            sums = None if big is None else _whole_sums(block, big, runs)
            if sums is not None and big is not None:  # counts: exact integer sums, kept until the group is complete
                self._stash(g, k, big, *sums)
            else:
                self._flush()
                block = block.astype(np.float64, copy=False)
                ref = self._mean_of(g) if self._n[g] else block[0]  # a shift near the data keeps the sums exact
                dev = block - ref
                s1f = dev.sum(axis=0)
                s2f = np.einsum("rp,rp->p", dev, dev)
                block_m2 = np.maximum(s2f - s1f * s1f / k, 0.0)
                sq = k * ref * ref + 2.0 * ref * s1f + s2f
                self._merge(g, k, ref + s1f / k, block_m2, sq)
            i += k
        self.added += x.shape[0]
        return big

    def add_sums(self, k: int, s1: npt.ArrayLike, s2: npt.ArrayLike, big: int) -> bool:
        """Add the next ``k`` whole-number repeats given by their per-pixel sum and sum of squares (eq. 8's sums):
        the same state, to the last bit, as :meth:`add` of the repeats themselves.

        For a caller that sums its counts itself (``evtk enob`` with the compiled kernel,
        :func:`evtk._native.net_sums`). The ``k`` repeats must lie in one group (blocks cut at
        :attr:`group_starts`). The accumulator copies what it keeps of ``s1`` and ``s2``: the caller may
        overwrite them once this returns (enob sums every batch into the same two arrays).

        Parameters
        ----------
        k : int
            Repeats summed (at least 1).
        s1, s2 : array_like
            Each pixel's sum and sum of squares over them: exact integers, one per pixel of a capture.
        big : int
            The largest magnitude among the repeats' values.

        Returns
        -------
        bool
            True when added; False, nothing added, where the exact integer sums could leave int64 (``k**2 *
            big**2 >= 2**62``): :meth:`add` then takes the repeats themselves by the float route.

        Raises
        ------
        EvtkError
            Sums that are not integers or not one per pixel, ``k`` below 1 or a negative ``big``, more repeats than
            announced, or repeats that span two groups.
        """
        k, big = int(k), int(big)
        a1, a2 = np.asarray(s1), np.asarray(s2)
        p = self._mean.shape[1]
        if not (np.issubdtype(a1.dtype, np.integer) and np.issubdtype(a2.dtype, np.integer)):
            raise EvtkError(f"SINAD: the sums must be integers, not {a1.dtype} and {a2.dtype}")
        if a1.size != p or a2.size != p:
            raise EvtkError(f"SINAD: the sums must hold {p} values each, got {a1.size} and {a2.size}")
        if k < 1 or big < 0:
            raise EvtkError(f"SINAD: {k} repeats of largest magnitude {big}")
        if self.added + k > self.repeats:
            raise EvtkError(f"SINAD: more than the {self.repeats} repeats announced")
        g = int(np.searchsorted(self._bounds, self.added, side="right")) - 1
        if self.added + k > int(self._bounds[g + 1]):
            raise EvtkError(f"SINAD: repeats {self.added} .. {self.added + k - 1} span two groups (cut them at "
                            "group_starts)")
        if not _sums_exact(k, big):
            return False
        self._stash(g, k, big, a1.reshape(p), a2.reshape(p))
        self.added += k
        return True

    def _stash(self, g: int, k: int, big: int, s1: np.ndarray, s2: np.ndarray) -> None:
        """Add a block of ``k`` whole-number repeats of group ``g`` (magnitudes at most ``big``, per-pixel sum
        ``s1`` and sum of squares ``s2``, exact in an integer type) to the group's integer sums; merged
        (:meth:`_flush`) when the group is complete, or before its sums could leave int64. A block that is a whole
        group (as enob gives them) is merged straight from its own sums."""
        pend = self._pending
        if pend is not None and (pend[0] != g or (pend[1] + k) ** 2 * max(pend[2], big) ** 2 >= 2**62):
            self._flush()
            pend = None
        complete = self._n[g] + k + (0 if pend is None else pend[1]) == self._bounds[g + 1] - self._bounds[g]
        if pend is None:
            if complete:
                self._merge_sums(g, k, big, s1, s2)
                return
            self._pending = pend = [g, k, big, s1.astype(np.int64), s2.astype(np.int64)]
        else:
            pend[1] += k
            pend[2] = max(pend[2], big)
            pend[3] += s1
            pend[4] += s2
        if complete:
            self._flush()

    def _flush(self) -> None:
        """Merge the stashed integer sums, if any (:meth:`_merge_sums`)."""
        if self._pending is not None:
            g, k, big, s1, s2 = self._pending
            self._pending = None
            self._merge_sums(g, k, big, s1, s2)

    def _merge_sums(self, g: int, k: int, big: int, s1: np.ndarray, s2: np.ndarray) -> None:
        """Merge ``k`` whole-number repeats of group ``g`` given by their per-pixel sum ``s1`` and sum of squares
        ``s2`` (exact integers, magnitudes of the values at most ``big``): mean ``S1 / k`` and squared deviation
        ``(k S2 - S1^2) / k``, whose numerator is an exact integer.

        A group's only block (a whole group of counts, as enob gives them) keeps its per-pixel sum as the group's
        row of integer sums (int16 or int32; its mean that over ``k``, formed by the report a run of pixels at a
        time), its two summed scalars from exact integer sums, and its per-pixel ``S2`` and ``S1^2`` in the sums
        of its size of group (:meth:`_pool`): a handful of passes over the pixels a group, each in the narrowest
        exact type.
        """
        big2 = k * big * big  # bounds S2 (and k S2 bounds S1^2)
        if self._n[g]:  # a block after a float-merged one (rare): Chan's update from the block's own mean
            s1 = s1.astype(np.int64, copy=False)
            num = np.multiply(s2, k, dtype=np.int64)  # k S2 - S1^2 (exact in int64), with one temporary
            num -= np.square(s1)
            self._merge(g, k, s1 / k, np.divide(num, k), s2.astype(np.float64))
            return
        most = k * big  # bounds S1, below 2**31 (checked by _whole_sums)
        if self._s1 is None:
            self._s1 = np.zeros(self._mean.shape, np.int16 if most <= np.iinfo(np.int16).max else np.int32)
        elif most > np.iinfo(self._s1.dtype).max:
            self._s1 = self._s1.astype(np.int32)
        self._s1[g] = s1
        self._whole[g] = True
        q = np.square(s1, dtype=np.int64)  # S1^2, exact: below 2**62 (checked by _whole_sums)
        p = s1.size
        if p * k * big2 < 2**63:  # the pixels' sums of S2 and S1^2 stay in int64: exact, as Python ints
            s2_sum, q_sum = int(np.add.reduce(s2, dtype=np.int64)), int(np.add.reduce(q))
            self._m2[g] += (k * s2_sum - q_sum) / k
            self._sq[g] += float(s2_sum)
            self._exact_sums[g] = (s2_sum, q_sum)
        else:
            num = np.multiply(s2, k, dtype=np.int64)
            num -= q
            self._m2[g] += float(np.divide(num, k).sum())
            self._sq[g] += float(s2.sum(dtype=np.float64))
        if self.per_pixel:
            self._pool(k, big2, s2, q)
        self._n[g] = k

    def _pool(self, k: int, big2: int, s2: np.ndarray, q: np.ndarray) -> None:
        """Add a whole group of ``k`` repeats' per-pixel ``S2`` and ``S1^2`` (``s2`` at most ``big2``) to the int64
        sums of the groups of its size, spilling (:meth:`_spill`) those before they could leave int64 and the
        oldest size beyond :data:`_SIZES_KEPT`."""
        kept = self._sizes.get(k)
        if kept is not None and (k * (kept[2] + big2) >= 2**62 or kept[3] + k * big2 >= 2**62):
            self._spill(k)
            kept = None
        if kept is None:
            if len(self._sizes) >= _SIZES_KEPT:
                self._spill(next(iter(self._sizes)))
            self._sizes[k] = [s2.astype(np.int64), q, big2, k * big2]
            return
        np.add(kept[0], s2, out=kept[0])
        np.add(kept[1], q, out=kept[1])
        kept[2] += big2
        kept[3] += k * big2

    def _spill(self, k: int | None = None) -> None:
        """Move the int64 sums of the groups of ``k`` repeats (every size: None) into the float per-pixel squared
        deviation (``(k S2 - S1^2) / k`` over those groups) and sum of squares."""
        for size in list(self._sizes) if k is None else [k]:
            s2, q, _, _ = self._sizes.pop(size)
            q *= -1
            q += s2 * size  # k S2 - S1^2, exact: below 2**62 (checked by _pool)
            self._m2_px += q / size
            self._sq_px += s2

    def _merge(self, g: int, k: int, block_mean: np.ndarray | None, block_m2: np.ndarray, sq: np.ndarray) -> None:
        """Merge a block of ``k`` repeats of group ``g`` (its per-pixel mean, squared deviation from that mean and
        sum of squares) into the group by Chan's pairwise update (a group's first block: ``block_mean`` None where
        it is in the group's row already)."""
        had = self._n[g]
        if not had:  # the group's first block: nothing to merge with
            if self.per_pixel:
                self._m2_px += block_m2
                self._sq_px += sq
            self._m2[g] += float(block_m2.sum())
            if block_mean is not None:
                self._mean[g] = block_mean
            self._sq[g] += float(sq.sum())
            self._n[g] = k
            return
        delta = block_mean - self._mean_of(g)
        w = had * k / (had + k)
        if self.per_pixel:
            self._m2_px += block_m2 + w * delta * delta
            self._sq_px += sq
        # (einsum, not @: a BLAS dot of one vector wakes its threads, 600x slower on a busy machine)
        self._m2[g] += float(block_m2.sum()) + w * float(np.einsum("p,p->", delta, delta))
        self._mean[g] += delta * (k / (had + k))
        self._sq[g] += float(sq.sum())
        self._n[g] += k

    def _mean_of(self, g: int) -> np.ndarray:
        """Group ``g``'s mean row, its float row from now on where the group held integer sums."""
        if self._whole[g]:
            assert self._s1 is not None
            np.divide(self._s1[g], self._n[g], out=self._mean[g])
            self._whole[g] = False
            self._exact_sums[g] = None
        return self._mean[g]

    def _between(self, gram: bool, per_pixel: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """The groups' means centred on the overall mean, a run of pixels at a time (never a groups x pixels
        float copy): each group's squared norm of them, with their Gram matrix (``gram``) and the per-pixel sum
        over groups of ``n_g`` times their square (``per_pixel``).

        Without the Gram matrix the runs go to :data:`_REPORT_RUN` threads, each with its own buffer of a run
        (``bytes_needed`` counts them); each run's squared norms are kept apart and summed in the runs' order,
        so the result does not depend on the threads.
        """
        g, p = self._mean.shape
        n = self._n
        run_px = min(p, max(32, p // g))  # a run a buffer, _REPORT_RUN buffers (bytes_needed counts them)
        runs = [(a, min(p, a + run_px)) for a in range(0, p, run_px)]
        per_run = np.zeros((len(runs), g))  # (bytes_needed counts it: at most a row a 32 pixels)
        gm = np.zeros((g, g)) if gram else None
        pp = np.empty(p) if per_pixel else None
        whole = self._whole.all()

        def part(lo: int, hi: int) -> None:  # runs lo .. hi - 1
            buf = np.empty((g, run_px))
            for r in range(lo, hi):
                a, z = runs[r]
                off = buf[:, :z - a]
                if whole:
                    assert self._s1 is not None
                    np.divide(self._s1[:, a:z], n[:, None], out=off)
                else:
                    for i in range(g):
                        if self._whole[i]:
                            assert self._s1 is not None
                            np.divide(self._s1[i, a:z], n[i], out=off[i])
                        else:
                            off[i] = self._mean[i, a:z]
                off -= np.einsum("g,gp->p", n, off) / self.repeats
                per_run[r] = np.einsum("gp,gp->g", off, off)
                if gm is not None:  # (one thread: the matrix is summed in place)
                    np.add(gm, off @ off.T, out=gm)
                if pp is not None:
                    pp[a:z] = np.einsum("g,gp,gp->p", n, off, off)

        threads = 1 if gm is not None else min(_REPORT_RUN, workers(), len(runs))
        cut = [len(runs) * t // threads for t in range(threads + 1)]
        run(part, list(zip(cut, cut[1:])))
        return np.add.reduce(per_run, axis=0), gm, pp

    def _group_terms(self, centred=None):
        """``(M, N, P, n)`` of the groups, for the intervals (``centred``: :meth:`_between`'s squared norms and
        Gram matrix, if at hand).

        With ``xc`` the captures centred per pixel and ``d_ij = mean_p (xc_i - xc_j)^2 / 2`` (half the squared
        difference of repeats i and j, pooled over pixels): ``M[g, h]`` the sum of ``d_ij`` over i in g and j
        in h (i != j; twice the within-group sum on the diagonal), ``N`` the number of such pairs, ``P[g]`` the
        summed mean square of g's repeats and ``n[g]`` their number. No repeat-by-repeat matrix is formed.
        """
        p = self._mean.shape[1]
        n = self._n
        between, gram = self._between(True, False)[:2] if centred is None else centred
        a = (self._m2 + n * between) / p  # per group: mean square of its centred repeats, summed
        # products of the groups' centred sums (n_g times their centred mean), without a groups x pixels copy
        k = n[:, None] * gram * n[None, :] / p
        m = (n[None, :] * a[:, None] + n[:, None] * a[None, :] - 2.0 * k) / 2.0  # between groups
        np.fill_diagonal(m, n * a - np.diag(k))  # twice the within-group sum
        pairs = np.outer(n, n)
        np.fill_diagonal(pairs, n * (n - 1))
        return m, pairs, self._sq / p, n

    def _exact_totals(self) -> tuple[np.ndarray, int, int] | None:
        """Where every group holds whole numbers merged from its exact integer sums (the counts `evtk enob`
        gives): each group's ``sum_p S1_gp T_p`` (int32 or int64), ``sum_p T_p^2`` and every group's ``sum S2``
        (Python ints), ``T`` the per-pixel sum over every group; None otherwise, or where they could leave int64
        (then the float route, :meth:`_between`)."""
        if any(v is None for v in self._exact_sums):
            return None
        s1 = self._s1
        assert s1 is not None  # (set with the first group's exact sums)
        g, p = s1.shape
        most = max(abs(int(s1.max())), abs(int(s1.min())))
        total = np.add.reduce(s1, axis=0, dtype=np.int32 if g * most < 2**31 else np.int64)
        most_t = max(abs(int(total.max())), abs(int(total.min())))
        if p * most_t * most >= 2**63 or p * most_t * most_t >= 2**63:
            return None  # (sums beyond int64)
        cross = np.einsum("gp,p->g", s1, total, dtype=np.int32 if p * most_t * most < 2**31 else np.int64)
        sq_total = int(np.dot(total.astype(np.int64, copy=False), total.astype(np.int64, copy=False)))
        return cross, sq_total, sum(v[0] for v in self._exact_sums if v is not None)

    def _exact_noise(self, totals: tuple[np.ndarray, int, int]) -> float:
        """The pooled per-pixel variance (ddof 1) of every repeat from the groups' exact integer sums
        (:meth:`_exact_totals`): ``(R sum S2 - sum_p T_p^2) / (R (R - 1) p)`` over the ``R`` repeats, an exact
        integer over an exact integer, rounded once (the sum of the groups' squared deviations and their means'
        spread that :meth:`_between` forms in floats)."""
        r, p = self.repeats, self._mean.shape[1]
        _, sq_total, s2_all = totals
        return (r * s2_all - sq_total) / (r * (r - 1) * p)

    def _exact_leave_one_out(self, totals: tuple[np.ndarray, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Each leave-one-group-out estimate's pooled noise and power, exactly, from the groups' exact integer sums
        and :meth:`_exact_totals` (else :func:`_leave_one_out` of :meth:`_group_terms`).

        Leaving group ``j`` out keeps ``N_j = N - n_j`` repeats, whose per-pixel sums are ``T - S1_j`` (``T``
        every group's): their pairs of distinct repeats give the noise numerator ``N_j S2_(-j) - sum_p (T_p -
        S1_jp)^2``, an exact integer from ``sum_p T_p^2``, ``sum_p T_p S1_jp`` and each group's ``sum_p S1^2``
        and ``S2``, over ``N_j (N_j - 1) p`` (a 64-group report formed the groups' Gram matrix for it, half its
        time, and rounding could leave a leave-out without noise a tiny positive one: a finite upper end).
        """
        cross, sq_total, s2_all = totals
        g, p = self._mean.shape
        sums = [v for v in self._exact_sums if v is not None]
        s2 = [v[0] for v in sums]
        s1_sq = [v[1] for v in sums]
        sizes = [int(v) for v in self._n]
        n_all = sum(sizes)
        noise, power = np.empty(g), np.empty(g)
        for j in range(g):
            n_j = n_all - sizes[j]
            s2_j = s2_all - s2[j]
            num = n_j * s2_j - (sq_total - 2 * int(cross[j]) + s1_sq[j])
            noise[j] = num / (n_j * (n_j - 1) * p)  # (Python ints: the quotient rounded once)
            power[j] = s2_j / (n_j * p)
        return noise, power

    def report(self, per_pixel: bool = False, interval: str | None = "jackknife", confidence: float = 0.95,
               resamples: int = 1000, seed: int = 0) -> SinadReport:
        """The :class:`SinadReport` of the repeats (all ``repeats`` must have been added); see :func:`sinad`.

        Parameters
        ----------
        per_pixel : bool
            Also report each pixel's own SINAD (from an accumulator that keeps per-pixel sums: the default).
        interval : "jackknife", "bootstrap" or None
            Confidence interval over repeats (needs at least three); see :func:`sinad`.
        confidence : float
            Nominal coverage of the interval, in (0, 1).
        resamples : int
            Resamples of the bootstrap interval.
        seed : int
            Seed of the resampling.

        Returns
        -------
        SinadReport
            SINAD and ENOB (eq. 8), with the interval and per-pixel values when asked for.

        Raises
        ------
        EvtkError
            Repeats missing, an unknown interval, a confidence outside (0, 1), an all-zero signal, or
            ``per_pixel`` from an accumulator made without per-pixel sums.
        """
        if self.added != self.repeats:
            raise EvtkError(f"SINAD: {self.added} of the {self.repeats} repeats announced were added")
        if interval not in INTERVALS:
            raise EvtkError(f"interval must be one of {INTERVALS}, not {interval!r}")
        if not 0 < confidence < 1:
            raise EvtkError(f"confidence must be between 0 and 1, not {confidence}")
        if per_pixel and not self.per_pixel:
            raise EvtkError("SINAD: this accumulator keeps no per-pixel sums (made with per_pixel=False); make it "
                            "with per_pixel=True for per-pixel SINAD")
        self._flush()
        if per_pixel:
            self._spill()
        r, p = self.repeats, self._mean.shape[1]
        n = self._n
        want_interval = interval is not None and r >= 3 and (interval == "jackknife" or bool(resamples))
        totals = self._exact_totals()
        loo = self._exact_leave_one_out(totals) if totals is not None and want_interval and interval == "jackknife" \
            else None
        between: np.ndarray | None = None
        gram: np.ndarray | None = None
        pp_between: np.ndarray | None = None
        if totals is None or per_pixel or (want_interval and loo is None):  # (counts' exact sums need no float pass)
            between, gram, pp_between = self._between(want_interval and loo is None, per_pixel)
        power = float(self._sq.sum()) / (r * p)
        if power == 0.0:
            raise EvtkError("SINAD: the signal is zero everywhere (no light reached the pixels?)")
        if totals is not None:
            noise = self._exact_noise(totals)
        else:  # pooled per-pixel variance, ddof 1
            assert between is not None
            noise = float(self._m2.sum() + n @ between) / ((r - 1) * p)
        s_db = _ratio_db(power, noise)
        report = SinadReport(s_db, enob_bits(s_db), noise == 0.0, math.sqrt(power), math.sqrt(noise), r, p,
                             confidence=confidence)
        if want_interval:
            if interval == "jackknife":
                noise_loo, power_loo = loo if loo is not None else _leave_one_out(self._group_terms((between, gram)))
                lo, hi = _jackknife_interval_db(noise_loo, power_loo, s_db, confidence)
            else:
                boot = np.sort(_bootstrap_db(self._group_terms((between, gram)), int(resamples), seed))
                tail = (1.0 - confidence) / 2
                lo = float(boot[int(math.floor(tail * (boot.size - 1)))])
                hi = float(boot[int(math.ceil((1 - tail) * (boot.size - 1)))])
            report.ci_db = (lo, hi)
            report.ci_enob = (enob_bits(lo), enob_bits(hi))
            report.interval = interval
        if pp_between is not None:  # (per_pixel)
            var = (self._m2_px + pp_between) / (r - 1)
            ms = self._sq_px / r
            pp = np.full(p, np.inf)
            noisy = var > 0
            pp[noisy] = 10.0 * np.log10(ms[noisy] / var[noisy])
            report.per_pixel_db = np.ma.masked_array(pp, mask=ms == 0).reshape(self.shape)
        return report


def sinad(captures: npt.ArrayLike, per_pixel: bool = False, interval: str | None = "jackknife",
          confidence: float = 0.95, resamples: int = 1000, seed: int = 0) -> SinadReport:
    """Signal-to-noise-and-distortion ratio of repeated captures of one scene (eq. 8).

    ``SINAD = 10 log10(RMS(I)^2 / std(I)^2)``: ``RMS`` over every capture and
    pixel, ``std`` the standard deviation over repeats of each pixel (ddof 1),
    pooled over pixels as the mean variance. ENOB follows from eq. 8
    (:func:`enob_bits`). Time and memory are linear in the captures; for more
    captures than fit in memory feed a :class:`SinadAccumulator`.

    Parameters
    ----------
    captures : array_like, shape (repeats, ...)
        Repeated captures (responses, counts, images) of one scene.
    per_pixel : bool
        Also report each pixel's own SINAD.
    interval : "jackknife", "bootstrap" or None
        Confidence interval over repeats (needs at least three).
        ``"jackknife"`` (default): delete-one-group jackknife of the SINAD in
        dB with a Student t quantile on groups - 1 degrees of freedom; its
        coverage is close to nominal from three repeats on, for noise
        independent between repeats and for noise shared by a whole repeat
        (tested by simulation in ``tests/test_metrics.py``).
        ``"bootstrap"``: percentile interval of ``resamples`` resamplings of
        the repeats; it undercovers with few repeats (about 60-75 % at three
        for a nominal 95 %) and is kept for comparison.
    confidence : float
        Nominal coverage of the interval.
    resamples : int
        Resamples of the bootstrap interval.
    seed : int
        Seed of the resampling.

    Returns
    -------
    SinadReport
        Pooled SINAD and ENOB, the signal and noise levels, the interval and (when asked) per-pixel SINAD.

    Raises
    ------
    EvtkError
        Fewer than two repeats, NaN or infinite values, or an all-zero signal.

    Examples
    --------
    >>> r = sinad([[1.0, 2.0], [1.0, 2.0]], interval=None)
    >>> r.sinad_db, r.noise_free
    (inf, True)
    >>> round(sinad([[3.0], [5.0]], interval=None).sinad_db, 4)   # 10 log10(17 / 2)
    9.2942
    """
    x = _as_repeats(captures, "SINAD")
    acc = SinadAccumulator(x.shape[0], x.shape[1:], per_pixel=per_pixel)
    acc.add(x)
    return acc.report(per_pixel=per_pixel, interval=interval, confidence=confidence, resamples=resamples, seed=seed)


def _leave_one_out(terms):
    """Each leave-one-group-out estimate's pooled noise and power from the groups' terms
    (:meth:`SinadAccumulator._group_terms`): the pairs of distinct repeats outside the group left out."""
    m, pairs, power, sizes = terms
    g = sizes.size
    keep = np.ones((g, g)) - np.eye(g)  # row j: every group but j
    noise = np.einsum("jg,gh,jh->j", keep, m, keep) / np.einsum("jg,gh,jh->j", keep, pairs, keep)
    return noise, (keep @ power) / (keep @ sizes)


def _jackknife_interval_db(noise, pw, estimate_db, confidence):
    """Delete-one-group jackknife interval of the SINAD in dB, Student t on groups - 1 degrees of freedom.

    ``noise`` and ``pw`` are the leave-one-group-out estimates' pooled noise and power (:func:`_leave_one_out`,
    or :meth:`SinadAccumulator._exact_leave_one_out`); each keeps only pairs of distinct repeats
    outside the left-out group (the estimate's own U-statistic). Where
    leaving a group out leaves no noise, the interval reaches ``+inf``; where
    it leaves no signal (a few events in mostly empty windows), ``-inf``.
    """
    g = noise.size
    if not math.isfinite(estimate_db):
        return math.inf, math.inf
    no_noise, no_signal = noise <= 0, pw <= 0
    if np.any(no_noise | no_signal):
        # some leave-outs see no noise (no finite upper end) or no signal (all of it was in the group left
        # out: no finite lower end); the other end from the leave-outs that see both
        ok = ~(no_noise | no_signal)
        loo = 10.0 * np.log10(pw[ok] / noise[ok])
        lo = -math.inf if no_signal.any() else min(float(np.min(loo, initial=estimate_db)), estimate_db)
        hi = math.inf if no_noise.any() else max(float(np.max(loo, initial=estimate_db)), estimate_db)
        return lo, hi
    loo = 10.0 * np.log10(pw / noise)
    se = math.sqrt((g - 1) / g * float(np.sum((loo - loo.mean()) ** 2)))
    t = _t_quantile_two_sided(confidence, g - 1)
    return estimate_db - t * se, estimate_db + t * se


def _t_central(t: float, df: int) -> float:
    """P(|T| < t) of Student's t with ``df`` (a whole number >= 1) degrees of freedom, by its closed form for
    whole degrees of freedom (Abramowitz and Stegun 26.7.3 for odd ``df``, 26.7.4 for even), with
    ``theta = atan(t / sqrt(df))``."""
    theta = math.atan(t / math.sqrt(df))
    c2 = math.cos(theta) ** 2
    if df % 2:  # odd: 2/pi (theta + sin theta (cos + 2/3 cos^3 + 2*4/(3*5) cos^5 + ...)), up to cos^(df - 2)
        term, total = math.cos(theta), 0.0
        for k in range((df - 1) // 2):
            total += term
            term *= c2 * (2 * k + 2) / (2 * k + 3)
        return 2.0 / math.pi * (theta + math.sin(theta) * total)
    term, total = 1.0, 0.0  # even: sin theta (1 + 1/2 cos^2 + 1*3/(2*4) cos^4 + ...), up to cos^(df - 2)
    for k in range(df // 2):
        total += term
        term *= c2 * (2 * k + 1) / (2 * k + 2)
    return math.sin(theta) * total


def _t_quantile_two_sided(confidence: float, df: int) -> float:
    """The ``t`` with P(|T| < t) = ``confidence`` (Student's t, ``df`` whole degrees of freedom): the
    ``0.5 + confidence / 2`` quantile, found by bisection of :func:`_t_central` to the last bit (numpy and the
    standard library alone: no scipy to import for an interval)."""
    lo, hi = 0.0, 1.0
    while _t_central(hi, df) < confidence:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if _t_central(mid, df) < confidence:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _ratio_db(power, noise):
    return math.inf if noise == 0.0 else 10.0 * math.log10(power / noise)


def _bootstrap_db(terms, n, seed):
    """SINAD of ``n`` resamplings of the groups of repeats (``SinadAccumulator._group_terms``; one repeat a group up to
    :data:`MAX_BOOTSTRAP_GROUPS` repeats, contiguous blocks beyond), noise from pairs of distinct repeats only.

    Resampling a repeat twice adds a pair with no difference; the pooled
    variance is a mean over pairs, so only pairs of different original
    repeats enter (a U-statistic bootstrap), which keeps the interval centred
    on the estimate. With a resample's group counts ``c`` the noise is
    ``c'Mc / c'Nc`` and the power ``c.P / c.n``: time and memory grow with the
    groups and the resamples, not with the repeats. Resamples without a pair
    of distinct repeats are skipped.
    """
    m, pairs, power, sizes = terms
    g = sizes.size
    rng = np.random.default_rng(seed)
    out = []
    batch = min(n, 4096)
    offsets = (np.arange(batch) * g)[:, None]
    while len(out) < n:
        idx = rng.integers(0, g, size=(batch, g))
        c = np.bincount((idx + offsets).ravel(), minlength=batch * g).reshape(batch, g).astype(np.float64)
        npairs = np.einsum("bg,gh,bh->b", c, pairs, c)
        ok = npairs > 0
        noise = np.einsum("bg,gh,bh->b", c[ok], m, c[ok]) / npairs[ok]
        pw = (c[ok] @ power) / (c[ok] @ sizes)
        with np.errstate(divide="ignore"):
            out.extend(np.where(noise > 0, 10.0 * np.log10(pw / np.where(noise > 0, noise, 1.0)), np.inf))
    return np.asarray(out[:n])
