"""Many recordings at once: one reconstruction task per recording, a manifest, resumable.

:func:`batch_reconstruct` reconstructs every input into ``out_dir`` (one
evtk HDF5 or NPZ file per input, each written atomically), on the workers of
a Dask client when given (:mod:`evtk.cluster`), and writes ``batch.json``:
every input with its status ("ok", "skipped": already done, "error"), output,
events, windows, seconds and error. A damaged input is an "error" entry;
the rest of the batch completes. Running it again skips inputs whose output
exists (outputs only appear complete), so an interrupted batch resumes.

Every input has its own output name (inputs of one name from different
folders are told apart by folder, extension or a digest of their path), and
an output is put in place only if the file there is still the one the batch
saw when it began (or none): a result another batch wrote into the same folder
meanwhile is left alone and this input is an "error" entry that says so. A
folder's files of a format evtk does not read are listed under ``left_out``.

A recording with more than ``split_events`` events is split into tasks by
time: :func:`reconstruct_split` counts contiguous groups of whole windows
in separate tasks (each reads only its time span, through the AEDAT4 data
table or the HDF5 time index) and stitches the counts, so the result is
exactly the single-process one.
"""

from __future__ import annotations

import glob
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from ._atomic import AtomicFile, check_outputs, expect_target, file_identity
from .cluster import run_tasks
from .errors import EvtkError
from .io import open as open_recording
from .io.reconstruction import save_reconstruction
from .plan import SimulationRecord
from .reconstruct import (
    Reconstruction,
    WindowCounts,
    Windows,
    accumulate,
    check_crop,
    plan,
    reconstruct_counts,
    wants_times,
)
from .workflow import reconstruct_recording

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["find_recordings", "batch_reconstruct", "reconstruct_split", "MANIFEST"]

MANIFEST = "batch.json"
#: Extensions of every format evtk reads. A folder's files with the first five are always taken (a damaged one
#: is an error entry); the others (names other programs use too, or none) when their first bytes name a format
#: evtk reads (:func:`evtk.io.detect_format`), and are listed as left out otherwise.
RECORDING_EXTENSIONS = (".aedat4", ".h5", ".hdf5", ".parquet", ".pq", ".aedat", ".raw", ".dat", ".es")
_ALWAYS = RECORDING_EXTENSIONS[:5]


def find_recordings(inputs: Iterable[str | os.PathLike[str]],
                    left_out: list[tuple[str, str]] | None = None) -> list[str]:
    """Files named, recordings inside directories named (not recursive), and glob patterns, sorted, without repeats.

    A directory's files are recordings when their extension is one of
    evtk's own formats (AEDAT4, HDF5, Parquet) or their first bytes name a
    format evtk reads (legacy AEDAT, Prophesee RAW and DAT, Event Stream
    too), whatever their extension.

    Parameters
    ----------
    inputs : iterable of str or os.PathLike
        Files, folders and glob patterns.
    left_out : list of (str, str), optional
        Receives ``(file, reason)`` for each file of a folder that is not a recording.

    Returns
    -------
    list of str
        The recordings (a missing file or a pattern matching nothing stays, to be reported as an error).
    """
    from .errors import one_line
    from .io import detect_format

    found = []
    for item in inputs:
        item = os.fspath(item)
        if os.path.isdir(item):
            for f in sorted(os.listdir(item)):
                full = os.path.join(item, f)
                if not os.path.isfile(full):
                    continue
                if f.lower().endswith(_ALWAYS):
                    found.append(full)
                    continue
                try:
                    detect_format(full)
                except EvtkError as exc:
                    if left_out is not None:
                        left_out.append((full, one_line(str(exc))))
                    continue
                found.append(full)
        elif any(c in item for c in "*?["):
            # a pattern that matches nothing stays, to be reported as such
            found += sorted(glob.glob(item)) or [item]
        else:
            found.append(item)  # a missing file becomes an "error" entry, not a crash
    seen, out = set(), []
    for f in found:
        key = os.path.abspath(f)
        if key not in seen:
            seen.add(key)
            out.append(f)
    return out


def _output_names(inputs, out_dir, ext):
    """One output name per input: the input's stem, or, where stems repeat, the shortest of stem and folder,
    file name, file name and folder, and stem and a digest of the full path that tells them apart."""
    import hashlib

    def schemes(f):
        stem, name = os.path.splitext(os.path.basename(f))[0], os.path.basename(f)
        folder = os.path.basename(os.path.dirname(os.path.abspath(f))) or "root"
        digest = hashlib.sha1(os.path.abspath(f).encode("utf-8", "surrogateescape")).hexdigest()[:10]
        return [stem, f"{stem}.{folder}", name, f"{name}.{folder}", f"{stem}.{digest}"]

    groups = {}
    for f in inputs:
        groups.setdefault(os.path.splitext(os.path.basename(f))[0], []).append(f)
    out, taken = {}, set()
    for stem, files in groups.items():
        if len(files) == 1 and stem not in taken:
            out[files[0]], taken = stem, taken | {stem}
            continue
        for k in range(5):  # the first scheme that tells the group's files apart and clashes with no other
            names = [schemes(f)[k] for f in files]
            if len(set(names)) == len(names) and not taken & set(names):
                break
        out.update(zip(files, names))
        taken |= set(names)
    if len(set(out.values())) != len(out):  # pragma: no cover - the digests differ
        raise EvtkError("inputs map to the same output name; rename them or run them in separate batches")
    return {f: os.path.join(out_dir, name + ext) for f, name in out.items()}


def _reconstruct_one(args):
    """A batch task: reconstruct one recording into its output; never raises for a bad input."""

    path, out, options, seen = args
    t0 = time.perf_counter()
    entry = {"input": path, "output": out, "status": "error", "events": None, "windows": None, "seconds": None,
             "error": None}
    try:
        if not os.path.exists(path) and any(c in path for c in "*?["):
            raise EvtkError(f"the pattern {path!r} matches no file")
        with open_recording(path) as rec:
            result = reconstruct_recording(rec, **options)
            events = rec.info()["events"]
            sensor = rec.sensor_size
        with expect_target(out, seen):  # what another batch wrote there meanwhile is reported, not replaced
            save_reconstruction(out, result, sensor, {"source": path})
        entry.update(status="ok", events=int(events), windows=int(result.summary.windows))
    except Exception as exc:  # noqa: BLE001 - one bad input is recorded; the batch goes on
        entry["error"] = _error_text(exc)
    entry["seconds"] = time.perf_counter() - t0
    return entry


def _error_text(exc) -> str:
    """One line for the manifest: evtk's own message, or the exception's type and message."""
    text = " ".join(str(exc).split())
    if isinstance(exc, EvtkError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _accumulate_part(args):
    """A split task: counts of one contiguous group of windows of one recording."""

    path, starts, ends, capture, region, chunk_events, times = args
    with open_recording(path) as rec:
        c = accumulate(rec, Windows(starts, ends, capture, "part"), region, chunk_events=chunk_events, times=times)
    return c.on, c.off, c.events_used, c.on_first_us, c.on_last_us


def reconstruct_split(path: str | os.PathLike[str], parts: int, client: Client | None = None,
                      chunk_events: int = 4_000_000, **options: Any) -> Reconstruction:
    """:func:`evtk.reconstruct.reconstruct` of one recording as ``parts`` tasks over groups of whole windows.

    Equals the single-process result exactly (the counts are the same
    integers). ``options`` are ``reconstruct``'s (window, skip_us, length_us,
    region, size, ...).

    Parameters
    ----------
    path : str or os.PathLike
        The recording; each task opens it and reads only its windows' time span.
    parts : int
        Number of tasks (at most one per window): the windows, in time order, split into this many groups.
    client : distributed.Client, optional
        Where the tasks run (:func:`evtk.cluster.scheduler`); None: one after another in this process.
    chunk_events : int
        Events a task reads at a time.
    **options : Any
        :func:`evtk.reconstruct.reconstruct`'s keyword arguments (``oracle`` is ignored: the split runs on the
        record's own model).

    Returns
    -------
    evtk.reconstruct.Reconstruction
        The same result as :func:`evtk.reconstruct.reconstruct` on the whole recording.

    Raises
    ------
    EvtkError
        As :func:`evtk.reconstruct.reconstruct`: an unreadable recording, no schedule for ``window="schedule"``,
        a bad crop or region, counts over the memory budget.
    """

    opts = dict(options)
    opts.pop("oracle", None)  # the split runs the pipeline on the record's model: the oracle, for simulated runs
    window = opts.pop("window", "schedule")
    skip_us, length_us = opts.get("skip_us", 0), opts.get("length_us")
    check_crop(opts.get("crop", "valid"))
    with open_recording(path) as rec:
        sim, win, region = plan(rec, window, skip_us, length_us, opts.pop("region", None))
    order = np.argsort(win.t_start_us, kind="stable")
    groups = [g for g in np.array_split(order, max(1, min(int(parts), len(order)))) if g.size]
    times = wants_times(sim, opts.get("linear", True), opts.get("theta"), opts.get("timing"))
    tasks = [(path, win.t_start_us[g], win.t_end_us[g], win.capture[g], region, chunk_events, times)
             for g in groups]
    x0, x1, y0, y1 = region
    on = np.zeros((len(win), y1 - y0, x1 - x0), np.int32)
    off = np.zeros_like(on)
    first, last = (np.full_like(on, -1), np.full_like(on, -1)) if times else (None, None)
    used = 0
    for g, (on_g, off_g, used_g, first_g, last_g) in zip(groups, run_tasks(_accumulate_part, tasks, client)):
        on[g], off[g] = on_g, off_g
        if first is not None and last is not None:  # (with times)
            first[g], last[g] = first_g, last_g
        used += used_g
    return reconstruct_counts(WindowCounts(on, off, win, region, int(used), first, last), sim, **opts)


def _split_large(todo, split_events, client, entries):
    """Reconstruct the inputs of more than ``split_events`` events in time-split tasks; return the others."""

    rest = []
    for path, out, options, seen in todo:
        try:
            with open_recording(path) as rec:
                n, sensor = rec.info()["events"], rec.sensor_size
                record = SimulationRecord.from_metadata(rec.metadata)
        except Exception:  # noqa: BLE001 - its own task reports the error
            rest.append((path, out, options, seen))
            continue
        # the calibrated route fits its pixel model on the whole run: it is not split (its counting streams)
        calibrated = (record is not None and not options.get("oracle") and options.get("theta") is None
                      and options.get("window", "schedule") == "schedule")
        if n <= split_events or calibrated:
            rest.append((path, out, options, seen))
            continue
        t0 = time.perf_counter()
        parts = math.ceil(n / split_events)
        entry = {"input": path, "output": out, "status": "error", "events": int(n), "windows": None,
                 "seconds": None, "error": None, "parts": parts}
        try:
            result = reconstruct_split(path, parts, client, **options)
            with expect_target(out, seen):
                save_reconstruction(out, result, sensor, {"source": path})
            entry.update(status="ok", windows=int(result.summary.windows))
        except Exception as exc:  # noqa: BLE001 - recorded; the batch goes on
            entry["error"] = _error_text(exc)
        entry["seconds"] = time.perf_counter() - t0
        entries[path] = entry
    return rest


def _reconstruct_group(group):
    return [_reconstruct_one(args) for args in group]


def batch_reconstruct(inputs: Iterable[str | os.PathLike[str]], out_dir: str | os.PathLike[str],
                      options: Mapping[str, Any] | None = None, fmt: str = "h5", client: Client | None = None,
                      progress: Callable[[int], object] | None = None, force: bool = False,
                      split_events: int | None = None) -> dict[str, Any]:
    """Reconstruct every recording of ``inputs`` into ``out_dir``; returns the manifest (also written there).

    ``options`` are :func:`evtk.workflow.reconstruct_recording` keyword arguments.
    Inputs whose output already exists are "skipped" unless ``force``.
    Recordings of more than ``split_events`` events are split by time into
    about ``events / split_events`` tasks (:func:`reconstruct_split`).

    Parameters
    ----------
    inputs : iterable of str or os.PathLike
        Files, folders (their recordings, not recursive) and glob patterns (:func:`find_recordings`).
    out_dir : str or os.PathLike
        Where the reconstructions and :data:`MANIFEST` (``batch.json``) go; made if missing.
    options : Mapping of str to object, optional
        Keyword arguments of :func:`evtk.workflow.reconstruct_recording` (``oracle``, ``size``, ``window``, ...),
        the same for every input; recorded in the manifest.
    fmt : {"h5", "npz"}
        Output format (:func:`evtk.io.reconstruction.save_reconstruction`).
    client : distributed.Client, optional
        Where the tasks run (:func:`evtk.cluster.scheduler`); None: one after another in this process.
    progress : callable, optional
        Called with the number of inputs each finished task reconstructed.
    force : bool
        Reconstruct inputs whose output exists too (else they are "skipped").
    split_events : int, optional
        Recordings of more events are split by time into tasks (not those the calibrated route reads whole).

    Returns
    -------
    dict
        The manifest: ``evtk_batch`` (1), ``options``, ``format``, ``seconds``, ``inputs`` (one entry per
        input: ``input``, ``output``, ``status`` "ok", "skipped" or "error", ``events``, ``windows``,
        ``seconds``, ``error``), ``left_out`` (files of a folder that are not recordings) and ``counts``
        (inputs by status). The file also keeps the entries another batch wrote into the same folder.

    Raises
    ------
    EvtkError
        When ``fmt`` is not h5 or npz, ``inputs`` hold no recording, or an output is an input. A bad
        input is an "error" entry, not an exception.
    """

    if fmt not in ("h5", "npz"):
        raise EvtkError(f"batch output format must be h5 or npz, not {fmt!r}")
    left_out: list = []
    files = find_recordings(inputs, left_out)
    if not files:
        what = f"; left out, not recordings: {', '.join(f for f, _ in left_out)}" if left_out else ""
        raise EvtkError(f"no recordings to reconstruct (give files, folders or glob patterns){what}")
    os.makedirs(out_dir, exist_ok=True)
    outputs = _output_names(files, out_dir, "." + fmt)
    manifest_path = os.path.join(out_dir, MANIFEST)
    check_outputs([*outputs.values(), manifest_path], files)
    options = dict(options or {})
    old = _read_manifest(manifest_path)
    owners = {os.path.abspath(e["output"]): key for key, e in old.items()
              if e.get("output") and e.get("status") in ("ok", "skipped")}
    todo, entries = [], {}
    for f in files:
        out = outputs[f]
        prev = old.get(os.path.abspath(f))
        if not force and os.path.exists(out):
            owner = owners.get(os.path.abspath(out))
            if owner is not None and owner != os.path.abspath(f):
                entries[f] = {"input": f, "output": out, "status": "error", "events": None, "windows": None,
                              "seconds": None, "error": f"{out} holds the reconstruction of another input "
                                                        f"({owner}); rename this one or pass --force"}
                continue
            prev = prev or {}
            entries[f] = {**prev, "input": f, "output": out, "status": "skipped",
                          "error": None, "seconds": prev.get("seconds")}
        else:
            todo.append((f, out, options, file_identity(out)))
    t0 = time.perf_counter()
    if split_events:
        todo = _split_large(todo, int(split_events), client, entries)
    # small recordings reconstruct in tens of milliseconds: on a cluster, hand each task a few of them
    # (two tasks per worker) so the scheduler's per-task cost is spread
    per_task = 1
    if client is not None and todo:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        per_task = max(1, len(todo) // (2 * workers))
    groups = [todo[i:i + per_task] for i in range(0, len(todo), per_task)]
    try:
        for group in run_tasks(_reconstruct_group, groups, client, progress):
            for entry in group:
                entries[entry["input"]] = entry
    finally:  # interrupted or not, the manifest records what was done
        for f, out, _, _ in todo:
            entries.setdefault(f, {"input": f, "output": out, "status": "error", "events": None, "windows": None,
                                   "seconds": None, "error": "not done: the batch was interrupted"})
        manifest = {
            "evtk_batch": 1,
            "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in options.items()},
            "format": fmt,
            "seconds": time.perf_counter() - t0,
            "inputs": [entries[f] for f in files],
            "left_out": [{"file": f, "reason": why} for f, why in left_out],
        }
        manifest = _write_manifest(manifest_path, manifest)
    return manifest


def _read_manifest(path) -> dict:
    """The entries of an existing manifest by absolute input path ({} when there is none or it is unreadable)."""
    try:
        with open(path) as fh:
            data = json.load(fh)
        entries = data.get("inputs", []) if isinstance(data, dict) else []
        return {os.path.abspath(e["input"]): e for e in entries if isinstance(e, dict) and "input" in e}
    except (OSError, ValueError, KeyError, TypeError):
        return {}  # an unreadable manifest is rebuilt


def _write_manifest(path, manifest) -> dict:
    """Write ``manifest`` atomically, merged under a lock with the entries another batch run wrote into
    the same folder meanwhile (theirs kept for inputs this run did not touch). Returns what was written."""
    import fcntl

    with open(path + ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            mine = {os.path.abspath(e["input"]) for e in manifest["inputs"]}
            others = [e for k, e in _read_manifest(path).items() if k not in mine]
            merged = dict(manifest, inputs=others + manifest["inputs"])
            merged["counts"] = _counts(merged["inputs"])
            with AtomicFile(path) as fh:
                fh.write(json.dumps(merged, indent=1).encode())
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return dict(manifest, counts=_counts(manifest["inputs"]))


def _counts(entries) -> dict:
    return {s: sum(e.get("status") == s for e in entries) for s in ("ok", "skipped", "error")}
