"""The simulated device: :class:`Simulation` runs a schedule through the optics and the pixel model."""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from .._version import __version__
from ..errors import EvtkError
from ..events import Events, TriggerKind, Triggers
from ..io import open_writer
from ..limits import require_memory
from ..optics import (
    Bench,
    brightest_response,
    glow_response,
    ideal_response,
    response_origin_px,
    response_region,
    screen_response,
)
from ..optics.camera import Camera, CellMap
from ..plan.core import Plan
from ..plan.record import SimulationRecord
from ..plan.schedule import (
    DOTS_ID,
    FLAT_ID,
    LEVEL_ID,
    METADATA_KEY,
    CaptureCounts,
    Schedule,
    dot_grid,
    level_kernel,
    level_steps,
    sign_pass,
    split_passes,
)
from ..sensor import PixelState, SensorModel, log_noise_std, pixel_thresholds, simulate_pixels, time_constant_us
from .events import _sorted_events
from .table import count_table, table_batches

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["Simulation"]

_T_LIMIT = np.iinfo(np.int64).max


def _as_patterns(name, a):
    """A stack (n, h, w) of patterns with values in {-1, 0, 1}."""
    a = np.asarray(a)
    if a.dtype == bool:
        a = a.astype(np.int8)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or 0 in a.shape:
        raise EvtkError(f"{name} must be a 2-D pattern or a stack of them (n, h, w), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number):
        raise EvtkError(f"{name} must be numeric, got {a.dtype}")
    if not np.all(np.isfinite(a)) or not np.all((a == -1) | (a == 0) | (a == 1)):
        raise EvtkError(f"{name} must hold only -1, 0 and 1 (binary DMD patterns, optionally signed)")
    return a.astype(np.int8)


def _int_param(name, v, low):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or (isinstance(v, float) and not v.is_integer()):
        raise EvtkError(f"{name} must be a whole number, not {v!r}")
    v = int(v)
    if v < low:
        raise EvtkError(f"{name} must be at least {low}, not {v}")
    return v


def _decay(dt_us, tau_us):
    """``exp(-dt / tau)``, 0 for a pixel that follows the light at once (``tau`` 0)."""
    return math.exp(-dt_us / tau_us) if tau_us > 0 else 0.0


class Simulation:
    """A simulated run of the device.

    Parameters
    ----------
    kernels, features : array_like
        One pattern (h, w) or a stack (n, h, w) each, values in {-1, 0, 1}.
        Every kernel is paired with every features pattern.
    bench : Bench, optional
        The optical bench (DMDs, distances, light power, camera sensor size); default :class:`Bench`'s nominal
        one.
    sensor : SensorModel, optional
        The event camera's pixel model (thresholds and their mismatch, noise, refractory period, dark current);
        default :class:`~evtk.sensor.SensorModel`'s.
    window_us : int
        How long a pattern is shown, µs; must not be shorter than eq. 7 allows.
    settle_us : int, optional
        Darkness after each pattern (and before the first), µs. Default: long
        enough for a pixel to fall back from the brightest pattern to within
        5 % of a threshold of the dark level (:meth:`recommended_settle_us`).
    repeat : int
        Times each pair is shown.
    seed : int
        The device: threshold mismatch and hot pixels follow from it.
    noise_seed : int, optional
        The trial: shot noise and background activity (default: ``seed``).
        Same ``seed`` with another ``noise_seed`` is the same camera recording again.
    start_us : int
        Timestamp of the start of the recording, µs.
    flat_field : int
        Flat-field captures shown before everything else: every kernel
        element and every features element on. They let the reconstruction
        calibrate each pixel's threshold (:func:`evtk.reconstruct.flat_field_gain`);
        in the schedule their ``kernel_id`` and ``features_id`` are -1 (:data:`FLAT_ID`).
    calibration : int
        Dot-grid captures shown after the flat fields: the kernel's centre
        element on, and on the feature DMD one element every ``dot_spacing``
        along each axis (:func:`dot_grid`). Each dot lights one response cell
        (blurred by the optics), so they tell where the response lies and how
        its cells map to pixels (:func:`evtk.calibrate.calibrate`); ids -2
        (:data:`DOTS_ID`).
    dot_spacing : int
        Feature elements between dots.
    camera : Camera or dict, optional
        The camera's pose and lens (:class:`evtk.optics.camera.Camera`):
        rotation, tilt, offset, scale, radial distortion, vignetting,
        defocus. Default: the nominal view.
    levels : int
        Level captures shown after the dots, a staircase of light: features
        all on and ``level`` kernel elements on (:func:`level_kernel`), for
        ``levels`` element counts from 1 to all (:func:`level_steps`). The
        response's interior then sees 1, ..., K units of light, to which the
        reconstruction fits the pixel model instead of assuming one
        (:func:`evtk.reconstruct.fit_pixel_model`); ids -3
        (:data:`LEVEL_ID`), the element count in the schedule's ``level``.
    light_delay_us : int
        How long (µs) the light takes to change after each trigger edge (a DMD's
        trigger-to-mirror latency, 0 or more). The schedule keeps the
        light's times, the trigger edges come this much earlier, as a bench
        records them; the calibrated reconstruction fits the delay
        (:attr:`evtk.reconstruct.PixelFit.delay_us`).
    light_rise_us : float
        How gradually the light follows each edge (a time constant, µs): it rises as ``1 -
        exp(-t / light_rise_us)`` after the light's rising edge and falls as
        ``exp(-t / light_rise_us)`` after its falling one (a lamp's or
        diffuser's response; 0, the default: at once). Simulated as pieces
        of constant light, finest at the edge.

    Raises
    ------
    EvtkError
        On patterns of the wrong shape or values, a window shorter than eq. 7 allows, a negative or
        non-integer count, seed or time, a light delay not shorter than the darkness, a light rise not under a
        fifth of the window and of the darkness, or a bench so bright that the photon rates overflow.

    Examples
    --------
    >>> sim = Simulation(np.ones((3, 3)), np.eye(16), seed=1)
    >>> len(sim.schedule)
    3
    """

    def __init__(self, kernels: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None,
                 sensor: SensorModel | None = None, window_us: int = 1000, settle_us: int | None = None,
                 repeat: int = 1, seed: int = 0, start_us: int = 0, noise_seed: int | None = None,
                 flat_field: int = 2, calibration: int = 0, dot_spacing: int = 4, levels: int = 0,
                 camera: Camera | dict | None = None, light_delay_us: int = 0, light_rise_us: float = 0.0) -> None:
        self.bench = bench if bench is not None else Bench()
        self.sensor = sensor if sensor is not None else SensorModel()
        self.kernels = _as_patterns("kernels", kernels)
        self.features = _as_patterns("features", features)
        self.bench.check_pattern(self.kernels.shape[1:], self.features.shape[1:])
        self.window_us = _int_param("window_us", window_us, 1)
        if self.window_us < self.bench.min_window_us:
            raise EvtkError(f"window_us={self.window_us} is shorter than the bench allows: eq. 7 gives "
                            f"e_min = {self.bench.min_window_us:g} us")
        self.repeat = _int_param("repeat", repeat, 1)
        self.seed = _int_param("seed", seed, 0)
        self.noise_seed = self.seed if noise_seed is None else _int_param("noise_seed", noise_seed, 0)
        self.start_us = _int_param("start_us", start_us, np.iinfo(np.int64).min // 2)
        kshape = self.kernels.shape[1:]
        self.gain_e_per_s = self.bench.electrons_per_s_per_unit(kshape)  # photoelectrons/s per response unit
        if not math.isfinite(self.gain_e_per_s * brightest_response(kshape, self.bench)):
            raise EvtkError(f"power_mw {self.bench.power_mw:g} makes the photon rates overflow float64; "
                            "no bench is that bright")
        self.settle_us = self.recommended_settle_us() if settle_us is None else _int_param("settle_us", settle_us, 1)
        self.light_delay_us = _int_param("light_delay_us", light_delay_us, 0)
        if self.light_delay_us >= self.settle_us:
            raise EvtkError(f"light_delay_us={self.light_delay_us} must be shorter than the darkness between patterns "
                            f"(settle_us={self.settle_us})")
        if isinstance(light_rise_us, bool) or not isinstance(light_rise_us, (int, float)) \
                or not (math.isfinite(light_rise_us) and 0 <= light_rise_us):
            raise EvtkError(f"light_rise_us must be a finite number >= 0, not {light_rise_us!r}")
        self.light_rise_us = float(light_rise_us)
        if 5 * self.light_rise_us >= min(self.window_us, self.settle_us):
            raise EvtkError(f"light_rise_us={self.light_rise_us:g} must be under a fifth of the window "
                            f"({self.window_us} us) and of the darkness ({self.settle_us} us)")
        self.camera = None if camera is None or Camera.from_dict(camera).is_ideal else Camera.from_dict(camera)
        self.region = response_region(self.bench, kshape, self.features.shape[1:])
        if self.camera is not None:  # where the camera's pose and lens put the nominal response
            self.region = self.camera.sensor_region(self.region, self._sensor_size)
        self._passes: dict = {}
        self._rate_cache: dict = {}  # region (or "glow") -> {(kernel, features, signs): photoelectron rates}
        self.flat_field = _int_param("flat_field", flat_field, 0)
        per_pair = max(len(self._pair_passes(0, 0)), 1) if len(self.kernels) and len(self.features) else 1
        n_est = self.flat_field + self.repeat * len(self.kernels) * len(self.features) * per_pair
        x0, x1, y0, y1 = self.region
        # the schedule, and one response-sized light map per capture while it is simulated and written
        require_memory(n_est * (64 + 16 * (x1 - x0) * (y1 - y0)),
                       f"a run of {n_est:,} captures ({self.flat_field:,} flat fields, {self.repeat:,} repeats)")
        self.calibration = _int_param("calibration", calibration, 0)
        self.dot_spacing = _int_param("dot_spacing", dot_spacing, 2)
        if self.calibration and not dot_grid(self.features.shape[1:], self.dot_spacing).any():
            raise EvtkError(f"a dot spacing of {self.dot_spacing} leaves no dot on {self.features.shape[1:]} features")
        self.levels = _int_param("levels", levels, 0)
        steps = level_steps(self.kernels.shape[1] * self.kernels.shape[2], self.levels)
        rows = [(FLAT_ID, FLAT_ID, 1, 1, i, 0) for i in range(self.flat_field)]
        rows += [(DOTS_ID, DOTS_ID, 1, 1, i, 0) for i in range(self.calibration)]
        rows += [(LEVEL_ID, LEVEL_ID, 1, 1, 0, int(m)) for m in steps]
        n_setup = len(rows)
        for r in range(self.repeat):
            for ki in range(len(self.kernels)):
                for fi in range(len(self.features)):
                    for ks, fs, _kp, _fp in self._pair_passes(ki, fi):
                        rows.append((ki, fi, ks, fs, r, 0))
        if len(rows) == n_setup:
            raise EvtkError("nothing to show: every kernel or features pattern is all zero")
        n = len(rows)
        period = self.window_us + self.settle_us
        end = self.start_us + self.settle_us + n * period
        if end >= _T_LIMIT:
            raise EvtkError(f"the run would end at t = {end} us, beyond the int64 timestamp range")
        self._check_size(n, end - self.start_us)
        table = np.asarray(rows, dtype=np.int64)
        t_on = self.start_us + self.settle_us + np.arange(n, dtype=np.int64) * period
        self.schedule = Schedule(np.arange(n, dtype=np.int64), table[:, 0], table[:, 1], table[:, 2], table[:, 3],
                                 t_on, t_on + self.window_us, table[:, 4], table[:, 5])
        self.end_us = int(end)

        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x5E5]))
        w, h = self.bench.sensor_width, self.bench.sensor_height
        self._theta_on, self._theta_off = pixel_thresholds(self.sensor, w * h, rng)
        n_hot = int(round(self.sensor.hot_pixel_fraction * w * h))
        self._hot = np.sort(rng.choice(w * h, size=n_hot, replace=False)) if n_hot else np.zeros(0, np.int64)

    def _check_size(self, n_captures, span_us):
        """Refuse, before any work, a run whose events or per-pixel state exceed the memory budget.

        Each pixel of the response region can give at most about ``ln(bright /
        blank) / theta`` events as the light rises and as many as it falls,
        per capture (the brightest pattern bounds every capture's light); the
        background activity and hot pixels add their rates over the whole
        sensor and span. The simulator keeps state for every sensor pixel.
        """
        b, sm = self.bench, self.sensor
        w, h = b.sensor_width, b.sensor_height
        require_memory(48 * w * h, f"the per-pixel state of a {w}x{h} sensor")
        blank = self.blank_rate_e_per_s
        bright = self._rate(brightest_response(self.kernels.shape[1:], b))
        theta = min(sm.theta_on, sm.theta_off)
        x0, x1, y0, y1 = self.region
        per_capture = (x1 - x0) * (y1 - y0) * 2 * (math.log(max(bright / blank, 1.0)) / theta + 1)
        span_s = span_us * 1e-6
        noise = span_s * (sm.background_rate_hz * w * h + sm.hot_pixel_rate_hz * sm.hot_pixel_fraction * w * h)
        events = n_captures * per_capture + noise
        require_memory(16 * events, f"a run of {n_captures:,} captures ({self.repeat:,} repeats over {span_s:,.0f} s: "
                       f"up to about {events:.3g} events at 16 bytes; fewer repeats or patterns make it smaller)")

    # -- patterns and light -----------------------------------------------------------
    def _pair_passes(self, ki, fi):
        key = (ki, fi)
        if key not in self._passes:
            self._passes[key] = split_passes(self.kernels[ki], self.features[fi])
        return self._passes[key]

    def _pass_patterns(self, c):
        s = self.schedule
        ks, fs = int(s.kernel_sign[c]), int(s.features_sign[c])
        if s.kernel_id[c] == FLAT_ID:  # flat field
            return np.ones(self.kernels.shape[1:], np.int8), np.ones(self.features.shape[1:], np.int8)
        if s.kernel_id[c] == DOTS_ID:  # calibration dots under the kernel's centre element
            k = np.zeros(self.kernels.shape[1:], np.int8)
            k[(k.shape[0] - 1) // 2, (k.shape[1] - 1) // 2] = 1
            return k, dot_grid(self.features.shape[1:], self.dot_spacing)
        if s.kernel_id[c] == LEVEL_ID:  # a step of the staircase: ``level`` kernel elements over flat features
            return level_kernel(self.kernels.shape[1:], s.level[c]), np.ones(self.features.shape[1:], np.int8)
        return sign_pass(self.kernels[s.kernel_id[c]], ks), sign_pass(self.features[s.features_id[c]], fs)

    def _rate(self, response):
        return self.gain_e_per_s * response + self.sensor.dark_current_e_per_s

    @property
    def blank_rate_e_per_s(self) -> float:
        """Photoelectron rate of every pixel while both DMDs are dark."""
        return self._rate(glow_response(np.zeros(self.kernels.shape[1:]), self.bench))

    def recommended_settle_us(self) -> int:
        """Darkness after a pattern for a pixel to fall back close to the dark level.

        Time for the mean photoreceptor output to decay from the brightest
        possible level (every kernel element through every feature element)
        to within 5 % of a threshold of the dark level, at the dark level's
        time constant; at least the eq. 7 window.

        Returns
        -------
        int
            The settling time (µs).
        """
        b = self.bench
        blank = self.blank_rate_e_per_s
        bright = self._rate(brightest_response(self.kernels.shape[1:], b))
        tau_us = float(time_constant_us(blank, self.sensor))
        theta = min(self.sensor.theta_on, self.sensor.theta_off)
        span = math.log(bright / blank)
        need = tau_us * math.log(max(span / (0.05 * theta), 1.0))
        return int(max(math.ceil(need), math.ceil(b.min_window_us)))

    def pass_response(self, c: int, region: tuple | None = None) -> np.ndarray:
        """Light (response units) each pixel of a region receives during a capture.

        Parameters
        ----------
        c : int
            The capture.
        region : tuple, optional
            ``(x0, x1, y0, y1)``; default the whole sensor.

        Returns
        -------
        ndarray
            The light, ``(y1 - y0, x1 - x0)``.
        """
        k, f = self._pass_patterns(c)
        if self.camera is None:
            return screen_response(k, f, self.bench, region)
        region = (0, self.bench.sensor_width, 0, self.bench.sensor_height) if region is None else region
        return self.camera.view(k, f, self.bench, region)

    @property
    def _sensor_size(self):
        return (self.bench.sensor_width, self.bench.sensor_height)

    def cell_map(self) -> CellMap:
        """Where each cell (column, row) of the full response lands on the sensor (pose and lens included).

        Returns
        -------
        CellMap
            From response cells to sensor pixels.
        """
        record = self.record()
        found = record.placement() or record.replace(camera=Camera().to_dict()).placement()
        assert found is not None  # a record with a camera always has a placement
        return found

    def ideal(self, c: int) -> np.ndarray:
        """Ground truth of a capture: the noise-free digital response of its pass (full correlation).

        Parameters
        ----------
        c : int
            The capture.

        Returns
        -------
        ndarray
            The full response of the capture's kernel and features passes.
        """
        k, f = self._pass_patterns(c)
        return ideal_response(k, f, self.bench)

    def ideal_pair(self, kernel_id: int, features_id: int) -> np.ndarray:
        """Ground truth of a signed pair: what the ± passes combine to.

        Parameters
        ----------
        kernel_id, features_id : int
            The pair.

        Returns
        -------
        ndarray
            The full signed response.
        """
        return ideal_response(self.kernels[kernel_id], self.features[features_id], self.bench)

    # -- metadata ---------------------------------------------------------------------
    def record(self) -> SimulationRecord:
        """How this run is made, typed (stored with the recording; see ``docs/formats/schedule.md``).

        Returns
        -------
        SimulationRecord
            Bench, pixel model, patterns, schedule, timing, placement and seeds.
        """
        return SimulationRecord(
            bench=self.bench, sensor=self.sensor, kernels=self.kernels, features=self.features,
            schedule=self.schedule, window_us=self.window_us, settle_us=self.settle_us, start_us=self.start_us,
            end_us=self.end_us, response_region=tuple(int(v) for v in self.region),
            response_origin_px=tuple(float(v) for v in response_origin_px(self.bench, self.kernels.shape[1:],
                                                                         self.features.shape[1:])),
            gain_e_per_s_per_unit=float(self.gain_e_per_s), blank_rate_e_per_s=float(self.blank_rate_e_per_s),
            seed=self.seed, noise_seed=self.noise_seed, repeat=self.repeat, flat_field=self.flat_field,
            calibration=self.calibration, dot_spacing=self.dot_spacing, levels=self.levels,
            camera=None if self.camera is None else self.camera.to_dict(), light_delay_us=self.light_delay_us,
            light_rise_us=self.light_rise_us,
            correlation="convolution" if self.bench.kernel_flipped else "correlation", evtk_version=__version__)

    def plan(self) -> Plan:
        """The plan of this run, the oracle's (:meth:`evtk.plan.Plan.from_record` of :meth:`record`).

        Returns
        -------
        Plan
            Schedule, patterns, bench, placement, pixel model and light delay, with the record.
        """
        return Plan.from_record(self.record())

    def metadata(self) -> dict:
        """The recording's metadata: :meth:`record` in its dict form, under ``simulation``.

        Returns
        -------
        dict
            ``{"simulation": record}``.
        """
        return {METADATA_KEY: self.record().to_dict()}

    def triggers(self) -> Triggers:
        """Rising edge at each pattern's appearance, falling edge when it goes (``light_delay_us`` earlier).

        Returns
        -------
        Triggers
            Two edges per capture, in time order.
        """
        s = self.schedule
        t = np.empty(2 * len(s), np.int64)
        t[0::2] = s.t_on_us - self.light_delay_us
        t[1::2] = s.t_off_us - self.light_delay_us
        kind = np.empty(2 * len(s), np.int8)
        kind[0::2] = TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE
        kind[1::2] = TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE
        return Triggers(t, kind)

    # -- the pixel simulation ---------------------------------------------------------
    def _segments(self, c0, c1, lead_in):
        """Segment bounds (float us relative to the batch base), which capture each counts for (-1: none),
        whose light it has (-1: darkness) and what share of that light (:attr:`light_rise_us`)."""
        s = self.schedule
        base = int(s.t_on_us[c0]) - (self.settle_us if lead_in else 0)
        starts, ends, which, light, share = [], [], [], [], []
        if lead_in:
            starts.append(0.0)
            ends.append(float(self.settle_us))
            which.append(-1)
            light.append(-1)
            share.append(1.0)
        r = self.light_rise_us
        # pieces of the rise (and of the fall), in units of the rise's time constant, finest at the edge
        cuts = np.array([0.0, 0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0]) * r if r > 0 else np.zeros(1)
        rise = 1.0 - r * (np.exp(-cuts[:-1] / r) - np.exp(-cuts[1:] / r)) / np.diff(cuts) if r > 0 else cuts[:0]
        for c in range(c0, c1):
            on = float(s.t_on_us[c] - base)
            off = on + self.window_us
            starts += list(on + cuts[:-1]) + [on + cuts[-1]] + list(off + cuts[:-1]) + [off + cuts[-1]]
            ends += list(on + cuts[1:]) + [off] + list(off + cuts[1:]) + [off + self.settle_us]
            which += [c] * cuts.size + [-1] * cuts.size
            light += [c] * cuts.size + [c] * (cuts.size - 1) + [-1]
            share += list(rise) + [1.0] + list(1.0 - rise) + [1.0]
        return (base, np.array(starts), np.array(ends), np.array(which, np.int64), np.array(light, np.int64),
                np.array(share))

    def _levels(self, which, region, share=None):
        """(level, tau, noise) arrays, shape (n_segments, n_pixels), for pixels of ``region``; ``which``
        the capture whose light each segment has (-1: darkness), ``share`` the part of it come (default all)."""
        x0, x1, y0, y1 = region
        blank = self.blank_rate_e_per_s
        rates = np.empty((which.size, (x1 - x0) * (y1 - y0)))
        cache = self._rate_cache.setdefault(tuple(region), {})
        for k, c in enumerate(which):
            if c < 0:
                rates[k] = blank
                continue
            key = self._pass_key(c)
            if key not in cache:
                cache[key] = self._rate(self.pass_response(c, region)).ravel()
            rates[k] = cache[key]
            if share is not None and share[k] != 1.0:  # the light part-way between darkness and the pattern's
                rates[k] = blank + share[k] * (rates[k] - blank)
        return np.log(rates), time_constant_us(rates, self.sensor), log_noise_std(rates, self.sensor)

    def _pass_key(self, c):
        """What capture ``c`` shows: (kernel id, features id, kernel sign, features sign, level)."""
        s = self.schedule
        return (int(s.kernel_id[c]), int(s.features_id[c]), int(s.kernel_sign[c]), int(s.features_sign[c]),
                int(s.level[c]))

    def _glow_rate(self, c):
        """Photoelectron rate of the uniform glow outside the region during capture ``c`` (cached per pass)."""
        key = self._pass_key(c)
        cache = self._rate_cache.setdefault("glow", {})
        if key not in cache:
            cache[key] = float(self._rate(glow_response(self._pass_patterns(c)[0], self.bench)))
        return cache[key]

    def _region_pixels(self, region):
        x0, x1, y0, y1 = region
        w = self.bench.sensor_width
        yy, xx = np.mgrid[y0:y1, x0:x1]
        return (yy * w + xx).ravel()

    def _run(self, emit, batch, progress=None, region=None):
        """Simulate batches of captures; yields, per batch, its time base and segments, the
        region's pixel output, the outside pixels' output (or None), a seed for background
        activity, and the pixel indices of both."""
        region = self.region if region is None else region
        roi_idx = self._region_pixels(region)
        b = self.bench
        w, h = b.sensor_width, b.sensor_height
        blank = self.blank_rate_e_per_s
        lvl0 = np.full(roi_idx.size, math.log(blank))
        s0 = log_noise_std(blank, self.sensor)
        seq = np.random.SeedSequence([self.noise_seed, 0xE7E])
        rng = np.random.default_rng(seq.spawn(1)[0])
        roi_state = PixelState(lvl0, s0, self._theta_on[roi_idx], self._theta_off[roi_idx], rng)

        # pixels outside the region see a uniform glow; simulate them (noise-free) only if it can cross
        outside = None
        if emit:
            mask = np.ones(w * h, bool)
            mask[roi_idx] = False
            out_idx = np.flatnonzero(mask)
            if out_idx.size:
                # until its first event every such pixel follows the same noise-free path V(t);
                # it is monotone within a segment, so its extremes are at segment ends
                v0 = v = math.log(blank)
                tau_blank = float(time_constant_us(blank, self.sensor))
                reach = 0.0
                for c in range(len(self.schedule)):
                    g = self._glow_rate(c)
                    lg = math.log(g)
                    v = lg + (v - lg) * _decay(self.window_us, float(time_constant_us(g, self.sensor)))
                    reach = max(reach, abs(v - v0))
                    v = v0 + (v - v0) * _decay(self.settle_us, tau_blank)
                    reach = max(reach, abs(v - v0))
                th_min = min(self._theta_on[out_idx].min(), self._theta_off[out_idx].min())
                # a pixel whose thresholds both exceed the reach of the glow can never fire
                can = np.minimum(self._theta_on[out_idx], self._theta_off[out_idx]) <= reach
                out_idx = out_idx[can]
                if reach >= th_min:
                    quiet = SensorModel.from_dict({**self.sensor.to_dict(), "shot_noise": False, "leak_rate_hz": 0.0,
                                                   "shot_event_rate_hz": 0.0})
                    outside = (out_idx, quiet, PixelState(np.full(out_idx.size, math.log(blank)), 0.0,
                                                          self._theta_on[out_idx], self._theta_off[out_idx], rng))
        n = len(self.schedule)
        for c0 in range(0, n, batch):
            c1 = min(n, c0 + batch)
            base, st, en, which, light, share = self._segments(c0, c1, lead_in=(c0 == 0))
            slot = np.where(which >= 0, which - c0, -1)
            lvl, tau, noise = self._levels(light, region, share)
            seed_roi, seed_out, seed_ba = (int(v) for v in rng.integers(0, 2**31 - 1, 3))
            roi = simulate_pixels(roi_state, lvl, tau, noise, st, en, self.sensor, seed_roi,
                                  emit=emit, count_slot=slot, n_slots=c1 - c0, t0_us=base)
            out = None
            if outside is not None:
                out_idx, quiet, ostate = outside
                g = np.array([math.log(blank + f * (self._glow_rate(c) - blank)) if f != 1.0 else
                              math.log(self._glow_rate(c)) if c >= 0 else math.log(blank)
                              for c, f in zip(light, share)])
                olvl = np.repeat(g[:, None], out_idx.size, axis=1)
                rates = np.exp(g)
                otau = np.repeat(time_constant_us(rates, quiet)[:, None], out_idx.size, axis=1)
                onoise = np.zeros_like(olvl)
                out = simulate_pixels(ostate, olvl, otau, onoise, st, en, quiet, seed_out, t0_us=base)
            yield base, c0, c1, st, en, which, roi, out, seed_ba, roi_idx, (outside[0] if outside else None)
            if progress is not None:
                progress(c1 - c0)

    def _noise_events(self, duration_us, seed):
        """Background activity and hot pixels over the whole sensor: (t_rel_us, pixel, polarity)."""
        sm = self.sensor
        w, h = self.bench.sensor_width, self.bench.sensor_height
        rng = np.random.default_rng(seed)
        n_ba = rng.poisson(sm.background_rate_hz * 1e-6 * duration_us * w * h) if sm.background_rate_hz else 0
        pix = rng.integers(0, w * h, n_ba)
        t = rng.random(n_ba) * duration_us
        if self._hot.size and sm.hot_pixel_rate_hz:
            k = rng.poisson(sm.hot_pixel_rate_hz * 1e-6 * duration_us, self._hot.size)
            pix = np.concatenate([pix, np.repeat(self._hot, k)])
            t = np.concatenate([t, rng.random(int(k.sum())) * duration_us])
        pol = rng.integers(0, 2, pix.size).astype(np.uint8)
        return t, pix.astype(np.int64), pol

    def iter_events(self, batch_captures: int = 8, progress: Any = None) -> Iterator[Events]:
        """Yield the recording's events in time order, one batch of captures at a time.

        Parameters
        ----------
        batch_captures : int
            Captures simulated at a time (memory is bounded by a batch).
        progress : callable, optional
            Called with the captures done.

        Yields
        ------
        Events
            One batch's events, in time order.
        """
        w, h = self.bench.sensor_width, self.bench.sensor_height
        maps = None
        for base, _c0, _c1, _st, en, _which, roi, out, seed_ba, roi_idx, out_idx in self._run(True, batch_captures,
                                                                                            progress):
            if maps is None:  # events carry indices into [region pixels, outside pixels, every pixel]
                every = np.arange(w * h)
                sensor = np.concatenate([roi_idx, every[:0] if out_idx is None else out_idx, every])
                maps = ((sensor % w).astype(np.uint16), (sensor // w).astype(np.uint16),
                        roi_idx.size, roi_idx.size + (0 if out_idx is None else out_idx.size))
            x_of, y_of, out_base, every_base = maps
            span = float(en[-1])
            nt, ni, npol = self._noise_events(span, seed_ba)
            parts = [roi] + ([] if out is None else [(out[0], out[1] + out_base, out[2])])
            parts.append((nt, ni + every_base, npol))
            t_rel, local, pol = (np.concatenate([part[k] for part in parts]) for k in range(3))
            t, x, y, p = _sorted_events(t_rel, local, pol, int(math.ceil(span)), base, x_of, y_of)
            # frame readout and the camera's clock, if any
            yield Events._trusted(self.sensor.stamp(t, self.start_us), x, y, p, (w, h), is_sorted=True)

    def events(self) -> Events:
        """All events in memory (use :meth:`write` or :meth:`iter_events` for long runs).

        Returns
        -------
        Events
            The whole sensor's events, in time order.
        """
        size = (self.bench.sensor_width, self.bench.sensor_height)
        return Events.concatenate(list(self.iter_events()), sensor_size=size)

    def write(self, path: str | os.PathLike, compression: str = "lz4", batch_captures: int = 8,
              progress: Any = None) -> dict:
        """Stream the run to a file (.aedat4, .h5, .parquet) with triggers and metadata; atomic.

        Parameters
        ----------
        path : str or os.PathLike
            The output; its extension picks the format.
        compression : str
            The container's compression.
        batch_captures : int
            Captures simulated at a time.
        progress : callable, optional
            Called with the captures done.

        Returns
        -------
        dict
            ``path``, ``events``, ``triggers``, ``captures``, the span and the run's timing and seeds.
        """

        size = (self.bench.sensor_width, self.bench.sensor_height)
        n = 0
        with open_writer(path, size, compression, self.metadata(), self.triggers()) as writer:
            for ev in self.iter_events(batch_captures, progress):
                writer.write_events(ev)
                n += len(ev)
        return {"path": str(path), "events": n, "triggers": 2 * len(self.schedule), "captures": len(self.schedule),
                "t_start_us": self.start_us, "t_end_us": self.end_us, "window_us": self.window_us,
                "settle_us": self.settle_us, "seed": self.seed, "noise_seed": self.noise_seed}

    def responses(self, region: tuple | None = None, method: str = "auto", batch_captures: int = 64,
                  progress: Any = None) -> CaptureCounts:
        """The fast path: ON/OFF counts per pixel inside each capture window, without events.

        Parameters
        ----------
        region : (x0, x1, y0, y1), optional
            Sensor pixels to report; default where the pattern's shadow can fall.
        method : {"auto", "table", "exact"}
            "exact" runs the event path's pixel model on the region's pixels and
            keeps only the counts (history between captures included).
            "table" draws each pixel's counts from the distribution the same
            model gives for its light and threshold, tabulated once per run
            (:meth:`count_table`); it assumes every capture starts from the
            settled dark state. "auto" takes "table" when ``settle_us`` is at
            least :meth:`recommended_settle_us`, else "exact".
        batch_captures : int
            Captures simulated at a time.
        progress : callable, optional
            Called with the captures done.

        Returns
        -------
        CaptureCounts
            ON and OFF counts per capture over the region, with the schedule.

        Notes
        -----
        Background activity and hot pixels are added as Poisson counts.
        """
        region = self.region if region is None else tuple(int(v) for v in region)
        x0, x1, y0, y1 = region
        b = self.bench
        if not (0 <= x0 <= x1 <= b.sensor_width and 0 <= y0 <= y1 <= b.sensor_height):
            raise EvtkError(f"region {region} is not inside the {b.sensor_width}x{b.sensor_height} sensor")
        if method not in ("auto", "table", "exact"):
            raise EvtkError(f"method must be 'auto', 'table' or 'exact', not {method!r}")
        plain = not self.sensor.stepped and self.light_rise_us == 0
        if method == "table" and not plain:
            raise EvtkError("the count table models evtk's asynchronous pixel under sharp light: use method='exact' "
                            "for another pixel, a frame-compared readout or a light with a rise time")
        if method == "auto":
            method = "table" if self.settle_us >= self.recommended_settle_us() and plain else "exact"
        n = len(self.schedule)
        ny, nx = y1 - y0, x1 - x0
        on = np.zeros((n, ny, nx), np.int32)
        off = np.zeros((n, ny, nx), np.int32)
        roi_idx = self._region_pixels(region)
        hot = np.isin(roi_idx, self._hot)
        batches: Iterator[tuple[int, int, np.ndarray, np.ndarray, int]]
        if method == "exact":
            batches = ((c0, c1, roi[3], roi[4], seed_ba) for _, c0, c1, _, _, _, roi, _, seed_ba, _, _
                       in self._run(False, batch_captures, progress, region))
        else:
            batches = table_batches(self, region, roi_idx, batch_captures, progress)
        for c0, c1, on_b, off_b, seed_ba in batches:
            on[c0:c1] = on_b.reshape(c1 - c0, ny, nx)
            off[c0:c1] = off_b.reshape(c1 - c0, ny, nx)
            rng = np.random.default_rng(seed_ba)
            lam = 0.5 * self.sensor.background_rate_hz * 1e-6 * self.window_us
            if lam > 0:
                on[c0:c1] += rng.poisson(lam, (c1 - c0, ny, nx)).astype(np.int32)
                off[c0:c1] += rng.poisson(lam, (c1 - c0, ny, nx)).astype(np.int32)
            if hot.any() and self.sensor.hot_pixel_rate_hz:
                lam_h = 0.5 * self.sensor.hot_pixel_rate_hz * 1e-6 * self.window_us
                on[c0:c1] += (rng.poisson(lam_h, (c1 - c0, ny * nx)) * hot).reshape(c1 - c0, ny, nx).astype(np.int32)
                off[c0:c1] += (rng.poisson(lam_h, (c1 - c0, ny * nx)) * hot).reshape(c1 - c0, ny, nx).astype(np.int32)
        return CaptureCounts(on, off, region, self.schedule)

    #: Grid of the count table (:func:`evtk.simulate.table.count_table`): log-light steps, threshold points,
    #: replicates per cell.
    TABLE_LIGHT_POINTS = 256
    TABLE_THRESHOLD_POINTS = 7
    TABLE_REPLICATES = 32

    def count_table(self) -> tuple:
        """:func:`evtk.simulate.table.count_table` of this run (shared by runs of the same bench, sensor and timing).

        Returns
        -------
        tuple
            ``(v_grid, theta_grid, on, off)``.
        """
        return count_table(self)
