"""The two-dimensional sampling model and its regularised inversion (evtk.reconstruct.deblur).

Oracles: the simulator's renderer, which integrates each pixel's footprint
over a supersampled nominal screen (evtk.optics.camera.Camera.view and
evtk.optics.screen_response), against the closed-form footprint of
sampling_matrix; and exact recovery where the system is well posed.
"""

import numpy as np
import pytest
from scipy.signal import correlate2d

from evtk import EvtkError
from evtk.optics import Bench, response_origin_px, response_region, screen_response
from evtk.optics.camera import Camera, CellMap
from evtk.reconstruct.deblur import relative_noise, sampling_matrix, solve_cells, wiener_lambda

RNG = np.random.default_rng(5)
K, F = RNG.choice([0, 1], (3, 3)), RNG.choice([0, 1], (16, 16))


def _nominal(bench):
    return response_region(bench, K.shape, F.shape), np.asarray(response_origin_px(bench, K.shape, F.shape))


@pytest.mark.parametrize("bench", [Bench(), Bench(source_extent="point"), Bench(psf_sigma_um=40.0)])
def test_the_nominal_view_is_the_screen_the_simulator_renders(bench):
    region, origin = _nominal(bench)
    full = correlate2d(F, K)
    a = sampling_matrix(bench, lambda p: p - origin, region, full.shape)
    got = (a @ full.ravel()).reshape(region[3] - region[2], region[1] - region[0])
    want = screen_response(K, F, bench, region)
    # the renderer adds the DMD's leak light, a constant of 0.3 % of the peak
    assert np.max(np.abs(got - want)) < 0.005 * want.max()
    assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.9999


def test_a_rotated_tilted_distorted_defocused_view_is_the_camera_the_simulator_renders():
    bench = Bench()
    region, origin = _nominal(bench)
    size = (bench.sensor_width, bench.sensor_height)
    cam = Camera(rotation_deg=2.5, tilt=(0.04, -0.02), offset_px=(0.3, -0.4), scale=1.02, k1=0.03, defocus_px=0.7)
    sensor_region = cam.sensor_region(region, size)
    view = cam.view(K, F, bench, sensor_region)
    cmap = CellMap(cam.homography(size) @ np.array([[1, 0, origin[0]], [0, 1, origin[1]], [0, 0, 1.0]]), cam.k1, size)
    full = correlate2d(F, K)
    got = (sampling_matrix(bench, cmap.to_cells, sensor_region, full.shape, blur_px=0.7) @ full.ravel())
    assert np.max(np.abs(got.reshape(view.shape) - view)) < 0.01 * view.max()
    unblurred = sampling_matrix(bench, cmap.to_cells, sensor_region, full.shape) @ full.ravel()
    assert np.max(np.abs(unblurred.reshape(view.shape) - view)) > 0.05 * view.max()  # the blur is seen


def test_every_cell_puts_all_its_light_on_the_pixels():
    bench = Bench()
    region, origin = _nominal(bench)
    x0, x1, y0, y1 = region
    a = sampling_matrix(bench, lambda p: p - origin, (x0 - 3, x1 + 3, y0 - 3, y1 + 3), (18, 18), blur_px=0.5)
    assert np.allclose(a.sum(axis=0), 1.0, atol=1e-3)  # unit light per cell, pixel areas of one cell


def test_a_well_posed_system_is_solved_exactly_and_noise_is_damped_by_its_measure():
    bench = Bench()
    region, origin = _nominal(bench)
    truth = RNG.normal(size=(40, 18 * 18))
    a = sampling_matrix(bench, lambda p: p - origin, region, (18, 18))
    assert np.allclose(solve_cells(truth @ a.T, a, lam=0.0)[0], truth, atol=1e-8)
    blurred = sampling_matrix(bench, lambda p: p - origin, region, (18, 18), blur_px=1.0)
    clean = truth @ blurred.T
    lams, errors = [], []
    for sigma in (1e-4, 0.05, 0.5):
        noisy = clean + RNG.normal(scale=sigma, size=clean.shape)
        lam = wiener_lambda(blurred, noisy.T, np.full(noisy.T.shape, sigma ** 2))
        plain = np.sqrt(np.mean((solve_cells(noisy, blurred, lam=0.0)[0] - truth) ** 2))
        damped = np.sqrt(np.mean((solve_cells(noisy, blurred, lam)[0] - truth) ** 2))
        lams.append(lam)
        errors.append((damped, plain))
    assert lams[0] < 0.01 < lams[1] < lams[2]  # more noise, more regularisation; none to speak of without
    assert errors[0][0] < 0.15 and errors[0][0] <= 1.05 * errors[0][1]  # noise-free: about the plain inverse
    for damped, plain in errors[1:]:  # inverting a 1-pixel blur blows the noise up; the measured prior does not
        assert damped < 0.5 * plain and damped < 1.0


def test_the_relative_noise_is_read_from_uniform_captures():
    """Level captures' spread over the interior and flat-field differences: the analytic relative error."""
    inner = np.zeros((20, 20), bool)
    inner[4:16, 4:16] = True
    light = np.array([0, 2, 4, 0, 0])
    level = np.array([False, True, True, False, False])
    flat = np.array([False, False, False, True, True])
    values = np.zeros((5, 20, 20))
    values[1] = 2.0 * (1 + 0.05 * RNG.normal(size=(20, 20)))
    values[2] = 4.0 * (1 + 0.05 * RNG.normal(size=(20, 20)))
    common = 9.0 * (1 + 0.2 * RNG.normal(size=(20, 20)))  # what the flat-field gain takes out is common to both
    values[3] = common + 9.0 * 0.05 * RNG.normal(size=(20, 20))
    values[4] = common + 9.0 * 0.05 * RNG.normal(size=(20, 20))
    assert relative_noise(values, light, level, flat, inner) == pytest.approx(0.05, rel=0.2)
    assert relative_noise(values, light, level & False, flat & False, inner) is None


def test_bad_input_is_named():
    bench = Bench()
    with pytest.raises(EvtkError, match="blur_px"):
        sampling_matrix(bench, lambda p: p, (0, 4, 0, 4), (2, 2), blur_px=float("nan"))
    with pytest.raises(EvtkError, match="empty region"):
        sampling_matrix(bench, lambda p: p, (4, 4, 0, 4), (2, 2))
    a = sampling_matrix(bench, lambda p: p, (0, 4, 0, 4), (2, 2))
    with pytest.raises(EvtkError, match="pixel values"):
        solve_cells(np.zeros(5), a)
    with pytest.raises(EvtkError, match="regularisation"):
        solve_cells(np.zeros(16), a, lam=-1.0)
    with pytest.raises(EvtkError, match="zero"):  # a view that misses the response altogether
        solve_cells(np.zeros(16), sampling_matrix(bench, lambda p: p + 100.0, (0, 4, 0, 4), (2, 2)))


def _scipy_reference(values, a_mat, lam):
    """The deblur's solve as scipy did it before: sparse products, LAPACK's top eigenvalue, a Cholesky solve."""
    from scipy.linalg import cho_factor, cho_solve, eigvalsh
    from scipy.sparse import csr_array

    a = csr_array(a_mat)
    gram = (a.T @ a).toarray()
    n = gram.shape[0]
    top = float(eigvalsh(gram, subset_by_index=[n - 1, n - 1])[0])
    gram[np.diag_indices(n)] += lam * lam * top
    return cho_solve(cho_factor(gram), a.T @ np.asarray(values, np.float64).T).T


@pytest.mark.parametrize("blur_px", [0.0, 0.7, 2.3])
@pytest.mark.parametrize("shape", [(4, 5), (16, 16)])
def test_the_numpy_solve_is_scipys_to_rounding(blur_px, shape):
    """Up to DENSE_MAX_CELLS cells the deblur runs in numpy (dense products, numpy's eigenvalues and solve, the
    defocus as a separable Gaussian): a fresh process loaded scipy.sparse, scipy.linalg and scipy.ndimage for it,
    more than the route's whole read. Same cells as scipy's path to rounding, and the same sampling matrix as
    scipy.ndimage's Gaussian filter."""
    from scipy.ndimage import gaussian_filter

    from evtk.reconstruct import deblur

    rows, cols = shape
    cmap = CellMap(np.array([[1.02, 0.03, 40.3], [-0.02, 0.98, 30.6], [0, 0, 1]]), 0.0, (320, 240))
    region = (38, 40 + cols + 3, 28, 30 + rows + 3)
    sharp = deblur.sampling_matrix(Bench(), cmap.to_cells, region, shape, 0.0)
    a_mat = deblur.sampling_matrix(Bench(), cmap.to_cells, region, shape, blur_px)
    if blur_px:
        h, w = region[3] - region[2], region[1] - region[0]
        want = gaussian_filter(sharp.reshape(h, w, -1), (blur_px, blur_px, 0), mode="constant").reshape(sharp.shape)
        assert np.allclose(a_mat, want, rtol=0, atol=1e-13 * sharp.max())
    else:
        assert np.array_equal(a_mat, sharp)
    rng = np.random.default_rng(5)
    values = rng.random((7, a_mat.shape[0]))
    for lam in (0.15, 0.02) if blur_px else (0.0, 0.15):  # (a blurred system's plain least squares is too
        got, used = deblur.solve_cells(values, a_mat, lam)  # ill-conditioned for any two solvers to agree)
        ref = _scipy_reference(values, a_mat, lam)
        assert used == lam and np.allclose(got, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_a_small_deblur_loads_no_scipy():
    """A fresh process solving a 16x16 response with defocus: no scipy module loads (0.15 s and more)."""
    from conftest import modules_after

    loaded = modules_after(
        "import numpy as np\nfrom evtk.optics import Bench\nfrom evtk.optics.camera import CellMap\n"
        "from evtk.reconstruct.deblur import sampling_matrix, solve_cells\n"
        "cmap = CellMap(np.array([[1.0, 0.0, 40.0], [0.0, 1.0, 30.0], [0, 0, 1]]), 0.0, (320, 240))\n"
        "a = sampling_matrix(Bench(), cmap.to_cells, (38, 58, 28, 48), (16, 16), 1.2)\n"
        "solve_cells(np.ones((3, a.shape[0])), a, 0.15)\n")
    assert [m for m in loaded if m.split(".")[0] == "scipy"] == []
