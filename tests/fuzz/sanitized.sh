#!/bin/bash
# evtk's compiled kernels under AddressSanitizer and UBSan: any read or write outside a buffer, and any undefined
# arithmetic (a signed overflow, a shift past the width), stops the run with its place in evtk/_ckernels.c.
#
#   bash tests/fuzz/sanitized.sh [CALLS] [CASES]      (from the repository root; gcc and the test extras needed)
#
# Builds the kernels with -fsanitize=address,undefined into a copy of the tree (the checkout's own build is left
# alone) and runs there, with the sanitizers' runtimes preloaded into Python:
#   1. tests/fuzz/kernels.py: CALLS (default 100000) raw calls with hostile arguments, four seeds;
#   2. the kernels' tests (the compiled decoders, batches and counting against numpy and word-by-word loops, the
#      timed counting and the timing solve against numba's kernels, the time order the AEDAT4 split finds);
#   3. the fuzz campaign, CASES (default 3000) cases over the targets the kernels read (EVT 2.0, EVT 3.0, DAT,
#      Event Stream DVS and ATIS, and the AEDAT4 files), each read compared with the numpy route's. ASan's
#      quarantine of freed memory is kept to 8 MiB, so that it does not pass for a case's memory blow-up.
set -euo pipefail
CALLS=${1:-100000}
CASES=${2:-3000}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
TOP=$(mktemp -d /tmp/evtk-sanitized-XXXXXX)
trap 'rm -rf "$TOP"' EXIT
WORK=$TOP/evtk
mkdir "$WORK"
[ -d "$ROOT/../shared" ] && ln -s "$(cd "$ROOT/../shared" && pwd)" "$TOP/shared"  # the real recordings, if present
cd "$ROOT"
git ls-files -z --cached --others --exclude-standard | xargs -0 cp --parents -t "$WORK"
cd "$WORK"
PY=${PYTHON:-python3}
INC=$($PY -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
EXT=$($PY -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))')
gcc -shared -fPIC -O1 -g -fno-omit-frame-pointer -fsanitize=address,undefined -fno-sanitize-recover=undefined \
    -std=c99 -Wall -Wextra -I"$INC" evtk/_ckernels.c -o "evtk/_ckernels$EXT" -lm
export LD_PRELOAD="$(gcc -print-file-name=libasan.so) $(gcc -print-file-name=libubsan.so)"
export ASAN_OPTIONS=detect_leaks=0:quarantine_size_mb=8 UBSAN_OPTIONS=print_stacktrace=1 PYTHONPATH=$WORK
$PY -c 'import evtk, evtk._native as n; assert evtk.__file__.startswith("'"$WORK"'") and n.enabled(), "not built"'
echo "== 1. raw kernels, $CALLS calls a seed"
for seed in 1 2 3 4; do
    $PY -m tests.fuzz.kernels --calls "$CALLS" --seed "$seed" | tr '\n' ' '
    echo
done
echo "== 2. the kernels' tests"
$PY -m pytest -q -p no:cacheprovider tests/test_native_batches.py tests/test_native_counting.py tests/test_native_zstd.py \
    tests/test_prophesee_numpy.py tests/test_accumulate_numpy.py tests/test_timing_numpy.py tests/test_aedat4_time_order.py
echo "== 3. the fuzz campaign, $CASES cases"
cd tests
$PY -m fuzz.campaign --cases "$CASES" --seed 101 --only f2.raw,f3.raw,f.dat,f.es,a.es,l.aedat4,f.aedat4,z.aedat4 \
    --cli-every 0
echo "== sanitized run passed"
