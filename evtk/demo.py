"""The main job on the embedded defaults: simulate the device, write AEDAT4, reconstruct, report.

``evtk demo`` is a thin call of :func:`run_demo`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from .io import open as open_recording
from .io.reconstruction import save_reconstruction
from .plots import contact_sheet, plot_enob
from .simulate import Simulation, default_features, load_patterns
from .sweeps import scene_noise
from .workflow import reconstruct_recording

__all__ = ["run_demo", "DEMO_KERNEL_BITS"]

#: The demo's kernel: a plus sign, filled row by row.
#: Level captures the demo shows, to which its reconstruction fits the pixel model.
DEMO_LEVELS = 6
DEMO_KERNEL_BITS = "010111010"


#: ``progress_factory(total, label)``: the ``(update, finish)`` callbacks of one long stage.
ProgressFactory = Callable[[int, str], "tuple[Callable[[int], object] | None, Callable[[], object]]"]


def run_demo(out_dir: str | os.PathLike[str] = "evtk-demo", repeat: int = 10, seed: int = 0,
             status: Callable[[str], object] | None = None,
             progress_factory: ProgressFactory | None = None) -> dict[str, Any]:
    """Simulate a 3x3 plus-shaped kernel on scikit-image's 16x16 binarised camera picture, reconstruct, measure.

    Writes ``demo.aedat4`` (the recording), ``reconstruction.h5``,
    ``responses.png`` (measured beside ideal) and ``enob.png`` into
    ``out_dir``. ``status(text)`` is called as each stage starts (the first
    stage includes numba's one-time compilation); ``progress_factory(total,
    label)`` may return ``(update, finish)`` callbacks for the two long
    stages. Returns the file names, event and capture counts, the error
    against the ideal correlation, the SINAD report (eq. 8) and the flip
    rates of the binary responses, and the seconds taken.

    Parameters
    ----------
    out_dir : str or os.PathLike
        Folder for the four files; made if missing.
    repeat : int
        Captures of each kernel and feature pair (the SINAD of eq. 8 is measured over them).
    seed : int
        The simulated device's seed (its threshold mismatch and hot pixels follow from it), also passed to
        :func:`evtk.sweeps.scene_noise`.
    status : callable, optional
        Called with a line of text as each stage starts.
    progress_factory : callable, optional
        Called as ``progress_factory(total, label)`` for the simulating (total: captures) and reconstructing
        (total: events) stages; returns ``(update, finish)``: ``update(n)`` (or None) as work is done,
        ``finish()`` when the stage ends.

    Returns
    -------
    dict
        ``recording``, ``reconstruction``, ``contact_sheet`` (the sheets' paths), ``enob_plot``: the files;
        ``events``, ``captures``, ``repeats``; ``binarize``, ``error``, ``route``: from the reconstruction's
        summary; ``sinad`` (the SINAD and ENOB report as a dict, or None), ``flips`` (flip rates); ``seconds``.
    """
    say = status or (lambda text: None)
    bar = progress_factory or (lambda total, label: (None, lambda: None))
    t0 = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    sim = Simulation(load_patterns(DEMO_KERNEL_BITS, "kernel"), default_features(), repeat=repeat, seed=seed,
                     levels=DEMO_LEVELS)
    rec_path = os.path.join(out_dir, "demo.aedat4")
    say(f"simulating {len(sim.schedule)} captures into {rec_path} (the first run also compiles evtk's numba "
        "kernels, about 30 s; later runs take a few seconds)")
    update, finish = bar(len(sim.schedule), "simulating")
    try:
        written = sim.write(rec_path, progress=update)
    finally:
        finish()
    say("reconstructing")
    with open_recording(rec_path) as rec:
        update, finish = bar(rec.info()["events"], "reconstructing")
        try:
            result = reconstruct_recording(rec, progress=update)  # the route evtk reconstruct takes
        finally:
            finish()
        sensor = rec.sensor_size
    out_h5 = os.path.join(out_dir, "reconstruction.h5")
    save_reconstruction(out_h5, result, sensor, {"source": rec_path})
    say("measuring the noise and drawing the figures")
    sheet = os.path.join(out_dir, "responses.png")
    sheets = contact_sheet(sheet, result)
    scenes = scene_noise(result, seed=seed)
    enob_png = os.path.join(out_dir, "enob.png")
    plot_enob(scenes, enob_png)
    s, flips = scenes[0]["sinad"], scenes[0]["flips"]
    return {
        "recording": rec_path, "reconstruction": out_h5, "contact_sheet": sheets, "enob_plot": enob_png,
        "events": written["events"], "captures": written["captures"], "repeats": repeat,
        "binarize": result.summary["binarize"], "error": result.summary["error"], "route": result.summary["route"],
        "sinad": None if s is None else s.to_dict(), "flips": flips.to_dict(),
        "seconds": time.perf_counter() - t0,
    }
