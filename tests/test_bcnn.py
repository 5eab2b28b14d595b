"""Binary CNN, its optimisers and data sets: oracles, toy objectives, tiny files made here."""

import gzip
import json
import pickle

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import signal

from evtk import EvtkError, FormatError
from evtk.bcnn import BCNN, DigitalBackend, OpticalBackend, bce_loss, binary_correlate, poisson_robustness
from evtk.cli import main
from evtk.datasets import face_not_face, letters_digits, read_cifar_batch, read_idx
from evtk.optimize import fit_mask, metropolis, train_layerwise, train_ste


@pytest.mark.parametrize("shape,kshape", [((5, 16, 16), (3, 3)), ((3, 7, 11), (2, 3)), ((2, 4, 4), (1, 1)),
                                          ((2, 9, 5), (4, 4))])
def test_binary_correlation_equals_the_float_correlation(shape, kshape):
    rng = np.random.default_rng(sum(shape))
    x = rng.choice([-1, 1], shape).astype(np.int8)
    k = rng.choice([-1, 1], kshape).astype(np.int8)
    got = binary_correlate(x, k)
    for i in range(shape[0]):
        np.testing.assert_array_equal(got[i], signal.correlate2d(x[i].astype(float), k.astype(float), "full"))


def test_binary_correlation_bad_input():
    with pytest.raises(EvtkError, match="1 values"):
        binary_correlate(np.zeros((1, 4, 4)), np.ones((3, 3)))
    with pytest.raises(EvtkError, match="64-bit"):
        binary_correlate(np.ones((1, 40, 40)), np.ones((3, 3)))
    with pytest.raises(EvtkError, match="takes"):
        binary_correlate(np.ones((4,)), np.ones((3, 3)))


def test_metropolis_improves_a_toy_objective_and_is_reproducible():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(14, 14))
    q = q @ q.T
    lin = rng.normal(size=14) * 3
    f = lambda b: float(b @ q @ b - lin @ b)  # noqa: E731
    exhaustive = min(f(((np.arange(2 ** 14)[i] >> np.arange(14)) & 1).astype(float)) for i in range(2 ** 14))
    best, value, trace = metropolis(f, 14, 3000, 5.0, 0.01, seed=3)
    assert value == pytest.approx(exhaustive) and f(best.astype(float)) == pytest.approx(value)
    again = metropolis(f, 14, 3000, 5.0, 0.01, seed=3)
    assert again[1] == value and np.array_equal(again[0], best) and np.array_equal(again[2], trace)
    walk_start = f(np.zeros(14))
    _, walk_value, _ = metropolis(f, 14, 2000, 1.0, seed=4, start=np.zeros(14, np.int8))
    assert walk_value <= walk_start
    with pytest.raises(EvtkError):
        metropolis(f, 14, 10, 0.0)
    with pytest.raises(EvtkError):
        metropolis(f, 14, 10, 1.0, 2.0)


def _toy_data(n=80, seed=0):
    """Bright blob top-left (label 1) or bottom-right (label 0), with pixel noise."""
    rng = np.random.default_rng(seed)
    y = rng.integers(0, 2, n).astype(np.int8)
    x = -np.ones((n, 16, 16), np.int8)
    for i in range(n):
        if y[i]:
            x[i, 2:8, 2:8] = 1
        else:
            x[i, 8:14, 8:14] = 1
    flip = rng.random(x.shape) < 0.1
    x[flip] *= -1
    return x, y


def test_layerwise_training_learns_a_separable_toy_task():
    x, y = _toy_data()
    be = DigitalBackend()
    for optimizer in ("anneal", "walk", "brute"):
        model = BCNN.random(layers=2, seed=1)
        rec = train_layerwise(model, be, x, y, optimizer=optimizer, steps=300, seed=2)
        assert model.accuracy(be, x, y) >= 0.95, optimizer
        assert len(rec["layers"]) == 2 and all(t is not None for t in model.thresholds)
    # the loss is binary cross-entropy of the mask scores, and brute force is the best kernel for its mask rule
    model = BCNN.random(layers=1, seed=3)
    train_layerwise(model, be, x, y, optimizer="brute")
    a, _, _ = model.layer(be, x[:, None], 0)
    best = bce_loss(*model.scores(a, model.masks[0]), y, model.beta)
    for _ in range(20):
        other = BCNN.random(layers=1, seed=int(np.random.default_rng(_).integers(1000)))
        ao, _, _ = other.layer(be, x[:, None], 0)
        assert bce_loss(*other.scores(ao, fit_mask(ao, y, 2)), y, other.beta) >= best - 1e-9
    with pytest.raises(EvtkError, match="optimizer"):
        train_layerwise(BCNN.random(), be, x, y, optimizer="sgd")
    with pytest.raises(EvtkError, match="labels"):
        train_layerwise(BCNN.random(), be, x, y * 2)


def test_ste_reference_learns_and_yields_a_binary_network():
    x, y = _toy_data(seed=5)
    model = BCNN.random(layers=3, seed=0)
    rec = train_ste(model, x, y, epochs=150, seed=1)
    assert rec["losses"][-1] < rec["losses"][0]
    assert all(set(np.unique(k)) <= {-1, 1} for k in model.kernels)
    assert model.accuracy(DigitalBackend(), x, y) >= 0.9


def test_channel_masks_score_each_channel():
    """A mask plane per channel: equal planes score exactly as one shared plane does; the scores are the
    per-channel pooled sums; both trainers fit (c, 8, 8) masks that separate a toy task."""
    rng = np.random.default_rng(0)
    a = rng.choice(np.array([-1, 1], np.int8), (5, 3, 16, 16))
    model = BCNN.random(layers=1, channels=3, seed=0, channel_masks=True)
    assert model.masks[0].shape == (3, 8, 8)
    shared = (rng.random((8, 8)) < 0.5).astype(np.int8)
    s_shared = model.scores(a, shared)
    s_planes = model.scores(a, np.repeat(shared[None], 3, axis=0))
    np.testing.assert_allclose(s_planes, s_shared, atol=1e-12)
    planes = (rng.random((3, 8, 8)) < 0.5).astype(np.int8)
    pooled = a.reshape(5, 3, 8, 2, 8, 2).mean(axis=(3, 5))
    expect1 = np.array([sum((pooled[n, c] * planes[c]).sum() for c in range(3)) / 3 for n in range(5)])
    np.testing.assert_allclose(model.scores(a, planes)[1], expect1, atol=1e-12)
    np.testing.assert_array_equal(fit_mask(a, np.array([1, 0, 1, 0, 1]), 2, per_channel=True).shape, (3, 8, 8))
    x, y = _toy_data(seed=7)
    for trainer in ("ste", "anneal"):
        m = BCNN.random(layers=1, channels=2, seed=1, channel_masks=True)
        if trainer == "ste":
            rec = train_ste(m, x, y, epochs=150, seed=2)
            assert rec["losses"][-1] < rec["losses"][0]
        else:
            train_layerwise(m, DigitalBackend(), x, y, steps=300, seed=2)
        assert m.masks[-1].shape == (2, 8, 8) and m.accuracy(DigitalBackend(), x, y) >= 0.9, trainer


def test_bce_loss_is_stable_and_correct():
    assert bce_loss([0.0], [0.0], [1], 1.0) == pytest.approx(np.log(2))
    assert bce_loss([1e6], [0.0], [1], 1.0) == pytest.approx(0.0)
    assert bce_loss([-1e6], [0.0], [1], 1.0) == pytest.approx(1e6)  # no overflow, no inf


def test_optical_backend_follows_the_digital_correlation():
    rng = np.random.default_rng(0)
    x = rng.choice([-1, 1], (12, 1, 16, 16)).astype(np.int8)
    k = rng.choice([-1, 1], (1, 1, 3, 3)).astype(np.int8)
    dig = DigitalBackend().correlate(x, k)
    opt = OpticalBackend(seed=1).correlate(x, k)
    assert opt.shape == dig.shape
    assert np.corrcoef(opt.ravel(), dig.ravel())[0, 1] > 0.8


def test_poisson_robustness_limits():
    x, y = _toy_data(seed=7)
    model = BCNN.random(layers=2, seed=2)
    be = DigitalBackend()
    train_layerwise(model, be, x, y, steps=300, seed=1)
    res = poisson_robustness(model, x, y, [0.0, 0.3, 30.0], seed=0)
    clean, mid, loud = res["rows"]
    assert clean["flip_pct"] == 0.0 and clean["accuracy"] == pytest.approx(res["clean_accuracy"])
    assert loud["flip_pct"] > mid["flip_pct"] > 0 and loud["accuracy"] <= clean["accuracy"]
    assert res["R_pct"] is not None and res["R_pct"] >= 0.0
    assert poisson_robustness(model, x, y, [30.0], target_accuracy=1.01)["R_pct"] is None
    with pytest.raises(EvtkError):
        poisson_robustness(model, x, y, [-1.0])


# -- data sets ---------------------------------------------------------------------------------

def _idx_bytes(arr):
    arr = np.asarray(arr, np.uint8)
    head = bytes([0, 0, 0x08, arr.ndim]) + b"".join(int(d).to_bytes(4, "big") for d in arr.shape)
    return head + arr.tobytes()


def test_idx_reader_plain_gzip_and_damaged(tmp_path):
    imgs = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
    (tmp_path / "a.idx").write_bytes(_idx_bytes(imgs))
    np.testing.assert_array_equal(read_idx(tmp_path / "a.idx"), imgs)
    with gzip.open(tmp_path / "a.idx.gz", "wb") as fh:
        fh.write(_idx_bytes(imgs))
    np.testing.assert_array_equal(read_idx(tmp_path / "a.idx.gz"), imgs)
    (tmp_path / "t.idx").write_bytes(_idx_bytes(imgs)[:-3])
    with pytest.raises(FormatError, match="truncated"):
        read_idx(tmp_path / "t.idx")
    (tmp_path / "m.idx").write_bytes(b"\x01\x02\x03\x04" + b"\x00" * 8)
    with pytest.raises(FormatError, match="magic"):
        read_idx(tmp_path / "m.idx")


def test_emnist_from_local_idx_files(tmp_path):
    rng = np.random.default_rng(0)
    n = 40
    labels = np.r_[np.arange(10).repeat(2), 10 + np.arange(20)].astype(np.uint8)  # 20 digits, 20 letters
    imgs = (rng.random((n, 28, 28)) * 255).astype(np.uint8)
    imgs[:, 5, :] = 255  # a horizontal bar, stored transposed as EMNIST does: vertical after loading
    (tmp_path / "emnist-balanced-train-images-idx3-ubyte").write_bytes(_idx_bytes(imgs))
    (tmp_path / "emnist-balanced-train-labels-idx1-ubyte").write_bytes(_idx_bytes(labels))
    d = letters_digits(data_dir=str(tmp_path), n_per_class=20, test_fraction=0.25)
    assert not d.synthetic and "EMNIST" in d.source
    assert len(d.y_train) + len(d.y_test) == 40 and d.y_train.mean() == pytest.approx(0.5)
    assert set(np.unique(d.x_train)) <= {-1, 1}
    with pytest.raises(EvtkError, match="EMNIST"):
        letters_digits(data_dir=str(tmp_path / "nowhere"))


def test_fnf_from_local_lfw_and_cifar(tmp_path):
    from skimage import io

    rng = np.random.default_rng(1)
    for p in range(3):
        d = tmp_path / "lfw" / f"Person_{p}"
        d.mkdir(parents=True)
        for j in range(2):
            io.imsave(d / f"Person_{p}_{j:04d}.jpg", (rng.random((40, 40, 3)) * 255).astype(np.uint8),
                      check_contrast=False)
    cdir = tmp_path / "cifar-10-batches-py"
    cdir.mkdir()
    with open(cdir / "data_batch_1", "wb") as fh:
        pickle.dump({b"data": (rng.random((10, 3072)) * 255).astype(np.uint8), b"labels": list(range(10))}, fh)
    grey, labels = read_cifar_batch(cdir / "data_batch_1")
    assert grey.shape == (10, 32, 32) and 0 <= grey.min() and grey.max() <= 1 and labels.tolist() == list(range(10))
    d = face_not_face(data_dir=str(tmp_path), n_per_class=6, test_fraction=0.5)
    assert len(d.y_train) + len(d.y_test) == 12 and "LFW" in d.source
    with open(cdir / "data_batch_2", "wb") as fh:
        fh.write(b"not a pickle")
    with pytest.raises(FormatError):
        read_cifar_batch(cdir / "data_batch_2")


def test_bundled_data_sets():
    d = face_not_face(seed=1)
    assert (len(d.y_train), len(d.y_test)) == (140, 60) and d.y_test.mean() == pytest.approx(0.5)
    assert d.x_train.dtype == np.int8 and set(np.unique(d.x_train)) == {-1, 1}
    assert not np.array_equal(face_not_face(seed=2).y_train, d.y_train)
    g = letters_digits(n_per_class=30, seed=0)
    assert g.synthetic and "synthetic" in g.source and len(g.y_train) + len(g.y_test) == 60
    np.testing.assert_array_equal(letters_digits(n_per_class=30, seed=0).x_train, g.x_train)


def test_cli_classify_and_robustness(tmp_path):
    res = CliRunner().invoke(main, ["classify", "--backend", "digital", "--runs", "2", "--steps", "60",
                                    "--out", str(tmp_path / "c"), "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.output)
    assert s["runs"] == 2 and 0.5 <= s["test_accuracy"]["mean"] <= 1 and s["data"]["train"] == 140
    runs = json.loads((tmp_path / "c" / "runs.json").read_text())["runs"]
    assert len(runs) == 2 and len(runs[0]["record"]["layers"][0]["trace"]) == 60
    text = CliRunner().invoke(main, ["classify", "--backend", "digital", "--runs", "2", "--steps", "30",
                                     "--task", "letters-digits", "--samples", "50", "--out", str(tmp_path / "d")])
    assert text.exit_code == 0 and "SYNTHETIC" in text.output and "70 train / 30 test" in text.output
    res = CliRunner().invoke(main, ["classify", "--backend", "digital", "--runs", "1", "--steps", "30", "--channels",
                                    "2", "--channel-masks", "--out", str(tmp_path / "e"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["channel_masks"] is True
    assert np.shape(json.loads((tmp_path / "e" / "runs.json").read_text())["runs"][0]["mask"]) == (2, 8, 8)
    res = CliRunner().invoke(main, ["classify", "--samples", "50"])  # the bundled FNF subset is fixed
    assert res.exit_code == 1 and "data directory" in res.output
    res = CliRunner().invoke(main, ["robustness", "--steps", "60", "--scales", "0,1,10", "--json", "--plot",
                                    str(tmp_path / "r.png")])
    assert res.exit_code == 0, res.output
    r = json.loads(res.output)
    assert [row["scale"] for row in r["rows"]] == [0, 1, 10] and r["rows"][0]["flip_pct"] == 0
    assert (tmp_path / "r.png").stat().st_size > 1000
    res = CliRunner().invoke(main, ["robustness", "--scales", "a,b"])
    assert res.exit_code == 2 and "--scales" in res.output  # a usage error


def test_baselines_against_brute_force_and_scipy():
    """Nearest centroid by brute force; the logistic regression's weights minimise its objective (scipy's
    minimiser finds the same predictions), and a separable set is classified perfectly."""
    from scipy.optimize import minimize

    from evtk.datasets import Dataset, baselines

    rng = np.random.default_rng(0)
    proto = rng.choice([-1, 1], (2, 6, 6))
    def draw(n):
        y = rng.integers(0, 2, n).astype(np.int8)
        x = proto[y] * np.where(rng.random((n, 6, 6)) < 0.2, -1, 1)
        return x.astype(np.int8), y
    xtr, ytr = draw(200)
    xte, yte = draw(100)
    data = Dataset("t", xtr, ytr, xte, yte, ("a", "b"), "test")
    got = baselines(data, l2=1e-2)
    a, b = xtr.reshape(200, -1).astype(float), xte.reshape(100, -1).astype(float)
    c0, c1 = a[ytr == 0].mean(0), a[ytr == 1].mean(0)
    nc = [int(np.sum((v - c1) ** 2) < np.sum((v - c0) ** 2)) for v in b]
    assert got["nearest_centroid"] == pytest.approx(np.mean(np.array(nc) == yte))
    A = np.hstack([a, np.ones((200, 1))])
    def loss(w):
        z = A @ w
        return np.sum(np.logaddexp(0, z) - ytr * z) + 0.5 * 1e-2 * 200 * np.sum(w[:-1] ** 2)
    w = minimize(loss, np.zeros(A.shape[1]), method="L-BFGS-B").x
    pred = (np.hstack([b, np.ones((100, 1))]) @ w > 0).astype(int)
    assert got["logistic_regression"] == pytest.approx(np.mean(pred == yte), abs=0.011)
    assert got["logistic_regression"] > 0.95 and got["test_images"] == 100
    with pytest.raises(EvtkError, match="one class"):
        baselines(Dataset("t", xtr, np.zeros(200, np.int8), xte, yte, ("a", "b"), "test"))
