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

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from .cluster import run_tasks
from .errors import EvtkError
from .optics import Bench
from .reconstruct import overlap_matrix
from .sensor import SensorModel
from .sweeps import simulated_reconstruction

if TYPE_CHECKING:
    import numpy.typing as npt

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


def _plus_minus_one(a: np.ndarray) -> bool:
    return bool(np.all(np.abs(a) == 1)) if np.issubdtype(a.dtype, np.number) else False


def binary_correlate(x: npt.ArrayLike, k: npt.ArrayLike) -> np.ndarray:
    """Full 2-D correlation of +-1 images with a +-1 kernel, by XNOR and popcount on bit-packed rows.

    Equals ``scipy.signal.correlate2d(x[i], k, "full")`` for each image
    (zero outside the image), as int32. The ``kh`` rows under the kernel sit
    side by side in one 64-bit word, so ``kh * (w + 2 (kw - 1))`` must not
    exceed 64 (16-pixel rows with a 3x3 kernel use 60 bits).

    Parameters
    ----------
    x : array_like
        +-1 images, shape ``(n, h, w)`` or one ``(h, w)`` image.
    k : array_like
        +-1 kernel, shape ``(kh, kw)``.

    Returns
    -------
    numpy.ndarray
        int32, shape ``(n, h + kh - 1, w + kw - 1)`` (``n = 1`` for a single image).

    Raises
    ------
    EvtkError
        Other shapes, empty arrays, values other than -1 and +1, or rows too wide for a 64-bit word.

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


def resample_matrix(n_in: int, n_out: int) -> np.ndarray:
    """Area-overlap resampling from ``n_in`` cells to ``n_out`` (rows sum to 1), as :func:`evtk.reconstruct.downsample`.

    Parameters
    ----------
    n_in : int
        Cells along the axis before.
    n_out : int
        Cells along the axis after.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(n_out, n_in)``: output cell ``i`` is row ``i`` dotted with the input.
    """

    step = n_in / n_out
    return overlap_matrix(n_out, 0.0, step, n_in)


class DigitalBackend:
    """Exact binary correlations (bit-packed), resampled to ``size``.

    Parameters
    ----------
    size : int
        Side of the resampled responses, cells.
    """

    name = "digital"

    def __init__(self, size: int = 16) -> None:
        self.size = int(size)
        self._mats: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _resample(self, r: np.ndarray) -> np.ndarray:
        h, w = r.shape[-2:]
        key = (h, w)
        if key not in self._mats:
            self._mats[key] = (resample_matrix(h, self.size), resample_matrix(w, self.size))
        my, mx = self._mats[key]
        return np.einsum("ij,...jk,lk->...il", my, r, mx, optimize=True)

    def correlate(self, x: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(n, c_in, s, s) +-1 inputs and (c_out, c_in, kh, kw) kernels: (n, c_out, size, size) responses.

        Each output channel sums the full correlations (:func:`binary_correlate`) over the input channels,
        then resamples them by area overlap to ``size`` x ``size``.

        Parameters
        ----------
        x : numpy.ndarray
            +-1 inputs, shape ``(n, c_in, s, s)``.
        k : numpy.ndarray
            +-1 kernels, shape ``(c_out, c_in, kh, kw)``.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(n, c_out, size, size)``.
        """
        n, c_in = x.shape[:2]
        out = np.zeros((n, k.shape[0], self.size, self.size))
        for o in range(k.shape[0]):
            acc: np.ndarray | None = None
            for c in range(c_in):
                r = binary_correlate(x[:, c], k[o, c]).astype(np.float64)
                acc = r if acc is None else acc + r
            assert acc is not None, "no input channel"
            out[:, o] = self._resample(acc)
        return out


class OpticalBackend:
    """Correlations captured on the simulated device (fast path), one device, a new trial per call.

    Each (kernel, input channel) is one simulated run over all images: +-
    passes, flat fields, reconstruction on the full grid resampled to
    ``size``, summed over input channels.

    Parameters
    ----------
    bench : Bench or None
        The simulated bench; None takes the default :class:`~evtk.optics.Bench`.
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    seed : int
        The device (fixed pattern: thresholds, mismatch); every call draws fresh shot noise.
    size : int
        Side of the resampled responses, cells.
    """

    name = "optical"

    def __init__(self, bench: Bench | None = None, sensor: SensorModel | None = None, seed: int = 0,
                 size: int = 16) -> None:
        self.bench = bench if bench is not None else Bench()
        self.sensor = sensor
        self.seed = int(seed)
        self.size = int(size)
        self.calls = 0

    def correlate(self, x: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The layer's responses captured on the simulated device, one run per (kernel, input channel).

        Parameters
        ----------
        x : numpy.ndarray
            +-1 inputs, shape ``(n, c_in, s, s)``.
        k : numpy.ndarray
            +-1 kernels, shape ``(c_out, c_in, kh, kw)``.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(n, c_out, size, size)``: reconstructed responses summed over input channels, in
            the reconstruction's linearised units (noisy; a new trial per call).
        """
        n, c_in = x.shape[:2]
        out = np.zeros((n, k.shape[0], self.size, self.size))
        for o in range(k.shape[0]):
            for c in range(c_in):
                self.calls += 1
                r, _ = simulated_reconstruction(k[o, c], x[:, c], self.bench, self.sensor, repeat=1, seed=self.seed,
                                                noise_seed=self.seed * 1_000_003 + self.calls, crop="full",
                                                size=(self.size, self.size))
                assert r.pairs is not None  # a simulated run knows its pairs
                out[:, o] += r.responses[np.argsort(r.pairs[:, 1], kind="stable")]
        return out


#: What computes a layer's correlations for :class:`BCNN`.
Backend = DigitalBackend | OpticalBackend


def bce_loss(scores0: npt.ArrayLike, scores1: npt.ArrayLike, labels: npt.ArrayLike, beta: float) -> float:
    """Summed binary cross-entropy of ``p(label 1) = sigmoid(beta * (s0 - s1))`` (the lower score wins).

    Parameters
    ----------
    scores0 : array_like
        Scores of the complement mask, one per sample.
    scores1 : array_like
        Scores of the mask, one per sample.
    labels : array_like
        0/1 labels.
    beta : float
        Sharpness of the sigmoid.

    Returns
    -------
    float
        The loss in nats, summed over samples (computed without overflow).
    """
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

    Parameters
    ----------
    kernels : list of numpy.ndarray
        Per layer, int8 +-1 kernels of shape ``(c_out, c_in, 3, 3)``.
    masks : list of numpy.ndarray
        Per layer, a 0/1 mask of shape ``(size/pool, size/pool)`` or ``(c, size/pool, size/pool)``.
    thresholds : list
        Per layer, the batch-normalisation means (one per channel), or None where not fixed yet (each batch
        then uses its own mean).
    pool : int
        Side of the average pooling before scoring.
    size : int
        Side of every layer's resampled responses, cells.
    beta : float
        Sharpness of the sigmoid in :func:`bce_loss`.
    """

    kernels: list[np.ndarray]
    masks: list[np.ndarray]
    thresholds: list[Any] = field(default_factory=list)
    pool: int = 2
    size: int = 16
    beta: float = 0.25

    @classmethod
    def random(cls, layers: int = 3, channels: int = 1, size: int = 16, pool: int = 2, seed: int = 0,
               channel_masks: bool = False) -> BCNN:
        """Random kernels and masks, thresholds not fixed.

        Parameters
        ----------
        layers : int
            Number of layers (>= 1).
        channels : int
            Channels of every layer (>= 1); the first layer takes one input channel.
        size : int
            Side of the responses, cells; ``pool`` must divide it.
        pool : int
            Side of the average pooling.
        seed : int
            Seed of the draw.
        channel_masks : bool
            One mask plane per channel ``(c, s/p, s/p)`` instead of one plane scoring the channels' mean.

        Returns
        -------
        BCNN
            The network, with ``thresholds`` all None.

        Raises
        ------
        EvtkError
            No layer or channel, or a size the pooling does not divide.
        """
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
    def n_layers(self) -> int:
        """Number of layers."""
        return len(self.kernels)

    def layer(self, backend: Backend, x: np.ndarray, i: int,
              threshold: npt.ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Layer ``i`` on +-1 inputs (n, c, s, s): (binary output, responses, threshold used).

        Parameters
        ----------
        backend : DigitalBackend or OpticalBackend
            Computes the correlations.
        x : numpy.ndarray
            +-1 inputs, shape ``(n, c_in, s, s)``.
        i : int
            Which layer.
        threshold : array_like or None
            Batch-normalisation mean per output channel; None takes this batch's mean.

        Returns
        -------
        binary : numpy.ndarray
            int8 +-1 activations, shape ``(n, c_out, size, size)`` (+1 where the response reaches the threshold).
        responses : numpy.ndarray
            float64 responses before binarisation, same shape.
        threshold : numpy.ndarray
            The threshold used, one per output channel.
        """
        r = backend.correlate(x, self.kernels[i])
        thr = r.mean(axis=(0, 2, 3)) if threshold is None else np.asarray(threshold)
        a = np.where(r >= thr[None, :, None, None], 1, -1).astype(np.int8)
        return a, r, thr

    def scores(self, a: np.ndarray, mask: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Dot products of the pooled map with ``mask`` and its complement: (s0, s1).

        A 2-D mask scores the channels' mean; a 3-D one (c, s/p, s/p) each
        channel with its own plane (scaled by 1/c, like the mean).

        Parameters
        ----------
        a : numpy.ndarray
            +-1 activations, shape ``(n, c, size, size)``.
        mask : array_like
            0/1 mask, ``(size/pool, size/pool)`` or ``(c, size/pool, size/pool)``.

        Returns
        -------
        s0 : numpy.ndarray
            float64, shape ``(n,)``: scores against the complement ``1 - mask`` (label 0).
        s1 : numpy.ndarray
            float64, shape ``(n,)``: scores against ``mask`` (label 1).
        """
        pooled = pool_map(a, self.pool, per_channel=np.ndim(mask) == 3).reshape(a.shape[0], -1)
        m = np.asarray(mask, np.float64).ravel()
        return pooled @ (1 - m), pooled @ m

    def forward(self, backend: Backend, x: np.ndarray, upto: int | None = None) -> np.ndarray:
        """Binary activations after layer ``upto`` (default the last), with the stored thresholds.

        Parameters
        ----------
        backend : DigitalBackend or OpticalBackend
            Computes the correlations.
        x : numpy.ndarray
            +-1 images, ``(n, s, s)`` or ``(n, c, s, s)``.
        upto : int or None
            Last layer to run (0-based); None runs them all.

        Returns
        -------
        numpy.ndarray
            int8 +-1 activations, shape ``(n, c, size, size)``.

        Raises
        ------
        EvtkError
            If ``x`` is not +-1 images.
        """
        a = as_binary_input(x)
        for i in range(self.n_layers if upto is None else upto + 1):
            a, _, _ = self.layer(backend, a, i, self.thresholds[i])
        return a

    def decide(self, a: np.ndarray) -> np.ndarray:
        """Labels from the last layer's activations: the lower mask score gives the label.

        Parameters
        ----------
        a : numpy.ndarray
            +-1 activations of the last layer, shape ``(n, c, size, size)``.

        Returns
        -------
        numpy.ndarray
            int8 labels, shape ``(n,)``: 1 where the mask's score is below its complement's.
        """
        s0, s1 = self.scores(a, self.masks[-1])
        return (s1 < s0).astype(np.int8)

    def predict(self, backend: Backend, x: np.ndarray) -> np.ndarray:
        """Labels of images: :meth:`forward` then :meth:`decide`.

        Parameters
        ----------
        backend : DigitalBackend or OpticalBackend
            Computes the correlations.
        x : numpy.ndarray
            +-1 images, ``(n, s, s)`` or ``(n, c, s, s)``.

        Returns
        -------
        numpy.ndarray
            int8 labels (0/1), shape ``(n,)``.
        """
        return self.decide(self.forward(backend, x))

    def accuracy(self, backend: Backend, x: np.ndarray, y: npt.ArrayLike) -> float:
        """Share of images whose predicted label equals ``y``.

        Parameters
        ----------
        backend : DigitalBackend or OpticalBackend
            Computes the correlations.
        x : numpy.ndarray
            +-1 images, ``(n, s, s)`` or ``(n, c, s, s)``.
        y : array_like
            0/1 labels, shape ``(n,)``.

        Returns
        -------
        float
            Accuracy in [0, 1].
        """
        return float(np.mean(self.predict(backend, x) == np.asarray(y)))


def pool_map(a: np.ndarray, pool: int, per_channel: bool = False) -> np.ndarray:
    """Mean over ``pool`` x ``pool`` blocks of activations, averaged over the channels or per channel.

    Parameters
    ----------
    a : numpy.ndarray
        Activations, shape ``(n, c, s, s)``; ``pool`` must divide ``s``.
    pool : int
        Side of the blocks.
    per_channel : bool
        Keep the channels, each divided by ``c`` (so both forms sum to the same scale).

    Returns
    -------
    numpy.ndarray
        float64, ``(n, s/p, s/p)`` averaged over the channels too, or ``(n, c, s/p, s/p)`` with ``per_channel``.
    """
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


def poisson_robustness(model: BCNN, x: np.ndarray, y: npt.ArrayLike, scales: Iterable[float], seed: int = 0,
                       target_accuracy: float | None = None, backend: Backend | None = None,
                       client: Any = None) -> dict:
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

    Parameters
    ----------
    model : BCNN
        The network, its thresholds fixed (they are used as stored).
    x : numpy.ndarray
        +-1 images, ``(n, s, s)`` or ``(n, c, s, s)``.
    y : array_like
        0/1 labels, shape ``(n,)``.
    scales : iterable of float
        Noise scales ``s`` (finite, >= 0; 0 is noise-free), in response units per photon.
    seed : int
        Seed of the noise (each scale gets ``(seed, index)``).
    target_accuracy : float or None
        The accuracy ``r`` to keep; None takes the noise-free accuracy minus 0.05.
    backend : DigitalBackend or OpticalBackend or None
        Computes the correlations; None takes a :class:`DigitalBackend` of the model's size.
    client : distributed.Client or None
        Runs the scales on its workers (:mod:`evtk.cluster`); None runs them here.

    Returns
    -------
    dict
        ``rows`` (per scale: ``scale``, ``accuracy``, ``flip_pct``, ``flip_pct_per_layer``), ``clean_accuracy``,
        ``r`` (the accuracy kept) and ``R_pct`` (the largest flip percentage that keeps it, None if no scale does).

    Raises
    ------
    EvtkError
        Inputs that are not +-1 images, or no scales, or a scale negative or not finite.
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
