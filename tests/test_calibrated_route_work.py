"""The calibrated route does each piece of work once and no more than it needs: the deblur's sampling matrix with
its products sparse and kept for the next reconstruction through the same calibration, the flat field's light
once per reconstruction; the numbers are those of the dense, recomputed forms to 1e-9."""

import importlib
import sys

import numpy as np
import pytest

import evtk
from evtk.calibrate import calibrate
from evtk.optics import Bench
from evtk.optics.camera import CellMap
from evtk.optics.screen import footprint_cdf
from evtk.plan import as_plan
from evtk.reconstruct import deblur, pipeline, reconstruct
from evtk.reconstruct.deblur import sampling_matrix, solve_cells, wiener_lambda


def _dense_sampling_matrix(bench, to_cells, region, shape, supersample=4):
    """The sampling matrix as the deblur's model writes it, each cell's share the footprint CDF at its two edges
    (no blur)."""
    from evtk.optics import shadow_magnification
    from evtk.optics.camera import footprint_points

    x0, x1, y0, y1 = region
    rows, cols = shape
    s = supersample
    uv = np.asarray(to_cells(footprint_points(region, s)), np.float64)
    c = np.array([[(x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2]])
    d = np.asarray(to_cells(np.concatenate([c - [0.5, 0], c + [0.5, 0], c - [0, 0.5], c + [0, 0.5]])))
    a = 1.0 / (s * 2.0 / (np.linalg.norm(d[1] - d[0]) + np.linalg.norm(d[3] - d[2])))
    b = bench.kernel_step_cells if bench.source_extent == "area" else 0.0
    psf = bench.shadow_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    npix = (y1 - y0) * (x1 - x0)
    out = np.zeros((npix, rows * cols))
    low = uv - 0.5 * (a + b)
    for n_row in range(rows):
        wy = footprint_cdf(n_row + 0.5 - low[:, 1], a, b, psf) - footprint_cdf(n_row - 0.5 - low[:, 1], a, b, psf)
        for n_col in range(cols):
            wx = footprint_cdf(n_col + 0.5 - low[:, 0], a, b, psf) - footprint_cdf(n_col - 0.5 - low[:, 0], a, b,
                                                                                     psf)
            share = np.maximum(wy, 0) * np.maximum(wx, 0) / (s * s)
            out[:, n_row * cols + n_col] = share.reshape(npix, s * s).sum(axis=1)
    return out


def _turned_view():
    angle = np.deg2rad(7.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) * 1.1
    matrix = np.eye(3)
    matrix[:2, :2], matrix[:2, 2] = rot, [150.3, 100.7]
    return CellMap(matrix, 0.0, (320, 240))


@pytest.mark.parametrize("turned", [True, False])
def test_sampling_matrix_equals_the_cell_by_cell_model(turned):
    """A turned view, and one along the sensor's axes (built as the outer product of a row and a column factor,
    equal to the sum over every sample but for rounding)."""
    bench = Bench()
    view = _turned_view() if turned else CellMap.scale_shift((150.3, 100.7), 1.02, (320, 240))
    region, shape = (146, 172, 98, 124), (18, 18)
    got = sampling_matrix(bench, view.to_cells, region, shape)
    want = _dense_sampling_matrix(bench, view.to_cells, region, shape)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))
    assert np.mean(got != 0) < 0.2  # a few cells per pixel: why its products run sparse


@pytest.mark.parametrize("blur_px", [0.0, 0.6])
def test_solve_cells_equals_the_dense_regularised_solve(blur_px):
    bench, view = Bench(), _turned_view()
    region, shape = (146, 172, 98, 124), (18, 18)
    a = sampling_matrix(bench, view.to_cells, region, shape, blur_px)
    rng = np.random.default_rng(4)
    truth = rng.random((9, a.shape[1]))
    values = truth @ a.T + 0.01 * rng.standard_normal((9, a.shape[0]))
    noise = np.full(values.shape, 1e-4)
    gram = a.T @ a
    top = float(np.linalg.eigvalsh(gram)[-1])
    for lam, noise_var in ((0.15, None), (0.0, None), (None, noise)):
        want_lam = wiener_lambda(a, values.T, noise.T, top) if lam is None else lam
        want = np.linalg.solve(gram + want_lam ** 2 * top * np.eye(len(gram)), a.T @ values.T).T
        got, got_lam = solve_cells(values, a, 0.0 if lam is None else lam, noise_var)
        assert got_lam == pytest.approx(want_lam, rel=1e-12)
        assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))


def test_deblur_system_is_kept_per_view_and_read_only():
    deblur._systems.clear()
    bench, view = Bench(), _turned_view()
    region, shape = (146, 172, 98, 124), (18, 18)
    first = deblur._deblur_system(bench, view, region, shape, 0.5)
    assert deblur._deblur_system(bench, _turned_view(), region, shape, 0.5) is first  # an equal view
    assert deblur._deblur_system(bench, view, region, shape, 0.6) is not first
    assert deblur._deblur_system(bench, view, (146, 172, 98, 125), shape, 0.5) is not first
    assert np.array_equal(first.a_mat, sampling_matrix(bench, view.to_cells, region, shape, 0.5))
    with pytest.raises(ValueError):
        first.a_mat[0, 0] = 1.0
    with pytest.raises(ValueError):
        first.gram_top()[0][0, 0] = 1.0
    deblur._systems.clear()


@pytest.fixture(scope="module")
def calibrated_job(tmp_path_factory):
    """A calibration run and a job of one 3x3 kernel on the bundled features, written as a camera would."""
    from evtk.patterns import write_patterns
    from evtk.simulate import Simulation, default_features

    tmp = tmp_path_factory.mktemp("calibrated")
    kernel = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
    out = {}
    for name, extra in (("cal", {"calibration": 2, "levels": 6}), ("job", {})):
        sim = Simulation(kernel, default_features(), repeat=6, seed=1, **extra)
        write_patterns(sim, tmp / name)
        sim.write(tmp / f"{name}_sim.aedat4")
        with evtk.open(tmp / f"{name}_sim.aedat4") as rec:
            evtk.write_events(tmp / f"{name}.aedat4", rec.events(), rec.triggers())
        out[name] = (tmp / f"{name}.aedat4", tmp / name / "schedule.json")
    with evtk.open(out["cal"][0]) as rec:
        cal = calibrate(rec, out["cal"][1])
    placed = {"region": cal.region, "origin_px": cal.origin_px, "cell_map": cal.cell_map(), "blur_px": cal.blur_px}
    return out["job"][0], as_plan(out["job"][1]).replace(pixel_model=cal.pixel_model, **placed)


def test_calibrated_route_computes_the_flat_field_light_once(calibrated_job, monkeypatch):
    """The flat field's light per pixel served the gain and the timing thresholds, computed for each (twice)."""
    path, plan = calibrated_job
    linearize = importlib.import_module("evtk.reconstruct.linearize")  # (the package exports a function so named)

    calls = []
    real = linearize._flat_log_step
    for module in (pipeline, linearize):
        monkeypatch.setattr(module, "_flat_log_step", lambda *a: calls.append(1) or real(*a))
    with evtk.open(path) as rec:
        result = reconstruct(rec, plan)
    assert result.summary["deblurred"] and result.summary["linearization"] == "pixel model and event times"
    assert len(calls) == 1


def test_calibrated_route_gives_the_same_numbers_with_the_kept_system(calibrated_job, monkeypatch):
    """A second reconstruction through the same calibration reuses its deblur system: the same numbers as the
    first, and as one that builds the sampling matrix densely and solves it with numpy."""
    path, plan = calibrated_job
    deblur._systems.clear()
    with evtk.open(path) as rec:
        first = reconstruct(rec, plan)
        assert len(deblur._systems) == 1
        again = reconstruct(rec, plan)
    assert np.array_equal(first.cells, again.cells) and np.array_equal(first.responses, again.responses)

    def dense(values, system, lam=0.0, noise_var=None):
        a = np.array(system.a_mat)
        v = np.asarray(values, np.float64).T
        gram = a.T @ a
        top = float(np.linalg.eigvalsh(gram)[-1])
        if noise_var is not None:
            lam = wiener_lambda(a, v, np.asarray(noise_var, np.float64).reshape(v.T.shape).T, top)
        cells = np.linalg.solve(gram + lam * lam * top * np.eye(len(gram)), a.T @ v)
        return cells.T, float(lam)

    monkeypatch.setattr(pipeline, "_solve", dense)
    with evtk.open(path) as rec:
        plain = reconstruct(rec, plan)
    scale = np.max(np.abs(plain.cells))
    assert np.max(np.abs(first.cells - plain.cells)) <= 1e-9 * scale
    assert first.summary["deblur_regularisation"] == pytest.approx(plain.summary["deblur_regularisation"], rel=1e-9)
    deblur._systems.clear()


def _chunk_sizes(method, sizes):
    """``method`` (a recording's chunk iterator) that appends each chunk's length to ``sizes``."""

    def spy(*args, **kwargs):
        for chunk in method(*args, **kwargs):
            sizes.append(len(chunk))
            yield chunk

    return spy


@pytest.mark.parametrize("counter", ["compiled", "numba", "numpy"])
def test_a_whole_read_is_counted_while_its_next_chunk_is_decoded(tmp_path, monkeypatch, counter):
    """Windows over the whole recording read it whole. With the compiled or numba's counter (no GIL held), in
    chunks of an eighth (at least 2**18 events), so that each is counted while the reader's threads decode the
    next (one 4 M-event chunk left the counting after all the decoding). numpy's counter makes many small calls
    that take the GIL back from the decoding threads (the bench job's warm count took 50 ms so, 30 decoded
    first): one chunk of up to 4 M events, decoded on the reader's threads, then counted. The counts are those of
    the events in memory either way."""
    from conftest import random_events

    from evtk import _native
    from evtk.reconstruct import Windows, accumulate

    acc = sys.modules["evtk.reconstruct.accumulate"]  # (the package's name `accumulate` is the function)
    if counter == "compiled" and not (_native.BUILT and _native.TIMED_KERNELS):
        pytest.skip("the compiled kernels are not built")
    monkeypatch.setenv("EVTK_NATIVE", "1" if counter == "compiled" else "0")
    monkeypatch.setattr(acc, "numba_ready", lambda: counter == "numba")

    ev = random_events(700_000, seed=9, span_us=2_000_000)
    path = tmp_path / "r.aedat4"
    evtk.write_events(path, ev)
    starts = np.arange(0, 2_000_000, 50_000)
    win = Windows(starts, starts + 30_000, np.arange(len(starts)), "test")
    sizes = []
    with evtk.open(path) as rec:
        rec.iter_events = _chunk_sizes(rec.iter_events, sizes)
        # a fresh recording knows no packet spans: it reads every packet
        rec.iter_events_meeting = _chunk_sizes(rec.iter_events_meeting, sizes)
        got = accumulate(rec, win, (100, 200, 50, 150), times=True)
    want = accumulate(ev, win, (100, 200, 50, 150), times=True)
    assert sizes == ([700_000] if counter == "numpy" else [2**18, 2**18, 700_000 - 2**19])
    assert np.array_equal(got.on, want.on) and np.array_equal(got.off, want.off)
    assert np.array_equal(got.on_first_us, want.on_first_us) and np.array_equal(got.on_last_us, want.on_last_us)
    assert got.stamp_period_us == want.stamp_period_us


def test_match_windows_tries_every_offset_at_once_as_one_at_a_time(calibrated_job):
    """The trigger windows' clock offset is chosen among candidates all at once: the same choice as trying each
    in turn (the first of the most matches, then of the least total distance), on edges dropped, shifted and
    jittered."""
    from evtk.reconstruct.bench import match_windows
    from evtk.reconstruct.windows import windows_from_triggers

    path, plan = calibrated_job
    schedule = plan.schedule
    with evtk.open(path) as rec:
        triggers = rec.triggers()
    order = np.argsort(schedule.t_on_us, kind="stable")
    sorted_on = schedule.t_on_us[order]

    def one_at_a_time(trig, tol):
        starts = windows_from_triggers(trig).t_start_us
        k = min(8, len(starts), len(sorted_on))
        best, best_score = None, None
        for off in np.unique((starts[:k, None] - sorted_on[None, :k]).ravel()).tolist():
            rel = starts - off
            j = np.clip(np.searchsorted(sorted_on, rel), 1, max(1, len(sorted_on) - 1))
            cand = np.stack([j - 1, np.minimum(j, len(sorted_on) - 1)])
            near = cand[np.argmin(np.abs(sorted_on[cand] - rel), axis=0), np.arange(len(rel))]
            dist = np.abs(sorted_on[near] - rel)
            ok = dist <= tol
            score = (int(ok.sum()), -float(dist[ok].sum()))
            if best_score is None or score > best_score:
                best, best_score = off, score
        return best

    rng = np.random.default_rng(5)
    gaps = np.diff(np.sort(schedule.t_on_us))
    for trial in range(12):
        pairs = rng.random(len(triggers) // 2) > 0.2 * (trial % 4)  # whole windows (rising and falling) dropped
        keep = np.repeat(pairs, 2)
        jitter = rng.integers(-3, 4, int(keep.sum())) * (trial % 2)
        trig = evtk.Triggers(triggers.t[keep] + int(rng.integers(-10**6, 10**6)) + jitter, triggers.kind[keep])
        for tol in (None, 40.0):
            _, report = match_windows(trig, schedule, tol)
            want = one_at_a_time(trig, tol if tol is not None else max(1.0, 0.25 * float(gaps.min())))
            assert report["offset_us"] == want


def test_flat_field_light_is_kept_per_placement(calibrated_job, monkeypatch):
    """The flat field's light per pixel depends on the bench and the placement only: a second reconstruction
    through the same calibration reuses it (the optics ran for each before), another region computes its own,
    and the numbers are those computed afresh."""
    path, plan = calibrated_job
    linearize = importlib.import_module("evtk.reconstruct.linearize")
    linearize._flat_lights.clear()
    calls = []
    for name in ("screen_response", "_flat_through_map"):
        real = getattr(linearize, name)
        monkeypatch.setattr(linearize, name, lambda *a, _real=real, **k: calls.append(1) or _real(*a, **k))
    with evtk.open(path) as rec:
        first = reconstruct(rec, plan)
        assert len(calls) == 1
        again = reconstruct(rec, plan)
        assert len(calls) == 1
        x0, x1, y0, y1 = plan.region
        other = reconstruct(rec, plan.replace(region=(x0 - 1, x1 + 1, y0 - 1, y1 + 1)))
        assert len(calls) == 2
        kept = next(iter(linearize._flat_lights.values()))
        with pytest.raises(ValueError):
            kept[0, 0] = 1.0
        linearize._flat_lights.clear()
        fresh = reconstruct(rec, plan)
    assert np.array_equal(first.cells, again.cells) and np.array_equal(first.cells, fresh.cells)
    assert np.array_equal(first.thresholds, fresh.thresholds, equal_nan=True)
    assert other.summary["region"] != first.summary["region"]
    linearize._flat_lights.clear()


def _gappy_recording(tmp_path, packet_events=500):
    """Events in bursts (a bench's lit windows) with fewer events between them, written in small packets; the
    windows are the bursts."""
    from conftest import random_events

    parts, starts = [], np.arange(20) * 20_000 + 1_000
    for k, a in enumerate(starts):
        parts.append(random_events(6_000, seed=k, t0=int(a), span_us=1_000))
        parts.append(random_events(4_000, seed=100 + k, t0=int(a) + 1_000, span_us=19_000))
    ev = evtk.Events.concatenate(parts).sorted()
    path = tmp_path / "bursts.aedat4"
    evtk.write_events(path, ev, packet_events=packet_events)
    return path, ev, starts, starts + 1_000


def test_iter_events_meeting_decodes_only_the_packets_that_meet_a_window(tmp_path):
    """Once the packets' spans are known (a windowed read scanned them), the packets that meet no window are left
    out, whole packets are given (the window's events all among them), in time order; before that, with the
    windows in any order or overlapping, every packet a brute-force test says meets a window is there."""
    path, ev, a, b = _gappy_recording(tmp_path)
    with evtk.open(path) as rec:
        assert sum(len(c) for c in rec.iter_events_meeting(a, b)) == len(ev)  # no spans known: every packet
        rec.events(int(a[0]), int(b[0]))  # a windowed read: the spans are scanned
        for starts, ends in ((a, b), (a[::-1], b[::-1]), (np.r_[a, a[3]], np.r_[b, b[3] + 30_000])):
            got = evtk.Events.concatenate(list(rec.iter_events_meeting(starts, ends, chunk_events=5_000)))
            assert np.all(np.diff(got.t) >= 0)
            inside = np.zeros(len(got), bool)
            want = np.zeros(len(ev), bool)
            for x, y in zip(starts, ends):
                inside |= (got.t >= x) & (got.t < y)
                want |= (ev.t >= x) & (ev.t < y)
            assert inside.sum() == want.sum()  # every window's events, none lost
            assert len(got) < 0.8 * len(ev)  # the sparse stretches' packets left out
        assert sum(len(c) for c in rec.iter_events_meeting(np.zeros(0), np.zeros(0))) == 0
        with pytest.raises(evtk.EvtkError, match="starts"):
            next(rec.iter_events_meeting(a, b[:-1]))


@pytest.mark.parametrize("chunk_events", [1_000_000, 5_000, 777])
def test_a_full_read_of_the_meeting_packets_learns_their_spans(tmp_path, chunk_events):
    """The first iter_events_meeting of an open recording reads every packet (no spans known, and scanning them
    costs a fresh process more than it saves); it now keeps each packet's earliest and latest stamp from what it
    decoded, the same spans a windowed read's scan finds, so that the next call skips packets without a scan.
    Chunks smaller than a packet split packets across chunks."""
    path, ev, a, b = _gappy_recording(tmp_path)
    with evtk.open(path) as scanned:
        scanned.events(int(a[0]), int(b[0]))  # the scan
        (want,) = scanned._spans.values()
    with evtk.open(path) as rec:
        assert sum(len(c) for c in rec.iter_events_meeting(a, b, chunk_events=chunk_events)) == len(ev)
        (got,) = rec._spans.values()
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        second = evtk.Events.concatenate(list(rec.iter_events_meeting(a, b, chunk_events=chunk_events)))
        assert len(second) < 0.8 * len(ev)
        keep, kept = np.zeros(len(ev), bool), np.zeros(len(second), bool)
        for x, y in zip(a, b):
            keep |= (ev.t >= x) & (ev.t < y)
            kept |= (second.t >= x) & (second.t < y)
        for col in ("t", "x", "y", "p"):  # every window's events, in order
            assert np.array_equal(getattr(second, col)[kept], getattr(ev, col)[keep])
    with evtk.open(path) as rec:  # a read given up before its end learns nothing
        next(rec.iter_events_meeting(a, b, chunk_events=777))
        assert rec._spans == {}


def test_accumulate_over_windows_with_gaps_counts_as_the_events_in_memory(tmp_path):
    """accumulate on a recording whose packet spans are known decodes only the packets meeting a window; the
    counts and event times are those of the events in memory."""
    from evtk.reconstruct import Windows, accumulate

    path, ev, a, b = _gappy_recording(tmp_path)
    win = Windows(a, b, np.arange(len(a)), "test")
    want = accumulate(ev, win, (50, 250, 20, 200), times=True)
    with evtk.open(path) as rec:
        rec.events(int(a[0]), int(b[0]))
        decoded = []
        rec.iter_events_meeting = _chunk_sizes(rec.iter_events_meeting, decoded)
        got = accumulate(rec, win, (50, 250, 20, 200), times=True)
    assert 0 < sum(decoded) < 0.8 * len(ev)
    for name in ("on", "off", "on_first_us", "on_last_us"):
        assert np.array_equal(getattr(got, name), getattr(want, name))
    assert got.events_used == want.events_used


def test_calibrated_route_numbers_do_not_depend_on_packets_left_out_threads_or_kept_work(calibrated_job, monkeypatch):
    """The route as it was (every packet decoded, one thread, nothing kept between reconstructions) and as it
    runs now (the packets meeting no window left out, the timing solve on three threads, the flat field's light
    and the deblur system kept): the same numbers, to 1e-9 of their scale."""
    path, plan = calibrated_job
    linearize = importlib.import_module("evtk.reconstruct.linearize")
    linearize._flat_lights.clear()
    deblur._systems.clear()
    monkeypatch.setenv("EVTK_THREADS", "1")
    with evtk.open(path) as rec:
        rec.iter_events_meeting = lambda starts, ends, chunk_events: rec.iter_events(chunk_events=chunk_events)
        before = reconstruct(rec, plan)
    monkeypatch.setenv("EVTK_THREADS", "3")
    with evtk.open(path) as rec:
        reconstruct(rec, plan)
        now = reconstruct(rec, plan)
    for name in ("cells", "responses", "thresholds"):
        a, b = getattr(before, name), getattr(now, name)
        assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(a))
    assert np.array_equal(before.binary, now.binary)
    assert before.summary["events_used"] == now.summary["events_used"]
    assert before.summary["error"] == pytest.approx(now.summary["error"], rel=1e-9)
    linearize._flat_lights.clear()
    deblur._systems.clear()
