"""Optimisers for the binary CNN: layerwise gradient-free search (paper 4.2, 4.5) and a gradient reference.

* :func:`metropolis`: simulated annealing (geometric cooling from
  ``temperature`` to ``final_temperature``) or a random walk (Metropolis at
  a constant temperature) over a bit vector, one bit flipped per step.
* :func:`train_layerwise`: optimises a :class:`evtk.bcnn.BCNN` one layer at
  a time; each layer's kernels and a pair of complementary masks are scored
  by binary cross-entropy against the labels (hidden layers through their
  own masks, as in 4.5), then frozen. ``"brute"`` enumerates a layer's
  kernels when there are at most 2^12, fitting the mask by a rule.
* :func:`train_ste`: the same network trained end to end with
  straight-through gradients and Adam, in numpy: the reference the
  gradient-free results are measured against.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from .bcnn import BCNN, Backend, DigitalBackend, as_binary_input, bce_loss, pool_map, resample_matrix
from .errors import EvtkError

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["metropolis", "train_layerwise", "train_ste", "fit_mask"]


def metropolis(objective: Callable[[np.ndarray], float], n_bits: int, steps: int, temperature: float,
               final_temperature: float | None = None, seed: int = 0, start: npt.ArrayLike | None = None,
               progress: Callable[[int], Any] | None = None) -> tuple[np.ndarray, float, np.ndarray]:
    """Minimise ``objective(bits)`` over 0/1 vectors by single-bit Metropolis moves.

    With ``final_temperature`` the temperature falls geometrically from
    ``temperature`` to it over ``steps`` (simulated annealing); without, it
    stays at ``temperature`` (a random walk). Returns ``(best_bits,
    best_value, trace)``: ``trace`` holds the current value after each step.

    Parameters
    ----------
    objective : callable
        Takes an int8 0/1 vector of ``n_bits`` (modified in place between calls: copy it to keep it) and
        returns the value to minimise.
    n_bits : int
        Length of the bit vector (>= 1).
    steps : int
        Proposed single-bit flips (>= 0).
    temperature : float
        Starting (or constant) temperature, in the objective's units (positive, finite).
    final_temperature : float or None
        Temperature at the last step, in ``(0, temperature]``; None keeps it constant.
    seed : int
        Seed of the start and the moves.
    start : array_like or None
        Starting bits; None draws them.
    progress : callable, optional
        Called with 1 after each step.

    Returns
    -------
    best_bits : numpy.ndarray
        int8 0/1, shape ``(n_bits,)``: the best vector met.
    best_value : float
        Its objective.
    trace : numpy.ndarray
        float64, shape ``(steps,)``: the current value after each step.

    Raises
    ------
    EvtkError
        No bits, negative steps, or a temperature that is not positive and finite (or a final one above it).

    Examples
    --------
    >>> target = np.array([1, 0, 1, 1, 0, 0, 1, 0])
    >>> best, value, _ = metropolis(lambda b: float(np.sum(b != target)), 8, 400, 2.0, 0.01, seed=1)
    >>> value, best.tolist() == target.tolist()
    (0.0, True)
    """
    if n_bits < 1 or steps < 0:
        raise EvtkError("need at least one bit and a non-negative number of steps")
    if not (temperature > 0 and math.isfinite(temperature)):
        raise EvtkError(f"temperature must be positive and finite, not {temperature}")
    if final_temperature is not None and not (0 < final_temperature <= temperature):
        raise EvtkError("final temperature must be positive and at most the starting one")
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 2, n_bits).astype(np.int8) if start is None else np.array(start, np.int8)
    value = objective(bits)
    best, best_value = bits.copy(), value
    trace = np.empty(steps)
    ratio = 1.0 if final_temperature is None else final_temperature / temperature
    for s in range(steps):
        t = temperature * ratio ** (s / max(steps - 1, 1))
        i = int(rng.integers(n_bits))
        bits[i] ^= 1
        new = objective(bits)
        if new <= value or rng.random() < math.exp(-(new - value) / t):
            value = new
            if value < best_value:
                best, best_value = bits.copy(), value
        else:
            bits[i] ^= 1
        trace[s] = value
        if progress is not None:
            progress(1)
    return best, best_value, trace


def fit_mask(a: np.ndarray, y: npt.ArrayLike, pool: int, per_channel: bool = False) -> np.ndarray:
    """The mask rule: a pooled cell scores class 1 where class 1's mean activation is lower there.

    Parameters
    ----------
    a : numpy.ndarray
        +-1 activations, shape ``(n, c, s, s)``.
    y : array_like
        0/1 labels, shape ``(n,)``.
    pool : int
        Side of the average pooling.
    per_channel : bool
        One mask plane per channel (as :meth:`evtk.bcnn.BCNN.scores` takes a 3-D mask).

    Returns
    -------
    numpy.ndarray
        int8 0/1 mask, ``(s/pool, s/pool)`` or ``(c, s/pool, s/pool)`` with ``per_channel``.
    """
    pooled = pool_map(a, pool, per_channel)
    y = np.asarray(y)
    m1 = pooled[y == 1].mean(axis=0) if np.any(y == 1) else np.zeros(pooled.shape[1:])
    m0 = pooled[y == 0].mean(axis=0) if np.any(y == 0) else np.zeros(pooled.shape[1:])
    return (m1 < m0).astype(np.int8)


class _LayerObjective:
    """Loss of one layer's (kernel bits, mask bits), caching responses per kernel."""

    def __init__(self, model, backend, x, y, i):
        self.model, self.backend, self.x, self.y, self.i = model, backend, x, y, i
        self.kshape = model.kernels[i].shape
        self.n_kernel_bits = int(np.prod(self.kshape))
        self.mask_shape = model.masks[i].shape
        self._cache = {}  # kernel bytes -> (activations, thresholds); the current and the last proposal
        self.kernel_evaluations = 0

    def split(self, bits):
        k = np.where(bits[: self.n_kernel_bits] > 0, 1, -1).astype(np.int8).reshape(self.kshape)
        return k, bits[self.n_kernel_bits:].reshape(self.mask_shape)

    def activations(self, k):
        key = k.tobytes()
        if key not in self._cache:
            self.model.kernels[self.i] = k
            act, _, thr = self.model.layer(self.backend, self.x, self.i)
            if len(self._cache) >= 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = (act, thr)
            self.kernel_evaluations += 1
        else:  # most recently used last
            self._cache[key] = self._cache.pop(key)
        return self._cache[key]

    def __call__(self, bits):
        k, mask = self.split(bits)
        a, _ = self.activations(k)
        s0, s1 = self.model.scores(a, mask)
        return bce_loss(s0, s1, self.y, self.model.beta)


def train_layerwise(model: BCNN, backend: Backend, x: np.ndarray, y: npt.ArrayLike, optimizer: str = "anneal",
                    steps: int = 600, temperature: float = 10.0, final_temperature: float = 0.01, seed: int = 0,
                    progress: Callable[[int], Any] | None = None) -> dict:
    """Optimise ``model`` layer by layer on (x, y); returns a record with per-layer traces and timing.

    ``optimizer``: "anneal" (``temperature`` falling to ``final_temperature``
    over ``steps`` per layer), "walk" (constant ``temperature``) or "brute"
    (every kernel of a layer, mask by :func:`fit_mask`; at most 2^12 kernel
    bits combinations). The loss is the summed binary cross-entropy.

    Parameters
    ----------
    model : BCNN
        The network; its kernels, masks and thresholds are replaced in place, layer by layer.
    backend : DigitalBackend or OpticalBackend
        Computes the correlations.
    x : numpy.ndarray
        +-1 training images, ``(n, s, s)`` or ``(n, c, s, s)``.
    y : array_like
        0/1 labels, one per image.
    optimizer : {"anneal", "walk", "brute"}
        The search.
    steps : int
        Metropolis steps per layer (not used by "brute").
    temperature : float
        Starting (anneal) or constant (walk) temperature, in nats of the loss.
    final_temperature : float
        The annealing's last temperature.
    seed : int
        Seed of the searches.
    progress : callable, optional
        Called with 1 after each step or kernel tried.

    Returns
    -------
    dict
        ``optimizer``, ``steps_per_layer``, ``layers`` (per layer: ``loss``, ``trace``,
        ``kernel_evaluations``), ``seconds`` and ``steps``.

    Raises
    ------
    EvtkError
        An unknown optimizer, labels that are not 0/1 one per image, inputs that are not +-1 images, or brute
        force over more than 2^12 kernels.
    """
    if optimizer not in ("anneal", "walk", "brute"):
        raise EvtkError(f"optimizer must be 'anneal', 'walk' or 'brute', not {optimizer!r}")
    x = as_binary_input(x)
    y = np.asarray(y)
    if len(y) != len(x) or not np.isin(y, (0, 1)).all():
        raise EvtkError("labels must be 0/1, one per image")
    t0 = time.perf_counter()
    record: dict[str, Any] = {"optimizer": optimizer, "layers": [], "steps_per_layer": int(steps)}
    a = x
    rng = np.random.default_rng(seed)
    for i in range(model.n_layers):
        obj = _LayerObjective(model, backend, a, y, i)
        n_bits = obj.n_kernel_bits + int(np.prod(obj.mask_shape))
        if optimizer == "brute":
            if obj.n_kernel_bits > 12:
                raise EvtkError(f"brute force over 2^{obj.n_kernel_bits} kernels is too many; anneal instead")
            best, best_value, values = None, np.inf, []
            for code in range(2 ** obj.n_kernel_bits):
                kb = ((code >> np.arange(obj.n_kernel_bits)) & 1).astype(np.int8)
                act, _ = obj.activations(obj.split(np.r_[kb, np.zeros(n_bits - kb.size, np.int8)])[0])
                bits = np.r_[kb, fit_mask(act, y, model.pool, len(obj.mask_shape) == 3).ravel()]
                v = obj(bits)
                values.append(v)
                if v < best_value:
                    best, best_value = bits, v
                if progress is not None:
                    progress(1)
            trace = np.asarray(values)
        else:
            start = np.r_[(model.kernels[i].ravel() > 0).astype(np.int8), model.masks[i].ravel()]
            best, best_value, trace = metropolis(obj, n_bits, steps, temperature,
                                                 final_temperature if optimizer == "anneal" else None,
                                                 seed=int(rng.integers(2**31 - 1)), start=start, progress=progress)
        k, mask = obj.split(best)
        model.masks[i] = mask.astype(np.int8)
        a, thr = obj.activations(k)
        model.kernels[i] = k
        model.thresholds[i] = thr
        record["layers"].append({"loss": float(best_value), "trace": trace.tolist(),
                                 "kernel_evaluations": obj.kernel_evaluations})
    record["seconds"] = time.perf_counter() - t0
    record["steps"] = int(sum(len(layer["trace"]) for layer in record["layers"]))
    return record


# -- straight-through reference ----------------------------------------------------------

def _im2col(a, kh, kw):
    """(n, c, s, s) -> (n, c*kh*kw, (s+kh-1)*(s+kw-1)) patches of the zero-padded input (full correlation)."""
    n, c, h, w = a.shape
    p = np.pad(a, ((0, 0), (0, 0), (kh - 1, kh - 1), (kw - 1, kw - 1)))
    oh, ow = h + kh - 1, w + kw - 1
    cols = np.empty((n, c, kh, kw, oh, ow), a.dtype)
    for r in range(kh):
        for q in range(kw):
            cols[:, :, r, q] = p[:, :, r:r + oh, q:q + ow]
    return cols.reshape(n, c * kh * kw, oh * ow)


def _col2im(g, shape, kh, kw):
    n, c, h, w = shape
    oh, ow = h + kh - 1, w + kw - 1
    g = g.reshape(n, c, kh, kw, oh, ow)
    p = np.zeros((n, c, h + 2 * (kh - 1), w + 2 * (kw - 1)))
    for r in range(kh):
        for q in range(kw):
            p[:, :, r:r + oh, q:q + ow] += g[:, :, r, q]
    return p[:, :, kh - 1:kh - 1 + h, kw - 1:kw - 1 + w]


def train_ste(model: BCNN, x: np.ndarray, y: npt.ArrayLike, epochs: int = 300, lr: float = 0.02,
              seed: int = 0) -> dict:
    """Train ``model`` end to end with straight-through gradients (sign forward, clipped identity back) and Adam.

    Latent real weights for kernels and the output mask; batch normalisation
    divides by the batch standard deviation (which does not change a sign);
    loss the mean binary cross-entropy. The trained model's kernels, output
    mask and thresholds are set for the digital or optical backend.

    Parameters
    ----------
    model : BCNN
        The network (its shapes, pooling and ``beta``); kernels, masks and thresholds are replaced in place.
    x : numpy.ndarray
        +-1 training images, ``(n, s, s)`` or ``(n, c, s, s)``.
    y : array_like
        0/1 labels, one per image.
    epochs : int
        Full-batch Adam steps.
    lr : float
        Adam's learning rate.
    seed : int
        Seed of the latent weights.

    Returns
    -------
    dict
        ``optimizer`` (``"ste"``), ``losses`` (the mean loss, nats, per epoch) and ``epochs``.

    Raises
    ------
    EvtkError
        If ``x`` is not +-1 images.
    """
    x = as_binary_input(x).astype(np.float64)
    y = np.asarray(y, np.float64)
    rng = np.random.default_rng(seed)
    n, _, s, _ = x.shape
    p = model.pool
    w = [rng.normal(0, 0.5, k.shape) for k in model.kernels]
    m = rng.normal(0, 0.5, model.masks[-1].shape)
    params = w + [m]
    adam_m = [np.zeros_like(q) for q in params]
    adam_v = [np.zeros_like(q) for q in params]
    my = mx = None
    losses = []
    for ep in range(int(epochs)):
        # forward
        cache = []
        a = x
        for k in w:
            kb = np.where(k >= 0, 1.0, -1.0)
            co, ci, kh, kw = kb.shape
            cols = _im2col(a, kh, kw)
            full = np.einsum("ok,nkp->nop", kb.reshape(co, -1), cols).reshape(n, co, s + kh - 1, s + kw - 1)
            if my is None or mx is None:
                my, mx = resample_matrix(s + kh - 1, s), resample_matrix(s + kw - 1, s)
            r = np.einsum("ij,nojk,lk->noil", my, full, mx, optimize=True)
            mu = r.mean(axis=(0, 2, 3), keepdims=True)
            sd = r.std(axis=(0, 2, 3), keepdims=True) + 1e-8
            z = (r - mu) / sd
            a_next = np.where(z >= 0, 1.0, -1.0)
            cache.append((a, cols, kb, z, sd))
            a = a_next
        co = a.shape[1]
        per_channel = m.ndim == 3
        pooled = pool_map(a, p, per_channel)
        mb = (m >= 0).astype(np.float64)
        logit = model.beta * (pooled.reshape(n, -1) @ (1 - 2 * mb).ravel())
        prob = 1 / (1 + np.exp(-np.clip(logit, -50, 50)))
        losses.append(float(np.mean(np.logaddexp(0, -logit) * y + np.logaddexp(0, logit) * (1 - y))))
        # backward
        g_logit = (prob - y) / n * model.beta
        g_pooled = g_logit.reshape((n,) + (1,) * mb.ndim) * (1 - 2 * mb)
        g_mb = -2 * (g_logit @ pooled.reshape(n, -1)).reshape(mb.shape)
        grads = [None] * len(w) + [g_mb * (np.abs(m) <= 1)]
        g_up = g_pooled if per_channel else g_pooled[:, None]
        g_a = np.repeat(np.repeat(g_up, p, axis=2), p, axis=3) / (co * p * p)
        g_a = np.broadcast_to(g_a, a.shape)
        for li in range(len(w) - 1, -1, -1):
            a_in, cols, kb, z, sd = cache[li]
            g_z = g_a * (np.abs(z) <= 1)
            g_r = (g_z - g_z.mean(axis=(0, 2, 3), keepdims=True)
                   - z * (g_z * z).mean(axis=(0, 2, 3), keepdims=True)) / sd
            assert my is not None and mx is not None  # set by the forward pass
            g_full = np.einsum("ji,nojk,kl->noil", my, g_r, mx, optimize=True)
            co_, ci, kh, kw = kb.shape
            gf = g_full.reshape(n, co_, -1)
            g_kb = np.einsum("nop,nkp->ok", gf, cols).reshape(kb.shape)
            grads[li] = g_kb * (np.abs(w[li]) <= 1)
            if li > 0:
                g_cols = np.einsum("ok,nop->nkp", kb.reshape(co_, -1), gf)
                g_a = _col2im(g_cols, a_in.shape, kh, kw)
        # Adam
        for j, (q, g) in enumerate(zip(params, grads)):
            adam_m[j] = 0.9 * adam_m[j] + 0.1 * g
            adam_v[j] = 0.999 * adam_v[j] + 0.001 * g * g
            mhat = adam_m[j] / (1 - 0.9 ** (ep + 1))
            vhat = adam_v[j] / (1 - 0.999 ** (ep + 1))
            q -= lr * mhat / (np.sqrt(vhat) + 1e-8)

    model.kernels = [np.where(k >= 0, 1, -1).astype(np.int8) for k in w]
    model.masks = [np.where(m >= 0, 1, 0).astype(np.int8)] * model.n_layers
    backend = DigitalBackend(model.size)
    a = as_binary_input(x.astype(np.int8))
    for i in range(model.n_layers):
        a, _, model.thresholds[i] = model.layer(backend, a, i)
    return {"optimizer": "ste", "losses": losses, "epochs": int(epochs)}
