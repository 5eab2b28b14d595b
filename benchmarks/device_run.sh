#!/bin/bash
# Issue 32's many-core figures in one call on a lent 16-core machine (docs/performance.md, "Every core").
#
# The machine has Python 3.12 with numpy, numba, h5py, pyarrow, click and scikit-image but reaches no package
# index: the other packages travel as wheels in .whl/ (git-ignored through .git/info/exclude), fetched here with
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 ... -d .whl \
#     lz4 zstandard tomli_w dv-processing dask distributed tornado tblib zict partd locket
# (hdf5plugin stays behind: 46 MB, and nothing here needs it) and the command is
# `bash benchmarks/device_run.sh [steps]`, carrying .whl (and .old for env-ab). Results go to $OUT (or /tmp/evtk-out).
# The data files are made there (benchmarks/data is too large to travel). Steps: threads fresh reconstruct batch
# calibrate (all by default; about 6 minutes with the machine's start), threads-ab (against a tree in .new),
# limits (what bounds the AEDAT4 read on 16 cores: the stages of a read, and the read with the memory bound on
# its threads lifted and with half-size batches), phases (the first of those alone), memory (a whole read's peak,
# AEDAT4 and EVT 3.0, 20 M events), env (bench_env.py: read, reconstruct -o, enob and the calibrated route in fresh
# processes under BLAS and thread settings; ENVS="--env L=K=V ..." replaces them), env-ab (the same, this tree
# against one in .old, carried, and the variants in ENVS; ROUNDS sets the rounds), caps (the thread caps
# MOST_PARTS and PREFETCH_THREADS raised, in patched copies of this tree, against it; CAPS replaces the variants),
# serial (bench_serial.py: the share of a one-core read that holds the GIL), range-ab (the AEDAT4 read on 1, 8 and
# 16 cores with the reader's range kernel, then without it: one kernel call a batch, as before the sixteenth round),
# pipeline (bench_pipeline.py: whether the decoding of each chunk or its counting and sums bound enob and
# reconstruct -o).
set -u
OUT=${OUT:-/tmp/evtk-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
export PYTHONPATH=/tmp/site:$PWD
# evtk's compiled kernels (the reader's LZ4 batches, the counting), built in place for this machine's Python (the
# tree runs from PYTHONPATH, uninstalled); where there is no compiler or no Python.h, evtk runs its Python route
# and says so here
rm -f evtk/_ckernels.*.so
gcc -O3 -fwrapv -shared -fPIC -I"$(python3 -c 'import sysconfig; print(sysconfig.get_paths()["include"])')" \
    evtk/_ckernels.c -o "evtk/_ckernels$(python3 -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))')" \
    && echo "compiled kernels: built" || echo "compiled kernels: not built (the Python route)"
# the reader's compiled Zstandard batches need the system's libzstd (evtk.io._compression.zstd_addresses)
python3 -c "from evtk.io import _compression as c; lib = c._zstd(); print('libzstd:', lib.ZSTD_versionNumber() if lib else 'none (ZSTD batches take the Python loop)')"
STEPS=${*:-threads fresh reconstruct batch calibrate}
echo "cores: $(nproc), $(python3 -c 'import sys, numpy, numba; print(sys.version.split()[0], numpy.__version__, numba.__version__)')"
lscpu | grep -E "Model name|^CPU\(s\)|Thread|NUMA node\(s\)|L3" || true
free -g | head -2

# a fresh VM's memory is cold: the first touch of a page costs the host's backing of it (1.9 s of system time a
# GiB on the development VM, 0.29 s once touched; docs/performance.md, tenth round), the likely reason why that
# round's later calls ran every fresh process 0.3-0.4 s slower than its first, which had read 20 M events several
# times before. Touch WARM_GIB (16 by default) once, on every core, held at once.
t0=$(date +%s)
python3 - "${WARM_GIB:-16}" <<'PY'
import os, sys
from concurrent.futures import ThreadPoolExecutor
import numpy as np
gib = int(sys.argv[1])
def touch(_):
    a = np.empty(1 << 30, np.uint8)
    a[::4096] = 1
    return a
with ThreadPoolExecutor(os.cpu_count()) as ex:
    held = list(ex.map(touch, range(gib)))
PY
echo "memory touched in $(( $(date +%s) - t0 )) s"

# the data, in parallel: the 20 M-event files of bench_threads and bench_fresh_read, bench_calibrate's runs, batch's
# 16 recordings
t0=$(date +%s)

python3 -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_fresh_read as b; b.make_file(20_000_000, 'dv-lz4')" &
python3 -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_fresh_read as b; b.make_file(20_000_000, 'evtk-zstd')" &
if [[ " $STEPS " == *" threads "* ]]; then
    python3 -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_threads as b; b.data_file(20_000_000, 'evt3')" &
    python3 -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_threads as b; b.data_file(20_000_000, 'evt2')" &
fi
if [[ " $STEPS " == *" env"* ]]; then  # bench_calibrate's camera runs (dv-processing's files) and calibration
    python3 benchmarks/bench_calibrate.py --fresh 1 --writer dv --keep benchmarks/data/calkeep > /dev/null &
fi
if [[ " $STEPS " == *" batch "* ]]; then
    for i in $(seq 0 15); do
        python3 -c "import sys; sys.path.insert(0, 'benchmarks'); import bench_batch as b; b.make_one($i)" &
    done
fi
wait
echo "data made in $(( $(date +%s) - t0 )) s"; ls -la benchmarks/data

step() {  # name, seconds, command...
    local name=$1 secs=$2; shift 2
    echo "== $name ($(date +%T), load $(cut -d' ' -f1 /proc/loadavg))"
    timeout "$secs" "$@" 2>&1 | tee "$OUT/$name.log"
}
for s in $STEPS; do
    case $s in
    threads) step threads 200 python3 benchmarks/bench_threads.py --cores 1,2,4,8,16 --rounds 2 --reads 3 \
                 --formats aedat4-dv,aedat4-zstd,evt3,evt2 --json "$OUT/threads.json" ;;
    threads-ab)  # this tree against the one in .new (git archive of a branch, carried), alternating
        for r in 1 2; do
            for tree in "$PWD" "$PWD/.new"; do
                PYTHONPATH=/tmp/site:$tree step "threads-$r-$(basename "$tree")" 200 python3 benchmarks/bench_threads.py \
                    --cores 1,2,4,8,16 --rounds 1 --reads 5 --formats aedat4-dv,aedat4-zstd \
                    --json "$OUT/threads-$r-$(basename "$tree").json"
            done
        done ;;
    phases) step phases 60 python3 benchmarks/bench_threads.py --cores 1,8,16 --rounds 1 --reads 3 --phases \
                --formats aedat4-dv ;;
    env)  # which threads a short process pays for: the BLAS library's (spinning at start), evtk's
        step env 240 python3 benchmarks/bench_env.py --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 \
            --keep benchmarks/data/calkeep --rounds 5 --ops "read;reconstruct;enob;calibrated" ${ENVS:---env base= \
            --env blas1=OPENBLAS_NUM_THREADS=1 --env timeout4=OPENBLAS_THREAD_TIMEOUT=4 \
            --env blas1-t2=OPENBLAS_NUM_THREADS=1,EVTK_THREADS=2 --env blas1-t4=OPENBLAS_NUM_THREADS=1,EVTK_THREADS=4 \
            --env blas1-t8=OPENBLAS_NUM_THREADS=1,EVTK_THREADS=8} ;;
    env-ab)  # this tree against the one in .old (git archive of the commit before, carried), and knobs in ENVS
        step env-ab 300 python3 benchmarks/bench_env.py --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 \
            --keep benchmarks/data/calkeep --rounds ${ROUNDS:-7} --ops "read;reconstruct;enob;calibrated" \
            --env "old=TREE=$PWD/.old" --env new= $ENVS ;;
    caps)  # the tenth round's thread caps (MOST_PARTS = 2 counting parts, PREFETCH_THREADS = 3 threads decoding a
           # prefetched chunk), set while the GIL bound the counting and the batch loop: patched copies of this
           # tree, FILE:NAME=VALUE each, against it in whole fresh processes (CAPS="LABEL@PATCH,PATCH ..." replaces them)
        caps=()
        for v in ${CAPS:-parts4@evtk/_parallel.py:MOST_PARTS=4 parts8@evtk/_parallel.py:MOST_PARTS=8 \
                prefetch6@evtk/io/aedat4/reader.py:PREFETCH_THREADS=6 \
                both8-6@evtk/_parallel.py:MOST_PARTS=8,evtk/io/aedat4/reader.py:PREFETCH_THREADS=6}; do
            label=${v%%@*} d=/tmp/caps/$label
            rm -rf "$d" && mkdir -p "$d" && cp -r evtk "$d/"
            IFS=, read -ra patches <<< "${v#*@}"
            for patch in "${patches[@]}"; do
                file=${patch%%:*} name=${patch#*:} name=${name%%=*} value=${patch#*=}
                sed -i "s/^$name = .*/$name = $value/" "$d/$file"
                grep -q "^$name = $value\$" "$d/$file" && echo "caps: $label sets $name = $value" \
                    || echo "caps: $label did not set $name in $file"
            done
            caps+=(--env "$label=TREE=$d")
        done
        step caps 300 python3 benchmarks/bench_env.py --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 \
            --rounds ${ROUNDS:-5} --ops "read;reconstruct;enob" --env base= "${caps[@]}" ;;
    limits)  # against the threads step's 1-core read on the same machine
        step limits-phases 60 python3 benchmarks/bench_threads.py --cores 1,16 --rounds 1 --reads 3 --phases \
            --formats aedat4-dv
        step limits-unbounded 60 python3 benchmarks/bench_threads.py --cores 8,16 --rounds 1 --reads 5 \
            --formats aedat4-dv,aedat4-zstd --set evtk._threads.MEMORY_SHARE=1.0
        step limits-half-batch 60 python3 benchmarks/bench_threads.py --cores 8,16 --rounds 1 --reads 5 \
            --formats aedat4-dv,aedat4-zstd --set evtk.io.aedat4.reader.BATCH_EVENTS=32768 \
            --set evtk.io.aedat4.reader._THREAD_BYTES=1310720 ;;
    memory) step memory 60 python3 benchmarks/bench_memory.py --full-reads 2e7 --only aedat4,evt3 ;;
    serial) step serial 40 python3 benchmarks/bench_serial.py --rounds 2 --reads 5 ;;
    range-ab) step range-on 70 python3 benchmarks/bench_threads.py --cores 1,8,16 --rounds 2 --reads 3 \
                  --formats aedat4-dv --ceiling-rounds 0
        step range-off 70 python3 benchmarks/bench_threads.py --cores 1,8,16 --rounds 2 --reads 3 \
            --formats aedat4-dv --ceiling-rounds 0 --set evtk._native._kernel_decode_lz4_range=None ;;
    fresh) step fresh 55 python3 benchmarks/bench_fresh_read.py --writers dv-lz4,evtk-zstd --repeats 5 \
               --json "$OUT/fresh.json" ;;
    reconstruct) step reconstruct 80 python3 benchmarks/bench_reconstruct.py --fixed --repeats 5 \
                     --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 --ops "evtk reconstruct -o x.npz;evtk enob" ;;
    batch) step batch 150 python3 benchmarks/bench_batch.py --recordings 16 --workers 16 --rounds 2 --repeats 3 --fmt npz \
               --json "$OUT/batch.json" ;;
    calibrate) step calibrate 80 python3 benchmarks/bench_calibrate.py --fresh 7 --writer dv ;;
    pipeline)  # which side bounds enob and reconstruct -o here: the decoding of each chunk or its counting
        step pipeline-enob 60 python3 benchmarks/bench_pipeline.py --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 \
            --op enob --runs 2
        step pipeline-reconstruct 60 python3 benchmarks/bench_pipeline.py \
            --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 --op reconstruct --runs 2 ;;
    esac
done
echo "== done $(date +%T)"
