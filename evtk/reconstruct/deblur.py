"""Deblurring through any view of the response: the sampling model in two dimensions, solved with regularisation.

A rotated, tilted or distorted view, or a defocused one, mixes the
response's two axes, so deblurring cannot run along each axis alone. Here
the forward model is written out whole: :func:`sampling_matrix` gives ``A[p, n]``, the
light sensor pixel ``p`` collects from a unit response in cell ``n``:

* each cell's light spreads on the screen as a box of one cell, widened by
  the kernel sources' extent and blurred by the diffuser and diffraction
  (the Gaussian of :attr:`evtk.optics.Bench.shadow_sigma_um`), as in
  :func:`evtk.optics.axis_weights`;
* each pixel collects it over its footprint, sampled at ``supersample``
  squared points taken through the map from pixels to cells (a
  :class:`~evtk.optics.camera.CellMap`, or a scale and shift);
* the camera's defocus blurs the pixels' light by a Gaussian of
  ``blur_px`` pixels.

:func:`solve_cells` then finds the cell values ``c`` minimising
``|A c - v|^2 + (lam s_max)^2 |c|^2`` for every response ``v`` at once
(Tikhonov regularisation; ``lam`` from the run's own measured noise,
:func:`relative_noise` and :func:`wiener_lambda`), so that noise the blur
would amplify is damped rather than inverted.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.linalg import LinAlgError

from .._arrays import median
from .._blas import one_blas_thread
from ..errors import EvtkError
from ..optics import Bench, shadow_magnification
from ..optics.camera import CellMap, footprint_points
from ..optics.screen import footprint_cdf

if TYPE_CHECKING:
    import numpy.typing as npt
    from scipy.sparse import csr_array

__all__ = ["sampling_matrix", "solve_cells", "relative_noise", "wiener_lambda", "DEFAULT_LAMBDA"]


def sampling_matrix(bench: Bench, to_cells: Callable[[np.ndarray], npt.ArrayLike],
                    region: Sequence[int], shape: tuple[int, int], blur_px: float = 0.0,
                    supersample: int = 4) -> np.ndarray:
    """``A[p, n]`` (pixels of ``region`` row-major, cells of ``shape`` row-major): pixel ``p``'s light from a
    unit response in cell ``n``.

    Parameters
    ----------
    bench : Bench
        For the sources' extent and the shadow blur.
    to_cells : callable
        Sensor pixels (x, y), an (N, 2) array, to cell coordinates (column, row), cell centres on integers.
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels (half-open) whose light is modelled.
    shape : tuple of int
        ``(rows, cols)``: cells of the full response.
    blur_px : float
        Standard deviation of the camera's defocus, in pixels (>= 0; 0: in focus).
    supersample : int
        Points per pixel side over which each footprint is integrated; each
        point's width in cells is taken from ``to_cells`` at the region's
        centre.

    Returns
    -------
    numpy.ndarray
        float64, shape ``((y1 - y0) * (x1 - x0), rows * cols)``, entries >= 0: column ``n`` is the light each pixel
        collects from a unit response in cell ``n``.

    Raises
    ------
    EvtkError
        An empty region or response, or a ``blur_px`` that is negative or not finite.
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    rows, cols = (int(v) for v in shape)
    if x1 <= x0 or y1 <= y0 or rows < 1 or cols < 1:
        raise EvtkError(f"an empty region {tuple(region)} or response {tuple(shape)}")
    if not (math.isfinite(blur_px) and blur_px >= 0):
        raise EvtkError(f"blur_px must be a finite number >= 0, not {blur_px}")
    s = int(supersample)
    uv = np.asarray(to_cells(footprint_points((x0, x1, y0, y1), s)), dtype=np.float64)
    c = np.array([[(x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2]])
    d = np.asarray(to_cells(np.concatenate([c - [0.5, 0], c + [0.5, 0], c - [0, 0.5], c + [0, 0.5]])))
    step_px = 2.0 / (np.linalg.norm(d[1] - d[0]) + np.linalg.norm(d[3] - d[2]))
    a = 1.0 / (s * float(step_px))  # a sample's width, in cells
    b = bench.kernel_step_cells if bench.source_extent == "area" else 0.0
    psf = bench.shadow_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    r = int(math.ceil(0.5 * (a + b) + 5.0 * psf)) + 1
    offsets = np.arange(-r, r + 1)

    # the footprint of evtk.optics.axis_weights (a pixel a sample wide), but over the few cells around each sample:
    # the dense form over every cell took four times as long here
    def weights(u, n_cells):  # (N, 2r + 1) shares of the cells around u, and their indices
        # a view along the sensor's axes puts a column's (a row's) samples at the same few cell coordinates: the
        # footprint is evaluated once for each (the same floats, gathered)
        distinct, back = np.unique(u, return_inverse=True)
        if 2 * distinct.size <= u.size:
            w, n = weights(distinct, n_cells)
            return w[back], n[back]
        base = np.floor(u).astype(np.int64)[:, None]
        n = base + offsets[None, :]
        low = u[:, None] - 0.5 * (a + b)
        # the CDF at the 2r + 2 cell edges around u, each edge once (a cell's lower edge is the one below's
        # upper edge: n - 0.5 and (n - 1) + 0.5 are the same float)
        cdf = footprint_cdf(base + np.arange(-r - 1, r + 1)[None, :] + 0.5 - low, a, b, psf)
        w = cdf[:, 1:] - cdf[:, :-1]
        return np.where((n >= 0) & (n < n_cells), np.maximum(w, 0.0), 0.0), np.clip(n, 0, n_cells - 1)

    npix, ncell = (y1 - y0) * (x1 - x0), rows * cols
    grid = uv.reshape(y1 - y0, x1 - x0, s, s, 2)  # (pixel row, pixel column, sub-row, sub-column)
    u4, v4 = grid[..., 0], grid[..., 1]
    if np.array_equal(u4, np.broadcast_to(u4[:1, :, :1, :], u4.shape)) and \
            np.array_equal(v4, np.broadcast_to(v4[:, :1, :, :1], v4.shape)):
        # a view along the sensor's axes: a sample's cell column follows its pixel column alone and its cell row
        # its pixel row alone, so A is the outer product of a row and a column factor (the sums over the
        # samples taken per factor; equal to the sum of products but for rounding)
        def factor(coords, n_cells):  # (pixels along the axis, cells along it): each pixel's summed shares
            w, n = weights(coords.ravel(), n_cells)
            at = np.repeat(np.arange(coords.shape[0]), s)[:, None] * n_cells + n
            return np.bincount(at.ravel(), weights=w.ravel(), minlength=coords.shape[0] * n_cells).reshape(
                coords.shape[0], n_cells)

        fx, fy = factor(u4[0, :, 0, :], cols), factor(v4[:, 0, :, 0], rows)
        a_mat = (fy[:, None, :, None] * fx[None, :, None, :]).reshape(npix, ncell) / (s * s)
    else:
        wx, nx = weights(uv[:, 0], cols)
        wy, ny = weights(uv[:, 1], rows)
        pix = np.repeat(np.arange(npix), s * s)
        flat = pix[:, None, None] * ncell + ny[:, :, None] * cols + nx[:, None, :]
        val = wy[:, :, None] * wx[:, None, :] / (s * s)
        a_mat = np.bincount(flat.ravel(), weights=val.ravel(), minlength=npix * ncell).reshape(npix, ncell)
    if blur_px > 0:
        img = a_mat.reshape(y1 - y0, x1 - x0, ncell)
        a_mat = _gaussian_blur(_gaussian_blur(img, blur_px, 0), blur_px, 1).reshape(npix, ncell)
    return a_mat


def _gaussian_blur(img: np.ndarray, sigma_px: float, axis: int) -> np.ndarray:
    """``img`` correlated along ``axis`` with a sampled Gaussian of ``sigma_px``, zero outside (the separable
    filter ``scipy.ndimage.gaussian_filter(..., mode="constant")`` applies per axis: weights ``exp(-x^2 / 2
    sigma^2)`` on ``|x| <= int(4 sigma + 0.5)``, summing to 1), in numpy: a fresh process loads no scipy for it
    (scipy.ndimage costs more than the route's read)."""
    radius = int(4.0 * float(sigma_px) + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 / (float(sigma_px) * float(sigma_px)) * x * x)
    w = w / w.sum()
    src = np.moveaxis(img, axis, 0)
    n = src.shape[0]
    out = np.zeros(src.shape, np.float64)
    for k, wk in zip(range(-radius, radius + 1), w.tolist()):  # out[i] += w[k] * src[i + k] where i + k is inside
        lo, hi = max(0, -k), min(n, n - k)
        if lo < hi:
            out[lo:hi] += wk * src[lo + k:hi + k]
    return np.moveaxis(out, 0, axis)


#: Relative regularisation when the run holds no measure of its own noise and the view needs deblurring beyond the
#: bench's footprint (rotated, tilted, distorted or defocused); measured best at 0.1-0.2 on simulated runs.
DEFAULT_LAMBDA = 0.15


def relative_noise(values: np.ndarray, level_light: np.ndarray, is_level: npt.ArrayLike, is_flat: npt.ArrayLike,
                   interior: npt.ArrayLike) -> float | None:
    """The relative error of one capture's linearised light, from captures of uniform light over ``interior``.

    Level captures (``is_level``, light ``level_light``) light every
    interior cell alike: their spread over the interior pixels, against
    their mean, is the error (count quantisation, threshold mismatch left
    after the flat field, shot noise). Two or more flat fields (``is_flat``)
    give it from their differences (the flat-field gain is common to them).
    Returns the median over the captures, or None when there are none.

    Parameters
    ----------
    values : numpy.ndarray
        Linearised light per capture and pixel, shape (captures, y1 - y0, x1 - x0).
    level_light : numpy.ndarray
        Light of each capture's level pattern (mirrors on in the kernel of a level capture; 0 for the others),
        shape (captures,); only its sign is read.
    is_level, is_flat : array_like of bool
        Which captures are level captures and which flat fields, shape (captures,).
    interior : array_like of bool
        Pixels whose light is uniform in those captures (away from the response's edges), shape
        (y1 - y0, x1 - x0).

    Returns
    -------
    float or None
        The median relative error (standard deviation over mean, dimensionless) over the level captures and
        the neighbouring pairs of flat fields; None with fewer than 4 interior pixels or no such capture.
    """
    shares = []
    inner = np.asarray(interior, bool)
    if inner.sum() < 4:
        return None
    for c in np.flatnonzero(is_level):
        if level_light[c] > 0:
            v = values[c][inner]
            if np.mean(v) > 0:
                shares.append(float(np.std(v) / np.mean(v)))
    flats = np.flatnonzero(is_flat)
    for a, b in zip(flats[:-1], flats[1:]):
        mean = 0.5 * (np.mean(values[a][inner]) + np.mean(values[b][inner]))
        if mean > 0:
            shares.append(float(np.std(values[a][inner] - values[b][inner]) / math.sqrt(2.0) / mean))
    return median(shares) if shares else None


#: Most cells a sampling matrix may have for its products and solves to run dense in numpy (below, scipy's sparse
#: products and LAPACK's single eigenvalue: a fresh process would spend more loading scipy.sparse and scipy.linalg,
#: 0.15 s, than numpy spends on 512 cells, 40 ms; above, the dense work grows as the cube).
DENSE_MAX_CELLS = 512


def _top_eigenvalue(gram):
    """The largest eigenvalue of ``A^T A`` (the largest singular value of ``A``, squared)."""
    n = gram.shape[0]
    if n <= DENSE_MAX_CELLS:
        top = float(np.linalg.eigvalsh(gram)[-1])
    else:
        from scipy.linalg import eigvalsh

        top = float(eigvalsh(gram, subset_by_index=[n - 1, n - 1])[0])
    if top <= 1e-12:
        raise EvtkError("the sampling matrix is zero: no cell reaches the region's pixels")
    return top


def wiener_lambda(a_mat: np.ndarray, v: np.ndarray, noise_var: np.ndarray, top: float | None = None) -> float:
    """The relative ``lam`` of a Gaussian prior on the cells against the measured noise: ``lam^2 s_max^2 =
    sigma_n^2 / sigma_c^2``.

    ``v`` (pixels, m) are the responses, ``noise_var`` (pixels, m) their
    expected error variance; ``sigma_n^2`` is that variance averaged over the
    pixels weighted by the light each collects, ``sigma_c^2`` the cells'
    variance the responses' power leaves once the noise is taken off.
    ``top`` is ``s_max^2`` when known.

    Parameters
    ----------
    a_mat : numpy.ndarray
        The sampling matrix, shape (pixels, cells) (:func:`sampling_matrix`).
    v : numpy.ndarray
        The responses, one per column, shape (pixels, m).
    noise_var : numpy.ndarray
        Their expected error variance, shape (pixels, m), in the responses' units squared.
    top : float, optional
        ``s_max^2``, the largest eigenvalue of ``A^T A``; None computes it.

    Returns
    -------
    float
        ``lam`` in [0, 1]: 1 when the responses hold no power beyond the noise.

    Raises
    ------
    EvtkError
        When ``top`` is computed and the sampling matrix is zero.
    """
    rows = np.sum(a_mat * a_mat, axis=1)
    noise = float(rows @ noise_var.mean(axis=1) / max(rows.sum(), 1e-300))
    signal = (float(np.sum(v * v)) - float(np.sum(noise_var))) / v.shape[1] / max(float(rows.sum()), 1e-300)
    if top is None:
        with one_blas_thread():
            top = _top_eigenvalue(a_mat.T @ a_mat)
    if signal <= 0:  # the responses are all noise: regularise as far as the range goes
        return 1.0
    return float(min(1.0, math.sqrt(noise / signal / top)))


def _csr(a_mat: np.ndarray) -> csr_array:
    """``a_mat`` (2-d, float64) as a CSR matrix, built straight from its nonzero entries (``csr_array`` of a
    dense array goes through a COO copy, which took as long as the dense product it saves here)."""
    from scipy.sparse import csr_array

    a = np.ascontiguousarray(a_mat, np.float64)
    n_rows, n_cols = a.shape
    flat = np.flatnonzero(a)
    indptr = np.zeros(n_rows + 1, np.int64)
    np.cumsum(np.bincount(flat // n_cols, minlength=n_rows), out=indptr[1:])
    return csr_array((a.ravel()[flat], flat % n_cols, indptr), shape=(n_rows, n_cols))


def solve_cells(values: npt.ArrayLike, a_mat: np.ndarray, lam: float = 0.0,
                noise_var: npt.ArrayLike | None = None) -> tuple[np.ndarray, float]:
    """Cell values from pixel values through ``a_mat`` (:func:`sampling_matrix`), Tikhonov-regularised:
    ``argmin |A c - v|^2 + (lam s_max)^2 |c|^2`` for each response ``v``, ``s_max`` the largest singular value.

    Parameters
    ----------
    values : array_like
        Pixel values, shape (..., pixels), pixels in ``a_mat``'s row order.
    a_mat : numpy.ndarray
        The sampling matrix, shape (pixels, cells).
    lam : float
        Relative regularisation (:data:`DEFAULT_LAMBDA`), finite and >= 0; 0 is plain least squares.
    noise_var : array_like, optional
        The values' expected error variance, shape of ``values``: ``lam`` is then
        :func:`wiener_lambda`'s instead.

    Returns
    -------
    cells : numpy.ndarray
        float64, shape (..., cells): the solved cell values.
    lam : float
        The regularisation used.

    Raises
    ------
    EvtkError
        When the pixel counts of ``values`` and ``a_mat`` differ, the sampling matrix is zero, or ``lam`` is
        negative or not finite.
    """
    return _solve(values, _System(a_mat), lam, noise_var)


class _System:
    """A sampling matrix with what every solve through it needs: its sparse form, ``A^T A`` and that
    matrix's largest eigenvalue (computed on first use and kept; the arrays are not to be written)."""

    def __init__(self, a_mat: np.ndarray) -> None:
        self.a_mat = a_mat
        # a pixel sees the few cells around its footprint (a few percent of the matrix): a large one's products
        # run sparse; up to DENSE_MAX_CELLS cells they run dense, in numpy alone
        self.a_sparse = _csr(a_mat) if a_mat.shape[1] > DENSE_MAX_CELLS else None
        self._gram: np.ndarray | None = None
        self._top: float | None = None

    def transpose_times(self, m: np.ndarray) -> np.ndarray:
        """``A^T m``, dense or sparse (:data:`DENSE_MAX_CELLS`)."""
        return self.a_mat.T @ m if self.a_sparse is None else self.a_sparse.T @ m

    def gram_top(self) -> tuple[np.ndarray, float]:
        """``(A^T A, its largest eigenvalue)``: the matrix is shared, copy it before writing."""
        if self._gram is None or self._top is None:
            with one_blas_thread():
                if self.a_sparse is None:
                    gram = np.ascontiguousarray(self.a_mat.T @ self.a_mat)
                else:
                    gram = (self.a_sparse.T @ self.a_sparse).toarray()
                self._top = _top_eigenvalue(gram)
            gram.flags.writeable = False
            self._gram = gram
        return self._gram, self._top

    @property
    def nbytes(self) -> int:
        """Memory held, bytes (the dense matrix, its sparse form and ``A^T A``)."""
        ncell = self.a_mat.shape[1]
        sparse = 0 if self.a_sparse is None else self.a_sparse.data.nbytes * 2
        return int(self.a_mat.nbytes + sparse + ncell * ncell * 8)


#: Most memory the sampling matrices kept between reconstructions may hold (:func:`_deblur_system`), bytes.
SYSTEM_CACHE_BYTES = 64 << 20
_systems: OrderedDict[tuple, _System] = OrderedDict()
_systems_lock = threading.Lock()


def _deblur_system(bench: Bench, cell_map: CellMap, region: Sequence[int], shape: tuple[int, int],
                  blur_px: float = 0.0) -> _System:
    """The sampling matrix (:func:`sampling_matrix`) of a view, with ``A^T A`` and its largest eigenvalue, kept
    for the next reconstruction through the same calibration (a few per process, at most
    :data:`SYSTEM_CACHE_BYTES`): they depend on the bench, view, region, response shape and defocus only, not on
    the recording.

    Parameters
    ----------
    bench : Bench
        The bench (sources' extent, shadow blur).
    cell_map : CellMap
        The view: sensor pixels to cells through :meth:`~evtk.optics.camera.CellMap.to_cells`.
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels (half-open) whose light is modelled.
    shape : tuple of int
        ``(rows, cols)``: cells of the full response.
    blur_px : float
        The camera's defocus, pixels.

    Returns
    -------
    _System
        Its ``a_mat`` (read-only) and the rest, for :func:`solve_cells`' work (``_solve``).
    """
    matrix = np.asarray(cell_map.matrix, np.float64)
    key = (bench, matrix.tobytes(), float(cell_map.k1), tuple(int(v) for v in cell_map.sensor_size),
           tuple(int(v) for v in region), tuple(int(v) for v in shape), float(blur_px))
    with _systems_lock:
        got = _systems.get(key)
        if got is not None:
            _systems.move_to_end(key)
            return got
    a_mat = sampling_matrix(bench, cell_map.to_cells, region, shape, blur_px)
    a_mat.flags.writeable = False
    system = _System(a_mat)
    system.gram_top()
    if system.nbytes <= SYSTEM_CACHE_BYTES // 2:
        with _systems_lock:
            _systems[key] = system
            while sum(v.nbytes for v in _systems.values()) > SYSTEM_CACHE_BYTES:
                _systems.popitem(last=False)
    return system


def _solve(values: npt.ArrayLike, system: _System, lam: float = 0.0,
           noise_var: npt.ArrayLike | None = None) -> tuple[np.ndarray, float]:
    """:func:`solve_cells` through a :class:`_System` (whose ``A^T A`` and top eigenvalue may be kept)."""
    a_mat = system.a_mat
    vals = np.asarray(values, dtype=np.float64)
    lead = vals.shape[:-1]
    v = vals.reshape(-1, vals.shape[-1]).T  # (pixels, m)
    if v.shape[0] != a_mat.shape[0]:
        raise EvtkError(f"{v.shape[0]} pixel values for a sampling matrix of {a_mat.shape[0]} pixels")
    shared, top = system.gram_top()
    gram = shared.copy()
    with one_blas_thread():
        if noise_var is not None:
            lam = wiener_lambda(a_mat, v, np.asarray(noise_var, np.float64).reshape(v.T.shape).T, top)
        if not (math.isfinite(lam) and lam >= 0):
            raise EvtkError(f"the regularisation must be a finite number >= 0, not {lam}")
        gram[np.diag_indices(gram.shape[0])] += lam * lam * top
        try:
            cells = _spd_solve(gram, system.transpose_times(v))
        except LinAlgError:  # lam = 0 on a singular system
            cells = np.linalg.lstsq(a_mat, v, rcond=None)[0]
    return cells.T.reshape(lead + (a_mat.shape[1],)), float(lam)


def _spd_solve(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``gram^-1 rhs`` for a symmetric matrix that must be positive definite (else :class:`LinAlgError`, as a
    Cholesky factor's failure says): numpy's up to :data:`DENSE_MAX_CELLS` cells (its Cholesky as the test, then
    an LU solve, 2 ms at 256 cells), scipy's Cholesky solve above."""
    if gram.shape[0] <= DENSE_MAX_CELLS:
        np.linalg.cholesky(gram)
        return np.linalg.solve(gram, rhs)
    from scipy.linalg import cho_factor, cho_solve

    return cho_solve(cho_factor(gram), rhs)
