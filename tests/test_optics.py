"""Optics: eqs. 2-7, the shadow-cast light transport against scipy, bench files."""

import json
import math

import numpy as np
import pytest
from scipy import interpolate, signal

from evtk import EvtkError
from evtk.optics import (
    Bench,
    effective_extents_um,
    effective_stride,
    ideal_response,
    load_bench,
    min_capture_window_us,
    optical_scaling,
    response_region,
    response_to_sensor_grid,
    save_bench,
    screen_response,
    software_scaling,
    stride_mm,
)

IDEAL = dict(source_extent="point", psf_sigma_um=0.0)


def test_equations_by_hand():
    # eq. 3 and 4: u = 300, z = 100 -> sigma = 4/3; 45.36 um features on 7.56 um mirrors -> 8 mirrors
    assert optical_scaling(300, 100) == pytest.approx(4 / 3)
    assert software_scaling(4 / 3, 45.36, 7.56) == pytest.approx(8.0)
    k_eff, f_eff = effective_extents_um(7.56, 45.36, 4 / 3, 8.0)
    assert k_eff == pytest.approx(f_eff) == pytest.approx(60.48)
    # eq. 5: z * Phi / u in mm
    assert stride_mm(300, 100, 181.44) == pytest.approx(0.06048)
    # eq. 6: both forms agree when the kernel is matched, and decimation scales it
    closed = effective_stride(300, 100, 181.44, 45.36, decimation=3)
    general = effective_stride(300, 100, 181.44, 45.36, decimation=3, k_eff_um=60.48)
    assert closed == pytest.approx(general) == pytest.approx(3.0)
    # eq. 7: the slowest device sets the window
    assert min_capture_window_us(9523, 4000, 200) == pytest.approx(250.0)
    assert min_capture_window_us(9523, 9523, 500) == pytest.approx(500.0)


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "x", None])
def test_equations_refuse_non_positive(bad):
    with pytest.raises(EvtkError, match="positive"):
        optical_scaling(bad, 100)
    with pytest.raises(EvtkError, match="positive"):
        stride_mm(300, 100, bad)
    with pytest.raises(EvtkError, match="positive"):
        min_capture_window_us(1000, 1000, bad)


def test_bench_defaults_are_matched_and_stride_one():
    b = Bench()
    assert b.kernel_mirrors == 8 and b.varsigma == pytest.approx(8.0)
    assert b.kernel_step_cells == pytest.approx(1.0)
    assert b.stride_eff == pytest.approx(1.0)
    assert b.min_window_us == pytest.approx(200.0)


def _sensor_patch(bench, k, f, resp):
    xs, ys = response_to_sensor_grid(bench, k.shape, f.shape)
    x0, y0 = int(round(xs[0])), int(round(ys[0]))
    return resp[y0:y0 + len(ys), x0:x0 + len(xs)], (x0, y0)


@pytest.mark.parametrize("kshape,fshape", [((3, 3), (16, 16)), ((5, 5), (16, 16)), ((2, 4), (7, 12)), ((1, 1), (9, 5))])
@pytest.mark.parametrize("flipped", [False, True])
def test_ideal_case_is_the_digital_correlation(kshape, fshape, flipped):
    rng = np.random.default_rng(sum(kshape) * 31 + sum(fshape))
    k = rng.integers(0, 2, kshape)
    k[0, 0] = 1
    f = rng.integers(0, 2, fshape)
    bench = Bench(**IDEAL, kernel_flipped=flipped)
    resp = screen_response(k, f, bench, leak=False)
    oracle = (signal.convolve2d if flipped else signal.correlate2d)(f, k, mode="full")
    patch, (x0, y0) = _sensor_patch(bench, k, f, resp)
    np.testing.assert_allclose(patch, oracle, rtol=0, atol=1e-12)
    # nothing anywhere else on the sensor
    rest = resp.copy()
    rest[y0:y0 + patch.shape[0], x0:x0 + patch.shape[1]] = 0
    assert np.abs(rest).max() < 1e-12
    np.testing.assert_allclose(ideal_response(k, f, bench), oracle)


def test_area_sources_blur_by_the_source_and_pixel_footprints():
    rng = np.random.default_rng(5)
    k = rng.integers(0, 2, (3, 3))
    f = rng.integers(0, 2, (16, 16))
    bench = Bench(source_extent="area")
    resp = screen_response(k, f, bench, leak=False)
    box = np.array([[1 / 8, 3 / 4, 1 / 8]])  # U(-1/2,1/2) + U(-1/2,1/2) over unit cells
    oracle = signal.convolve2d(signal.convolve2d(signal.correlate2d(f, k, "full"), box), box.T)
    patch, (x0, y0) = _sensor_patch(bench, k, f, resp)
    got = resp[y0 - 1:y0 + patch.shape[0] + 1, x0 - 1:x0 + patch.shape[1] + 1]
    np.testing.assert_allclose(got, oracle, rtol=0, atol=1e-12)
    assert resp.sum() == pytest.approx(oracle.sum())


def _integral_oracle(corr, s1, n_pix, start):
    """Mean of the piecewise-constant surface ``corr`` over squares of side s1 starting at ``start``."""
    h, w = corr.shape
    integ = np.zeros((h + 1, w + 1))
    integ[1:, 1:] = corr.cumsum(0).cumsum(1)
    f = interpolate.RegularGridInterpolator((np.arange(h + 1), np.arange(w + 1)), integ, method="linear",
                                            bounds_error=False, fill_value=None)
    edges = start + s1 * np.arange(n_pix + 1)
    ey = np.clip(edges, 0, h)
    ex = np.clip(edges, 0, w)
    yy, xx = np.meshgrid(ey, ex, indexing="ij")
    integral = f(np.stack([yy, xx], -1))
    return (integral[1:, 1:] - integral[:-1, 1:] - integral[1:, :-1] + integral[:-1, :-1]) / s1 ** 2


@pytest.mark.parametrize("stride", [0.5, 0.75, 1.5, 2.0])
def test_fractional_stride_follows_eq6(stride):
    """Sensor pitch scaled by S_eff: the response is the correlation averaged over each footprint."""
    base = Bench(**IDEAL)
    bench = base.replace(sensor_pitch_um=base.sensor_pitch_um * stride, origin_px=(100.0, 80.0))
    assert bench.stride_eff == pytest.approx(stride)
    rng = np.random.default_rng(int(stride * 100))
    k = rng.integers(0, 2, (3, 3))
    f = rng.integers(0, 2, (16, 16))
    resp = screen_response(k, f, bench, leak=False)
    corr = signal.correlate2d(f, k, "full")
    n_pix = int(math.ceil(corr.shape[0] / stride)) + 2
    # pixel (100 + i) covers full-response coordinates [i * s1, (i + 1) * s1) shifted by half a cell
    start = -0.5 * stride + 0.5
    oracle = _integral_oracle(corr, stride, n_pix, start)
    got = resp[80:80 + n_pix, 100:100 + n_pix]
    np.testing.assert_allclose(got, oracle, rtol=0, atol=1e-9)


@pytest.mark.parametrize("mirrors", [6, 8, 10, 12])
def test_mismatched_kernel_scaling_moves_shadows_by_eq6(mirrors):
    """Shadows of two kernel elements (k - 1) apart sit (k - 1) * Delta / S_eff pixels apart."""
    bench = Bench(kernel_upsample=mirrors, origin_px=(140.0, 100.0))
    f = np.zeros((16, 16), int)
    f[7, 7] = 1
    k = 5
    cents = []
    for col in (0, k - 1):
        kern = np.zeros((1, k), int)
        kern[0, col] = 1
        r = screen_response(kern, f, bench, leak=False)
        cents.append((r.sum(0) * np.arange(r.shape[1])).sum() / r.sum())
    s_eff = bench.stride_eff  # eq. 6 with K_eff = mirrors * 7.56 um
    assert s_eff == pytest.approx(8 / mirrors)
    assert abs(cents[1] - cents[0]) == pytest.approx((k - 1) * bench.decimation / s_eff, abs=1e-9)


def test_blur_conserves_light_and_spreads_it():
    f = np.zeros((16, 16), int)
    f[8, 8] = 1
    k = np.ones((1, 1), int)
    sharp = screen_response(k, f, Bench(), leak=False)
    blurred = screen_response(k, f, Bench(psf_sigma_um=300.0), leak=False)
    assert blurred.sum() == pytest.approx(sharp.sum(), rel=1e-6)
    assert blurred.max() < sharp.max()
    assert np.all(np.isfinite(blurred)) and blurred.min() >= 0


def test_leak_and_stray_light():
    b = Bench(dmd_contrast=100.0, stray_light=0.01)
    dark = screen_response(np.zeros((3, 3), int), np.zeros((16, 16), int), b)
    # both DMDs off: leak * (leak * 9) + stray, everywhere
    assert np.allclose(dark, 0.01 * 0.01 * 9 + 0.01)
    lit = screen_response(np.ones((3, 3), int), np.ones((16, 16), int), b)
    assert lit.max() == pytest.approx(9.0 * (1 - 0.01) + 0.01 * 9 + 0.01, rel=1e-9)
    assert lit.min() == pytest.approx(0.01 * 9 + 0.01)
    from evtk.optics import brightest_response, glow_response

    assert lit.max() == pytest.approx(brightest_response((3, 3), b), rel=1e-12)
    assert glow_response(np.zeros((3, 3)), b) == pytest.approx(dark.max(), rel=1e-12)


def test_patterns_must_be_binary_and_fit():
    with pytest.raises(EvtkError, match="binary"):
        screen_response(np.full((3, 3), 0.5), np.ones((4, 4)), Bench())
    with pytest.raises(EvtkError, match="binary"):
        screen_response(-np.ones((3, 3)), np.ones((4, 4)), Bench())
    with pytest.raises(EvtkError, match="kernel DMD"):
        screen_response(np.ones((200, 200)), np.ones((4, 4)), Bench())
    with pytest.raises(EvtkError, match="feature DMD"):
        screen_response(np.ones((3, 3)), np.ones((300, 10)), Bench())


@pytest.mark.parametrize("field,value", [("u_mm", 0), ("z_mm", -5), ("sensor_pitch_um", 0), ("decimation", 0),
                                         ("decimation", 1.5), ("feature_upsample", 0), ("dmd_contrast", 0.5),
                                         ("power_mw", -1), ("source_extent", "disc"), ("sensor_width", 40000),
                                         ("origin_px", (1.0, float("nan")))])
def test_bench_rejects_bad_values(field, value):
    with pytest.raises(EvtkError, match=field.split("_")[0]):
        Bench(**{field: value})


@pytest.mark.parametrize("ext", [".toml", ".json"])
def test_bench_files_round_trip(tmp_path, ext):
    from evtk.sensor import SensorModel

    b = Bench(u_mm=250.5, kernel_upsample=7, origin_px=(10.5, 20.0), kernel_flipped=True)
    s = SensorModel(theta_on=0.25, shot_noise=False)
    p = tmp_path / f"bench{ext}"
    save_bench(p, b, s)
    b2, s2 = load_bench(p)
    assert b2 == b
    assert SensorModel.from_dict(s2) == s


def test_bench_file_errors_name_the_file(tmp_path):
    p = tmp_path / "b.toml"
    p.write_text("u_mm = [\n")
    with pytest.raises(EvtkError, match="b.toml"):
        load_bench(p)
    p.write_text("u_mm = 100\nspeed_of_dark = 3\n")
    with pytest.raises(EvtkError, match="speed_of_dark"):
        load_bench(p)
    p.write_text("u_mm = -100\n")
    with pytest.raises(EvtkError, match="u_mm"):
        load_bench(p)
    q = tmp_path / "b.json"
    q.write_text(json.dumps([1, 2]))
    with pytest.raises(EvtkError, match="table"):
        load_bench(q)
    with pytest.raises(EvtkError, match="cannot read"):
        load_bench(tmp_path / "missing.toml")


def test_response_region_covers_every_lit_pixel():
    rng = np.random.default_rng(2)
    for source in ("point", "area"):
        for pitch in (181.44, 120.0, 300.0):
            b = Bench(source_extent=source, sensor_pitch_um=pitch, psf_sigma_um=100.0)
            k = rng.integers(0, 2, (3, 3))
            k[1, 1] = 1
            f = np.ones((16, 16), int)
            resp = screen_response(k, f, b, leak=False)
            x0, x1, y0, y1 = response_region(b, k.shape, f.shape)
            inside = resp[y0:y1, x0:x1].sum()
            assert inside == pytest.approx(resp.sum(), rel=1e-9)


def test_fresnel_number_says_when_the_shadow_model_holds():
    """N_F = F_pt^2 / (lambda u): 0.0133 at the default bench (45.36 um elements, 514 nm, 300 mm), where each
    element's diffraction (lambda u / F_pt = 3.4 mm) dwarfs a 181 um pixel; a near screen makes it valid."""
    from evtk.optics import Bench

    b = Bench()
    assert b.fresnel_number == pytest.approx(45.36e-6 ** 2 / (514e-9 * 0.3), rel=1e-9)
    assert b.fresnel_number == pytest.approx(0.01334, rel=1e-3)
    assert b.diffraction_spread_um == pytest.approx(514e-9 * 0.3 / 45.36e-6 * 1e6, rel=1e-9)
    assert "Fresnel number 0.0133" in b.shadow_model_note()
    near = b.replace(u_mm=1.0, feature_upsample=40)
    assert near.fresnel_number > 1 and near.shadow_model_note() is None


def test_diffraction_blurs_the_shadows_by_its_gaussian_approximation():
    """With diffraction on, the shadows are those of a diffuser blur of diffraction_sigma_um (added in quadrature):
    the far-field width where the Fresnel number is below 1, the Fresnel zone above it, continuous at 1."""
    import math

    from evtk.optics import Bench, screen_response

    b = Bench()
    lam_u = b.wavelength_nm * 1e-3 * b.u_mm * 1e3
    assert b.fresnel_number < 1 and b.diffraction_sigma_um == pytest.approx(0.376 * lam_u / b.feature_pitch_um)
    near = Bench(u_mm=b.u_mm * b.fresnel_number / 20)  # Fresnel number 20
    lam_u_near = near.wavelength_nm * 1e-3 * near.u_mm * 1e3
    assert near.fresnel_number == pytest.approx(20) and near.diffraction_sigma_um == pytest.approx(
        0.376 * math.sqrt(lam_u_near))
    k, f = np.ones((3, 3)), (np.arange(256).reshape(16, 16) % 3 == 0).astype(int)
    small = b.replace(u_mm=b.u_mm / 50, psf_sigma_um=20.0)
    on = screen_response(k, f, small.replace(diffraction=True))
    same = screen_response(k, f, small.replace(psf_sigma_um=math.hypot(20.0, small.diffraction_sigma_um)))
    assert np.allclose(on, same) and not np.allclose(on, screen_response(k, f, small))
    assert b.shadow_model_note() is not None and b.replace(diffraction=True).shadow_model_note() is None
