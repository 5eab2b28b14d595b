"""Many recordings at once: one reconstruction task per recording, a manifest, resumable.

:func:`batch_reconstruct` reconstructs every input into ``out_dir`` (one
evtk HDF5 or NPZ file per input, each written atomically), on the workers of
a Dask client when given (:mod:`evtk.cluster`), and writes ``batch.json``:
every input with its status ("ok", "skipped": already done, "error"), output,
events, windows, seconds and error. A damaged input is an "error" entry;
the rest of the batch completes. Running it again skips inputs whose output
exists (outputs only appear complete), so an interrupted batch resumes.
"""

from __future__ import annotations

import glob
import json
import os
import time

from .errors import EvtkError

__all__ = ["find_recordings", "batch_reconstruct", "MANIFEST"]

MANIFEST = "batch.json"
RECORDING_EXTENSIONS = (".aedat4", ".h5", ".hdf5", ".parquet")


def find_recordings(inputs) -> list:
    """Files named, files inside directories named (not recursive), and glob patterns, sorted, without repeats."""
    found = []
    for item in inputs:
        item = os.fspath(item)
        if os.path.isdir(item):
            found += [os.path.join(item, f) for f in sorted(os.listdir(item))
                      if f.lower().endswith(RECORDING_EXTENSIONS) and os.path.isfile(os.path.join(item, f))]
        elif any(c in item for c in "*?["):
            found += sorted(glob.glob(item))
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
    names = {}
    for f in inputs:
        stem = os.path.splitext(os.path.basename(f))[0]
        names.setdefault(stem, []).append(f)
    out = {}
    for stem, files in names.items():
        if len(files) == 1:
            out[files[0]] = os.path.join(out_dir, stem + ext)
        else:  # same name in different folders: keep them apart by their folder
            for f in files:
                tag = os.path.basename(os.path.dirname(os.path.abspath(f))) or "root"
                out[f] = os.path.join(out_dir, f"{stem}.{tag}{ext}")
    if len(set(out.values())) != len(out):
        raise EvtkError("inputs map to the same output name; rename them or run them in separate batches")
    return out


def _reconstruct_one(args):
    """A batch task: reconstruct one recording into its output; never raises for a bad input."""
    from .io import open as open_recording
    from .reconstruct import reconstruct, save_reconstruction

    path, out, options = args
    t0 = time.perf_counter()
    entry = {"input": path, "output": out, "status": "error", "events": None, "windows": None, "seconds": None,
             "error": None}
    try:
        with open_recording(path) as rec:
            result = reconstruct(rec, **options)
            events = rec.info()["events"]
            sensor = rec.sensor_size
        save_reconstruction(out, result, sensor, {"source": path})
        entry.update(status="ok", events=int(events), windows=int(result.summary["windows"]))
    except (EvtkError, OSError, MemoryError, ValueError) as exc:
        entry["error"] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    entry["seconds"] = time.perf_counter() - t0
    return entry


def _reconstruct_group(group):
    return [_reconstruct_one(args) for args in group]


def batch_reconstruct(inputs, out_dir, options=None, fmt="h5", client=None, progress=None, force=False) -> dict:
    """Reconstruct every recording of ``inputs`` into ``out_dir``; returns the manifest (also written there).

    ``options`` are :func:`evtk.reconstruct.reconstruct` keyword arguments.
    Inputs whose output already exists are "skipped" unless ``force``.
    """
    from .cluster import run_tasks
    from .io._atomic import AtomicFile

    if fmt not in ("h5", "npz"):
        raise EvtkError(f"batch output format must be h5 or npz, not {fmt!r}")
    files = find_recordings(inputs)
    if not files:
        raise EvtkError("no recordings to reconstruct (give files, folders or glob patterns)")
    os.makedirs(out_dir, exist_ok=True)
    outputs = _output_names(files, out_dir, "." + fmt)
    options = dict(options or {})
    old = {}
    manifest_path = os.path.join(out_dir, MANIFEST)
    if os.path.exists(manifest_path):
        try:
            with open(manifest_path) as fh:
                old = {e["input"]: e for e in json.load(fh).get("inputs", [])}
        except (OSError, ValueError, KeyError, TypeError):
            old = {}  # an unreadable manifest is rebuilt
    todo, entries = [], {}
    for f in files:
        out = outputs[f]
        if not force and os.path.exists(out):
            prev = old.get(f, {})
            entries[f] = {**prev, "input": f, "output": out, "status": "skipped",
                          "error": None, "seconds": prev.get("seconds")}
        else:
            todo.append((f, out, options))
    t0 = time.perf_counter()
    # small recordings reconstruct in tens of milliseconds: on a cluster, hand each task a few of them
    # (about four tasks per worker) so the scheduler's per-task cost is spread
    per_task = 1
    if client is not None and todo:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        per_task = max(1, len(todo) // (4 * workers))
    groups = [todo[i:i + per_task] for i in range(0, len(todo), per_task)]
    for group in run_tasks(_reconstruct_group, groups, client, progress):
        for entry in group:
            entries[entry["input"]] = entry
    manifest = {
        "evtk_batch": 1,
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in options.items()},
        "format": fmt,
        "seconds": time.perf_counter() - t0,
        "counts": {s: sum(e["status"] == s for e in entries.values()) for s in ("ok", "skipped", "error")},
        "inputs": [entries[f] for f in files],
    }
    with AtomicFile(manifest_path) as fh:
        fh.write(json.dumps(manifest, indent=1).encode())
    return manifest
