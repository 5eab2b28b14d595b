"""Kernel recovery: which binary kernel made a captured response (the paper's section 4.4), and faster than trying all.

Two ways to search the ``2 ** (s * s)`` binary ``s`` x ``s`` kernels:

* :func:`recover_brute` compares the target with the response of every
  candidate (each run through the device: the simulator, or a recording
  holding one capture per candidate; or through the device's linear model)
  by mean squared error, and keeps the whole loss curve.
* :func:`recover_search` never enumerates them. The device is linear in the
  kernel (the response is the sum of what each lit kernel element casts),
  so the loss is a convex quadratic in the kernel's bits. It relaxes the
  bits to ``[0, 1]`` (bounded least squares), rounds, improves by single and
  double bit flips, and then proves the result optimal by branch and bound
  whose bound is the relaxation over the still-free bits (a convex problem
  over a box that contains every binary completion, so it never exceeds the
  best binary loss below a node). Guarantee: when ``proven`` is True the
  returned kernel minimises ``||y - a A k||^2`` over all binary ``k`` for
  the fitted scale ``a``; with a node budget exhausted it is the best found.

Results are classified against the true kernel when it is known: "exact",
"shift" (the same pattern translated inside the window, which casts the same
response translated) or "wrong"; candidates whose loss is within a tolerance
of the best are listed, so an ambiguous answer is visible.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .cluster import run_tasks
from .errors import EvtkError
from .limits import require_memory
from .optics import Bench, ideal_response, response_origin_px, response_region
from .reconstruct import footprint_matrix
from .sensor import SensorModel
from .sweeps import simulated_reconstruction

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "Recovery",
    "all_kernels",
    "kernel_bits",
    "kernel_from_bits",
    "is_shift",
    "classify",
    "response_matrix",
    "recover_brute",
    "recover_search",
    "device_responses",
    "success_rate",
]

MAX_BRUTE_BITS = 25


@dataclass
class Recovery:
    """What a recovery found.

    Parameters
    ----------
    kernel : ndarray (s, s) of int8 (0/1)
        The kernel found.
    loss : float
        Mean squared error of the (scaled) candidate response against the target.
    scale : float
        Factor applied to candidate responses (1 unless fitted).
    status : str or None
        "exact", "shift" or "wrong" against ``true_kernel``; None when unknown.
    near : list of (bits, loss)
        Other candidates within the tolerance of the best loss, at most 50 (brute
        force: all of them; search: those met on the way).
    losses : ndarray or None
        Brute force: the loss of every candidate, indexed by :func:`all_kernels`.
    method : str
        "brute" or "search".
    proven : bool
        The loss is the global minimum over all binary kernels (brute force
        always; search when branch and bound finished).
    nodes : int
        Branch-and-bound nodes (search only).
    seconds : float
        Wall time of the recovery, s.
    """

    kernel: np.ndarray
    loss: float
    scale: float
    status: str | None
    near: list[tuple[str, float]] = field(default_factory=list)
    losses: np.ndarray | None = None
    method: str = "brute"
    proven: bool = True
    nodes: int = 0
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """The recovery as a JSON-ready dict (``losses`` left out).

        Returns
        -------
        dict
            ``kernel_bits``, ``kernel`` (nested lists), ``loss``, ``scale``, ``status``, ``method``, ``proven``,
            ``nodes``, ``seconds`` and ``near`` (a list of ``{kernel_bits, loss}``).
        """
        return {"kernel_bits": kernel_bits(self.kernel), "kernel": self.kernel.tolist(), "loss": self.loss,
                "scale": self.scale, "status": self.status, "method": self.method, "proven": self.proven,
                "nodes": self.nodes, "seconds": self.seconds,
                "near": [{"kernel_bits": b, "loss": v} for b, v in self.near]}


def _check_size(size: int) -> int:
    s = int(size)
    if s != size or s < 1 or s * s > 62:
        raise EvtkError(f"kernel size must be a whole number from 1 to 7, not {size!r}")
    return s


def all_kernels(size: int) -> np.ndarray:
    """Every binary ``size`` x ``size`` kernel, index ``i`` holding the bits of ``i``.

    Row-major, the first element the most significant bit.

    Parameters
    ----------
    size : int
        Side of the kernels (``size * size`` at most 25 bits).

    Returns
    -------
    numpy.ndarray
        int8 0/1, shape ``(2 ** (size * size), size, size)``.

    Raises
    ------
    EvtkError
        A size that is not a whole number from 1 to 7, too many kernels to enumerate, or more memory than the
        budget.
    """
    s = _check_size(size)
    n = s * s
    if n > MAX_BRUTE_BITS:
        raise EvtkError(f"{2 ** n} kernels of {s}x{s} are too many to enumerate; use the search")
    require_memory(2 ** n * n * 17, f"the {2 ** n:,} kernels of {s}x{s}")  # int64 bits, then int8
    idx = np.arange(2 ** n, dtype=np.int64)
    bits = (idx[:, None] >> np.arange(n - 1, -1, -1)) & 1
    return bits.astype(np.int8).reshape(-1, s, s)


def kernel_bits(kernel: npt.ArrayLike) -> str:
    """Row-major bit string of a binary kernel, e.g. ``"010111010"``.

    Parameters
    ----------
    kernel : array_like
        0/1 kernel, any shape.

    Returns
    -------
    str
        One character per element, row-major.
    """
    k = np.asarray(kernel)
    return "".join(str(int(v)) for v in k.ravel())


def kernel_from_bits(bits: str, size: int | None = None) -> np.ndarray:
    """A square binary kernel from its row-major bit string.

    Parameters
    ----------
    bits : str
        ``"0"`` and ``"1"`` characters, a square number of them.
    size : int or None
        The side the kernel must have; None accepts any square.

    Returns
    -------
    numpy.ndarray
        int8 0/1, shape ``(s, s)``.

    Raises
    ------
    EvtkError
        Empty or non-binary text, a length that is not a square, or not ``size`` squared.
    """
    if not bits or set(bits) - {"0", "1"}:
        raise EvtkError(f"kernel bits must be a non-empty string of 0s and 1s, not {bits!r}")
    s = int(round(len(bits) ** 0.5))
    if s * s != len(bits) or (size is not None and s != size):
        raise EvtkError(f"{len(bits)} bits do not make a {size or 'square'} kernel")
    return np.array([int(c) for c in bits], np.int8).reshape(s, s)


def _as_binary(name: str, a: npt.ArrayLike, ndim: int) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != ndim or a.size == 0:
        raise EvtkError(f"{name} must be a non-empty {ndim}-D array, got shape {a.shape}")
    if not np.isin(a, (0, 1)).all():
        raise EvtkError(f"{name} must be binary (0/1)")
    return a.astype(np.int8)


def is_shift(a: npt.ArrayLike, b: npt.ArrayLike) -> bool:
    """True when ``b`` is ``a``'s pattern translated (not by zero) without losing a lit element.

    Parameters
    ----------
    a : array_like
        0/1 (or boolean) kernel.
    b : array_like
        0/1 kernel of the same shape.

    Returns
    -------
    bool
        Whether ``b`` is a non-zero translation of ``a`` within the window (False for different shapes or
        counts of lit elements, an empty ``a``, or ``b`` equal to ``a``).
    """
    ab = np.asarray(a, bool)
    bb = np.asarray(b, bool)
    if ab.shape != bb.shape or ab.sum() != bb.sum() or not ab.any() or np.array_equal(ab, bb):
        return False
    ya, xa = np.nonzero(ab)
    yb, xb = np.nonzero(bb)
    dy, dx = yb.min() - ya.min(), xb.min() - xa.min()
    return bool(np.array_equal(np.sort((ya + dy) * ab.shape[1] + xa + dx), np.sort(yb * ab.shape[1] + xb)))


def classify(found: npt.ArrayLike, true_kernel: npt.ArrayLike) -> str:
    """``"exact"``, ``"shift"`` or ``"wrong"``.

    Parameters
    ----------
    found : array_like
        The recovered 0/1 kernel.
    true_kernel : array_like
        The kernel that made the response.

    Returns
    -------
    str
        ``"exact"`` when equal, ``"shift"`` when ``found`` is ``true_kernel`` translated (:func:`is_shift`),
        else ``"wrong"``.
    """
    if np.array_equal(np.asarray(found), np.asarray(true_kernel)):
        return "exact"
    return "shift" if is_shift(true_kernel, found) else "wrong"


def response_matrix(features: npt.ArrayLike, size: int, bench: Bench | None = None,
                    blurred: bool = False) -> np.ndarray:
    """The device's linear model: column ``j`` is the full response to a kernel with only element ``j`` lit.

    Cells are :func:`evtk.optics.ideal_response`'s (what a deblurred,
    calibrated reconstruction approximates), flattened row-major; with
    ``blurred`` they carry the optics' footprint blur (what a reconstruction
    without deblurring sees; needs matched scaling).

    Parameters
    ----------
    features : array_like
        0/1 features, 2-D ``(fh, fw)``.
    size : int
        Side ``s`` of the kernels (1 to 7).
    bench : Bench or None
        The bench (its ``kernel_flipped``, and the blur when ``blurred``); None takes the default.
    blurred : bool
        Carry the optics' footprint blur.

    Returns
    -------
    numpy.ndarray
        float64, shape ``((fh + s - 1) * (fw + s - 1), s * s)``, in response units per lit element.

    Raises
    ------
    EvtkError
        Non-binary features, a bad size, a blurred model without matched scaling, or more memory than the
        budget.
    """

    s = _check_size(size)
    f = _as_binary("features", features, 2)
    cells = (f.shape[0] + s - 1) * (f.shape[1] + s - 1)
    # the columns, their stacked copy and one ideal response
    require_memory(8 * cells * (2 * s * s + 1), f"the model of a {s}x{s} kernel on {f.shape[0]}x{f.shape[1]} features")
    my: np.ndarray | None = None
    mx: np.ndarray | None = None
    if blurred:
        bench = bench if bench is not None else Bench()
        if abs(bench.kernel_step_cells / bench.pixel_cells - 1.0) > 1e-9:
            raise EvtkError("the blurred model needs matched scaling (one pixel per cell)")
        region = response_region(bench, (s, s), f.shape)
        ox, oy = response_origin_px(bench, (s, s), f.shape)
        my = footprint_matrix(bench, oy, region[2], region[3], f.shape[0] + s - 1, 1.0)
        mx = footprint_matrix(bench, ox, region[0], region[1], f.shape[1] + s - 1, 1.0)
    cols = []
    for j in range(s * s):
        e = np.zeros(s * s)
        e[j] = 1.0
        r = ideal_response(e.reshape(s, s), f, bench)
        cols.append((r if my is None or mx is None else my @ r @ mx.T).ravel())
    return np.stack(cols, axis=1)


def _fit_scale(r, y):
    """Least-squares factor ``a >= 0`` for ``a * r`` against ``y`` (1 when ``r`` is zero)."""
    rr = float(r @ r)
    return max(float(r @ y) / rr, 0.0) if rr > 0 else 1.0


def _near(order, losses, best, rtol, atol, kernels_bits, limit=50):
    thr = best * (1 + rtol) + atol
    out = []
    for i in order[1:]:
        if losses[i] > thr or len(out) >= limit:
            break
        out.append((kernels_bits(i), float(losses[i])))
    return out


def _relative_weights(y, weights, floor):
    """Per-cell weights: ``1 / max(|y|, floor)`` for "relative", none for None."""
    if weights is None:
        return None
    if weights != "relative":
        raise EvtkError(f"weights must be 'relative' or None, not {weights!r}")
    if not floor > 0:
        raise EvtkError(f"floor must be positive, not {floor!r}")
    return 1.0 / np.maximum(np.abs(y), float(floor))


def recover_brute(target: npt.ArrayLike, candidates: npt.ArrayLike, true_kernel: npt.ArrayLike | None = None,
                  fit_scale: bool = False, weights: str | None = "relative", floor: float = 1.0, rtol: float = 0.05,
                  atol: float = 1e-9) -> Recovery:
    """Brute force (paper 4.4): the candidate whose response is closest to ``target`` in (weighted) MSE.

    Parameters
    ----------
    target : array_like
        The captured response (any shape).
    candidates : array_like, shape (2 ** (s * s), *target.shape)
        Each candidate kernel's response, in :func:`all_kernels` order.
    true_kernel : array_like, optional
        To classify the answer.
    fit_scale : bool
        Compare ``a * response`` with ``a`` fitted per candidate (for
        candidates from a model in other units); off for responses captured
        the same way as the target.
    weights : "relative" or None
        As in :func:`recover_search`; ``weights=None`` is the paper's plain
        MSE (which recovers slightly fewer kernels on the simulated device:
        99 of 100 against 100 at nominal light).
    floor : float
        As in :func:`recover_search`.
    rtol : float
        Candidates with loss at most ``best * (1 + rtol) + atol`` are listed as near.
    atol : float
        The absolute part of that tolerance.

    Returns
    -------
    Recovery
        The best candidate, every candidate's loss (``losses``) and the near ones; ``proven`` is True.

    Raises
    ------
    EvtkError
        Candidates that are not every kernel of one size, responses of another size than the target, NaN or
        infinite values, bad weights, or more memory than the budget.
    """
    t0 = time.perf_counter()
    y = np.asarray(target, dtype=np.float64).ravel()
    given = np.asarray(candidates)
    # a float64 copy of the candidates, its weighted copy and the squared errors
    require_memory(3 * 8 * given.size, f"comparing {given.shape[0] if given.ndim else 0:,} candidate responses")
    r = given.astype(np.float64, copy=False)
    n = r.shape[0]
    size = int(round(np.log2(n) ** 0.5)) if n > 1 else 0
    if n < 2 or 2 ** (size * size) != n:
        raise EvtkError(f"{n} candidates are not every binary kernel of one size (2^(s*s))")
    r = r.reshape(n, -1)
    if r.shape[1] != y.size:
        raise EvtkError(f"candidate responses have {r.shape[1]} values, the target {y.size}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(y))):
        raise EvtkError("responses hold NaN or infinite values")
    w = _relative_weights(y, weights, floor)
    if w is not None:
        y, r = y * w, r * w
    if fit_scale:
        rr = np.einsum("ij,ij->i", r, r)
        a = np.where(rr > 0, np.maximum(r @ y, 0) / np.where(rr > 0, rr, 1), 1.0)
    else:
        a = np.ones(n)
    losses = np.mean((a[:, None] * r - y) ** 2, axis=1)
    order = np.argsort(losses, kind="stable")
    best = int(order[0])
    kernels = all_kernels(size)
    near = _near(order, losses, float(losses[best]), rtol, atol, lambda i: kernel_bits(kernels[i]))
    status = None if true_kernel is None else classify(kernels[best], true_kernel)
    return Recovery(kernels[best], float(losses[best]), float(a[best]), status, near, losses, "brute", True, 0,
                    time.perf_counter() - t0)


def _bounded_ls(a_mat, rhs, n_free):
    from scipy.optimize import lsq_linear

    if n_free == 0:
        return np.zeros(0), float(rhs @ rhs)
    sol = lsq_linear(a_mat, rhs, bounds=(0.0, 1.0), method="bvls")
    res = a_mat @ sol.x - rhs
    return sol.x, float(res @ res)


def _local_search(k, g, b, c0):
    """Best single/double bit flips of ``q(k) = k'Gk - 2 b'k + c0`` until none improves."""
    k = k.astype(np.float64).copy()
    gk = g @ k
    q = float(k @ gk - 2 * b @ k + c0)
    diag = np.diag(g)
    while True:
        d = 1.0 - 2.0 * k  # +1 to set a bit, -1 to clear it
        one = d * d * diag + 2 * d * (gk - b)  # change of q per single flip
        i = int(np.argmin(one))
        best_delta, flip = one[i], (i,)
        # pairs: delta_ij = one_i + one_j + 2 d_i d_j G_ij
        pair = one[:, None] + one[None, :] + 2 * np.outer(d, d) * g
        np.fill_diagonal(pair, np.inf)
        ij = np.unravel_index(int(np.argmin(pair)), pair.shape)
        if pair[ij] < best_delta:
            best_delta, flip = pair[ij], ij
        if best_delta >= -1e-12 * max(1.0, abs(q)):
            return k, q
        for j in flip:
            gk += g[:, j] * d[j]
            k[j] += d[j]
        q += float(best_delta)


def recover_search(target: npt.ArrayLike, a_mat: npt.ArrayLike, size: int, true_kernel: npt.ArrayLike | None = None,
                   fit_scale: bool = True, weights: str | None = "relative", floor: float = 1.0,
                   max_nodes: int = 20_000, rtol: float = 0.05, atol: float = 1e-9) -> Recovery:
    """Kernel recovery without enumeration: relaxation, rounding, bit-flip search, branch and bound.

    Parameters
    ----------
    target : array_like
        Captured response, flattened to match ``a_mat``'s rows.
    a_mat : ndarray (cells, s * s)
        The device's linear model (:func:`response_matrix`).
    size : int
        Side ``s`` of the kernel (1 to 7).
    true_kernel : array_like, optional
        To classify the answer.
    fit_scale : bool
        Start from a scale read off the unconstrained least-squares kernel,
        refit it for the kernel found and search again until it settles (at
        most four rounds); else the scale is 1.
    weights : "relative" or None
        "relative" weighs each cell by ``1 / max(|target|, floor)``: the
        device's errors grow with the light (counts are logarithmic), so
        bright cells are trusted less; the loss stays a quadratic in the
        bits and the branch-and-bound bound stays valid. None: plain MSE.
    floor : float
        Response level below which cells are not weighted up further.
    max_nodes : int
        Branch-and-bound budget; ``proven`` is False when it runs out.
    rtol : float
        Kernels met on the way with loss at most ``best * (1 + rtol) + atol`` are listed as near.
    atol : float
        The absolute part of that tolerance.

    Returns
    -------
    Recovery
        The kernel found, its loss (mean over cells of the weighted squared error), the scale, whether it is
        proven optimal and the nodes visited (``losses`` is None).

    Raises
    ------
    EvtkError
        A bad size, a model that does not fit the target, NaN or infinite values, or bad weights.
    """
    t0 = time.perf_counter()
    s = _check_size(size)
    n = s * s
    model = np.asarray(a_mat, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64).ravel()
    if model.shape != (y.size, n):
        raise EvtkError(f"model matrix {model.shape} does not fit a target of {y.size} values and {n} kernel bits")
    if not (np.all(np.isfinite(model)) and np.all(np.isfinite(y))):
        raise EvtkError("target or model holds NaN or infinite values")
    w = _relative_weights(y, weights, floor)
    if w is not None:
        y, model = y * w, model * w[:, None]
    seen: dict[str, float] = {}
    scale, total_nodes = (_initial_scale(model, y) if fit_scale else 1.0), 0
    for _ in range(4 if fit_scale else 1):
        am = scale * model
        k, q, proven, nodes = _branch_and_bound(am, y, max_nodes, seen)
        total_nodes += nodes
        new_scale = _fit_scale(model @ k, y) if fit_scale else 1.0
        if abs(new_scale - scale) <= 1e-3 * max(scale, 1e-12):
            break
        scale = new_scale
    m = y.size
    loss = q / m
    near = sorted(((b, v / m) for b, v in seen.items() if b != kernel_bits(k.astype(np.int8))
                   and v / m <= loss * (1 + rtol) + atol), key=lambda t: t[1])[:50]
    kern = k.astype(np.int8).reshape(s, s)
    status = None if true_kernel is None else classify(kern, true_kernel)
    return Recovery(kern, float(loss), float(scale), status, near, None, "search", proven, total_nodes,
                    time.perf_counter() - t0)


def _initial_scale(a_mat, y):
    """Scale guess from the unconstrained least-squares kernel: lit bits sit near ``a``, dark ones near 0."""
    x = np.linalg.lstsq(a_mat, y, rcond=None)[0]
    a = float(x.max())
    if not a > 0:
        return 1.0
    for _ in range(20):  # two clusters, one pinned at zero
        hi = x[x > a / 2]
        a_new = float(hi.mean()) if hi.size else a
        if abs(a_new - a) <= 1e-9 * a:
            break
        a = a_new
    return a if a > 0 else 1.0


def _branch_and_bound(am, y, max_nodes, seen):
    """Minimise ``||y - am k||^2`` over binary k; returns (k, q, proven, nodes)."""
    n = am.shape[1]
    g = am.T @ am
    b = am.T @ y
    c0 = float(y @ y)
    x, _ = _bounded_ls(am, y, n)
    k, q = _local_search(np.round(x), g, b, c0)
    for t in (0.3, 0.7):  # other roundings, cheap extra starts
        k2, q2 = _local_search((x > t).astype(np.float64), g, b, c0)
        if q2 < q:
            k, q = k2, q2
    seen[kernel_bits(k.astype(np.int8))] = q
    tol = 1e-9 * max(1.0, c0)
    stack = [np.full(n, -1, np.int8)]
    nodes = 0
    while stack:
        if nodes >= max_nodes:
            return k, q, False, nodes
        fixed = stack.pop()
        nodes += 1
        free = np.flatnonzero(fixed < 0)
        on = np.flatnonzero(fixed == 1)
        rhs = y - am[:, on].sum(axis=1)
        z, lb = _bounded_ls(am[:, free], rhs, free.size)
        if lb >= q - tol:
            continue
        frac = np.abs(z - np.round(z))
        if free.size == 0 or frac.max() < 1e-7:
            cand = fixed.astype(np.float64)
            cand[free] = np.round(z)
            cand, qc = _local_search(cand, g, b, c0)
            seen[kernel_bits(cand.astype(np.int8))] = qc
            if qc < q:
                k, q = cand, qc
            continue
        j = int(np.argmax(frac))
        first = 1 if z[j] >= 0.5 else 0
        for v in (1 - first, first):  # the nearer value is explored first (pushed last)
            child = fixed.copy()
            child[free[j]] = v
            stack.append(child)
    return k, q, True, nodes


def device_responses(kernels: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None,
                     sensor: SensorModel | None = None, seed: int = 0, noise_seed: int | None = None,
                     crop: str = "full", method: str = "fast", deblur: bool = False) -> np.ndarray:
    """Each kernel's response as the device captures it (simulated, one capture each), on the cell grid.

    ``method="fast"`` uses the simulator's count path; ``"events"`` writes the
    event stream and reconstructs it, as a bench recording would be. Not
    deblurred by default (compare with ``response_matrix(..., blurred=True)``).
    All-zero kernels show no light: their response is zero.

    Parameters
    ----------
    kernels : array_like
        0/1 kernels, shape ``(n, s, s)``.
    features : array_like
        0/1 features, 2-D.
    bench : Bench or None
        The simulated bench (None: the default).
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    seed : int
        The device (fixed pattern noise).
    noise_seed : int or None
        The trial's shot noise (None: derived from ``seed``).
    crop : str
        The reconstruction's crop (``"full"``: the full correlation).
    method : {"fast", "events"}
        Count path or written event stream.
    deblur : bool
        Deblur the reconstruction.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(n, *cells)``: the reconstructed responses, zero for all-zero kernels.

    Raises
    ------
    EvtkError
        Non-binary features, every kernel all zero, or more memory than the budget.
    """

    k = np.asarray(kernels)
    lit = np.flatnonzero(k.reshape(len(k), -1).any(axis=1))
    f = _as_binary("features", features, 2)
    if lit.size == 0:
        raise EvtkError("every kernel is all zero: nothing to show")
    result, _ = simulated_reconstruction(k[lit], f, bench, sensor, repeat=1, seed=seed, noise_seed=noise_seed,
                                         method=method, crop=crop, deblur=deblur)
    require_memory(8 * len(k) * math.prod(result.cells.shape[1:]), f"the responses of {len(k):,} kernels")
    out = np.zeros((len(k),) + result.cells.shape[1:])
    assert result.pairs is not None  # a simulated run knows its pairs
    out[lit[result.pairs[:, 0]]] = result.cells
    return out


def success_rate(powers_mw: Iterable[float], size: int = 3, trials: int = 100, method: str | None = None,
                 bench: Bench | None = None, sensor: SensorModel | None = None,
                 features_shape: tuple[int, int] = (16, 16), seed: int = 0, weights: str | None = "relative",
                 progress: Callable[[int], Any] | None = None, client: Any = None) -> list:
    """Share of random (kernel, features) trials recovered exactly or up to a shift, per laser power.

    Each trial draws a random non-zero binary kernel and random binary
    features, captures the target on the simulated device (fast path,
    flat-field calibrated, not deblurred), and recovers the kernel: for ``method="brute"``
    (default for 3x3) every candidate is captured on the device with the
    same features, as in the paper; for ``"search"`` (default otherwise) the
    device's linear model (with its blur) is searched, cells weighted
    relatively. Returns one row per power:
    ``power_mw``, ``trials``, ``exact_pct``, ``shift_pct``, ``recovered_pct``,
    ``median_s``/``max_s`` per recovery (target capture excluded),
    ``proven_pct``. Trials run as independent tasks (on ``client``'s
    workers when given).

    Parameters
    ----------
    powers_mw : iterable of float
        Laser powers, mW (positive).
    size : int
        Side of the kernels (1 to 7).
    trials : int
        Trials per power.
    method : {"brute", "search"} or None
        Recovery method; None picks brute force up to 3x3, else the search.
    bench : Bench or None
        The simulated bench (None: the default); its power is replaced by each of ``powers_mw``.
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    features_shape : tuple of int
        ``(rows, cols)`` of the random features.
    seed : int
        Seed of the draws and of the device.
    weights : "relative" or None
        The loss's cell weights (:func:`recover_search`).
    progress : callable, optional
        Called with 1 after each power.
    client : distributed.Client or None
        Runs the trials on its workers (:mod:`evtk.cluster`).

    Returns
    -------
    list of dict
        One row per power, with the keys above (and ``size``, ``method``, ``weights``).

    Raises
    ------
    EvtkError
        A bad size or method, a power that is not positive, or more memory than the budget.
    """

    s = _check_size(size)
    method = method or ("brute" if s <= 3 else "search")
    if method not in ("brute", "search"):
        raise EvtkError(f"method must be 'brute' or 'search', not {method!r}")
    bench = bench if bench is not None else Bench()
    # every trial's kernel, features and task tuple are drawn before the trials run
    require_memory(int(trials) * (512 + s * s + math.prod(features_shape)), f"the tasks of {int(trials):,} trials")

    rows = []
    for pi, p in enumerate(powers_mw):
        if not (np.isfinite(p) and p > 0):
            raise EvtkError(f"power must be positive, not {p!r}")
        b = bench.replace(power_mw=float(p))
        rng = np.random.default_rng([seed, pi])
        tasks = []
        for _ in range(int(trials)):  # every trial's draws come from the run's seed, in order
            k = np.zeros(s * s, np.int8)
            while not k.any():
                k = (rng.random(s * s) < 0.5).astype(np.int8)
            f = (rng.random(features_shape) < 0.5).astype(np.int8)
            tasks.append((k.reshape(s, s), f, int(rng.integers(2**31 - 1)), b, sensor, seed, method, weights))
        results = run_tasks(_recovery_trial, tasks, client)
        status = [r[0] for r in results]
        secs = [r[1] for r in results]
        proven = [r[2] for r in results]
        n = len(status)
        rows.append({"power_mw": float(p), "size": s, "method": method, "weights": weights, "trials": n,
                     "exact_pct": 100.0 * status.count("exact") / n, "shift_pct": 100.0 * status.count("shift") / n,
                     "recovered_pct": 100.0 * (status.count("exact") + status.count("shift")) / n,
                     "median_s": float(np.median(secs)), "max_s": float(np.max(secs)),
                     "proven_pct": 100.0 * float(np.mean(proven))})
        if progress is not None:
            progress(1)
    return rows


def _recovery_trial(args):
    """One trial of :func:`success_rate`: (status, seconds, proven)."""
    k, f, noise, b, sensor, seed, method, weights = args
    s = k.shape[0]
    target = device_responses(k[None], f, b, sensor, seed=seed, noise_seed=noise)[0]
    t0 = time.perf_counter()
    if method == "brute":
        resp = device_responses(all_kernels(s), f, b, sensor, seed=seed, noise_seed=noise + 1)
        rec = recover_brute(target, resp, true_kernel=k, weights=weights)
    else:
        rec = recover_search(target, response_matrix(f, s, b, blurred=True), s, true_kernel=k, weights=weights)
    return rec.status, time.perf_counter() - t0, rec.proven
