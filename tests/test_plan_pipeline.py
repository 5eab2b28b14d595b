"""Issue 30 item 1: the stages after counting read a Plan (schedule, patterns, placement, pixel model), not a
simulation record; the oracle's record becomes a plan (:meth:`Plan.from_record`) and the calibrated route puts
its fitted pixel model in the bench's plan (no record made up around a calibration)."""

import numpy as np
import pytest

import evtk
from evtk.errors import EvtkError


def _simulated(tmp_path, levels=0, **extra):
    from evtk.simulate import Simulation

    rng = np.random.default_rng(11)
    sim = Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (12, 12)), seed=11, flat_field=2,
                     levels=levels, repeat=2, **extra)
    sim.write(tmp_path / "r.h5")
    return sim


def test_reconstruct_counts_takes_a_plan_and_a_record_alike(tmp_path):
    """A plan read from the record gives the record's numbers exactly; a plan whose pixel model is changed is
    inverted by that model (the plan, not a record behind it, is what the stages read)."""
    from evtk.plan import PixelModel, Plan
    from evtk.reconstruct import WindowCounts, reconstruct_counts
    from evtk.sensor import SensorModel

    sim = _simulated(tmp_path)
    counts = WindowCounts.from_capture_counts(sim.responses())
    record = sim.record()
    by_record = reconstruct_counts(counts, record)
    plan = Plan.from_record(record)
    by_plan = reconstruct_counts(counts, plan)
    assert np.array_equal(by_plan.responses, by_record.responses)
    assert by_plan.summary.to_dict() == by_record.summary.to_dict()
    # another pixel model in the plan: the stages read it (as the record with that sensor would give)
    other = SensorModel(theta_on=0.3, theta_off=0.3)
    changed = reconstruct_counts(counts, plan.replace(pixels=PixelModel(other, plan.pixels.gain_e_per_s_per_unit,
                                                                        plan.pixels.blank_rate_e_per_s)))
    expected = reconstruct_counts(counts, record.replace(sensor=other))
    assert np.array_equal(changed.responses, expected.responses)
    assert not np.allclose(changed.responses, by_record.responses)


def test_a_plan_without_a_pixel_model_is_named(tmp_path):
    """The counts' stages invert a pixel model: a bench plan without one is one clear error saying where to go."""
    from evtk.reconstruct import WindowCounts, reconstruct_counts, schedule_of_record

    sim = _simulated(tmp_path)
    counts = WindowCounts.from_capture_counts(sim.responses())
    with pytest.raises(EvtkError, match="no pixel model"):
        reconstruct_counts(counts, schedule_of_record(sim.record()))


def test_the_oracle_reads_the_plan_it_is_given(tmp_path):
    """``reconstruct(rec, Plan.from_record(r).replace(...))``: the changed plan is what is inverted (before, the
    record behind the plan was read and the change silently ignored)."""
    from evtk.plan import PixelModel, Plan
    from evtk.reconstruct import reconstruct
    from evtk.sensor import SensorModel

    _simulated(tmp_path)
    with evtk.open(tmp_path / "r.h5") as rec:
        plan = Plan.from_record(rec.metadata["simulation"])
        own = reconstruct(rec)
        same = reconstruct(rec, plan)
        # the plan alone, without the record it was read from: the same oracle (its windows from the plan's
        # schedule, its pixels from the plan's region)
        alone = reconstruct(rec, plan.replace(record=None))
        px = plan.pixels
        other = reconstruct(rec, plan.replace(pixels=PixelModel(SensorModel(theta_on=0.3, theta_off=0.3),
                                                                px.gain_e_per_s_per_unit, px.blank_rate_e_per_s)))
    assert np.array_equal(same.responses, own.responses)
    assert np.array_equal(alone.responses, own.responses) and alone.summary.to_dict() == own.summary.to_dict()
    assert not np.allclose(other.responses, own.responses)


def test_the_calibrated_route_makes_no_record(tmp_path, monkeypatch):
    """The calibrated route hands the stages the bench's plan with the fitted pixel model, the matched captures'
    times on the recording's clock and the placement; no SimulationRecord is built."""
    import evtk.plan.record as record_module
    import evtk.reconstruct.pipeline as pipeline
    from evtk.plan import Plan
    from evtk.reconstruct import fit as fit_module
    from evtk.reconstruct import reconstruct, schedule_of_record

    assert not hasattr(fit_module, "_fitted_record") and not hasattr(fit_module, "fitted_record")
    _simulated(tmp_path, levels=5)
    seen = []
    real = pipeline._reconstruct_counts

    def spy(counts, run, *args, **kwargs):
        seen.append(run)
        return real(counts, run, *args, **kwargs)

    made = []
    init = record_module.SimulationRecord.__init__

    def no_record(self, *args, **kwargs):
        made.append(1)
        init(self, *args, **kwargs)

    with evtk.open(tmp_path / "r.h5") as rec:
        bench_plan = schedule_of_record(rec.metadata["simulation"])
        monkeypatch.setattr(pipeline, "_reconstruct_counts", spy)
        monkeypatch.setattr(record_module.SimulationRecord, "__init__", no_record)
        result = reconstruct(rec, bench_plan)
    assert result.summary.pixel_model_from == "the run's own level captures"
    assert seen and not made
    run = seen[0]
    assert isinstance(run, Plan) and run.record is None and run.pixels is not None
    assert run.pixels.sensor.theta_on == pytest.approx(result.summary.pixel_model["theta_on"])
    assert run.region == tuple(result.summary.region) and len(run.schedule) == result.summary.windows
    assert np.array_equal(run.schedule.t_on_us, result.counts.windows.t_start_us - result.summary.skip_us)


def test_the_schedule_is_a_plan_not_a_dict(tmp_path):
    """Issue 30: ``read_schedule`` gives the plan itself (attributes, no seven-key dict); reading a plan by key
    still works for old callers but warns, and evtk's own reconstruction and calibration never do it."""
    import warnings

    from evtk.calibrate import calibrate
    from evtk.patterns import write_patterns
    from evtk.plan import Plan, read_schedule
    from evtk.reconstruct import reconstruct

    sim = _simulated(tmp_path, levels=4, calibration=2)
    write_patterns(sim, tmp_path / "p")
    path = tmp_path / "p" / "schedule.json"
    plan = read_schedule(path)
    assert isinstance(plan, Plan) and not isinstance(plan, dict)
    assert plan.kernels.shape[1:] == (3, 3) and plan.window_us == sim.window_us and plan.dot_spacing == 4
    with pytest.warns(DeprecationWarning, match=r"plan\.kernels"):
        assert plan["kernels"] is plan.kernels
    with pytest.raises(KeyError):
        plan["region"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        with evtk.open(tmp_path / "r.h5") as rec:
            cal = calibrate(rec, path)
            result = reconstruct(rec, cal.place(Plan.read(path)))
    assert result.summary.match["matched"] > 0
