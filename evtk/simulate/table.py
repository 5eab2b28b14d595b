"""The fast path's count table: a pixel's window counts tabulated over light and threshold, and drawn from.

:meth:`evtk.simulate.Simulation.responses` with ``method="table"`` reads
each pixel's counts from this table instead of running the pixel model on
it; the table itself is built with that same model.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from ..optics import brightest_response
from ..sensor import PixelState, log_noise_std, pixel_thresholds, simulate_pixels, time_constant_us

if TYPE_CHECKING:
    from .run import Simulation

__all__ = ["count_table", "table_batches"]

# count tables of the fast path, shared by simulations of the same bench, sensor and timing
_TABLES: dict = {}
_TABLES_KEPT = 8


def count_table(sim: Any) -> tuple:
    """Window counts of the pixel model, tabulated over light and ON threshold.

    ``v`` is the log-light step
    in units of the pixel's own ON threshold, ``log(rate / blank rate) /
    theta`` (about the count a noise-free slow pixel would give, so
    neighbouring cells differ little along ``theta``), from 0 to the
    brightest pattern; ``theta`` spans the ON threshold mismatch (+-4 sd),
    and ``on``/``off`` (theta, v, replicate)
    hold counts in the window of a capture that follows a settle, a
    capture at the same light and another settle (the schedule a repeated
    pair has). OFF thresholds vary between replicates as on the sensor.
    Built once per bench, sensor, timing and kernel shape (not per trial)
    with the event path's pixel model.

    Parameters
    ----------
    sim : Simulation
        The run (its bench, sensor, timing and kernel shape).

    Returns
    -------
    tuple
        ``(v_grid, theta_grid, on, off)``.
    """
    key = _table_key(sim)
    if key in _TABLES:
        return _TABLES[key]
    sm = sim.sensor
    blank = sim.blank_rate_e_per_s
    u_max = max(math.log(sim._rate(brightest_response(sim.kernels.shape[1:], sim.bench)) / blank), 1e-6) * 1.01
    spread = 4.0 * sm.theta_mismatch
    th = np.linspace(max(sm.theta_on - spread, 0.01 * sm.theta_on), sm.theta_on + spread,
                     sim.TABLE_THRESHOLD_POINTS) if spread > 0 else np.array([sm.theta_on])
    u = np.linspace(0.0, u_max / th[0], sim.TABLE_LIGHT_POINTS)  # v, in thresholds
    n_u, n_th, n_r = u.size, th.size, sim.TABLE_REPLICATES
    # the table describes the pixel model, not a trial: its draws are the same for every trial,
    # which picks among them with its own noise seed
    rng = np.random.default_rng(np.random.SeedSequence([0x7AB]))
    # pixels ordered (theta, v, replicate)
    th_on = np.repeat(th, n_u * n_r)
    _, th_off = pixel_thresholds(sm, th_on.size, rng)
    lvl_on = math.log(blank) + np.tile(np.repeat(u, n_r), n_th) * th_on
    rates = np.exp(np.stack([np.full(th_on.size, math.log(blank)), lvl_on] * 2 + [np.full(th_on.size, math.log(blank))]))
    rates[0] = blank
    lvl = np.log(rates)
    tau = time_constant_us(rates, sm)
    noise = log_noise_std(rates, sm)
    st = PixelState(lvl[0], noise[0], th_on, th_off, rng)
    w, z = float(sim.window_us), float(sim.settle_us)
    starts = np.array([0.0, z, z + w, 2 * z + w, 2 * z + 2 * w])
    ends = np.array([z, z + w, 2 * z + w, 2 * z + 2 * w, 3 * z + 2 * w])
    slot = np.array([-1, -1, -1, 0, -1])
    _, _, _, on, off = simulate_pixels(st, lvl, tau, noise, starts, ends, sm, int(rng.integers(2**31 - 1)),
                                       emit=False, count_slot=slot, n_slots=1)
    table = (u, th, on[0].reshape(n_th, n_u, n_r), off[0].reshape(n_th, n_u, n_r))
    while len(_TABLES) >= _TABLES_KEPT:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = table
    return table

def _table_key(sim):
    return json.dumps([sim.bench.to_dict(), sim.sensor.to_dict(), sim.window_us, sim.settle_us,
                       list(sim.kernels.shape[1:])], sort_keys=True)

def table_batches(sim: Simulation, region: tuple[int, int, int, int], roi_idx: np.ndarray, batch: int,
                  progress: Callable[[int], Any] | None
                  ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, int]]:
    """The fast path's counts, a batch of captures at a time, each pixel's drawn from :func:`count_table`.

    Each pixel reads the table at its own ON threshold and at its light in each capture (log rate over the
    blank rate, in units of that threshold), taking one of the two neighbouring table cells on each axis with
    the probability that interpolates linearly between them. Which threshold neighbour, which light
    neighbour's share and (without shot noise) which replicate a pixel reads follow from the device
    (``sim.seed``); with shot noise the replicate is drawn per capture from the trial (``sim.noise_seed``).

    Parameters
    ----------
    sim : Simulation
        The run: its schedule, lights, pixels' ON thresholds, sensor and seeds.
    region : tuple of int
        ``(x0, x1, y0, y1)``: the sensor pixels counted (half-open).
    roi_idx : numpy.ndarray
        Flat sensor indices (``y * width + x``) of the region's pixels, row-major, shape
        ((y1 - y0) * (x1 - x0),).
    batch : int
        Captures per batch, >= 1.
    progress : callable or None
        Called with the number of captures of each batch once the caller has taken it.

    Yields
    ------
    tuple
        ``(c0, c1, on, off, seed)``: the batch's captures ``[c0, c1)`` of the schedule, their ON and OFF
        counts (integers, shape (c1 - c0, pixels), pixels in ``roi_idx``'s order), and a seed drawn from the
        trial for what the caller adds (background activity and hot pixels).
    """
    u_grid, th_grid, t_on, t_off = count_table(sim)
    blank = sim.blank_rate_e_per_s
    theta = sim._theta_on[roi_idx]
    rng = np.random.default_rng(np.random.SeedSequence([sim.noise_seed, 0xFA5]))
    # which table neighbours a pixel reads is a property of the pixel (the device), not of
    # the trial: a noise-free pixel shown the same light twice counts the same twice
    dev = np.random.default_rng(np.random.SeedSequence([sim.seed, 0xDE7, roi_idx.size]))
    if th_grid.size > 1:
        pos = np.clip((theta - th_grid[0]) / (th_grid[1] - th_grid[0]), 0, th_grid.size - 1)
    else:
        pos = np.zeros_like(theta)
    it = np.minimum(pos.astype(np.int64) + (dev.random(theta.size) < pos - np.floor(pos)), th_grid.size - 1)
    u_pick = dev.random(theta.size)  # a mixture of the two light neighbours: linear in the mean over pixels
    n_r = t_on.shape[2]
    r_fixed = dev.integers(0, n_r, theta.size)
    du = u_grid[1] - u_grid[0]
    n = len(sim.schedule)
    for c0 in range(0, n, batch):
        c1 = min(n, c0 + batch)
        which = np.arange(c0, c1)
        lvl, _, _ = sim._levels(which, region)  # (captures, pixels) log rates
        upos = np.clip((lvl - math.log(blank)) / theta[None, :] / du, 0, u_grid.size - 1)
        i_u = upos.astype(np.int64)
        i_u += u_pick[None, :] < (upos - i_u)
        i_u = np.minimum(i_u, u_grid.size - 1)
        # replicates differ by shot noise (the trial) and by OFF threshold (the device)
        r = rng.integers(0, n_r, upos.shape) if sim.sensor.shot_noise else np.broadcast_to(r_fixed, upos.shape)
        yield c0, c1, t_on[it[None, :], i_u, r], t_off[it[None, :], i_u, r], int(rng.integers(2**31 - 1))
        if progress is not None:
            progress(c1 - c0)
