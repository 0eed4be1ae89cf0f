#!/usr/bin/env bash
# The checks a machine with an NVIDIA GPU runs, in one go (CI has no GPU; a lease is short):
#
#     bash benchmarks/cuda_checks.sh OUT [DEVICE]
#
# in the order that matters when time runs out: tests/solve/test_cuda.py, the everyday commands on
# the GPU (the default scene cold, again from the cache, EO, SSIM, auto, the camera loop, the colour
# scene by least squares and SSIM on one operator per channel), then the
# CUDA sections of benchmarks/solvers.py (--cuda-only) and benchmarks/batch_solves.py. Writes
# OUT/summary.txt (each step's exit status and wall seconds), OUT/log.txt (every step's output) and
# the two benchmarks' results. DEVICE (default cuda) lets the script itself be tried on a CPU.
# On the GPU machines (their image: torch with CUDA, no torchproj dependencies beyond numpy, scipy,
# scikit-image and an OpenCV without contrib), carry kornia, kornia_rs and platformdirs as wheels
# (the device tool's README says how) and put benchmarks/device_shim on PYTHONPATH for OpenCV's
# Gray-code generator:
#     pip install --no-index --no-deps --target /tmp/site .whl/*.whl
#     PYTHONPATH=/tmp/site:$PWD/benchmarks/device_shim:$PWD bash benchmarks/cuda_checks.sh $OUT
# CHECKS_BUDGET_S (default 380) skips the steps that would start after that many seconds;
# CHECKS_SKIP names steps to leave out (space-separated, e.g. "test_cuda run_refine").
set -u
out=${1:?usage: cuda_checks.sh OUT [DEVICE]}
device=${2:-cuda}
budget=${CHECKS_BUDGET_S:-380}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
export TORCHPROJ_CACHE_DIR=${TORCHPROJ_CACHE_DIR:-/tmp/torchproj-checks-cache}
runs=$(mktemp -d)
start=$(date +%s%N)

elapsed() { echo $(( ($(date +%s%N) - start) / 1000000000 )); }

step() {  # step NAME LIMIT_S COMMAND...: run it with a time limit, log it, note its status and time
    local name=$1 limit=$2
    shift 2
    if [[ " ${CHECKS_SKIP:-} " == *" $name "* ]]; then
        echo "$name skipped: CHECKS_SKIP" | tee -a "$out/summary.txt"
        return
    fi
    if [ "$(elapsed)" -ge "$budget" ]; then
        echo "$name skipped: ${budget} s budget spent" | tee -a "$out/summary.txt"
        return
    fi
    local t0 rc
    t0=$(date +%s%N)
    echo "===== $name: $*" >> "$out/log.txt"
    timeout "$limit" "$@" >> "$out/log.txt" 2>&1
    rc=$?
    printf '%s rc=%s %.1f s\n' "$name" "$rc" "$(( ($(date +%s%N) - t0) / 1000000 ))e-3" | tee -a "$out/summary.txt"
}

{ nvidia-smi -L 2>&1; python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"; } \
    | tee "$out/summary.txt"
run="python3 -m torchproj.cli run --device $device"
step test_cuda 240 python3 -m pytest -q -p no:cacheprovider tests/solve/test_cuda.py
step run_cold 150 $run --out "$runs/cold"
step run_again 90 $run --out "$runs/again"
step run_eo 90 $run --solver eo --bounds=-100,255 --out "$runs/eo"
step run_ssim 90 $run --objective ssim --out "$runs/ssim"
step run_auto 90 $run --footprint auto --out "$runs/auto"
step run_refine 120 $run --refine 2 --out "$runs/refine"
# A colour scene: one operator per channel, least squares and the SSIM solve on the channel stack.
step run_colour 120 $run colour_two_planes --out "$runs/colour"
step run_colour_ssim 90 $run colour_two_planes --objective ssim --out "$runs/colour_ssim"
if [ "$device" = cuda ]; then
    step solvers_cuda 200 python3 benchmarks/solvers.py --cuda-only --sizes quarter half full --out "$runs/solvers"
    cp "$runs/solvers/results.json" "$out/solvers_cuda.json" 2>/dev/null
fi
step batch_solves 150 python3 benchmarks/batch_solves.py --device "$device" --out "$runs/batch"
cp "$runs/batch/results.md" "$out/batch_solves.md" 2>/dev/null
cp "$runs/batch/results.json" "$out/batch_solves.json" 2>/dev/null
for r in "$runs"/*/report.json; do
    python3 -c "import json, sys; r = json.load(open(sys.argv[1])); print(sys.argv[1].split('/')[-2], [(t['name'], round(t['psnr_db'], 2), round(t['ssim'], 3)) for t in r['targets']], {k: round(v, 2) for k, v in r.get('timings_s', {}).items()})" "$r"
done | tee "$out/reports.txt"
echo "total $(elapsed) s" | tee -a "$out/summary.txt"
