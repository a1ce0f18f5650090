#!/usr/bin/env bash
# The GPU check: on a machine with a CUDA GPU, PyTorch and nvcc but no network, install gsmsdr-ns and what it needs
# from a carried wheelhouse, build gsplat's CUDA kernels, run the `cuda` tests (CUDA against the CPU path), time
# training steps per method, and train `ns-train gsmsdr-lite` to the end of its schedule against plain Gaussians.
# Everything it measures goes to OUT/results.md; logs to OUT/check.log and OUT/cuda-tests.log.
#
# Prepare on a machine with network (here, on the CPU), then carry .gpu/wheels, .gpu/scenes and .gpu/commit (about
# 58 MiB; .gpu/ is git-ignored):
#   .venv/bin/python scripts/gpu_wheelhouse.py .gpu    # wheels for the device's Python (3.12; --python to change)
#   .venv/bin/python scripts/gpu_scenes.py .gpu        # the generated scenes below (CPU, about 10 minutes)
#   git rev-parse --short HEAD > .gpu/commit            # the commit results.md names
# Run on the GPU machine, from the repository root:
#   bash scripts/gpu_check.sh OUT [STAGE ...]
# STAGE: install build tests step lite realsize (default: all but realsize, in that order; install and build are
# needed by the others in a fresh shell, and are quick when already done). A gsplat extension built by an earlier run
# can be carried as .gpu/gsplat/gsplat_cuda.so (OUT/gsplat_cuda.so of that run): it is used instead of building again.
# realsize trains configs/bench/real-size-gpu.yaml from the scene folders carried in .gpu/rs-scenes/ (the real-size
# suite's built fern scene, scenes/llff-fern-images_8-motion-strong-h8-s0-r2-x1-estimated-l3 of its --out).
set -uo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
OUT=${1:?usage: bash scripts/gpu_check.sh OUT [install|build|tests|step|lite|realsize ...]}
shift
STAGES=${*:-install build tests step lite}
GPU=${GSMSDR_GPU_DIR:-$ROOT/.gpu}
SITE=${GSMSDR_GPU_SITE:-/tmp/gsmsdr-gpu-site}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
LOG=$OUT/check.log
RESULTS=$OUT/results.md
WORK=${GSMSDR_GPU_WORK:-/tmp/gsmsdr-gpu-work}
mkdir -p "$WORK"

export PYTHONUNBUFFERED=1 PYTHONPATH=$SITE PATH=$SITE/bin:$PATH
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/gsmsdr-torch-extensions}
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then  # build for this GPU only (all architectures would take many times longer)
  TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())" 2>/dev/null)
  export TORCH_CUDA_ARCH_LIST
fi

say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }
result() { echo "$*" >> "$RESULTS"; }
has_stage() { [[ " $STAGES " == *" $1 "* ]]; }
seconds_since() { python3 -c "import sys, time; print(f'{time.time() - float(sys.argv[1]):.1f}')" "$1"; }

if [ ! -f "$RESULTS" ]; then
  {
    echo "# GPU check"
    echo
    echo "Command: \`bash scripts/gpu_check.sh OUT $STAGES\` at git $(cat "$GPU/commit" 2>/dev/null || echo unknown)"
    echo
    echo "Device: $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null);" \
      "$(nproc) CPU cores; $(python3 -c 'import sys, torch; print(f"Python {sys.version.split()[0]}, torch {torch.__version__}")');" \
      "nvcc $(nvcc --version 2>/dev/null | sed -n 's/.*release \([0-9.]*\).*/\1/p')"
    echo
  } > "$RESULTS"
fi

if has_stage install; then
  say "install: wheels from $GPU/wheels and the project into $SITE"
  t0=$(date +%s.%N)
  # one pip call (a second --target install would replace the first one's bin/); the project is built by the
  # device's setuptools, and its entry points register the methods with nerfstudio
  python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --no-cache-dir --upgrade \
    --target "$SITE" "$GPU"/wheels/*.whl "$ROOT" >> "$LOG" 2>&1 || say "install: FAILED (see check.log)"
  say "install: done in $(seconds_since "$t0") s"
fi

if has_stage build; then
  if [ -f "$GPU/gsplat/gsplat_cuda.so" ]; then
    # a module named gsplat.csrc is what gsplat imports before it tries to build: make it the carried extension
    cp "$GPU/gsplat/gsplat_cuda.so" "$SITE/gsplat_cuda.so"
    printf 'import sys\n\nimport gsplat_cuda\n\nsys.modules[__name__] = gsplat_cuda\n' > "$SITE/gsplat/csrc.py"
    say "build: using the carried gsplat extension"
  fi
  say "build: gsplat's CUDA kernels (TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST, MAX_JOBS=$MAX_JOBS), and our C++ CPU kernels"
  python3 - > "$WORK/cpu-ext.log" 2>&1 <<'EOF' &
from gsmsdr_ns.ops.disk_defocus_cpp import EXTENSION as disk
from gsmsdr_ns.ops.grid_kernels import EXTENSION as grid
from gsmsdr_ns.ops.pixel_kernels_cpp import EXTENSION as pixel
from gsmsdr_ns.render.pixels_cpp import EXTENSION as raster

for extension in (raster, pixel, grid, disk):
    print(extension.name, "built" if extension.available() else f"FAILED: {extension.error()}")
EOF
  cpu_ext=$!
  t0=$(date +%s.%N)
  timeout "${GSMSDR_GPU_BUILD_TIMEOUT:-330}" python3 - > "$WORK/gsplat-build.log" 2>&1 <<'EOF'
import glob
import os
import sys

from gsmsdr_ns.render.gsplat_backend import gsplat_cuda_problem

problem = gsplat_cuda_problem()
print("gsplat backend:", "loaded" if problem is None else problem)
if problem is None:
    import gsplat.cuda._backend as backend

    path = getattr(backend._C, "__file__", "")
    print(f"module: {path} ({os.path.getsize(path) / 2**20:.1f} MiB)" if path else "module: ?")
sys.exit(0 if problem is None else 1)
EOF
  status=$?
  build_s=$(seconds_since "$t0")
  cat "$WORK/gsplat-build.log" >> "$LOG"
  wait $cpu_ext
  cat "$WORK/cpu-ext.log" >> "$LOG"
  so=$(ls "$TORCH_EXTENSIONS_DIR"/gsplat_cuda/gsplat_cuda.so 2>/dev/null | head -1)
  if [ -n "$so" ] && [ "$(stat -c %s "$so")" -lt 16000000 ]; then cp "$so" "$OUT/gsplat_cuda.so"; fi
  result "## gsplat's CUDA backend"
  result ""
  result "$(tail -2 "$WORK/gsplat-build.log" | sed 's/^/    /')"
  result ""
  result "Build and load: ${build_s} s (MAX_JOBS=$MAX_JOBS, TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST); our C++ CPU kernels: $(tr '\n' ';' < "$WORK/cpu-ext.log")"
  result ""
  say "build: gsplat status $status in $build_s s"
fi

if has_stage tests; then
  say "tests: pytest -m cuda tests/test_cuda.py"
  t0=$(date +%s.%N)
  (cd "$ROOT" && timeout 480 python3 -m pytest -p no:cacheprovider -q -m cuda tests/test_cuda.py -rA \
    > "$OUT/cuda-tests.log" 2>&1)
  status=$?
  tests_s=$(seconds_since "$t0")
  (cd "$ROOT" && timeout 120 python3 tests/test_stability_autocast.py cuda > "$WORK/autocast.log" 2>&1)
  autocast=$?
  result "## \`pytest -m cuda tests/test_cuda.py\` (exit $status, ${tests_s} s)"
  result ""
  result "$(grep -E '^(PASSED|FAILED|ERROR|SKIPPED)|passed|failed' "$OUT/cuda-tests.log" | tail -40 | sed 's/^/    /')"
  result ""
  result "What the tests printed (errors against the CPU path; synchronising calls outside gsmsdr_ns):"
  result ""
  result "$(grep -E '^(rgb|rgb-unpacked|sh3-rgb[+]ed|antialiased-background): image|^(gsmsdr|plain): (losses|[0-9]+ synchronising)|^  [0-9.]+ per step:' "$OUT/cuda-tests.log" | sed 's/^/    /')"
  result ""
  result "\`python tests/test_stability_autocast.py cuda\` (exit $autocast):"
  result ""
  result "$(tail -12 "$WORK/autocast.log" | sed 's/^/    /')"
  result ""
  say "tests: exit $status in $tests_s s; autocast checks exit $autocast"
fi

if has_stage step; then
  say "step: gsmsdr-bench step"
  (cd "$WORK" && timeout 300 gsmsdr-bench step --data "$GPU/scenes/motion-strong-600x400" \
    --methods plain full view gsmsdr-lite --warmup 20 --steps 100 --breakdown-steps 20 --out "$WORK/step-600x400" >> "$LOG" 2>&1) \
    || say "step: 600x400 FAILED"
  (cd "$WORK" && timeout 240 gsmsdr-bench step --data "$GPU/scenes/sharp-1297x840" --methods plain full \
    --warmup 10 --steps 50 --breakdown-steps 10 --no-estimate --out "$WORK/step-1297x840" >> "$LOG" 2>&1) || say "step: 1297x840 FAILED"
  for size in 600x400 1297x840; do
    if [ -f "$WORK/step-$size/results.md" ]; then
      result "$(sed 's/^# /## /' "$WORK/step-$size/results.md")"
      result ""
      cp "$WORK/step-$size/results.csv" "$OUT/step-$size.csv"
    fi
  done
  say "step: done"
fi

if has_stage lite; then
  # GSMSDR_GPU_LITE_PARALLEL=1: both trainings at the same time on the one GPU (half the device time; each one's
  # wall time then includes the other's competition, which the table says). GSMSDR_GPU_LITE_ARGS: more ns-train
  # arguments for both runs (a dry run of this stage on a CPU: "--max-num-iterations 5 --machine.device-type cpu")
  parallel=${GSMSDR_GPU_LITE_PARALLEL:-0}
  scene=$GPU/scenes/motion-strong-160x120
  result "## \`ns-train gsmsdr-lite\` to the end of its schedule, against plain Gaussians"
  result ""
  if [ "$parallel" = 1 ]; then how="both at the same time on the GPU"; else how="one after the other, each alone on the GPU"; fi
  result "Scene: $(basename "$scene") (generated strong camera shake; sharp held-out test views). Runs: $how."
  result "Wall time of the whole \`ns-train\` process (start-up included); PSNR / SSIM from \`ns-eval\` on the test views."
  result ""
  result "| run | command | wall s | PSNR | SSIM | LPIPS |"
  result "| --- | --- | ---: | ---: | ---: | ---: |"
  train() {  # run name, extra arguments...; writes $WORK/train-<run>.{log,status,seconds}
    local run=$1
    shift
    local t0
    t0=$(date +%s.%N)
    (cd "$WORK" && timeout 480 ns-train gsmsdr-lite --data "$scene" --output-dir "$WORK/runs" \
      --experiment-name lite-vs-plain --timestamp "$run" --vis tensorboard --steps-per-eval-image 0 \
      --steps-per-eval-all-images 0 --steps-per-save 100000 ${GSMSDR_GPU_LITE_ARGS:-} "$@" > "$WORK/train-$run.log" 2>&1)
    echo $? > "$WORK/train-$run.status"
    seconds_since "$t0" > "$WORK/train-$run.seconds"
  }
  runs=(gsmsdr-lite plain)
  say "lite: training ${runs[*]} ($how)"
  if [ "$parallel" = 1 ]; then
    train gsmsdr-lite &
    train plain --pipeline.model.degradation sharp &
    wait
  else
    train gsmsdr-lite
    train plain --pipeline.model.degradation sharp
  fi
  for run in "${runs[@]}"; do
    status=$(cat "$WORK/train-$run.status")
    wall=$(cat "$WORK/train-$run.seconds")
    tail -5 "$WORK/train-$run.log" >> "$LOG"
    metrics="FAILED (exit $status) | | |"
    config=$WORK/runs/lite-vs-plain/gsmsdr-lite/$run/config.yml
    if [ "$status" = 0 ] && (cd "$WORK" && timeout 120 ns-eval --load-config "$config" \
         --output-path "$WORK/eval-$run.json" >> "$LOG" 2>&1); then
      metrics=$(python3 -c "import json, sys; r = json.load(open(sys.argv[1]))['results']; \
print(f\"{r['psnr']:.2f} | {r['ssim']:.4f} | {r.get('lpips', float('nan')):.4f}\")" "$WORK/eval-$run.json")
    fi
    extra=""
    [ "$run" = plain ] && extra=" --pipeline.model.degradation sharp"
    result "| $run | \`ns-train gsmsdr-lite --data $(basename "$scene")$extra\` | $wall | $metrics |"
    say "lite: $run exit $status in $wall s: $metrics"
  done
  result ""
fi
if has_stage realsize; then
  # the real-size fern on the GPU from carried scene folders (.gpu/rs-scenes/<scene>, built on the CPU by the
  # real-size suite: structure-from-motion is not repeated here); SIGINT at the time limit keeps the finished runs
  # and writes the report of those
  rs=$WORK/real-size-gpu
  mkdir -p "$rs/scenes"
  cp -r "$GPU"/rs-scenes/* "$rs/scenes/" 2>/dev/null || say "realsize: no carried scenes in $GPU/rs-scenes"
  say "realsize: gsmsdr-bench suite --config real-size-gpu"
  (cd "$WORK" && timeout -s INT "${GSMSDR_GPU_RS_TIMEOUT:-420}" gsmsdr-bench suite --config real-size-gpu \
    --out "$rs" --no-progress >> "$LOG" 2>&1) || say "realsize: suite exit $?"
  for f in results.md results.csv psnr_vs_time_fern-motion-504.png; do
    [ -f "$rs/$f" ] && cp "$rs/$f" "$OUT/real-size-gpu-$f"
  done
  say "realsize: done"
fi
say "done: $RESULTS"
