"""``evtk recover``, ``evtk classify`` and ``evtk robustness``: the paper's experiments."""

from __future__ import annotations

import math

import click
import numpy as np

from .. import io as evio  # (light: its readers and writers load on first use)
from ..errors import EvtkError
from ..limits import require_memory
from ._base import (
    _MAX_INT,
    OutputPath,
    _dumps,
    _load_array,
    _progress,
    _scheduler_option,
    _stats,
    _table,
    _with_task_options,
    main,
    number_list,
)


def _recorded_candidates(path, size, features):
    """Responses of every candidate kernel from a recording holding one capture (at least) per candidate."""
    from ..reconstruct import reconstruct
    from ..recover import all_kernels, kernel_bits

    with evio.open(path) as rec:
        sim = (rec.metadata or {}).get("simulation")
        if sim is None:
            raise EvtkError(f"{path}: no capture schedule, so the candidates cannot be told apart")
        result = reconstruct(rec, crop="full", deblur=False)
    feats = np.asarray(sim["features"])
    if feats.shape[0] != 1 or not np.array_equal(feats[0], features):
        raise EvtkError(f"{path}: its features are not the ones given")
    index = {kernel_bits(k): i for i, k in enumerate(np.asarray(sim["kernels"]))}
    require_memory(8 * 2 ** (size * size) * math.prod(result.cells.shape[1:]),
                   f"the responses of the {2 ** (size * size):,} candidate kernels")
    out = np.zeros((2 ** (size * size),) + result.cells.shape[1:])
    missing = 0
    for j, cand in enumerate(all_kernels(size)):
        i = index.get(kernel_bits(cand))
        rows = [] if i is None else [r for r, (k, _, _) in enumerate(result.pairs.tolist()) if k == i]
        if rows:
            out[j] = result.cells[rows].mean(axis=0)
        elif cand.any():
            missing += 1
    if missing:
        raise EvtkError(f"{path}: {missing} candidate kernels of {size}x{size} were never captured")
    return out


@main.command()
@click.option("--features", "features_path", type=click.Path(dir_okay=False, exists=True),
              help="Binary features (.npy or image). Default: the bundled 16x16 picture (or random per trial).")
@click.option("--target", "target_path", type=click.Path(dir_okay=False, exists=True),
              help="Captured response (.npy) on the full cell grid, as evtk reconstruct --crop full --no-deblur "
                   "saves in 'cells'.")
@click.option("--target-kernel-bits", help="Capture the target on the simulated device with this kernel.")
@click.option("--size", type=click.IntRange(1, 7), default=3, show_default=True, help="Kernel side.")
@click.option("--method", type=click.Choice(["brute", "search"]), help="Default: brute up to 3x3, search above.")
@click.option("--weights", type=click.Choice(["relative", "none"]), default="relative", show_default=True,
              help="Weigh cells by 1/max(|target|, 1) (better at nominal light) or plain MSE (better when dim).")
@click.option("--candidates", "candidates_path", type=click.Path(dir_okay=False, exists=True),
              help="Brute force from a recording with one capture per candidate (default: the simulated device).")
@click.option("--events", is_flag=True, help="Simulate candidates through the event stream, not the count path.")
@click.option("--power-mw", "powers", type=number_list("--power-mw"), default="20", show_default=True,
              help="Laser power of the simulated device; with --trials a comma-separated sweep.")
@click.option("--trials", type=click.IntRange(min=1, max=_MAX_INT), help="Success rate over this many random trials per power.")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--plot", "plot_path", type=OutputPath(dir_okay=False),
              help="PNG: Fig. 4 for one recovery, success against power for --trials.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def recover(features_path, target_path, target_kernel_bits, size, method, weights, candidates_path, events, powers,
            trials, seed, plot_path, scheduler_spec, as_json):
    """Find the binary kernel behind a captured response (paper 4.4), or measure how often that works."""
    from ..optics import Bench
    from ..recover import (
        all_kernels,
        device_responses,
        kernel_from_bits,
        recover_brute,
        recover_search,
        response_matrix,
        success_rate,
    )
    from ..simulate import default_features, load_patterns

    w = None if weights == "none" else weights
    power_list = powers
    method = method or ("brute" if size <= 3 else "search")
    if trials:
        if target_path or target_kernel_bits or candidates_path:
            raise EvtkError("--trials draws its own kernels and features: drop --target, --target-kernel-bits "
                            "and --candidates")
        from ..cluster import scheduler

        update, finish = _progress(len(power_list), "trials")
        try:
            with scheduler(scheduler_spec) as client:
                rows = success_rate(power_list, size=size, trials=trials, method=method, seed=seed, weights=w,
                                    progress=update, client=client)
        finally:
            finish()
        if plot_path:
            from ..plots import plot_success

            plot_success(rows, plot_path)
        if as_json:
            click.echo(_dumps({"rows": rows}))
            return
        click.echo(_table(rows, [("power mW", "power_mw", "g"), ("trials", "trials", "d"),
                                 ("exact %", "exact_pct", ".1f"), ("shift %", "shift_pct", ".1f"),
                                 ("recovered %", "recovered_pct", ".1f"), ("median s", "median_s", ".3f"),
                                 ("max s", "max_s", ".3f"), ("proven %", "proven_pct", ".0f")]))
        return
    if bool(target_path) == bool(target_kernel_bits):
        raise EvtkError("give exactly one of --target and --target-kernel-bits")
    features = load_patterns(features_path, "features") if features_path else default_features()
    features = np.asarray(features)
    if features.ndim == 3:
        if features.shape[0] != 1:
            raise EvtkError("recovery takes one features pattern, not a stack")
        features = features[0]
    if not np.isin(features, (0, 1)).all():
        raise EvtkError("features must be binary (0/1) for kernel recovery")
    bench = Bench(power_mw=power_list[0])
    true_kernel = None
    if target_kernel_bits:
        true_kernel = kernel_from_bits(target_kernel_bits, size)
        if not true_kernel.any():
            raise EvtkError("an all-zero target kernel casts no light: nothing to recover")
        target = device_responses(true_kernel[None], features, bench, seed=seed, noise_seed=seed + 1,
                                  method="events" if events else "fast")[0]
    else:
        target = np.asarray(_load_array(target_path, "target"), dtype=np.float64)
        if target.ndim == 3 and target.shape[0] == 1:
            target = target[0]
        full = (features.shape[0] + size - 1, features.shape[1] + size - 1)
        if target.shape != full:
            raise EvtkError(f"target has shape {target.shape}; a {size}x{size} kernel on {features.shape[0]}x"
                            f"{features.shape[1]} features gives a full response of {full[0]}x{full[1]}")
    if method == "brute":
        if candidates_path:
            cands = _recorded_candidates(candidates_path, size, features)
        else:
            cands = device_responses(all_kernels(size), features, bench, seed=seed, noise_seed=seed + 2,
                                     method="events" if events else "fast")
        result = recover_brute(target, cands, true_kernel=true_kernel, weights=w)
        solution = cands[int(np.argmin(result.losses))]
    else:
        a_mat = response_matrix(features, size, bench, blurred=True)
        result = recover_search(target, a_mat, size, true_kernel=true_kernel, weights=w)
        solution = (result.scale * (a_mat @ result.kernel.ravel())).reshape(target.shape)
    if plot_path:
        from ..plots import plot_recovery

        plot_recovery(plot_path, features, target, solution, result, true_kernel)
    out = result.to_dict()
    if true_kernel is not None:
        out["target_kernel_bits"] = target_kernel_bits
    if as_json:
        click.echo(_dumps(out))
        return
    lines = [f"solution kernel {out['kernel_bits']} ({method}, loss {result.loss:.4g}"
             + (", proven optimal" if result.proven else ", best found: node budget ran out") + ")"]
    for row in result.kernel:
        lines.append("  " + " ".join("#" if v else "." for v in row))
    if result.status is not None:
        lines.append(f"against the target kernel {target_kernel_bits}: {result.status}")
    if result.near:
        near = ", ".join(f"{b} ({v:.4g})" for b, v in result.near[:5])
        lines.append(f"within 5 % of the best loss: {near}" + (" ..." if len(result.near) > 5 else ""))
    lines.append(f"search time {result.seconds:.3f} s")
    click.echo("\n".join(lines))


def _train(task_data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, seed,
           power_mw=None, progress=None, channel_masks=False):
    """One run: a fresh network trained on the data; returns (model, backend, record)."""
    from ..bcnn import BCNN, DigitalBackend, OpticalBackend
    from ..optics import Bench
    from ..optimize import train_layerwise, train_ste

    model = BCNN.random(layers=3, channels=channels, seed=seed, channel_masks=channel_masks)
    if backend_name == "digital":
        backend = DigitalBackend()
    else:
        backend = OpticalBackend(bench=Bench() if power_mw is None else Bench(power_mw=power_mw), seed=seed)
    if optimizer == "ste":
        record = train_ste(model, task_data.x_train, task_data.y_train, epochs=epochs, seed=seed)
    else:
        record = train_layerwise(model, backend, task_data.x_train, task_data.y_train, optimizer=optimizer,
                                 steps=steps, temperature=temperature, final_temperature=final_temperature,
                                 seed=seed, progress=progress)
    return model, backend, record


def _classify_run(args):
    """One training run of ``evtk classify`` (a task: everything it needs is in ``args``)."""
    import time

    (data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks, run_seed,
     power_mw, r) = args
    t0 = time.perf_counter()
    model, backend, record = _train(data, backend_name, optimizer, steps, temperature, final_temperature, epochs,
                                    channels, run_seed, power_mw, channel_masks=channel_masks)
    return {"run": r, "seed": run_seed, "seconds": time.perf_counter() - t0,
            "train_accuracy": model.accuracy(backend, data.x_train, data.y_train),
            "test_accuracy": model.accuracy(backend, data.x_test, data.y_test),
            "kernels": [k.tolist() for k in model.kernels], "mask": model.masks[-1].tolist(), "record": record}


@main.command()
@_with_task_options
@click.option("--backend", "backend_name", type=click.Choice(["digital", "optical"]), default="optical",
              show_default=True, help="Exact binary correlations, or every correlation through the simulated device.")
@click.option("--power-mw", type=float, help="Laser power of the simulated device (optical backend).")
@click.option("--runs", type=click.IntRange(min=1, max=_MAX_INT), default=10, show_default=True)
@click.option("--out", "out_dir", type=OutputPath(file_okay=False), default="evtk-classify", show_default=True,
              help="Where the per-run curves (runs.json) go.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def classify(task, data_dir, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
             n_per_class, seed, backend_name, power_mw, runs, out_dir, scheduler_spec, as_json):
    """Train the binary CNN several times and report test accuracy (the paper's Tables 2 and 3)."""
    import os
    import time

    from ..datasets import baselines, load_dataset

    if temperature is None:
        temperature = 5.0 if optimizer == "walk" else 10.0
    data = load_dataset(task, seed=seed, data_dir=data_dir, n_per_class=n_per_class)
    floor = baselines(data)
    from ..cluster import run_tasks, scheduler

    update, finish = _progress(runs, f"{task} {optimizer} on {backend_name}")
    t_all = time.perf_counter()
    tasks = [(data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
              seed + r, power_mw, r) for r in range(runs)]
    try:
        with scheduler(scheduler_spec) as client:
            per_run = run_tasks(_classify_run, tasks, client, update)
    finally:
        finish()
    seconds = time.perf_counter() - t_all
    steps_done = sum(run["record"].get("steps", 0) for run in per_run)
    summary = {
        "task": task, "data": data.summary(), "backend": backend_name, "optimizer": optimizer, "runs": runs,
        "channels": channels, "channel_masks": bool(channel_masks),
        "steps_per_layer": steps if optimizer in ("anneal", "walk") else None,
        "temperature": temperature if optimizer in ("anneal", "walk") else None,
        "test_accuracy": _stats([r["test_accuracy"] for r in per_run]),
        "train_accuracy": _stats([r["train_accuracy"] for r in per_run]),
        "seconds": seconds, "steps_per_s": steps_done / seconds if steps_done else None,
        "baselines": floor,
    }
    os.makedirs(out_dir, exist_ok=True)
    from .._atomic import AtomicFile

    with AtomicFile(os.path.join(out_dir, "runs.json")) as fh:
        fh.write(_dumps({"summary": summary, "runs": per_run}).encode())
    summary["curves"] = os.path.join(out_dir, "runs.json")
    if as_json:
        click.echo(_dumps(summary))
        return
    note = " (SYNTHETIC glyphs, not EMNIST)" if data.synthetic else ""
    click.echo(f"{task}{note}: {data.summary()['train']} train / {data.summary()['test']} test images; "
               f"{optimizer} on the {backend_name} backend, {runs} runs, {seconds:.1f} s")
    rows = [dict(summary["test_accuracy"], what="test accuracy %"), dict(summary["train_accuracy"],
                                                                         what="train accuracy %")]
    pct = lambda key: lambda r: 100 * r[key]  # noqa: E731
    click.echo(_table(rows, [("", "what", "s"), ("max", pct("max"), ".1f"), ("min", pct("min"), ".1f"),
                             ("mean", pct("mean"), ".1f"), ("std", pct("std"), ".1f")]))
    click.echo(f"baselines on the same split: nearest centroid {100 * floor['nearest_centroid']:.1f} %, "
               f"logistic regression {100 * floor['logistic_regression']:.1f} % (test)")
    if summary["steps_per_s"]:
        click.echo(f"{summary['steps_per_s']:.0f} optimisation steps/s; curves in {summary['curves']}")


@main.command(short_help="Accuracy and flipped pixels under Poisson noise (Fig. 3 left, eq. 12).")
@_with_task_options
@click.option("--scales", type=number_list("--scales", allow_zero=True), default="0,0.01,0.03,0.1,0.3,1,3",
              show_default=True,
              help="Poisson noise scales (response units per photon; 0 is noise-free).")
@click.option("--target-accuracy", type=float, help="r of eq. 12 (default: noise-free accuracy minus 0.05).")
@click.option("--plot", "plot_path", type=OutputPath(dir_okay=False), help="Accuracy and flips against noise (PNG).")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def robustness(task, data_dir, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
               n_per_class, seed, scales, target_accuracy, plot_path, scheduler_spec, as_json):
    """Fig. 3 (left) and eq. 12: test accuracy and flipped pixels with scaled Poisson noise in every layer."""
    from ..bcnn import poisson_robustness
    from ..datasets import load_dataset

    if temperature is None:
        temperature = 5.0 if optimizer == "walk" else 10.0
    data = load_dataset(task, seed=seed, data_dir=data_dir, n_per_class=n_per_class)
    model, backend, _ = _train(data, "digital", optimizer, steps, temperature, final_temperature, epochs, channels,
                               seed, channel_masks=channel_masks)
    from ..cluster import scheduler

    with scheduler(scheduler_spec) as client:
        res = poisson_robustness(model, data.x_test, data.y_test, scales,
                                 seed=seed, target_accuracy=target_accuracy, client=client)
    if plot_path:
        from ..plots import plot_robustness

        plot_robustness(res, plot_path)
    if as_json:
        click.echo(_dumps(res))
        return
    click.echo(_table(res["rows"], [("noise scale", "scale", "g"), ("test accuracy %", lambda r: 100 * r["accuracy"],
                                                                    ".1f"), ("flipped %", "flip_pct", ".2f")]))
    big_r = "none" if res["R_pct"] is None else f"{res['R_pct']:.2f} %"
    click.echo(f"eq. 12: keeping accuracy >= {100 * res['r']:.1f} % tolerates R = {big_r} flipped pixels")
