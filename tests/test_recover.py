"""Kernel recovery: exactness without noise, search against brute force, ambiguity, bad input, the command."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import signal

from evtk import EvtkError
from evtk.cli import main
from evtk.optics import Bench
from evtk.recover import (
    all_kernels,
    classify,
    device_responses,
    is_shift,
    kernel_bits,
    kernel_from_bits,
    recover_brute,
    recover_search,
    response_matrix,
    success_rate,
)
from evtk.sensor import SensorModel

QUIET = SensorModel(shot_noise=False, background_rate_hz=0.0, theta_mismatch=0.0)


def _random_kernel(rng, s):
    k = np.zeros(s * s, np.int8)
    while not k.any():
        k = (rng.random(s * s) < 0.5).astype(np.int8)
    return k.reshape(s, s)


def test_enumeration_bits_and_shifts():
    k3 = all_kernels(3)
    assert k3.shape == (512, 3, 3) and len({kernel_bits(k) for k in k3}) == 512
    assert kernel_bits(k3[0b010111010]) == "010111010"
    np.testing.assert_array_equal(kernel_from_bits("010111010"), k3[0b010111010])
    a = np.array([[1, 1, 0], [0, 1, 0], [0, 0, 0]])
    assert is_shift(a, np.roll(np.roll(a, 1, 0), 1, 1)) and is_shift(a, np.roll(a, 1, 1))
    assert not is_shift(a, a) and not is_shift(a, np.roll(a, 2, 1))  # wraps around: not a translation
    assert not is_shift(a, a.T) and not is_shift(np.zeros((3, 3)), np.zeros((3, 3)))
    assert classify(a, a) == "exact" and classify(np.roll(a, 1, 0), a) == "shift" and classify(a.T, a) == "wrong"
    for bad in ("", "0120", "01010"):
        with pytest.raises(EvtkError):
            kernel_from_bits(bad)
    with pytest.raises(EvtkError, match="search"):
        all_kernels(6)
    with pytest.raises(EvtkError, match="size"):
        all_kernels(8)


def test_model_matrix_is_the_correlation():
    rng = np.random.default_rng(1)
    f = (rng.random((16, 16)) < 0.5).astype(np.int8)
    a = response_matrix(f, 3)
    for k in all_kernels(3)[::37]:
        np.testing.assert_allclose(a @ k.ravel(), signal.correlate2d(f, k, "full").ravel())
    # with the optics' blur: the footprint applied to the correlation, and still linear
    ab = response_matrix(f, 3, Bench(), blurred=True)
    k = all_kernels(3)[300]
    assert not np.allclose(ab @ k.ravel(), a @ k.ravel())
    np.testing.assert_allclose(ab @ (k.ravel() * 2), 2 * ab @ k.ravel())


def test_noise_free_recovery_is_exact_for_random_kernels():
    """Noise-free responses: brute force on the device (noise-free pixels) and the search on the model."""
    rng = np.random.default_rng(2)
    f = (rng.random((16, 16)) < 0.5).astype(np.int8)
    cands = device_responses(all_kernels(3), f, sensor=QUIET, seed=1)
    for _ in range(8):
        k = _random_kernel(rng, 3)
        target = device_responses(k[None], f, sensor=QUIET, seed=1)[0]
        r = recover_brute(target, cands, true_kernel=k)
        assert r.status == "exact" and r.loss == 0.0 and r.losses.shape == (512,)
    for s in (3, 4, 5):
        a = response_matrix(f, s)
        for _ in range(6):
            k = _random_kernel(rng, s)
            r = recover_search(1.3 * (a @ k.ravel()), a, s, true_kernel=k)
            assert r.status == "exact" and r.proven and r.scale == pytest.approx(1.3) and r.loss < 1e-12


@pytest.mark.parametrize("size", [3, 4])
def test_search_agrees_with_brute_force_on_noisy_targets(size):
    """Same loss (weighted, fixed scale) over every kernel: the proven search finds brute force's minimum."""
    rng = np.random.default_rng(size)
    f = (rng.random((16, 16)) < 0.5).astype(np.int8)
    a = response_matrix(f, size)
    cands = (all_kernels(size).reshape(2 ** (size * size), -1) @ a.T)
    for trial in range(6):
        k = _random_kernel(rng, size)
        y = a @ k.ravel() + rng.normal(0, 1.5 + trial, a.shape[0])  # noisy enough to be wrong sometimes
        for weights in (None, "relative"):
            brute = recover_brute(y, cands, weights=weights)
            search = recover_search(y, a, size, fit_scale=False, weights=weights)
            assert search.proven
            np.testing.assert_array_equal(search.kernel, brute.kernel)
            assert search.loss == pytest.approx(brute.loss, rel=1e-9)


def test_ambiguity_of_shift_equivalent_kernels_is_reported():
    """A misaligned capture (the response one cell off) is explained exactly by the shifted kernel: "shift".

    A target halfway between a kernel's response and its shift's ties the two; both are listed.
    """
    rng = np.random.default_rng(7)
    f = np.zeros((14, 14), np.int8)
    f[2:-2, 2:-2] = rng.random((10, 10)) < 0.5  # a dark border: translations lose nothing
    k = np.array([[1, 1, 0], [1, 0, 0], [0, 0, 0]], np.int8)
    shifted = np.roll(np.roll(k, 1, 0), 1, 1)
    full = lambda kern: signal.correlate2d(f, kern, "full")  # noqa: E731
    cands = np.stack([full(c).ravel() for c in all_kernels(3)])
    misaligned = np.roll(np.roll(full(k), -1, 0), -1, 1)  # the device's image one cell up and left
    r = recover_brute(misaligned, cands, true_kernel=k, weights=None)
    np.testing.assert_array_equal(r.kernel, shifted)
    assert r.status == "shift" and r.loss == 0.0
    # uniform features: inside the valid region every kernel with as many lit elements casts the same
    # response, shifts included; the tie is listed, not hidden
    u = np.ones((12, 12), np.int8)
    valid = np.stack([signal.correlate2d(u, c, "valid").ravel() for c in all_kernels(3)])
    r = recover_brute(valid[int(kernel_bits(k), 2)], valid, true_kernel=k, weights=None)
    tied = [b for b, v in r.near if v == r.loss == 0.0]
    assert len(tied) == 50 and all(b.count("1") == 3 for b in tied)  # 84 tie; the list stops at 50
    assert r.status in ("exact", "shift", "wrong")
    assert kernel_bits(shifted) in tied + [kernel_bits(r.kernel)]


def test_recovery_bad_input():
    f = np.ones((8, 8), np.int8)
    a = response_matrix(f, 3)
    with pytest.raises(EvtkError, match="binary"):
        response_matrix(f * 2, 3)
    with pytest.raises(EvtkError, match="2-D"):
        response_matrix(np.ones(8), 3)
    with pytest.raises(EvtkError, match="does not fit"):
        recover_search(np.ones(5), a, 3)
    with pytest.raises(EvtkError, match="NaN"):
        recover_search(np.full(a.shape[0], np.nan), a, 3)
    with pytest.raises(EvtkError, match="every binary kernel"):
        recover_brute(np.ones(4), np.ones((100, 4)))
    with pytest.raises(EvtkError, match="values"):
        recover_brute(np.ones(5), np.ones((512, 4)))
    with pytest.raises(EvtkError, match="weights"):
        recover_search(np.ones(a.shape[0]), a, 3, weights="log")
    with pytest.raises(EvtkError, match="all zero"):
        device_responses(np.zeros((2, 3, 3)), f)


def test_success_rate_rows_and_light():
    """Nominal light recovers every kernel of a small sample; without light nothing is recovered."""
    rows = success_rate([20.0], size=3, trials=6, seed=4)
    assert rows[0]["recovered_pct"] == 100.0 and rows[0]["trials"] == 6 and rows[0]["method"] == "brute"
    rows = success_rate([1e-4, 20.0], size=5, trials=6, seed=4)
    assert [r["method"] for r in rows] == ["search", "search"]
    assert rows[0]["recovered_pct"] < 50 and rows[1]["recovered_pct"] >= 5 / 6 * 100
    assert all(r["proven_pct"] == 100.0 for r in rows)


def test_cli_recover(tmp_path):
    res = CliRunner().invoke(main, ["recover", "--target-kernel-bits", "110010011", "--json", "--plot",
                                    str(tmp_path / "fig4.png")])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["kernel_bits"] == "110010011" and out["status"] == "exact" and out["method"] == "brute"
    assert (tmp_path / "fig4.png").stat().st_size > 5000
    # a captured response from a file, searched
    rng = np.random.default_rng(0)
    f = (rng.random((16, 16)) < 0.5).astype(np.int8)
    k = kernel_from_bits("1011001110100101")
    np.save(tmp_path / "f.npy", f)
    np.save(tmp_path / "t.npy", device_responses(k[None], f, seed=0, noise_seed=5)[0])
    res = CliRunner().invoke(main, ["recover", "--features", str(tmp_path / "f.npy"), "--target",
                                    str(tmp_path / "t.npy"), "--size", "4", "--method", "search", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["kernel_bits"] == "1011001110100101" and out["proven"] and out["status"] is None
    res = CliRunner().invoke(main, ["recover", "--trials", "2", "--power-mw", "20", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["rows"][0]["trials"] == 2
    for bad, msg in ((["--target-kernel-bits", "0101"], "kernel"), ([], "exactly one"),
                     (["--target", str(tmp_path / "t.npy")], "full response"),
                     (["--target-kernel-bits", "000000000"], "all-zero"),
                     (["--trials", "2", "--target-kernel-bits", "110010011"], "draws its own")):
        res = CliRunner().invoke(main, ["recover", *bad])
        assert res.exit_code == 1 and msg in res.output, (bad, res.output)


def test_cli_recover_from_recorded_candidates(tmp_path):
    """A recording with one capture per candidate stands in for the device."""
    from evtk.simulate import Simulation

    rng = np.random.default_rng(3)
    f = (rng.random((6, 6)) < 0.5).astype(np.int8)
    np.save(tmp_path / "f.npy", f)
    size = 2
    kernels = all_kernels(size)[1:]  # every non-zero 2x2 kernel
    Simulation(kernels, f, seed=0).write(tmp_path / "cands.aedat4")
    k = kernel_from_bits("1001")
    np.save(tmp_path / "t.npy", device_responses(k[None], f, seed=0, noise_seed=9)[0])
    res = CliRunner().invoke(main, ["recover", "--features", str(tmp_path / "f.npy"), "--target",
                                    str(tmp_path / "t.npy"), "--size", "2", "--candidates",
                                    str(tmp_path / "cands.aedat4"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["kernel_bits"] == "1001"
    np.save(tmp_path / "g.npy", 1 - f)
    res = CliRunner().invoke(main, ["recover", "--features", str(tmp_path / "g.npy"), "--target",
                                    str(tmp_path / "t.npy"), "--size", "2", "--candidates",
                                    str(tmp_path / "cands.aedat4")])
    assert res.exit_code == 1 and "not the ones given" in res.output
