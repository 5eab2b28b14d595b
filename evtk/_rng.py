"""Random numbers inside compiled loops: xoshiro256+ seeded through splitmix64, and a ziggurat for normals.

The pixel simulation (:mod:`evtk.sensor`) draws its shot noise here, one
stream per pixel, so that a run is reproducible from its seed whatever the
number of threads.
"""

from __future__ import annotations

import math

import numpy as np

from ._lazyjit import njit  # numba loads on the first draw


@njit(cache=True)
def rng_state(seed):
    """xoshiro256+ state from a seed through splitmix64."""
    st = np.empty(4, np.uint64)
    z = np.uint64(seed) + np.uint64(0x9E3779B97F4A7C15)
    for k in range(4):
        z = z + np.uint64(0x9E3779B97F4A7C15)
        x = z
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        st[k] = x ^ (x >> np.uint64(31))
    return st


@njit(cache=True, inline="always")
def _next_u64(st):
    """The next 64-bit word of xoshiro256+ (its lowest bits are its weakest)."""
    s0, s1, s2, s3 = st[0], st[1], st[2], st[3]
    result = s0 + s3
    t = s1 << np.uint64(17)
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = (s3 << np.uint64(45)) | (s3 >> np.uint64(19))
    st[0], st[1], st[2], st[3] = s0, s1, s2, s3
    return result


@njit(cache=True, inline="always")
def uniform(st):
    """A double in [0, 1) from the 53 high bits of a draw."""
    return float(_next_u64(st) >> np.uint64(11)) * 1.1102230246251565e-16


_ZIG_R = 3.6541528853610088  # right edge of the base strip for 256 strips


def _ziggurat_tables(layers=256, r=_ZIG_R):
    """Tables of Marsaglia and Tsang's ziggurat for the standard normal.

    ``layers`` strips of equal area ``v`` under ``exp(-x^2 / 2)``: the base
    strip (index 0) is the rectangle ``[0, r] x [0, f(r)]`` plus the tail
    beyond ``r``, given the virtual width ``v / f(r)``; strip ``j >= 1`` is
    ``[0, x_{j-1}] x [f(x_{j-1}), f(x_j)]`` with ``x_0 = r`` and the top edge
    ``x_{layers-1} = 0``. Returns (width, inner edge, lower f, upper f) per
    strip; a point with ``x`` below the inner edge is under the curve.
    """
    from math import erfc, exp, log, pi, sqrt

    f = lambda x: exp(-0.5 * x * x)  # noqa: E731
    v = r * f(r) + sqrt(pi / 2) * erfc(r / sqrt(2))
    x = [r]
    for _ in range(1, layers - 1):
        x.append(sqrt(-2.0 * log(f(x[-1]) + v / x[-1])))
    x.append(0.0)
    width = np.array([v / f(r)] + x[:-1])
    inner = np.array([r] + x[1:])
    lower = np.array([0.0] + [f(a) for a in x[:-1]])
    upper = np.array([f(r)] + [f(a) for a in x[1:]])
    return width, inner, lower, upper


_ZIG_W, _ZIG_IN, _ZIG_LO, _ZIG_HI = _ziggurat_tables()


@njit(cache=True)
def _normal_tail(st):
    """A normal deviate conditioned on exceeding the ziggurat's r (Marsaglia's method)."""
    while True:
        a = -math.log(1.0 - uniform(st)) / _ZIG_R
        b = -math.log(1.0 - uniform(st))
        if 2.0 * b > a * a:
            return _ZIG_R + a


@njit(cache=True, inline="always")
def normal(st):
    """A standard normal deviate by the ziggurat (exact up to rounding; one 64-bit draw 99 % of the time).

    Bits 4-11 of the draw pick the strip, bit 3 the sign and bits 12-63 the
    position; xoshiro256+'s lowest three bits are not used.
    """
    while True:
        word = _next_u64(st)
        j = np.int64((word >> np.uint64(4)) & np.uint64(0xFF))
        x = float(np.int64(word >> np.uint64(12))) * 2.220446049250313e-16 * _ZIG_W[j]
        if x < _ZIG_IN[j]:  # inside the strip's rectangle under the curve
            return -x if (word >> np.uint64(3)) & np.uint64(1) else x
        if j == 0:
            x = _normal_tail(st)
            return -x if (word >> np.uint64(3)) & np.uint64(1) else x
        if _ZIG_LO[j] + uniform(st) * (_ZIG_HI[j] - _ZIG_LO[j]) < math.exp(-0.5 * x * x):  # in the wedge
            return -x if (word >> np.uint64(3)) & np.uint64(1) else x


@njit(cache=True)
def normal_outlined(st):
    """:func:`normal` as a call, for the less frequent draws (keeps the pixel loop's code small)."""
    return normal(st)
