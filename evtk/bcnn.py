"""A binary convolutional network the device can run (paper 4.1 and 4.5).

Layers: binary 3x3 kernels (+-1, XNOR-Net scaling by the mean absolute
weight, which sign binarisation after batch normalisation makes irrelevant
for the decision), the full correlation resampled to ``size`` x ``size`` as
the bench does, batch normalisation (each channel's mean over the batch is
subtracted) and sign binarisation. After the last layer a ``pool`` x
``pool`` average pooling; two complementary binary masks score the pooled
map (dot products) and the lower score gives the label.

Backends compute the layer responses:

* :class:`DigitalBackend`: exact integer correlations, bit-packed
  XNOR/popcount in numba.
* :class:`OpticalBackend`: every correlation runs through the simulated
  device (the fast path with its +- passes, flat-field calibration,
  reconstruction and resampling), with its noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from .cluster import run_tasks
from .errors import EvtkError
from .optics import Bench
from .reconstruct import overlap_matrix
from .sweeps import simulated_reconstruction

__all__ = ["binary_correlate", "BCNN", "DigitalBackend", "OpticalBackend", "resample_matrix", "bce_loss",
           "poisson_robustness"]


@numba.njit(cache=True, inline="always")
def _popcount(v):
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (v * np.uint64(0x0101010101010101)) >> np.uint64(56)


@numba.njit(cache=True)
def _xnor_correlate(x, k):
    n, h, w = x.shape
    kh, kw = k.shape
    oh, ow = h + kh - 1, w + kw - 1
    out = np.zeros((n, oh, ow), np.int32)
    stride = w + 2 * (kw - 1)  # one padded row per lane of a 64-bit word: kh lanes
    kbits = np.uint64(0)
    for r in range(kh):
        for c in range(kw):
            if k[r, c] > 0:
                kbits |= np.uint64(1) << np.uint64(r * stride + c)
    rowmask = (np.uint64(1) << np.uint64(kw)) - np.uint64(1)
    wmask = np.uint64(0)
    for r in range(kh):
        wmask |= rowmask << np.uint64(r * stride)
    hp = h + 2 * (kh - 1)
    pos = np.zeros(hp, np.uint64)
    val = np.zeros(hp, np.uint64)
    for m in range(n):
        pos[:] = 0
        val[:] = 0
        for i in range(h):
            for j in range(w):
                bit = np.uint64(1) << np.uint64(j + kw - 1)
                val[i + kh - 1] |= bit
                if x[m, i, j] > 0:
                    pos[i + kh - 1] |= bit
        for oi in range(oh):
            sp = np.uint64(0)
            sv = np.uint64(0)
            for r in range(kh):  # kh rows side by side in one word
                sp |= pos[oi + r] << np.uint64(r * stride)
                sv |= val[oi + r] << np.uint64(r * stride)
            for oj in range(ow):
                wb = (sp >> np.uint64(oj)) & wmask
                wv = (sv >> np.uint64(oj)) & wmask
                agree = _popcount(~(wb ^ kbits) & wv)
                out[m, oi, oj] = np.int32(2 * agree) - np.int32(_popcount(wv))
    return out


def _plus_minus_one(a):
    return bool(np.all(np.abs(a) == 1)) if np.issubdtype(a.dtype, np.number) else False


def binary_correlate(x, k):
    """Full 2-D correlation of +-1 images with a +-1 kernel, by XNOR and popcount on bit-packed rows.

    Equals ``scipy.signal.correlate2d(x[i], k, "full")`` for each image
    (zero outside the image), as int32. The ``kh`` rows under the kernel sit
    side by side in one 64-bit word, so ``kh * (w + 2 (kw - 1))`` must not
    exceed 64 (16-pixel rows with a 3x3 kernel use 60 bits).

    Examples
    --------
    >>> binary_correlate(np.array([[[1, -1], [-1, 1]]]), np.array([[1, 1], [1, 1]]))[0].tolist()
    [[1, 0, -1], [0, 0, 0], [-1, 0, 1]]
    """
    x = np.asarray(x)
    k = np.asarray(k)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or k.ndim != 2 or x.size == 0 or k.size == 0:
        raise EvtkError(f"binary_correlate takes (n, h, w) images and an (h, w) kernel, not {x.shape} and {k.shape}")
    if not (_plus_minus_one(x) and _plus_minus_one(k)):
        raise EvtkError("binary_correlate takes +-1 values only")
    if k.shape[0] * (x.shape[2] + 2 * (k.shape[1] - 1)) > 64:
        raise EvtkError(f"{k.shape[0]} rows of {x.shape[2] + 2 * (k.shape[1] - 1)} padded pixels do not fit a "
                        "64-bit word")
    return _xnor_correlate(np.ascontiguousarray(x, dtype=np.int8), np.ascontiguousarray(k, dtype=np.int8))


def resample_matrix(n_in, n_out):
    """Area-overlap resampling from ``n_in`` cells to ``n_out`` (rows sum to 1), as :func:`evtk.reconstruct.downsample`."""

    step = n_in / n_out
    return overlap_matrix(n_out, 0.0, step, n_in)


class DigitalBackend:
    """Exact binary correlations (bit-packed), resampled to ``size``."""

    name = "digital"

    def __init__(self, size=16):
        self.size = int(size)
        self._mats = {}

    def _resample(self, r):
        h, w = r.shape[-2:]
        key = (h, w)
        if key not in self._mats:
            self._mats[key] = (resample_matrix(h, self.size), resample_matrix(w, self.size))
        my, mx = self._mats[key]
        return np.einsum("ij,...jk,lk->...il", my, r, mx, optimize=True)

    def correlate(self, x, k):
        """(n, c_in, s, s) +-1 inputs and (c_out, c_in, kh, kw) kernels: (n, c_out, size, size) responses."""
        n, c_in = x.shape[:2]
        out = np.zeros((n, k.shape[0], self.size, self.size))
        for o in range(k.shape[0]):
            acc = None
            for c in range(c_in):
                r = binary_correlate(x[:, c], k[o, c]).astype(np.float64)
                acc = r if acc is None else acc + r
            out[:, o] = self._resample(acc)
        return out


class OpticalBackend:
    """Correlations captured on the simulated device (fast path), one device, a new trial per call.

    Each (kernel, input channel) is one simulated run over all images: +-
    passes, flat fields, reconstruction on the full grid resampled to
    ``size``, summed over input channels.
    """

    name = "optical"

    def __init__(self, bench=None, sensor=None, seed=0, size=16):
        self.bench = bench if bench is not None else Bench()
        self.sensor = sensor
        self.seed = int(seed)
        self.size = int(size)
        self.calls = 0

    def correlate(self, x, k):
        n, c_in = x.shape[:2]
        out = np.zeros((n, k.shape[0], self.size, self.size))
        for o in range(k.shape[0]):
            for c in range(c_in):
                self.calls += 1
                r, _ = simulated_reconstruction(k[o, c], x[:, c], self.bench, self.sensor, repeat=1, seed=self.seed,
                                                noise_seed=self.seed * 1_000_003 + self.calls, crop="full",
                                                size=(self.size, self.size))
                out[:, o] += r.responses[np.argsort(r.pairs[:, 1], kind="stable")]
        return out


def bce_loss(scores0, scores1, labels, beta):
    """Summed binary cross-entropy of ``p(label 1) = sigmoid(beta * (s0 - s1))`` (the lower score wins)."""
    z = beta * (np.asarray(scores0, np.float64) - np.asarray(scores1, np.float64))
    y = np.asarray(labels, np.float64)
    # log(1 + exp(-z)) for y = 1, log(1 + exp(z)) for y = 0, without overflow
    return float(np.sum(np.logaddexp(0.0, -z) * y + np.logaddexp(0.0, z) * (1 - y)))


@dataclass
class BCNN:
    """Binary CNN parameters: per layer kernels (c_out, c_in, 3, 3) of +-1 and a 0/1 scoring mask.

    ``thresholds`` are the batch-normalisation means fixed on the training
    set; ``masks[-1]`` scores the output, the others scored hidden layers
    while they were optimised.
    """

    kernels: list
    masks: list
    thresholds: list = field(default_factory=list)
    pool: int = 2
    size: int = 16
    beta: float = 0.25

    @classmethod
    def random(cls, layers=3, channels=1, size=16, pool=2, seed=0, channel_masks=False):
        """Random kernels and masks; ``channel_masks``: one mask plane per channel (c, s/p, s/p) instead of
        one plane scoring the channels' mean."""
        rng = np.random.default_rng(seed)
        if layers < 1 or channels < 1 or size % pool:
            raise EvtkError("need at least one layer and one channel, and a size the pooling divides")
        kernels, c_in = [], 1
        for _ in range(layers):
            kernels.append(rng.choice(np.array([-1, 1], np.int8), (channels, c_in, 3, 3)))
            c_in = channels
        plane = (channels,) if channel_masks else ()
        masks = [(rng.random(plane + (size // pool, size // pool)) < 0.5).astype(np.int8) for _ in range(layers)]
        return cls(kernels, masks, [None] * layers, pool, size)

    @property
    def n_layers(self):
        return len(self.kernels)

    def layer(self, backend, x, i, threshold=None):
        """Layer ``i`` on +-1 inputs (n, c, s, s): (binary output, responses, threshold used)."""
        r = backend.correlate(x, self.kernels[i])
        thr = r.mean(axis=(0, 2, 3)) if threshold is None else np.asarray(threshold)
        a = np.where(r >= thr[None, :, None, None], 1, -1).astype(np.int8)
        return a, r, thr

    def scores(self, a, mask):
        """Dot products of the pooled map with ``mask`` and its complement: (s0, s1).

        A 2-D mask scores the channels' mean; a 3-D one (c, s/p, s/p) each
        channel with its own plane (scaled by 1/c, like the mean).
        """
        pooled = pool_map(a, self.pool, per_channel=np.ndim(mask) == 3).reshape(a.shape[0], -1)
        m = np.asarray(mask, np.float64).ravel()
        return pooled @ (1 - m), pooled @ m

    def forward(self, backend, x, upto=None):
        """Binary activations after layer ``upto`` (default the last), with the stored thresholds."""
        a = as_binary_input(x)
        for i in range(self.n_layers if upto is None else upto + 1):
            a, _, _ = self.layer(backend, a, i, self.thresholds[i])
        return a

    def decide(self, a):
        """Labels from the last layer's activations: the lower mask score gives the label."""
        s0, s1 = self.scores(a, self.masks[-1])
        return (s1 < s0).astype(np.int8)

    def predict(self, backend, x):
        return self.decide(self.forward(backend, x))

    def accuracy(self, backend, x, y):
        return float(np.mean(self.predict(backend, x) == np.asarray(y)))


def pool_map(a, pool, per_channel=False):
    """Mean over ``pool`` x ``pool`` blocks of activations (n, c, s, s): (n, s/p, s/p) averaged over the
    channels too, or (n, c, s/p, s/p) divided by c with ``per_channel`` (so both sum to the same scale)."""
    n, c, s, _ = a.shape
    blocks = a.reshape(n, c, s // pool, pool, s // pool, pool)
    if per_channel:
        return blocks.mean(axis=(3, 5)) / c
    return blocks.mean(axis=(1, 3, 5))


def as_binary_input(x: np.ndarray) -> np.ndarray:
    """Network inputs as int8 ``(n, c, s, s)`` images of +-1, checked.

    Parameters
    ----------
    x : numpy.ndarray
        +-1 images, ``(n, s, s)`` (one channel) or ``(n, c, s, s)``.

    Returns
    -------
    numpy.ndarray
        ``int8``, shape ``(n, c, s, s)``.

    Raises
    ------
    evtk.EvtkError
        When ``x`` has another shape or a value other than -1 and +1.
    """
    x = np.asarray(x)
    if x.ndim == 3:
        x = x[:, None]
    if x.ndim != 4 or not _plus_minus_one(x):
        raise EvtkError("network inputs must be +-1 images (n, s, s) or (n, c, s, s)")
    return x.astype(np.int8)


def poisson_robustness(model: BCNN, x, y, scales, seed=0, target_accuracy=None, backend=None, client=None) -> dict:
    """Fig. 3 (left) and eq. 12: accuracy and flipped pixels with scaled Poisson noise in every layer.

    At noise scale ``s`` each layer's response ``r`` becomes
    ``sign(r) * s * Poisson(|r| / s)`` (``|r| / s`` photons; ``s = 0`` is
    noise-free) before batch normalisation and binarisation. Flips are the
    share of binary activations that differ from the noise-free network's,
    averaged over layers. The robustness pair (R, r) of eq. 12: ``r`` the
    accuracy to keep (default the noise-free accuracy minus 5 points) and
    ``R`` the largest flip percentage among the scales that keep it. Each
    scale is an independent task seeded by ``(seed, its index)`` (on
    ``client``'s workers when given).
    """

    backend = backend if backend is not None else DigitalBackend(model.size)
    x = as_binary_input(x)
    y = np.asarray(y)
    scales = [float(s) for s in scales]
    if not scales or any(not np.isfinite(s) or s < 0 for s in scales):
        raise EvtkError("noise scales must be finite and >= 0")
    clean, a = [], x  # the noise-free activations every scale is compared with, computed once
    for i in range(model.n_layers):
        a, _, _ = model.layer(backend, a, i, model.thresholds[i])
        clean.append(a)
    rows = run_tasks(_noisy_inference, [(model, backend, x, y, clean, s, seed, i) for i, s in enumerate(scales)],
                     client)
    clean_acc = float(np.mean(model.decide(clean[-1]) == y))
    r_keep = clean_acc - 0.05 if target_accuracy is None else float(target_accuracy)
    kept = [row["flip_pct"] for row in rows if row["accuracy"] >= r_keep]
    return {"rows": rows, "clean_accuracy": clean_acc, "r": r_keep, "R_pct": max(kept) if kept else None}


def _noisy_inference(args):
    model, backend, x, y, clean, s, seed, index = args
    rng = np.random.default_rng([seed, index])
    a = x
    flips = []
    for i in range(model.n_layers):
        thr = np.asarray(model.thresholds[i])[None, :, None, None]
        r = backend.correlate(a, model.kernels[i])
        if s > 0:
            r = np.sign(r) * s * rng.poisson(np.abs(r) / s)
        a = np.where(r >= thr, 1, -1).astype(np.int8)
        flips.append(float(np.mean(a != clean[i])))
    acc = float(np.mean(model.decide(a) == y))
    return {"scale": s, "accuracy": acc, "flip_pct": 100.0 * float(np.mean(flips)),
            "flip_pct_per_layer": [100.0 * f for f in flips]}
