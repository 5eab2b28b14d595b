"""Every public callable of the library is typed and documented (issue 30, item 4).

"Public" is every function and class a non-private module of :mod:`evtk` offers (its ``__all__``, or its names
without a leading underscore that it defines itself), and every public method of those classes. The command-line
package is left out: its commands are documented by their ``--help``, which ``docs/cli.md`` renders and
``tests/test_options.py`` checks. Each callable must pass numpydoc's validator on the checks below and carry type
hints on every parameter and on its return.

``PENDING`` names the callables not yet brought up to this; it may only shrink (a test fails when one of them
passes, so the list is never stale), and the goal is an empty list.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import evtk

numpydoc_validate = pytest.importorskip("numpydoc.validate").validate

#: numpydoc's codes we enforce: a docstring exists, its summary is one line, every parameter is documented (and
#: none that does not exist), parameters have descriptions, and a callable that returns something has Returns.
CHECKS = {"GL08", "SS01", "PR01", "PR02", "PR07", "RT01", "RT03"}


def _public_modules() -> list[str]:
    names = []
    for info in pkgutil.walk_packages(evtk.__path__, "evtk."):
        parts = info.name.split(".")[1:]
        if parts[0] == "cli" or any(p.startswith("_") for p in parts):
            continue
        names.append(info.name)
    return names


def public_callables() -> list[str]:
    """Dotted names of the public functions, classes and methods, each once (where it is defined)."""
    seen: dict[str, None] = {}
    for name in _public_modules():
        module = importlib.import_module(name)
        exported = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
        for attr in exported:
            obj = getattr(module, attr, None)
            if not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            if not getattr(obj, "__module__", "").startswith("evtk."):
                continue
            if any(p.startswith("_") for p in obj.__module__.split(".")[1:]) and not getattr(module, "__all__", None):
                continue
            qual = f"{obj.__module__}.{obj.__qualname__}"
            seen[qual] = None
            if inspect.isclass(obj):
                for meth, value in vars(obj).items():
                    if not meth.startswith("_") and (inspect.isfunction(value) or isinstance(value, (classmethod, staticmethod))):
                        seen[f"{qual}.{meth}"] = None
    return list(seen)


def _resolve(dotted: str) -> object:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = inspect.getattr_static(obj, attr) if inspect.isclass(obj) else getattr(obj, attr)
        return obj.__func__ if isinstance(obj, (classmethod, staticmethod)) else obj
    raise LookupError(dotted)


def problems(dotted: str) -> list[str]:
    """What keeps ``dotted`` from being typed and documented: numpydoc codes, and unannotated names."""
    found = [f"{code}: {msg}" for code, msg in numpydoc_validate(dotted)["errors"] if code in CHECKS]
    obj = _resolve(dotted)
    func = obj.__init__ if inspect.isclass(obj) else obj  # type: ignore[misc]
    if inspect.isclass(obj) and func is object.__init__:
        return found
    try:
        sig = inspect.signature(func)
    except (TypeError, ValueError):
        return found
    params = list(sig.parameters.values())
    if params and params[0].name in ("self", "cls"):
        params = params[1:]
    missing = [p.name for p in params if p.annotation is inspect.Parameter.empty]
    if missing:
        found.append(f"no type hint on {', '.join(missing)}")
    if not inspect.isclass(obj) and sig.return_annotation is inspect.Signature.empty:
        found.append("no return type hint")
    return found


#: Not yet typed and documented; remove a name when its callable passes (the list only shrinks).
PENDING: set[str] = set(
    """
    evtk.batch.batch_reconstruct
    evtk.batch.find_recordings
    evtk.batch.reconstruct_split
    evtk.bcnn.BCNN
    evtk.bcnn.BCNN.accuracy
    evtk.bcnn.BCNN.decide
    evtk.bcnn.BCNN.forward
    evtk.bcnn.BCNN.layer
    evtk.bcnn.BCNN.predict
    evtk.bcnn.BCNN.random
    evtk.bcnn.BCNN.scores
    evtk.bcnn.DigitalBackend
    evtk.bcnn.DigitalBackend.correlate
    evtk.bcnn.OpticalBackend
    evtk.bcnn.OpticalBackend.correlate
    evtk.bcnn.bce_loss
    evtk.bcnn.binary_correlate
    evtk.bcnn.poisson_robustness
    evtk.bcnn.resample_matrix
    evtk.calibrate.Calibration
    evtk.calibrate.background_rate_hz
    evtk.calibrate.calibrate
    evtk.calibrate.dot_blur_px
    evtk.calibrate.load_calibration
    evtk.calibrate.plot_calibration
    evtk.calibrate.save_calibration
    evtk.cluster.dask_available
    evtk.cluster.default_scheduler
    evtk.cluster.run_tasks
    evtk.cluster.scheduler
    evtk.cluster.to_dask
    evtk.datasets.Dataset
    evtk.datasets.Dataset.summary
    evtk.datasets.baselines
    evtk.datasets.binarize_images
    evtk.datasets.face_not_face
    evtk.datasets.letters_digits
    evtk.datasets.load_dataset
    evtk.datasets.read_cifar_batch
    evtk.datasets.read_idx
    evtk.demo.run_demo
    evtk.errors.EvtkError
    evtk.errors.FormatError
    evtk.errors.check_parameters
    evtk.errors.one_line
    evtk.events.Events
    evtk.events.Events.between
    evtk.events.Events.concatenate
    evtk.events.Events.empty
    evtk.events.Events.from_arrow
    evtk.events.Events.from_structured
    evtk.events.Events.out_of_bounds
    evtk.events.Events.sorted
    evtk.events.Events.stamp_period_us
    evtk.events.Events.to_arrow
    evtk.events.Events.to_structured
    evtk.events.TriggerKind
    evtk.events.Triggers
    evtk.events.Triggers.between
    evtk.events.Triggers.of_channel
    evtk.events.Triggers.of_kind
    evtk.io._convert.convert
    evtk.io.aedat4.reader.Recording
    evtk.io.aedat4.reader.Recording.events
    evtk.io.aedat4.reader.Recording.iter_events
    evtk.io.aedat4.reader.Recording.other_streams
    evtk.io.aedat4.reader.Recording.packets
    evtk.io.aedat4.reader.Recording.triggers
    evtk.io.aedat4.writer.Aedat4Writer
    evtk.io.aedat4.writer.Aedat4Writer.write_events
    evtk.io.aedat4.writer.Aedat4Writer.write_packet
    evtk.io.aedat4.writer.Aedat4Writer.write_triggers
    evtk.io.aedat4.writer.write_aedat4
    evtk.io.aedat_legacy.LegacyAedatRecording
    evtk.io.aedat_legacy.LegacyAedatRecording.events
    evtk.io.aedat_legacy.LegacyAedatRecording.iter_events
    evtk.io.arrow.ParquetRecording
    evtk.io.arrow.ParquetRecording.events
    evtk.io.arrow.ParquetRecording.iter_events
    evtk.io.arrow.ParquetRecording.triggers
    evtk.io.arrow.from_arrow
    evtk.io.arrow.to_arrow
    evtk.io.arrow.write_parquet
    evtk.io.base.BaseRecording
    evtk.io.base.BaseRecording.close
    evtk.io.base.BaseRecording.events
    evtk.io.base.BaseRecording.info
    evtk.io.base.BaseRecording.iter_events
    evtk.io.base.BaseRecording.scan
    evtk.io.base.BaseRecording.triggers
    evtk.io.base.BaseWriter.abort
    evtk.io.base.BaseWriter.close
    evtk.io.base.Damage
    evtk.io.base.StreamInfo
    evtk.io.base.StreamInfo.as_dict
    evtk.io.base.text_header
    evtk.io.base.time_chunks
    evtk.io.base.window_blocks
    evtk.io.decoded.DecodedRecording
    evtk.io.decoded.DecodedRecording.events
    evtk.io.decoded.DecodedRecording.iter_events
    evtk.io.decoded.DecodedRecording.triggers
    evtk.io.decoded.NmnistRecording
    evtk.io.decoded.TextRecording
    evtk.io.decoded.csv_lines
    evtk.io.decoded.sniff_nmnist
    evtk.io.detect_format
    evtk.io.foreign.ForeignWriter
    evtk.io.hdf5.checks.blosc1_chunk_damage
    evtk.io.hdf5.checks.root_link
    evtk.io.hdf5.reader.Hdf5Recording
    evtk.io.hdf5.reader.Hdf5Recording.events
    evtk.io.hdf5.reader.Hdf5Recording.iter_events
    evtk.io.hdf5.reader.Hdf5Recording.read_array
    evtk.io.hdf5.reader.Hdf5Recording.read_arrays
    evtk.io.hdf5.reader.Hdf5Recording.triggers
    evtk.io.hdf5.writer.Hdf5Writer
    evtk.io.hdf5.writer.Hdf5Writer.write_array
    evtk.io.hdf5.writer.Hdf5Writer.write_events
    evtk.io.hdf5.writer.Hdf5Writer.write_triggers
    evtk.io.hdf5.writer.write_hdf5
    evtk.io.open
    evtk.io.open_writer
    evtk.io.prophesee.decoders.sniff
    evtk.io.prophesee.decoders.sniff_lines
    evtk.io.prophesee.recording.EventStreamRecording
    evtk.io.prophesee.recording.PropheseeRecording
    evtk.io.prophesee.recording.PropheseeRecording.events
    evtk.io.prophesee.recording.PropheseeRecording.iter_events
    evtk.io.prophesee.recording.PropheseeRecording.triggers
    evtk.io.read_events
    evtk.io.reconstruction.describe_reconstruction
    evtk.io.reconstruction.is_reconstruction
    evtk.io.reconstruction.save_reconstruction
    evtk.io.table.columns_to_table
    evtk.io.table.load_json
    evtk.io.table.sensor_dims
    evtk.io.table.table_to_columns
    evtk.io.write_events
    evtk.io.write_format
    evtk.metrics.flips.FlipReport
    evtk.metrics.flips.FlipReport.to_dict
    evtk.metrics.flips.flip_rates
    evtk.metrics.poisson.capture_terms
    evtk.metrics.poisson.cumulative_factor
    evtk.metrics.poisson.log_cumulative_factor
    evtk.metrics.poisson.lowest_cumulative_factor
    evtk.metrics.poisson.poisson_log_pmf
    evtk.metrics.poisson.poisson_pmf
    evtk.metrics.sinad.SinadAccumulator
    evtk.metrics.sinad.SinadAccumulator.add
    evtk.metrics.sinad.SinadAccumulator.report
    evtk.metrics.sinad.SinadReport
    evtk.metrics.sinad.SinadReport.to_dict
    evtk.metrics.sinad.enob_bits
    evtk.metrics.sinad.sinad
    evtk.optics.bench.Bench
    evtk.optics.bench.Bench.check_pattern
    evtk.optics.bench.Bench.electrons_per_s_per_unit
    evtk.optics.bench.Bench.from_dict
    evtk.optics.bench.Bench.photons_per_s
    evtk.optics.bench.Bench.replace
    evtk.optics.bench.Bench.shadow_model_note
    evtk.optics.bench.Bench.to_dict
    evtk.optics.bench.load_bench
    evtk.optics.bench.save_bench
    evtk.optics.camera.Camera
    evtk.optics.camera.Camera.from_dict
    evtk.optics.camera.Camera.homography
    evtk.optics.camera.Camera.sensor_region
    evtk.optics.camera.Camera.to_dict
    evtk.optics.camera.Camera.to_nominal
    evtk.optics.camera.Camera.to_sensor
    evtk.optics.camera.Camera.view
    evtk.optics.camera.CellMap
    evtk.optics.camera.CellMap.axis_aligned
    evtk.optics.camera.CellMap.scale_shift
    evtk.optics.camera.CellMap.to_cells
    evtk.optics.camera.CellMap.to_pixels
    evtk.optics.camera.footprint_light
    evtk.optics.camera.footprint_points
    evtk.optics.camera.radial_distort
    evtk.optics.camera.radial_undistort
    evtk.optics.camera.render_nominal
    evtk.optics.geometry.effective_extents_um
    evtk.optics.geometry.effective_stride
    evtk.optics.geometry.min_capture_window_us
    evtk.optics.geometry.optical_scaling
    evtk.optics.geometry.shadow_magnification
    evtk.optics.geometry.software_scaling
    evtk.optics.geometry.stride_mm
    evtk.optics.screen.brightest_response
    evtk.optics.screen.glow_response
    evtk.optics.screen.ideal_response
    evtk.optics.screen.response_origin_px
    evtk.optics.screen.response_region
    evtk.optics.screen.response_to_sensor_grid
    evtk.optics.screen.screen_response
    evtk.optimize.fit_mask
    evtk.optimize.metropolis
    evtk.optimize.train_layerwise
    evtk.optimize.train_ste
    evtk.patterns.dmd_frame
    evtk.patterns.job_simulation
    evtk.patterns.load_job
    evtk.patterns.write_patterns
    evtk.plots.contact_sheet
    evtk.plots.plot_enob
    evtk.plots.plot_flips
    evtk.plots.plot_recovery
    evtk.plots.plot_robustness
    evtk.plots.plot_success
    evtk.plots.plot_tradeoff
    evtk.plots.wilson_interval
    evtk.reconstruct.accumulate.accumulate
    evtk.reconstruct.calibrated.fit_on_edges
    evtk.reconstruct.deblur.relative_noise
    evtk.reconstruct.deblur.sampling_matrix
    evtk.reconstruct.deblur.solve_cells
    evtk.reconstruct.deblur.wiener_lambda
    evtk.reconstruct.fit.LevelStatistics
    evtk.reconstruct.fit.PixelFit
    evtk.reconstruct.fit.fit_pixel_model
    evtk.reconstruct.fit.fit_refractory
    evtk.reconstruct.fit.hot_pixels
    evtk.reconstruct.fit.interior_pixels
    evtk.reconstruct.fit.level_off_times
    evtk.reconstruct.fit.level_rise_times
    evtk.reconstruct.fit.level_statistics
    evtk.reconstruct.fit.on_gaps
    evtk.reconstruct.fit.predict_levels
    evtk.reconstruct.grid.footprint_matrix
    evtk.reconstruct.linearize.count_curve
    evtk.reconstruct.options.ReconstructOptions
    evtk.reconstruct.options.ReconstructOptions.kwargs
    evtk.reconstruct.windows.WindowCounts
    evtk.reconstruct.windows.WindowCounts.from_capture_counts
    evtk.reconstruct.windows.Windows
    evtk.reconstruct.windows.windows_from_schedule
    evtk.reconstruct.windows.windows_from_triggers
    evtk.reconstruct.windows.windows_periodic
    evtk.recover.Recovery
    evtk.recover.Recovery.to_dict
    evtk.recover.all_kernels
    evtk.recover.classify
    evtk.recover.device_responses
    evtk.recover.is_shift
    evtk.recover.kernel_bits
    evtk.recover.kernel_from_bits
    evtk.recover.recover_brute
    evtk.recover.recover_search
    evtk.recover.response_matrix
    evtk.recover.success_rate
    evtk.sensor.SensorModel
    evtk.sensor.SensorModel.from_dict
    evtk.sensor.SensorModel.replace
    evtk.sensor.SensorModel.stamp
    evtk.sensor.SensorModel.to_dict
    evtk.sensor.log_noise_std
    evtk.sensor.pixel_thresholds
    evtk.sensor.simulate_pixels
    evtk.sensor.time_constant_us
    evtk.settings.Spec
    evtk.settings.Spec.describe
    evtk.settings.check_array
    evtk.settings.check_matrix
    evtk.settings.check_origin
    evtk.settings.check_region
    evtk.settings.check_table
    evtk.settings.check_value
    evtk.settings.read_table
    evtk.settings.toml_value
    evtk.simulate.run.Simulation
    evtk.simulate.table.table_batches
    evtk.sweeps.flip_sweep
    evtk.sweeps.pareto_front
    evtk.sweeps.random_kernels
    evtk.sweeps.recording_noise
    evtk.sweeps.scene_noise
    evtk.sweeps.simulated_reconstruction
    evtk.sweeps.tradeoff
""".split()
)

ALL = public_callables()


def test_the_list_of_public_callables_is_sane():
    assert len(ALL) > 300, "the walk over evtk's modules found too few callables"
    assert "evtk.events.Events" in ALL and any(d.endswith(".read_events") for d in ALL)


@pytest.mark.parametrize("dotted", [d for d in ALL if d not in PENDING])
def test_public_callable_is_typed_and_documented(dotted):
    assert problems(dotted) == []


def test_pending_only_shrinks():
    passing = sorted(d for d in PENDING if d in ALL and not problems(d))
    assert not passing, f"these now pass; take them off PENDING: {passing}"
    gone = sorted(PENDING - set(ALL))
    assert not gone, f"these are no longer public callables; take them off PENDING: {gone}"
