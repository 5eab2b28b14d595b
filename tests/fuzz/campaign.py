"""The fuzz campaign: byte-flip and structure-aware mutations of every file evtk reads, each read checked.

    python -m tests.fuzz.campaign --cases 100000 --seed 1 --out report.json

Targets (``targets.py``): AEDAT4 (LZ4, ZSTD, and faery's with checksums),
evtk and DSEC HDF5, Parquet, legacy AEDAT 1.0/2.0/3.1, Prophesee EVT 2.0,
EVT 2.1 (both word layouts), EVT 3.0 and DAT, Event Stream; reconstruction files (``.h5``, ``.npz``);
settings files (job TOML, ``schedule.json``, ``cal.toml``, the simulation
record). Case ``i`` takes target ``i % T``; even rounds mutate bytes
(bit flips, a cut, a lying 4-byte field, a duplicated or zeroed span), odd
rounds make a structure-aware change (packets, FlatBuffers, HDF5 objects,
record words, header lines, settings values). Each case is reproducible from
``--seed`` and its number (``--only``/``--case`` rerun one).

Outcomes: ``exact`` (the truth), ``altered`` (a change the format allows for
the bytes touched, every read path agreeing, values within bounds),
``error`` (a clean ``evtk.EvtkError``), ``wrong`` (a read the oracle
refutes: silently wrong), ``traceback`` (any other exception), ``hang``
(past ``--hang-seconds`` of CPU time), ``memory`` (``MemoryError``, or the case's peak
resident memory grew by more than ``--memory-growth-mb``) and ``crash`` (the
worker process died). Cases run in a worker subprocess with the evtk budget
``EVTK_MEMORY_LIMIT_MB`` (``--memory-mb``) and an address-space limit
(``RLIMIT_AS``); the parent restarts it after a crash or a hang it had to
kill, so one bad case costs one case.

``--rerun LOG`` runs again only the failing cases of an earlier run's
``--log`` (after a fix). ``--save DIR`` keeps the mutated file of the first few cases of each failing
(target, outcome, kind). The exit status is 1 when any case failed.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:
    sys.path.insert(0, str(HERE.parent))

FAILURES = ("wrong", "traceback", "crash", "hang", "memory")
OUTCOMES = ("exact", "altered", "error") + FAILURES + ("skipped",)


class Hang(BaseException):
    """Raised by the alarm: a case ran past its time (a BaseException, so that no ``except Exception`` eats it)."""


# --------------------------------------------------------------------------------------------------- one case
class Cases:
    """The targets of a built folder and how to run case ``i`` on them (in the worker process)."""

    def __init__(self, folder, scratch, cli_every=0, only=None):
        from fuzz import targets as tg

        self.tg = tg
        self.folder, self.scratch = Path(folder), Path(scratch)
        self.events = tg.load_event_targets(folder)
        runs = (self.folder / "r.h5").exists()  # built with the simulated run (targets.build(runs=True))
        self.settings = tg.load_settings_targets(folder) if runs else {}
        self.recon = {n: tg.reconstruction_state(self.folder / n) for n in ("r.h5", "r.npz")} if runs else {}
        self.names = sorted(self.events) + sorted(self.recon) + sorted(self.settings)
        if only:
            self.names = [n for n in self.names if n in only]
        self.cli_every = cli_every
        self._parts = {}
        self._bytes = {}
        if any(self.events[n].structured == "aedat4" for n in self.names if n in self.events):
            import numpy as np
            from fuzz import structured as st

            from evtk.io import _compression as cz

            for k in range(8):  # the decompression bombs, made once (before the worker's memory limit)
                st._bomb(cz.LZ4, np.random.default_rng(k))
                st._bomb(cz.ZSTD, np.random.default_rng(k))

    def source(self, name):
        if name not in self._bytes:
            p = (self.events[name].path if name in self.events else self.settings[name].path
                 if name in self.settings else self.folder / name)
            self._bytes[name] = p.read_bytes()
        return self._bytes[name]

    def target_of(self, case):
        return self.names[case % len(self.names)]

    def prepare(self, seed, case):
        """Write case ``case``'s mutated file: ``(target, kind, check, path)``; ``check()`` returns the outcome."""
        import numpy as np

        name = self.target_of(case)
        structured = (case // len(self.names)) % 2 == 1
        rng = np.random.default_rng([seed, case])
        path = self.scratch / ("case" + "".join(Path(name).suffixes[-1:]))
        if name in self.events:
            kind, check = self._event_case(name, structured, rng, path)
        elif name in self.recon:
            kind, check = self._recon_case(name, structured, rng, path)
        else:
            kind, check = self._settings_case(name, structured, rng, path)
        return name, kind, check, path

    def check(self, case, name, check, path):
        """The outcome and its detail (``wrong`` when the oracle refutes the read)."""
        try:
            outcome = check()
            if self.cli_every and case % self.cli_every == 0 and name not in self.settings:
                self._cli(path)
        except self.tg.Wrong as exc:
            return "wrong", str(exc)
        return outcome, ""

    def _event_case(self, name, structured, rng, path):
        tg = self.tg
        t = self.events[name]
        data = self.source(name)
        mutation = {"structured": False, "payload_only": False}
        if not structured:
            out, kind, touched, in_place = tg.byte_mutation(data, rng)
            path.write_bytes(out)
        elif t.structured == "aedat4":
            from fuzz import structured as st

            if name not in self._parts:
                self._parts[name] = st._aedat4_parts(t.path)
            out, kind, payload_only = st.mutate_aedat4(self._parts[name], rng)
            path.write_bytes(out)
            touched, in_place = [(0, len(out))], False
            mutation.update(structured=True, payload_only=payload_only)
        elif t.structured == "hdf5":
            from fuzz import structured as st

            kind, payload_only = st.mutate_hdf5(t.path, path, rng)
            touched, in_place = [(0, path.stat().st_size)], False
            mutation.update(structured=True, payload_only=payload_only)
        elif t.structured == "parquet":
            from fuzz import structured as st

            out, kind = st.mutate_parquet(t.path, rng)
            path.write_bytes(out)
            touched, in_place = [(0, len(out))], False
            mutation.update(structured=True, payload_only=False)
        elif t.structured is None:  # the DSEC layout: the HDF5 changes of evtk's layout do not apply
            out, kind, touched, in_place = tg.byte_mutation(data, rng, lo=len(data) // 2)
            path.write_bytes(out)
        else:
            out, kind, touched, in_place = tg.word_mutation(t, data, rng)
            path.write_bytes(out)
        mutation.update(kind=kind, touched=touched, in_place=in_place)
        return kind, lambda: tg.check_events(t, path, mutation)

    def _recon_case(self, name, structured, rng, path):
        tg = self.tg
        src = self.folder / name
        checksummed = False
        if not structured:
            out, kind, _, _ = tg.byte_mutation(self.source(name), rng)
            path.write_bytes(out)
            values_only = True
            checksummed = name.endswith(".npz")  # every member's CRC-32 is checked as it is read
            kind = "byte/" + kind
        elif name.endswith(".h5"):
            kind, values_only = tg.mutate_recon_h5(src, path, self.folder / "sim.h5", rng)
        else:
            out, kind, values_only = tg.mutate_recon_npz(src, rng)
            path.write_bytes(out)
        truth = self.recon[name]
        return kind, lambda: tg.check_reconstruction(truth, path, values_only, checksummed)

    def _settings_case(self, name, structured, rng, path):
        tg = self.tg
        t = self.settings[name]
        text = self.source(name)
        if not structured:
            out, kind, _, _ = tg.byte_mutation(text, rng)
            kind = "byte/" + kind
        else:
            doc, kind = tg.value_mutation(tg.parse_settings(t, text), rng)
            if t.toml:
                try:
                    out = tg.toml_text(doc).encode()
                except TypeError:
                    out = text
            else:
                out = json.dumps(doc).encode()
        path.write_bytes(out)
        return kind, lambda: tg.check_settings(t, path)

    def _cli(self, path):
        """``evtk info --check`` on the case: exit 0 or 1, and one line on error."""
        from click.testing import CliRunner

        from evtk.cli import main as cli

        r = CliRunner().invoke(cli, ["info", "--check", "--json", str(path)])
        if r.exit_code not in (0, 1) or (r.exit_code == 1 and len(r.output.strip().splitlines()) != 1):
            if isinstance(r.exception, MemoryError):
                raise r.exception
            if isinstance(r.exception, BaseException) and not isinstance(r.exception, SystemExit):
                raise r.exception
            raise RuntimeError(f"evtk info --check: exit {r.exit_code}, output {r.output[-300:]!r}")


def _peak_rss_mb():
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _reset_peak():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:  # pragma: no cover - not Linux
        return False


def guarded(cases, seed, case, hang_seconds, growth_mb):
    """Run one case in this process with a CPU-time alarm and a memory watch: a result dict. Writing the mutated file
    is outside both; an exception there is the campaign's own fault, counted as ``skipped``."""
    def on_alarm(signum, frame):
        raise Hang()

    name, kind, path = cases.target_of(case), "?", None
    try:
        name, kind, check, path = cases.prepare(seed, case)
    except Exception as exc:  # noqa: BLE001 - a fault of the mutators, not of evtk
        return {"case": case, "target": name, "kind": kind, "outcome": "skipped", "seconds": None, "grew_mb": None,
                "detail": f"mutation failed: {type(exc).__name__}: {exc}"[:300], "path": None}
    old = signal.signal(signal.SIGPROF, on_alarm)
    can_reset = _reset_peak()
    before = _peak_rss_mb() if can_reset else None
    detail = ""
    t0 = time.perf_counter()
    signal.setitimer(signal.ITIMER_PROF, hang_seconds)  # CPU seconds: a busy machine does not make a hang
    try:
        outcome, detail = cases.check(case, name, check, path)
    except Hang:
        outcome, detail = "hang", f"past {hang_seconds} s"
    except MemoryError as exc:
        outcome, detail = "memory", f"MemoryError {exc}"[:300]
    except Exception as exc:  # noqa: BLE001 - any exception but EvtkError is a traceback
        outcome = "traceback"
        tb = traceback.extract_tb(exc.__traceback__)
        where = next((f"{Path(f.filename).name}:{f.lineno}" for f in reversed(tb) if "/evtk/" in f.filename),
                     f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?")
        detail = f"{type(exc).__name__} at {where}: {' '.join(str(exc).split())}"[:300]
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)
    seconds = time.perf_counter() - t0
    grew = (_peak_rss_mb() - before) if before is not None else 0.0
    if outcome not in FAILURES and grew > growth_mb:
        outcome, detail = "memory", f"peak resident memory grew by {grew:.0f} MiB"
    return {"case": case, "target": name, "kind": kind, "outcome": outcome, "detail": detail,
            "seconds": round(seconds, 4), "grew_mb": round(grew, 1), "path": str(path) if path else None}


# --------------------------------------------------------------------------------------------------- worker
def worker(args):
    """Run cases ``--start`` .. ``--end`` and append one JSON line per case (and an ``S n`` line before it)."""
    os.environ["EVTK_MEMORY_LIMIT_MB"] = str(args.memory_mb)
    scratch = Path(tempfile.mkdtemp(prefix="evtk-fuzz-"))
    cases = Cases(args.dir, scratch, args.cli_every, set(args.only.split(",")) if args.only else None)
    if args.as_limit_mb:
        with open("/proc/self/status") as f:
            vm = next(int(ln.split()[1]) for ln in f if ln.startswith("VmSize:")) * 1024
        limit = vm + (args.as_limit_mb << 20)
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    import atexit
    import shutil

    atexit.register(shutil.rmtree, scratch, True)
    with open(args.log, "a") as log:
        for case in map(int, Path(args.case_list).read_text().split()):
            log.write(f"S {case}\n")
            log.flush()
            res = guarded(cases, args.seed, case, args.hang_seconds, args.memory_growth_mb)
            if res["outcome"] in FAILURES and args.save:
                _save(args.save, res)
            log.write(json.dumps(res) + "\n")
            log.flush()
    return 0


def _save(folder, res):
    """Keep the mutated file of the first 3 cases of each (target, outcome, kind)."""
    import shutil

    folder = Path(folder)
    key = f"{res['target']}__{res['outcome']}__{res['kind'].replace('/', '-')}"
    have = list(folder.glob(key + "__*"))
    if len(have) < 3 and res["path"] and os.path.exists(res["path"]):
        folder.mkdir(parents=True, exist_ok=True)
        dst = folder / f"{key}__{res['case']}{Path(res['path']).suffix}"
        shutil.copyfile(res["path"], dst)
        (folder / (dst.name + ".txt")).write_text(json.dumps(res, indent=1))


# --------------------------------------------------------------------------------------------------- parent
def run_campaign(args, todo=None):
    """Run the cases (``todo``, else ``--start`` onwards) in worker subprocesses; the list of result dicts."""
    results = {}
    log = Path(args.log or tempfile.mktemp(prefix="evtk-fuzz-", suffix=".jsonl"))
    todo = list(todo) if todo is not None else list(range(args.start, args.start + args.cases))
    kill_after = max(6 * args.hang_seconds, args.hang_seconds + 60)  # wall seconds without progress (in C code)
    t_report = time.time()
    errors = Path(str(log) + ".stderr")
    while todo:
        listing = Path(str(log) + ".todo")
        listing.write_text("\n".join(map(str, todo)))
        cmd = [sys.executable, "-m", "fuzz.campaign", "--worker", "--dir", str(args.dir), "--log", str(log),
               "--seed", str(args.seed), "--case-list", str(listing), "--hang-seconds",
               str(args.hang_seconds), "--memory-mb", str(args.memory_mb), "--as-limit-mb", str(args.as_limit_mb),
               "--memory-growth-mb", str(args.memory_growth_mb), "--cli-every", str(args.cli_every)]
        if args.only:
            cmd += ["--only", args.only]
        if args.save:
            cmd += ["--save", str(args.save)]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE.parent.parent), str(HERE.parent),
                                                             os.environ.get("PYTHONPATH", "")])}
        with open(errors, "ab") as err_file:  # a file, not a pipe: a worker never blocks on its warnings
            proc = subprocess.Popen(cmd, env=env, cwd=str(HERE.parent), stdout=subprocess.DEVNULL,
                                    stderr=err_file)
        started, last_change, pos = None, time.time(), log.stat().st_size if log.exists() else 0
        killed = False
        done = set()
        while True:
            rc = proc.poll()
            if log.exists():
                with open(log, "rb") as f:
                    f.seek(pos)
                    chunk = f.read()
                complete = chunk[:chunk.rfind(b"\n") + 1]
                pos += len(complete)
                for line in complete.decode().splitlines():
                    if line.startswith("S "):
                        started, last_change = int(line[2:]), time.time()
                    elif line.strip():
                        r = json.loads(line)
                        results[r["case"]] = r
                        done.add(r["case"])
                        started, last_change = None, time.time()
            if rc is not None:
                break
            if started is not None and time.time() - last_change > kill_after:
                proc.kill()
                killed = True
            if args.progress and time.time() - t_report > args.progress:
                t_report = time.time()
                _write_report(args, [results[k] for k in sorted(results)], partial=True)
            time.sleep(0.2)
        tail = errors.read_bytes()[-2000:].decode(errors="replace") if errors.exists() else ""
        if started is not None:  # the case in progress when the worker died
            outcome = "hang" if killed else "crash"
            results[started] = {"case": started, "target": "?", "kind": "?", "outcome": outcome,
                                "detail": f"worker exit {proc.returncode}: {tail.strip()[-300:]}", "seconds": None,
                                "grew_mb": None, "path": None}
            done.add(started)
        elif rc != 0 and len(done) < len(todo):
            raise SystemExit(f"the worker failed: exit {rc}\n{tail}")
        todo = [c for c in todo if c not in done]
    return [results[k] for k in sorted(results)]


def summarize(results) -> dict:
    by_target = collections.defaultdict(collections.Counter)
    for r in results:
        by_target[r["target"]][r["outcome"]] += 1
    failures = collections.defaultdict(list)
    for r in results:
        if r["outcome"] in FAILURES:
            key = f"{r['target']} | {r['outcome']} | {r['kind']}"
            if len(failures[key]) < 5:
                failures[key].append({"case": r["case"], "detail": r["detail"]})
    total = collections.Counter(r["outcome"] for r in results)
    times = [r["seconds"] for r in results if r.get("seconds") is not None]
    return {"cases": len(results), "totals": {k: total.get(k, 0) for k in OUTCOMES},
            "by_target": {t: {k: c.get(k, 0) for k in OUTCOMES} for t, c in sorted(by_target.items())},
            "failures": dict(sorted(failures.items())),
            "slowest_case_s": max(times) if times else None,
            "peak_growth_mb": max((r.get("grew_mb") or 0 for r in results), default=0)}


def table(summary) -> str:
    cols = OUTCOMES
    rows = [["target", *cols]] + [[t, *(str(c[k]) for k in cols)] for t, c in summary["by_target"].items()]
    rows.append(["total", *(str(summary["totals"][k]) for k in cols)])
    widths = [max(len(r[i]) for r in rows) for i in range(len(cols) + 1)]
    return "\n".join("  ".join(v.rjust(w) if i else v.ljust(w) for i, (v, w) in enumerate(zip(r, widths)))
                     for r in rows)


def _write_report(args, results, partial=False):
    if not args.out:
        return
    summary = summarize(results)
    summary.update(seed=args.seed, start=args.start, requested=args.cases, partial=partial)
    tmp = Path(str(args.out) + ".tmp")
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, args.out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0, help="first case number")
    ap.add_argument("--out", type=Path, help="write the summary as JSON here")
    ap.add_argument("--dir", type=Path, help="the built targets (built into a temporary folder if not given)")
    ap.add_argument("--only", help="comma-separated target names (e.g. l2.aedat,r.npz)")
    ap.add_argument("--hang-seconds", type=float, default=10.0,
                    help="CPU seconds a case may take (a case stuck outside Python is killed after 6x as long)")
    ap.add_argument("--memory-mb", type=int, default=256, help="EVTK_MEMORY_LIMIT_MB for the cases")
    ap.add_argument("--as-limit-mb", type=int, default=2048, help="address space the worker may add (RLIMIT_AS)")
    ap.add_argument("--memory-growth-mb", type=float, default=400.0,
                    help="a case whose peak resident memory grows by more is a memory blow-up")
    ap.add_argument("--cli-every", type=int, default=25, help="run evtk info --check on every Nth case (0: never)")
    ap.add_argument("--save", type=Path, help="keep the mutated files of failing cases here")
    ap.add_argument("--log", type=Path, help="the per-case JSON lines (kept; a temporary file if not given)")
    ap.add_argument("--progress", type=float, default=60.0, help="rewrite --out every this many seconds")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--case-list", help=argparse.SUPPRESS)
    ap.add_argument("--rerun", type=Path,
                    help="rerun only the failing cases of this per-case log (--log of an earlier run, same --seed)")
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)
    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix="evtk-fuzz-src-") as d:
        if args.dir is None:
            from fuzz import targets as tg

            args.dir = Path(d)
            tg.build(args.dir)
        todo = None
        if args.rerun:
            todo = sorted({json.loads(ln)["case"] for ln in args.rerun.read_text().splitlines()
                           if ln.startswith("{") and json.loads(ln)["outcome"] in FAILURES})
        results = run_campaign(args, todo)
    summary = summarize(results)
    _write_report(args, results)
    print(f"{summary['cases']} cases (seed {args.seed}) in {time.time() - t0:.0f} s")
    print(table(summary))
    for key, items in summary["failures"].items():
        print(f"FAIL {key}: case {items[0]['case']}: {items[0]['detail'][:200]}")
    return 1 if any(summary["totals"][k] for k in FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
