"""Driving the bench: a job file in, the DMDs' frames and the capture schedule out.

A *job* says what to compute and how to show it: kernels and features, the
signed (+/-) split, repeats, flat fields, the time each pattern is shown and
the dark time after it, and the bench's geometry. :func:`load_job` reads one
(TOML or JSON); :func:`write_patterns` writes, for every capture, the frame
each DMD shows (1-bit PNG or BMP at the DMD's native resolution, the kernel
upsampled by eq. 4's varsigma, the features by their mirrors per element,
both centred) and a schedule saying which frame pair each trigger edge
starts. The simulator takes the same job (:func:`job_simulation`), so a
simulated run and a bench run share the frames and the schedule and differ
only in where the recording comes from.

Job keys (all optional but ``kernels``)::

    kernels = ["010111010"]          # bit strings (square, row by row), nested lists, or a .npy/.png path
    features = "features.png"        # same forms; default: the 16x16 picture bundled with scikit-image
    signed = false                   # read 0 as -1 (each pair shown in up to four +/- passes)
    repeat = 10
    flat_field = 2                   # captures with every mirror on, first (per-pixel calibration)
    calibration = 2                  # dot-grid captures next (where the response lies: evtk calibrate)
    dot_spacing = 4                  # features elements between calibration dots
    levels = 6                       # level captures next: a staircase of light (the pixel model is fitted to it)
    window_us = 1000                 # how long each pattern is shown
    settle_us = 13340                # dark time after each pattern (default: the simulator's recommendation)
    [bench]                          # evtk.optics.Bench fields: DMD size and pitch, distances, rates, ...
    [sensor]                         # evtk.sensor.SensorModel fields (the simulator only)
    [camera]                         # evtk.optics.camera.Camera fields: pose and lens (the simulator only)
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import TYPE_CHECKING

import numpy as np

from ._atomic import AtomicFile
from .errors import EvtkError
from .limits import require_memory
from .optics import Bench
from .optics.camera import Camera
from .sensor import SensorModel
from .settings import MAX_COUNT, MAX_SIDE, MAX_US, Spec, check_table, read_table
from .simulate import Simulation, default_features, load_patterns
from .simulate.schedule import check_patterns

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["load_job", "job_simulation", "dmd_frame", "write_patterns", "SCHEDULE_VERSION", "JOB_KEYS", "JOB_SPECS"]

#: Version of the schedule file :func:`write_patterns` writes.
SCHEDULE_VERSION = 1
#: Keys a job file may hold.
JOB_KEYS = ("kernels", "features", "signed", "repeat", "flat_field", "calibration", "dot_spacing", "levels", "window_us",
            "settle_us", "seed", "bench", "sensor", "camera", "light_delay_us", "light_rise_us")


#: The range of each number a job may set (the ``bench``, ``sensor`` and ``camera`` tables are checked by
#: :class:`~evtk.optics.Bench`, :class:`~evtk.sensor.SensorModel` and :class:`~evtk.optics.camera.Camera`).
JOB_SPECS = {
    "signed": Spec("bool"),
    "repeat": Spec("int", 1, MAX_COUNT),
    "flat_field": Spec("int", 0, MAX_COUNT),
    "calibration": Spec("int", 0, MAX_COUNT),
    "dot_spacing": Spec("int", 2, MAX_SIDE, unit="features elements between dots"),
    "levels": Spec("int", 0, MAX_COUNT),
    "window_us": Spec("int", 1, MAX_US, unit="µs"),
    "settle_us": Spec("int", 1, MAX_US, unit="µs", optional=True),
    "seed": Spec("int", 0, 2 ** 63 - 1),
    "light_delay_us": Spec("int", 0, MAX_US, unit="µs"),
    "light_rise_us": Spec("float", 0, MAX_US, unit="µs"),
}


def _patterns(path, value, name, base_dir):
    """One or more 2-D 0/1 (or -1/0/1) patterns from a job value: bit strings, file paths or nested lists."""
    if isinstance(value, str):
        value = [value]
        one = True
    else:
        one = False
    if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
        pats = [np.asarray(load_patterns(v if v and set(v) <= {"0", "1"} else os.path.join(base_dir, v), name))
                for v in value]
        if len({p.shape for p in pats}) != 1:
            raise EvtkError(f"{path}: the job's {name} differ in shape: {[p.shape for p in pats]}")
        return pats[0] if one else np.stack(pats)
    if isinstance(value, list) and value and isinstance(value[0], list) and value[0] \
            and not isinstance(value[0][0], list):
        return check_patterns(path, name, [value])[0]  # one 2-D pattern
    return check_patterns(path, name, value)


def load_job(path: str | os.PathLike[str]) -> dict:
    """Read a job file (TOML or JSON; see the module docstring) into :class:`~evtk.simulate.Simulation`'s arguments.

    Parameters
    ----------
    path : str or os.PathLike
        The job file; paths in it are relative to it.

    Returns
    -------
    dict
        ``kernels``, ``features``, ``bench`` (a :class:`~evtk.optics.Bench`),
        ``sensor`` (a :class:`~evtk.sensor.SensorModel`), ``camera``, and
        ``repeat``, ``flat_field``, ``calibration``, ``dot_spacing``,
        ``levels``, ``window_us``, ``settle_us``, ``seed``,
        ``light_delay_us``, ``light_rise_us``, each checked against :data:`JOB_SPECS` (a bad
        value is an :class:`~evtk.EvtkError` naming the file, the key and
        the range).

    Raises
    ------
    EvtkError
        An unreadable file, unknown keys, no kernels, patterns that are not 0/1 or differ in shape, or a value
        out of range (naming the file).
    """
    path = os.fspath(path)
    data = read_table(path, "job")
    unknown = sorted(set(data) - set(JOB_KEYS))
    if unknown:
        raise EvtkError(f"{path}: unknown job settings {unknown}; a job holds {list(JOB_KEYS)}")
    values = check_table(path, {k: v for k, v in data.items() if k in JOB_SPECS}, JOB_SPECS)
    base = os.path.dirname(os.path.abspath(path))
    if "kernels" not in data:
        raise EvtkError(f"{path}: the job names no kernels")
    kernels = _patterns(path, data["kernels"], "kernels", base)
    features = _patterns(path, data["features"], "features", base) if "features" in data else default_features()
    if values.get("signed", False):
        kernels, features = np.where(kernels > 0, 1, -1), np.where(features > 0, 1, -1)
    for key in ("bench", "sensor", "camera"):
        if not isinstance(data.get(key, {}), dict):
            raise EvtkError(f"{path}: [{key}] must be a table of parameters")
    try:
        bench = Bench.from_dict(data.get("bench", {}))
        sensor = SensorModel.from_dict(data.get("sensor", {}))
        camera = Camera.from_dict(data["camera"]) if "camera" in data else None
    except (EvtkError, TypeError) as exc:
        raise EvtkError(f"{path}: {exc}") from None
    job = {"kernels": kernels, "features": features, "bench": bench, "sensor": sensor, "camera": camera}
    for key, default in (("repeat", 1), ("flat_field", 2), ("calibration", 0), ("dot_spacing", 4), ("levels", 0),
                         ("window_us", 1000), ("settle_us", None), ("seed", 0), ("light_delay_us", 0),
                         ("light_rise_us", 0.0)):
        job[key] = values.get(key, default)
    return job


def job_simulation(path: str | os.PathLike[str]) -> Simulation:
    """The :class:`~evtk.simulate.Simulation` of a job file: the same schedule :func:`write_patterns` writes.

    Parameters
    ----------
    path : str or os.PathLike
        The job file (:func:`load_job`).

    Returns
    -------
    Simulation
        The simulated run of the job, nothing simulated yet.

    Raises
    ------
    EvtkError
        A bad job, or settings the simulator refuses (naming the file).
    """
    job = load_job(path)
    try:
        return Simulation(**job)
    except EvtkError as exc:
        raise EvtkError(f"{os.fspath(path)}: {exc}") from None


def dmd_frame(pattern: npt.ArrayLike, upsample: int, dmd_cols: int,
              dmd_rows: int) -> tuple[np.ndarray, tuple[int, int]]:
    """One DMD frame: ``pattern`` (elements > 0 on) with each element ``upsample`` x ``upsample`` mirrors, centred.

    Returns the boolean frame (``dmd_rows`` x ``dmd_cols``) and the mirror
    (row, column) of the pattern's top-left element.

    Parameters
    ----------
    pattern : array_like
        2-D pattern; elements above 0 are on.
    upsample : int
        Mirrors per element along each axis.
    dmd_cols : int
        Mirrors per DMD row.
    dmd_rows : int
        Mirror rows of the DMD.

    Returns
    -------
    frame : numpy.ndarray
        bool, shape ``(dmd_rows, dmd_cols)``.
    top_left : tuple of int
        Mirror ``(row, column)`` of the pattern's top-left element.

    Raises
    ------
    EvtkError
        If the upsampled pattern needs more mirrors than the DMD has.

    Examples
    --------
    >>> frame, at = dmd_frame([[1, 0], [0, 1]], 2, 8, 6)
    >>> at, int(frame.sum()), frame[at[0]:at[0] + 4, at[1]:at[1] + 4].astype(int).tolist()
    ((1, 2), 8, [[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 1, 1]])
    """
    pat = np.asarray(pattern) > 0
    up = int(upsample)
    h, w = pat.shape[0] * up, pat.shape[1] * up
    if h > dmd_rows or w > dmd_cols:
        raise EvtkError(f"a {pat.shape[0]}x{pat.shape[1]} pattern at {up} mirrors per element needs {w}x{h} "
                        f"mirrors; the DMD has {dmd_cols}x{dmd_rows}")
    r0, c0 = (dmd_rows - h) // 2, (dmd_cols - w) // 2
    frame = np.zeros((dmd_rows, dmd_cols), bool)
    frame[r0:r0 + h, c0:c0 + w] = np.kron(pat, np.ones((up, up), bool))
    return frame, (r0, c0)


def _save_1bit(path, frame, image_format):
    from PIL import Image

    img = Image.fromarray(np.ascontiguousarray(frame, dtype=bool))  # mode "1": one bit a mirror
    with AtomicFile(path) as out:
        img.save(out.file, format=image_format.upper())


def write_patterns(sim: Simulation, out_dir: str | os.PathLike[str], image_format: str = "png") -> dict:
    """Write every DMD frame of a run and its schedule into ``out_dir``.

    Files: ``kernel/kNNN.<fmt>`` and ``features/fNNN.<fmt>`` (each distinct
    frame once), ``dark.<fmt>`` (all mirrors off, shown between patterns by
    both DMDs), and ``schedule.json``: per capture, its trigger edges
    (``t_on_us``/``t_off_us``: capture ``c`` is started by the ``c``-th rising
    edge and ended by the next falling edge), the frame each DMD shows, which
    kernel and features and which +/- pass it is, and the repeat; plus the
    kernels, features, timing and bench geometry (see
    ``docs/formats/schedule.md``). It holds no pixel model: nothing a bench
    would not know. Returns a summary (frames written, captures, paths).

    Parameters
    ----------
    sim : Simulation
        The run (its schedule, patterns and bench), e.g. from :func:`job_simulation`.
    out_dir : str or os.PathLike
        The folder to write into (made when missing).
    image_format : {"png", "bmp"}
        Format of the 1-bit frames.

    Returns
    -------
    dict
        ``out_dir``, ``schedule`` (the path of ``schedule.json``), ``captures``, ``kernel_frames``,
        ``features_frames``, ``format`` and ``dmd`` (``[cols, rows]``).

    Raises
    ------
    EvtkError
        An unknown image format, a pattern larger than its DMD, or more memory than the budget.
    """
    fmt = str(image_format).lower()
    if fmt not in ("png", "bmp"):
        raise EvtkError(f"image format must be png or bmp, not {image_format!r}")
    b = sim.bench
    out_dir = os.fspath(out_dir)
    os.makedirs(os.path.join(out_dir, "kernel"), exist_ok=True)
    os.makedirs(os.path.join(out_dir, "features"), exist_ok=True)
    # one frame at a time: the bool frame, its upsampled pattern, the packed bits and the 1-bit image
    require_memory(4 * b.dmd_rows * b.dmd_cols, f"a {b.dmd_cols}x{b.dmd_rows} DMD frame")
    written: dict = {}

    def frame_file(kind, pattern, upsample):
        # frames are told apart by their pattern (a few elements), so a run of many repeats draws each once
        pat = np.asarray(pattern) > 0
        key = (kind, pat.shape, hashlib.sha1(np.packbits(pat).tobytes()).hexdigest())
        if key not in written:
            frame, at = dmd_frame(pat, upsample, b.dmd_cols, b.dmd_rows)
            name = f"{kind}/{kind[0]}{sum(k[0] == kind for k in written):03d}.{fmt}"
            _save_1bit(os.path.join(out_dir, name), frame, fmt)
            written[key] = (name, at)
        return written[key]

    s = sim.schedule
    captures = []
    for c in range(len(s)):
        kpat, fpat = sim._pass_patterns(c)
        kname, k_at = frame_file("kernel", kpat, b.kernel_mirrors)
        fname, f_at = frame_file("features", fpat, b.feature_upsample)
        captures.append({"capture": c, "t_on_us": int(s.t_on_us[c]), "t_off_us": int(s.t_off_us[c]),
                         "kernel_frame": kname, "features_frame": fname, "kernel_id": int(s.kernel_id[c]),
                         "features_id": int(s.features_id[c]), "kernel_sign": int(s.kernel_sign[c]),
                         "features_sign": int(s.features_sign[c]), "repeat": int(s.repeat[c]),
                         "level": int(s.level[c]) if s.level is not None else 0})
    dark = f"dark.{fmt}"
    _save_1bit(os.path.join(out_dir, dark), np.zeros((b.dmd_rows, b.dmd_cols), bool), fmt)
    doc = {
        "evtk_schedule_version": SCHEDULE_VERSION,
        "window_us": int(sim.window_us), "settle_us": int(sim.settle_us), "start_us": int(sim.start_us),
        "repeat": int(sim.repeat), "flat_field": int(sim.flat_field),
        "calibration": {"captures": int(sim.calibration), "dot_spacing": int(sim.dot_spacing),
                        "levels": int(sim.levels)},
        "kernels": sim.kernels.tolist(), "features": sim.features.tolist(),
        "dmd": {"cols": int(b.dmd_cols), "rows": int(b.dmd_rows), "mirror_pitch_um": float(b.mirror_pitch_um),
                "kernel_mirrors_per_element": int(b.kernel_mirrors), "varsigma": float(b.varsigma),
                "feature_mirrors_per_element": int(b.feature_upsample),
                "kernel_top_left": list(_top_left(written, "kernel")),
                "features_top_left": list(_top_left(written, "features")),
                "kernel_hz": float(b.kernel_hz), "features_hz": float(b.features_hz)},
        "bench": b.to_dict(),
        "dark_frame": dark,
        "triggers": "capture c: the c-th rising edge shows its frames, the next falling edge returns both DMDs "
                    "to the dark frame",
        "captures": captures,
    }

    schedule_path = os.path.join(out_dir, "schedule.json")
    with AtomicFile(schedule_path) as out:
        out.file.write(json.dumps(doc, indent=1).encode())
    kinds = [k[0] for k in written]
    return {"out_dir": out_dir, "schedule": schedule_path, "captures": len(captures),
            "kernel_frames": kinds.count("kernel"), "features_frames": kinds.count("features"),
            "format": fmt, "dmd": [int(b.dmd_cols), int(b.dmd_rows)]}


def _top_left(written, kind):
    """Top-left mirror (row, column) of the frames of ``kind`` (all centred alike)."""
    for (k, *_), (_, at) in written.items():
        if k == kind:
            return at
    return (0, 0)
