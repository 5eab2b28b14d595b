"""Noise experiments on recordings and on the simulated bench: per-scene SINAD and flips, power sweeps, error against time.

* :func:`scene_noise`: SINAD/ENOB and flip rates of every scene (kernel,
  features) of a reconstruction, over its repeats; :func:`recording_noise`
  the same straight from a recording, in bounded memory.
* :func:`flip_sweep`: the paper's Fig. 3 (right) on the simulated bench:
  flip rates of several kernels against laser power.
* :func:`tradeoff`: error, ENOB and flips against device time per capture
  over capture windows (and powers), with the Pareto front marked.

The simulated runs use the simulator's fast path (counts without events,
:meth:`evtk.simulate.Simulation.responses`) and
:func:`evtk.reconstruct.reconstruct_counts`; :func:`tradeoff` also times the
event path's reconstruction of a written recording, which is what a bench
user waits for.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np

from ._native import net_sums as native_net_sums
from ._parallel import cuts, parts, run
from .errors import EvtkError
from .io import open as open_recording
from .limits import memory_limit_bytes, require_memory, require_window_work
from .metrics import SinadAccumulator, flip_rates, flip_rates_bytes
from .reconstruct import (
    WindowCounts,
    binarize,
    binarize_rule,
    downsample,
    plan,
    window_bytes,
)
from .reconstruct.accumulate import accumulate_batches
from .reconstruct.fixed import (
    count_batches,
    fixed_supported,
    linear_without_plan,
    net_count_batches,
    pixel_values,
)

if TYPE_CHECKING:
    import numpy.typing as npt

if TYPE_CHECKING:  # (the simulator, the optics and the per-pixel stages load where a function needs them:
    # measuring fixed windows needs none of them)
    from .io.base import BaseRecording
    from .optics import Bench
    from .reconstruct import Reconstruction
    from .sensor import SensorModel
    from .simulate import Simulation

__all__ = ["scene_noise", "recording_noise", "random_kernels", "simulated_reconstruction", "flip_sweep", "tradeoff",
           "pareto_front"]


def scene_noise(result: Reconstruction, interval: str | None = "jackknife", per_pixel: bool = False,
                seed: int = 0) -> list:
    """SINAD/ENOB (eq. 8) and flip rates of each scene of a reconstruction, over its repeats.

    Returns one dict per scene with at least two repeats: ``kernel_id``,
    ``features_id``, ``repeats``, ``sinad`` (:class:`evtk.metrics.SinadReport`
    of the signed responses on the cell grid, with an ``interval`` as in
    :func:`evtk.metrics.sinad`), ``flips`` (:class:`evtk.metrics.FlipReport`
    of the binary responses) and, for simulated recordings, ``error`` (mean
    correlation and NRMSE of the repeats against the ideal). Scenes whose
    responses are all zero get ``sinad = None``.

    Parameters
    ----------
    result : Reconstruction
        A reconstruction (:func:`evtk.reconstruct.reconstruct`).
    interval : "jackknife", "bootstrap" or None
        The SINAD's interval over repeats (:func:`evtk.metrics.sinad`).
    per_pixel : bool
        Also report each cell's SINAD.
    seed : int
        Seed of a bootstrap interval.

    Returns
    -------
    list of dict
        One row per scene captured at least twice, with the keys above.

    Raises
    ------
    EvtkError
        When no scene was captured at least twice.
    """

    out = []
    route = result.summary.get("route")
    for (k, f), idx in result.groups().items():
        if idx.size < 2:
            continue
        acc = SinadAccumulator(idx.size, result.cells.shape[1:], per_pixel=per_pixel)
        acc.add(result.cells[idx])
        row = _scene_row(k, f, acc, result.binary[idx], interval, per_pixel, seed)
        if route:
            row["route"] = route
        if result.ideal is not None:
            from .reconstruct import response_error

            errs = [response_error(result.cells[i], result.ideal[i]) for i in idx]
            row["error"] = {key: _mean_defined([e[key] for e in errs]) for key in ("correlation", "nrmse",
                                                                                    "nrmse_range")}
        out.append(row)
    if not out:
        raise EvtkError("no scene was captured at least twice: SINAD and flip rates need repeats")
    return out


def _scene_row(kernel_id, features_id, acc, binary, interval, per_pixel, seed):
    try:
        s = acc.report(per_pixel=per_pixel, interval=interval, seed=seed)
    except EvtkError as exc:
        if "zero everywhere" not in str(exc):
            raise
        s = None
    return {"kernel_id": int(kernel_id), "features_id": int(features_id), "repeats": int(acc.repeats), "sinad": s,
            "flips": flip_rates(binary)}


#: Most memory one batch of windows of :func:`recording_noise` may take, in bytes.
NOISE_BATCH_BYTES = 256 << 20

#: Most net counts (int32) one batch of :func:`recording_noise`'s net-count route holds (16 MB); a batch is one
#: group of the accumulator's repeats where that fits.
NOISE_NET_BINS = 1 << 22


def recording_noise(rec: BaseRecording, window: str | tuple[str, int] = "schedule", skip_us: int = 0,
                    length_us: int | None = None, interval: str | None = "jackknife", per_pixel: bool = False,
                    seed: int = 0, progress: Callable[[int], Any] | None = None, **options: Any) -> list:
    """:func:`scene_noise` of an open recording, in memory bounded by a batch of windows when it can be.

    Windows without a capture schedule (``"triggers"`` or ``("period",
    US)``) are repeats of one scene and independent of each other: they are
    reconstructed a batch at a time (at most :data:`NOISE_BATCH_BYTES`, and
    within the memory budget) and fed to one
    :class:`evtk.metrics.SinadAccumulator`, so a minute of 10 ms windows over
    a whole sensor is measured in one pass. A scheduled (simulated) recording
    ties its windows together (passes, flat fields) and is reconstructed
    whole. Fixed windows give net counts ON - OFF, or ``exp(n theta)`` where
    ``theta`` is given; the row's ``"route"`` says which. Net counts are
    counted into int16 (or int32) frames a group of the accumulator's repeats at a time
    (:func:`evtk.reconstruct.fixed.net_count_batches`, at most
    :data:`NOISE_NET_BINS` counts) and summed exactly in integers; no float
    value of a window's pixel is formed.

    Before any window is counted, the memory of one batch, the accumulator
    and the flip rates is checked against the budget
    (:func:`evtk.limits.require_memory`), and the windows' work against
    what the recording's events justify
    (:func:`evtk.limits.require_window_work`): a file of two events
    stamped far apart cannot ask for billions of windows.

    Parameters
    ----------
    rec : Recording
        An open recording.
    window : "schedule", "triggers" or ("period", period_us)
        How to cut the windows.
    skip_us : int
        Delay the start of every window, us.
    length_us : int or None
        Cut every window to this length, us (None: as long as it is).
    interval : "jackknife", "bootstrap" or None
        The SINAD's interval over repeats (:func:`evtk.metrics.sinad`).
    per_pixel : bool
        Also report each pixel's SINAD.
    seed : int
        Seed of a bootstrap interval.
    progress : callable, optional
        Called with the number of events counted.
    **options : Any
        Go to :func:`evtk.reconstruct.reconstruct_counts` (``linear``,
        ``theta``, ``binarize_method``, ``size``, ...); ``region`` picks the
        pixels.

    Returns
    -------
    list of dict
        One row per scene, as :func:`scene_noise` gives.

    Raises
    ------
    EvtkError
        No scene captured twice, more memory than the budget, or more windows than the events justify.
    """

    sim, win, region = plan(rec, window, skip_us, length_us, options.pop("region", None), check_memory=False)
    if sim is not None:
        from .reconstruct import ORACLE_ROUTE, reconstruct  # (here: fixed windows need neither)

        result = reconstruct(rec, window=window, skip_us=skip_us, length_us=length_us, region=region, progress=progress,
                             **options)
        result.summary["route"] = ORACLE_ROUTE
        return scene_noise(result, interval=interval, per_pixel=per_pixel, seed=seed)
    if len(win) < 2:
        raise EvtkError("no scene was captured at least twice: SINAD and flip rates need repeats")
    x0, x1, y0, y1 = region
    pixels = (x1 - x0) * (y1 - y0)
    spec = f"period:{window[1]}" if isinstance(window, tuple) else str(window)
    span = f"--window {spec} over {int(win.t_start_us[0]):,} .. {int(win.t_end_us[-1]):,} us"
    require_window_work(len(win), pixels, rec.info()["events"], span)
    out_px = math.prod(options.get("size", (16, 16)))
    # what stays for the whole run: the accumulator, the responses and binary responses, the flip rates' copies
    fixed = (SinadAccumulator.bytes_needed(len(win), pixels) + 9 * len(win) * out_px  # responses, binary ones
             + flip_rates_bytes(len(win), out_px))
    per_window = max(1, window_bytes(region, False))
    require_memory(fixed + per_window, f"{span}: measuring {len(win):,} windows over {x1 - x0}x{y1 - y0} pixels")
    batch = max(1, min(NOISE_BATCH_BYTES, (memory_limit_bytes() - fixed) // 2) // per_window)
    # the linearisation reconstruct_counts chooses without a plan: net counts unless a theta was given
    theta = options.get("theta")
    linear = linear_without_plan(options.get("linear", True), theta)
    acc: SinadAccumulator | None = None
    binary: np.ndarray | None = None
    if fixed_supported(dict(options, skip_us=skip_us, length_us=length_us)):
        # numpy alone (no compiler, no scipy): each batch's counts, each pixel's value as reconstruct_counts
        # gives it without a plan, and the responses binarised as it binarises them
        rows, cols = (int(v) for v in options.get("size", (16, 16)))
        size = (rows, cols)
        method = options.get("binarize_method", "auto")
        method = binarize_rule(None) if isinstance(method, str) and method == "auto" else method
        acc = SinadAccumulator(len(win), (y1 - y0, x1 - x0), per_pixel=per_pixel)
        binary = np.empty((len(win),) + size, np.int8)
        if linear and theta is not None:
            for i, on, off, _ in count_batches(rec, win, region, None, 0, batch, progress=progress):  # (checked)
                values = pixel_values(on, off, linear, float(theta))
                acc.add(values)
                binary[i:i + len(values)] = binarize(downsample(values, size), method)
        else:  # net counts: one signed int32 frame a window, summed exactly in integers by the accumulator
            # batches within the accumulator's groups of repeats (each group summed once), cut to the cap
            nb = max(1, min(NOISE_NET_BINS, (memory_limit_bytes() - fixed) // 8) // pixels)
            require_memory(fixed + 4 * (nb * pixels + 1), f"{span}: measuring {len(win):,} windows over "
                           f"{x1 - x0}x{y1 - y0} pixels, {nb:,} at a time")
            starts = acc.group_starts.tolist()
            # the kernel's int64 block sums hold any window's counts (each below 2**31) where a block holds fewer
            # than 2**32 pixels
            size_fits = pixels // (rows * cols) < 2**32
            firsts = [i for a, z in zip(starts, starts[1:] + [len(win)]) for i in range(a, z, nb)]
            responses = np.empty(binary.shape)
            sums_out = (np.empty((y1 - y0, x1 - x0), np.int64), np.empty((y1 - y0, x1 - x0), np.int64))
            for i, net, most in net_count_batches(rec, win, region, firsts, progress=progress):
                # the compiled kernel's sums in one pass, the GIL released, where built (numpy's otherwise), into
                # the same two arrays batch after batch (the accumulator copies what it keeps)
                sums = native_net_sums(net, size, sums_out) if size_fits else None
                if sums is not None and acc.add_sums(len(net), sums[0], sums[1], sums[2]):
                    if sums[3] is not None:  # the blocks' exact sums over their pixel count: their means
                        np.divide(sums[3], net[0].size // (rows * cols), out=responses[i:i + len(net)])
                    else:
                        responses[i:i + len(net)] = _net_block_means(net, size, sums[2])
                    continue
                big = acc.add(net)  # the largest magnitude (the events of a window only bound it)
                responses[i:i + len(net)] = _net_block_means(net, size, most if big is None else big)
            binary[:] = binarize(responses, method)  # each response at its own threshold: one call for all
    else:
        from .reconstruct import reconstruct_counts

        for i, counts in accumulate_batches(rec, win, region, batch, progress=progress, reuse=True):
            part = reconstruct_counts(counts, None, skip_us=skip_us, length_us=length_us, **options)
            if acc is None:
                acc = SinadAccumulator(len(win), part.cells.shape[1:], per_pixel=per_pixel)
                binary = np.empty((len(win),) + part.binary.shape[1:], part.binary.dtype)
            assert acc is not None and binary is not None  # made by the first batch
            acc.add(part.cells)
            binary[i:i + batch] = part.binary
    row = _scene_row(-1, -1, acc, binary, interval, per_pixel, seed)
    row["route"] = f"fixed windows (--window {spec}): " + (
        f"exp(n theta), theta = {theta:g}" if linear else "net counts (ON - OFF), not linearised")
    return [row]


def _net_block_means(net: np.ndarray, size: tuple[int, int], most: int) -> np.ndarray:
    """:func:`evtk.reconstruct.downsample` of integer net counts (magnitudes at most ``most``): for whole factors
    each block's exact integer sum over its pixel count (what the float block mean gives, without a float copy of
    every pixel)."""
    h, w = net.shape[-2:]
    oh, ow = size
    if h % oh or w % ow:
        return downsample(net, size)
    fy, fx = h // oh, w // ow
    out = np.empty((net.shape[0], oh, ow))

    def part(a: int, z: int) -> None:  # windows a .. z - 1 (runs of windows on the counting threads)
        blocks = net[a:z].reshape(z - a, oh, fy, w)
        # einsum sums in its input's type: whole rows in it where they cannot leave it (int16 counts), then the
        # rows' sums in int32 where they cannot overflow it, else in int64
        wide = np.int32 if fy * fx * most < 2**31 else np.int64
        if fy * most > np.iinfo(blocks.dtype).max:
            blocks = blocks.astype(wide)
        rows = np.einsum("naxw->naw", blocks)  # whole rows first
        if fy * fx * most > np.iinfo(rows.dtype).max:
            rows = rows.astype(wide)
        np.divide(np.einsum("naox->nao", rows.reshape(z - a, oh, ow, fx)), fy * fx, out=out[a:z])

    bounds = cuts(np.ones(net.shape[0], np.int64), parts(net.size))
    run(part, list(zip(bounds, bounds[1:])))
    return out


def _mean_defined(values):
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None


def random_kernels(n: int, shape: tuple[int, int] = (3, 3), seed: int = 0) -> np.ndarray:
    """``n`` distinct signed (+-1) kernels, drawn uniformly (at most ``2 ** size`` of them).

    Parameters
    ----------
    n : int
        How many (>= 1).
    shape : tuple of int
        ``(rows, cols)`` of each kernel.
    seed : int
        Seed of the draw.

    Returns
    -------
    numpy.ndarray
        int8 in {-1, +1}, shape ``(n, rows, cols)``, no two alike.

    Raises
    ------
    EvtkError
        When ``n`` is below 1 or more than the distinct kernels of that shape.
    """
    size = int(np.prod(shape))
    if n < 1 or (size < 63 and n > 2 ** size):
        raise EvtkError(f"cannot draw {n} distinct {shape[0]}x{shape[1]} kernels")
    rng = np.random.default_rng(seed)
    seen: set[bytes] = set()
    out: list[np.ndarray] = []
    while len(out) < n:
        k = rng.choice(np.array([-1, 1], np.int8), size)
        if k.tobytes() not in seen:
            seen.add(k.tobytes())
            out.append(k.reshape(shape))
    return np.stack(out)


@overload
def simulated_reconstruction(
    kernels: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None,
    sensor: SensorModel | None = None, window_us: int = 1000, repeat: int = 10, seed: int = 0,
    noise_seed: int | None = None, settle_us: int | None = None, flat_field: int = 2, method: str = "fast",
    timed: Literal[False] = False, **options: Any,
) -> tuple[Reconstruction, Simulation]: ...


@overload
def simulated_reconstruction(
    kernels: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None,
    sensor: SensorModel | None = None, window_us: int = 1000, repeat: int = 10, seed: int = 0,
    noise_seed: int | None = None, settle_us: int | None = None, flat_field: int = 2, method: str = "fast", *,
    timed: Literal[True], **options: Any,
) -> tuple[Reconstruction, Simulation, float]: ...


def simulated_reconstruction(
    kernels: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None,
    sensor: SensorModel | None = None, window_us: int = 1000, repeat: int = 10, seed: int = 0,
    noise_seed: int | None = None, settle_us: int | None = None, flat_field: int = 2, method: str = "fast",
    timed: bool = False, **options: Any,
) -> tuple[Reconstruction, Simulation] | tuple[Reconstruction, Simulation, float]:
    """Simulate a run and reconstruct it; returns ``(Reconstruction, Simulation)``.

    ``method="fast"`` reconstructs the simulator's fast-path counts
    (:func:`evtk.reconstruct.reconstruct_counts`); ``"events"`` writes the
    event stream to a temporary AEDAT4 file and reconstructs that, as a
    bench recording would be. ``options`` go to the reconstruction (size,
    binarize_method, crop, deblur, ...). With ``timed`` the reconstruction
    runs a second time, warm, and ``(Reconstruction, Simulation, seconds)``
    is returned: the time of exactly the pipeline whose result is returned.

    Parameters
    ----------
    kernels : array_like
        Kernels, ``(n, kh, kw)`` or one ``(kh, kw)``; 0/1, or signed (split into +- passes).
    features : array_like
        Features, ``(m, fh, fw)`` or one ``(fh, fw)``.
    bench : Bench or None
        The simulated bench (None: the default).
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    window_us : int
        How long each pattern is shown, us.
    repeat : int
        Captures of each (kernel, features) pair.
    seed : int
        The device (fixed pattern noise).
    noise_seed : int or None
        The trial's shot noise (None: derived from ``seed``).
    settle_us : int or None
        Dark time after each pattern, us (None: the simulator's recommendation).
    flat_field : int
        Flat-field captures before the run.
    method : {"fast", "events"}
        Count path or a written event stream.
    timed : bool
        Time a second, warm reconstruction.
    **options : Any
        Go to the reconstruction.

    Returns
    -------
    tuple
        ``(Reconstruction, Simulation)``, or ``(Reconstruction, Simulation, seconds)`` with ``timed``.

    Raises
    ------
    EvtkError
        An unknown method, or what the simulator or the reconstruction refuses.
    """

    from .reconstruct import reconstruct_counts
    from .simulate import Simulation

    sim = Simulation(kernels, features, bench=bench, sensor=sensor, window_us=window_us, settle_us=settle_us,
                     repeat=repeat, seed=seed, noise_seed=noise_seed, flat_field=flat_field)

    def run(work: Callable[[], Reconstruction]) -> tuple[Reconstruction, Simulation] | tuple[
            Reconstruction, Simulation, float]:
        result = work()  # with timed, also the warm-up: JIT caches, the count curve, imports
        if not timed:
            return result, sim
        t0 = time.perf_counter()
        work()
        return result, sim, time.perf_counter() - t0

    if method == "fast":
        counts = WindowCounts.from_capture_counts(sim.responses())
        return run(lambda: reconstruct_counts(counts, sim.record(), **options))
    if method != "events":
        raise EvtkError(f"method must be 'fast' or 'events', not {method!r}")

    import tempfile  # for the simulated run's file only: with shutil, bz2, lzma and random, 2-3 ms of every start

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.aedat4")
        sim.write(path)
        from .reconstruct import reconstruct

        with open_recording(path) as rec:
            return run(lambda: reconstruct(rec, **options))


def _positive_list(values: Iterable[float], name: str) -> list[float]:
    v = [float(x) for x in values]
    if not v or not all(math.isfinite(x) and x > 0 for x in v):
        raise EvtkError(f"{name} must be one or more positive numbers")
    return v


def flip_sweep(powers_mw: Iterable[float], kernels: npt.ArrayLike, features: npt.ArrayLike, repeats: int = 10,
               bench: Bench | None = None, sensor: SensorModel | None = None, window_us: int = 1000,
               seed: int = 0, progress: Callable[[int], Any] | None = None, client: Any = None) -> list:
    """Flip rates against laser power (the paper's Fig. 3, right), on the simulated bench.

    For each power, every kernel is paired with ``features`` and captured
    ``repeats`` times (one device: ``seed``; one trial per power); the
    16x16 sign-binarised responses are compared between repeats. Returns
    one row per (power, kernel): ``power_mw``, ``kernel_id``,
    ``pairwise_pct``, ``majority_pct``, ``enob_bits`` (None when noise-free),
    ``correlation``. Powers run as independent tasks (on ``client``'s
    workers when given; :mod:`evtk.cluster`).

    Parameters
    ----------
    powers_mw : iterable of float
        Laser powers, mW (positive).
    kernels : array_like
        Kernels, ``(n, kh, kw)``.
    features : array_like
        The features every kernel is paired with.
    repeats : int
        Captures of each pair (>= 2).
    bench : Bench or None
        The simulated bench (None: the default); its power is replaced.
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    window_us : int
        How long each pattern is shown, us.
    seed : int
        The device; each power gets its own shot noise.
    progress : callable, optional
        Called with 1 after each power.
    client : distributed.Client or None
        Runs the powers on its workers.

    Returns
    -------
    list of dict
        One row per (power, kernel), with the keys above.

    Raises
    ------
    EvtkError
        A power that is not positive, or fewer than two repeats.
    """

    powers = _positive_list(powers_mw, "powers_mw")
    if int(repeats) < 2:
        raise EvtkError("a flip rate needs at least two repeats")
    from .optics import Bench

    bench = bench if bench is not None else Bench()
    tasks = [(p, j, np.asarray(kernels), np.asarray(features), int(repeats), bench, sensor, window_us, seed)
             for j, p in enumerate(powers)]
    from .cluster import run_tasks  # (its sockets and temporary files load only for a sweep)

    return [row for rows in run_tasks(_flip_task, tasks, client, progress) for row in rows]


def _flip_task(args):
    p, j, kernels, features, repeats, bench, sensor, window_us, seed = args
    result, _ = simulated_reconstruction(kernels, features, bench.replace(power_mw=p), sensor, window_us, repeats,
                                         seed=seed, noise_seed=seed * 1000 + j + 1)
    rows = []
    for scene in scene_noise(result, interval=None):
        s = scene["sinad"]
        rows.append({"power_mw": p, "kernel_id": scene["kernel_id"],
                     "pairwise_pct": scene["flips"].pairwise_pct, "majority_pct": scene["flips"].majority_pct,
                     "enob_bits": None if s is None or s.noise_free else s.enob_bits,
                     "correlation": scene["error"]["correlation"]})
    return rows


def pareto_front(cost: npt.ArrayLike, error: npt.ArrayLike) -> np.ndarray:
    """Mask of the points no other point beats in both (lower cost and lower error, one strictly).

    Parameters
    ----------
    cost : array_like
        1-D costs (e.g. device time per capture), finite.
    error : array_like
        1-D errors, same length, finite.

    Returns
    -------
    numpy.ndarray
        bool, same length: True for the points on the front.

    Raises
    ------
    EvtkError
        Arrays that are not 1-D of equal length, or values that are not finite.

    Examples
    --------
    >>> pareto_front([1, 2, 3, 2], [5, 3, 4, 3]).tolist()
    [True, True, False, True]
    """
    c = np.asarray(cost, dtype=np.float64)
    e = np.asarray(error, dtype=np.float64)
    if c.shape != e.shape or c.ndim != 1:
        raise EvtkError("cost and error must be 1-D arrays of equal length")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(e))):
        raise EvtkError("cost and error must be finite")
    dominated = ((c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])
                 & ((c[None, :] < c[:, None]) | (e[None, :] < e[:, None]))).any(axis=1)
    return np.asarray(~dominated)


def tradeoff(windows_us: Iterable[float], kernels: npt.ArrayLike, features: npt.ArrayLike,
             powers_mw: Iterable[float] | None = None, settles_us: Iterable[float] | None = None,
             decimations: Iterable[int] | None = None, repeats: int = 10, bench: Bench | None = None,
             sensor: SensorModel | None = None, seed: int = 0, time_events: bool = True,
             progress: Callable[[int], Any] | None = None, client: Any = None) -> list:
    """Error against run time over capture windows (and powers, settle times, decimations) on the simulated bench.

    Each setting is simulated ``repeats`` times per (kernel, features), with
    the simulator's recommended settle unless ``settles_us`` are given (the
    dark time between patterns usually dominates the time per capture, and
    shortening it leaves pixels short of the dark level). A decimation
    ``d`` keeps every ``d``-th sensor pixel, so the response is the strided
    correlation (eq. 6) and its error is taken against the strided ideal.
    Per setting: ``device_us_per_capture`` (window plus
    settle; the window is at least eq. 7's minimum), ``compute_us_per_capture``
    (wall time of :func:`evtk.reconstruct.reconstruct` on the run written as
    AEDAT4, per capture; with ``time_events=False`` the fast path's
    :func:`~evtk.reconstruct.reconstruct_counts` instead), the error of the
    responses of that same reconstruction against the ideal (``nrmse`` and
    its spread over responses ``nrmse_std``, ``correlation``), ``pipeline``
    (``"events"`` or ``"counts"``), ``enob_bits``
    and ``flip_pct`` (pairwise), averaged over scenes, and ``pareto`` (not
    beaten in both device time and NRMSE by another setting). Settings run
    as independent tasks (on ``client``'s workers when given); each times
    its reconstruction after a warm-up in its own process.

    Parameters
    ----------
    windows_us : iterable of float
        Capture windows, whole us of at least eq. 7's ``e_min``.
    kernels : array_like
        Kernels, ``(n, kh, kw)``.
    features : array_like
        Features, ``(m, fh, fw)`` or one ``(fh, fw)``.
    powers_mw : iterable of float or None
        Laser powers, mW (None: the bench's).
    settles_us : iterable of float or None
        Dark times after each pattern, us (None: the simulator's recommendation).
    decimations : iterable of int or None
        Decimation factors ``Delta`` of eq. 6 (None: the bench's).
    repeats : int
        Captures per (kernel, features) pair (>= 2).
    bench : Bench or None
        The simulated bench (None: the default).
    sensor : SensorModel or None
        The event pixels (None: the simulator's default).
    seed : int
        The device; each setting gets its own shot noise.
    time_events : bool
        Time and measure the event path (a written AEDAT4 file); False: the fast path's counts.
    progress : callable, optional
        Called with 1 after each setting.
    client : distributed.Client or None
        Runs the settings on its workers.

    Returns
    -------
    list of dict
        One row per setting (``power_mw``, ``window_us``, ``settle_us``, ``decimation``, the keys above).

    Raises
    ------
    EvtkError
        Values that are not positive, windows shorter than ``e_min`` or fractional, or fewer than two repeats.
    """

    windows = _positive_list(windows_us, "windows_us")
    from .optics import Bench

    bench = bench if bench is not None else Bench()
    powers = _positive_list(powers_mw, "powers_mw") if powers_mw is not None else [bench.power_mw]
    if int(repeats) < 2:
        raise EvtkError("the trade-off needs at least two repeats per setting (ENOB and flips)")
    for w in windows:
        if w < bench.min_window_us or w != int(w):
            raise EvtkError(f"window {w:g} us: windows must be whole microseconds of at least eq. 7's "
                            f"e_min = {bench.min_window_us:g} us")
    settles = [None] if settles_us is None else _positive_list(settles_us, "settles_us")
    decs = [bench.decimation] if decimations is None else [int(d) for d in _positive_list(decimations, "decimations")]

    settings = [(p, w, z, d) for p in powers for w in windows for z in settles for d in decs]
    tasks = [(i, p, w, z, d, np.asarray(kernels), np.asarray(features), int(repeats), bench, sensor, seed,
              time_events) for i, (p, w, z, d) in enumerate(settings)]
    from .cluster import run_tasks

    rows = run_tasks(_tradeoff_task, tasks, client, progress)
    err = np.array([r["nrmse"] if r["nrmse"] is not None else np.inf for r in rows])
    finite = np.isfinite(err)
    front = np.zeros(len(rows), bool)
    if finite.any():
        front[finite] = pareto_front(np.array([r["device_us_per_capture"] for r in rows])[finite], err[finite])
    for r, f in zip(rows, front):
        r["pareto"] = bool(f)
    return rows


def _tradeoff_task(args):
    i, p, w, z, d, kernels, features, repeats, bench, sensor, seed, time_events = args
    b = bench.replace(power_mw=p, decimation=d)
    # error and time from one pipeline: the event path (the recording written once, its reconstruction timed)
    # or, with time_events=False, the counts of the simulator's fast path
    result, sim, compute_s = simulated_reconstruction(
        kernels, features, b, sensor, int(w), repeats, seed=seed, noise_seed=seed * 1000 + i + 1,
        settle_us=None if z is None else int(z), method="events" if time_events else "fast", timed=True)
    n_cap = len(sim.schedule)
    scenes = scene_noise(result, interval=None)
    enobs = [s["sinad"].enob_bits for s in scenes if s["sinad"] is not None and not s["sinad"].noise_free]
    from .reconstruct import response_error

    per_response = [response_error(result.cells[k], result.ideal[k])["nrmse"] for k in range(len(result.cells))]
    per_response = [v for v in per_response if v is not None]
    return {
        "power_mw": p, "window_us": int(w), "settle_us": int(sim.settle_us), "decimation": int(d),
        "device_us_per_capture": float(sim.window_us + sim.settle_us),
        "compute_us_per_capture": 1e6 * compute_s / n_cap,
        "captures": n_cap,
        "nrmse": _mean_defined([s["error"]["nrmse"] for s in scenes]),
        "nrmse_std": float(np.std(per_response, ddof=1)) if len(per_response) > 1 else None,
        "pipeline": "events" if time_events else "counts",
        "nrmse_range": _mean_defined([s["error"]["nrmse_range"] for s in scenes]),
        "correlation": _mean_defined([s["error"]["correlation"] for s in scenes]),
        "enob_bits": float(np.mean(enobs)) if enobs else None,
        "noise_free": not enobs,
        "flip_pct": float(np.mean([s["flips"].pairwise_pct for s in scenes])),
    }
