import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

import evtk

# CI explores a fixed set of examples (reproducible verdicts); local runs
# draw new ones every time.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"

# commands that fan out run serially in the tests unless a test asks for a cluster (test_cluster.py)
os.environ.setdefault("EVTK_SCHEDULER", "serial")


def event_stream_atis_file(path, records, width, height):
    """Write ``records`` (``event_stream.atis_dtype``) as an ATIS Event Stream with event_stream's own Encoder, in
    a child process: event_stream 1.6.3's ATIS write turns numpy's bool dtype little-endian (``<b1``) for the rest
    of the process it runs in, and Pillow then refuses every bool array (DMD frames among them)."""
    import subprocess
    import sys

    saved = Path(str(path) + ".npy")
    np.save(saved, records)
    code = ("import sys, numpy as np, event_stream\n"
            "with event_stream.Encoder(sys.argv[2], 'atis', int(sys.argv[3]), int(sys.argv[4])) as encoder:\n"
            "    encoder.write(np.load(sys.argv[1]))\n")
    subprocess.run([sys.executable, "-c", code, str(saved), str(path), str(width), str(height)], check=True)
    saved.unlink()


def random_events(n, seed=0, sensor_size=(320, 240), t0=0, span_us=1_000_000, sort=True):
    rng = np.random.default_rng(seed)
    t = rng.integers(t0, t0 + span_us, n, dtype=np.int64)
    if sort:
        t = np.sort(t)
    w, h = sensor_size
    return evtk.Events(
        t,
        rng.integers(0, w, n, dtype=np.uint16),
        rng.integers(0, h, n, dtype=np.uint16),
        rng.integers(0, 2, n, dtype=np.uint8),
        sensor_size,
    )


@pytest.fixture
def fixtures_dir():
    return FIXTURES


@pytest.fixture(params=["compiled", "python"])
def compiled(request, monkeypatch):
    """Each test that uses it runs twice: with evtk's compiled kernels (``evtk._ckernels``: the counting of fixed
    windows, the AEDAT4 reader's LZ4 batches; skipped where they were not built) and without them
    (``EVTK_NATIVE=0``: numpy's counting, the reader's Python loop). Modules of their tests take it for all their
    tests (``pytestmark = pytest.mark.usefixtures("compiled")``)."""
    from evtk import _native

    if request.param == "compiled" and not _native.BUILT:
        pytest.skip("evtk._ckernels was not built (no C compiler at install)")
    monkeypatch.setenv("EVTK_NATIVE", "1" if request.param == "compiled" else "0")
    return request.param


def modules_after(code: str) -> list[str]:
    """The modules a fresh interpreter has loaded after running ``code`` with this checkout's evtk first on the
    path (sorted); the calling test fails, with the child's stderr, when the code fails."""
    import json
    import subprocess
    import sys

    code += "\nimport json as _j, sys as _s\nprint('MODULES', _j.dumps(sorted(_s.modules)))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PYTHONPATH": str(Path(evtk.__file__).parents[1]), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.split("MODULES", 1)[1])


class Hang(Exception):
    """What :func:`no_hang` raises when its block runs past the limit."""


def no_hang(seconds=10.0):
    """A context manager that stops its block with :class:`Hang` after ``seconds`` (SIGALRM): a guard
    against parsers that hang or take minutes, not a speed assertion (the limit is generous)."""
    import contextlib
    import signal

    @contextlib.contextmanager
    def guard():
        def fire(signum, frame):
            raise Hang(f"still running after {seconds} s")

        old = signal.signal(signal.SIGALRM, fire)
        signal.setitimer(signal.ITIMER_REAL, seconds)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)

    return guard()
# -- the `slow` marker --------------------------------------------------------------------------------------------
#
# `pytest` (CI, README) runs everything; `pytest -m "not slow"` is the quick loop while developing. The tests
# below took 2 s or more each here (`pytest --durations=0`, a few files at a time, on two shared cores); tests
# whose time is mostly numba compiling a kernel for the first time stay in the quick loop, as the next test
# would pay it instead. Marked here rather than in each file, so that one list says what the quick loop leaves
# out; a name that no longer exists in its file is an error, not a silently unmarked test.
SLOW = {
    "test_bcnn.py": {"test_bundled_data_sets", "test_channel_masks_score_each_channel",
                     "test_cli_classify_and_robustness", "test_layerwise_training_learns_a_separable_toy_task",
                     "test_metropolis_improves_a_toy_objective_and_is_reproducible",
                     "test_ste_reference_learns_and_yields_a_binary_network"},
    "test_calibrate.py": {"test_bench_round_trip_patterns_simulate_calibrate_reconstruct",
                          "test_calibration_bad_input_is_one_clear_error_each",
                          "test_calibration_recovers_where_the_response_lies"},
    "test_camera.py": {"test_a_rotated_defocused_view_is_deblurred_in_two_dimensions",
                       "test_calibration_measures_the_cameras_defocus",
                       "test_each_pixels_threshold_is_recovered_within_2_percent",
                       "test_reconstruction_through_a_random_pose_stays_near_the_oracle"},
    "test_cluster.py": {"test_batch_on_a_cluster_equals_serial_and_resumes", "test_sweeps_equal_serial_runs",
                        "test_time_split_reconstruction_equals_the_whole", "test_to_dask_reads_lazily_by_time"},
    "test_crash_safety.py": {"test_killed_writer_keeps_previous_file",
                             "test_parquet_without_footer_salvages_complete_row_groups",
                             "test_salvaged_recording_left_open_exits_cleanly",
                             "test_writer_killed_at_random_moments"},
    "test_docs.py": {"test_snippets_run_as_written", "test_walkthrough_runs_in_page_order"},
    "test_fit.py": {"test_a_calibration_run_brings_the_pixel_model_to_a_job_without_level_captures",
                    "test_a_light_that_follows_its_trigger_edges_late_is_timed_and_the_windows_follow_it",
                    "test_a_pixel_model_that_misreads_the_levels_is_given_up",
                    "test_cli_defaults_to_the_calibrated_route_and_says_which",
                    "test_the_calibrated_route_is_within_15_percent_of_the_oracle",
                    "test_the_calibrated_route_needs_nothing_of_the_record",
                    "test_the_refractory_period_is_measured_where_the_gaps_show_it",
                    "test_the_rise_timed_half_way_up_pins_the_time_constant"},
    "test_guards.py": {"test_a_camera_turned_half_a_turn_reconstructs_as_well_as_the_upright_one",
                       "test_a_mirrored_camera_reconstructs_as_the_upright_one",
                       "test_a_pixel_model_no_camera_has_is_refused_and_never_saved",
                       "test_a_refractory_period_is_resolved_only_on_significant_evidence",
                       "test_a_synchronous_frame_readout_is_named_not_reconstructed",
                       "test_the_exp_n_theta_route_reads_a_mirrored_camera_through_the_calibrations_map"},
    "test_hdf5_parquet.py": {"test_convert_every_pair", "test_damaged_dsec_blosc1_chunk_is_an_error_not_a_crash",
                             "test_parquet_footer_with_a_bad_column_type_is_an_error_not_an_abort",
                             "test_sound_blosc1_chunks_pass_the_check"},
    "test_hostile.py": {"test_batch_onto_a_full_disk_writes_its_manifest",
                        "test_writing_onto_a_full_disk_is_one_error_and_the_old_file_stays"},
    "test_hostile_outputs.py": {"test_contact_sheet_page_replaces_no_other_output"},
    "test_integrity.py": {"test_no_bit_flip_gives_other_events", "test_npz_bomb_refused"},
    "test_layers.py": {"test_no_import_runs_back_up"},
    "test_metrics.py": {"test_cumulative_factor_extremes_stay_finite_in_log_space",
                        "test_poisson_counts_give_the_sinad_their_moments_imply"},
    "test_physics.py": {"test_calibrated_route_holds_on_a_log_node_pixel"},
    "test_plan_pipeline.py": {"test_the_schedule_is_a_plan_not_a_dict"},
    "test_plots.py": {"test_contact_sheet_of_counts_gives_counts_and_light_a_bar_each",
                      "test_contact_sheet_pages_are_balanced_labelled_and_share_a_scale_per_row"},
    "test_real_files.py": {"test_every_file_a_reference_reader_decodes_reads_exactly"},
    "test_reconstruct.py": {"test_cli_reconstruct_outputs", "test_one_entry_takes_its_route_from_the_plan"},
    "test_reconstruct_fixed.py": {"test_the_cli_on_fixed_windows_loads_no_compiler_and_stores_responses_only"},
    "test_recover.py": {"test_cli_recover", "test_search_agrees_with_brute_force_on_noisy_targets",
                        "test_success_rate_rows_and_light"},
    "test_sensor.py": {"test_ziggurat_normals_follow_the_normal_law"},
    "test_simulate.py": {"test_extreme_light_and_patterns"},
    "test_sweeps.py": {"test_cli_enob_flips_tradeoff", "test_demo_runs_on_the_embedded_defaults",
                       "test_recording_noise_in_batches_equals_the_whole_reconstruction",
                       "test_scene_noise_matches_the_metrics_on_each_scene"},
}


@pytest.hookimpl(tryfirst=True)  # before -k and -m deselect: every test of a collected file is seen
def pytest_collection_modifyitems(config, items):
    checked = set()
    for item in items:
        names = SLOW.get(item.path.name) if item.path.parent.name == "tests" else None
        module = getattr(item, "module", None)
        if names is None or module is None:
            continue
        if item.path not in checked:
            checked.add(item.path)
            missing = sorted(n for n in names if not callable(getattr(module, n, None)))
            if missing:
                raise pytest.UsageError(f"tests/conftest.py marks as slow what tests/{item.path.name} does not "
                                        f"define: {', '.join(missing)}")
        if getattr(item, "originalname", item.name) in names:
            item.add_marker(pytest.mark.slow)
