#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one run (a lent GPU is a few minutes of machine time):
#   1. gsplat's CUDA extension builds (JIT, sm_90 only) while
#   2. bench/bench_enhance_gpu.py times the full-size enhancer (FLUX.1-dev architecture, random
#      weights): denoising steps at 1024² and 4K, VAE, a whole 4K frame, bf16 LoRA training;
#   3. the CUDA tests (pytest -m gpu): gsplat against the torch back-end (forward, gradients,
#      rendered flow), Poly4DGS training through gsplat, RAFT with torchvision;
#   4. bench/bench_rasterizer.py on CUDA, gsplat beside the torch back-end;
#   5. bench/bench_poly4dgs_step.py: a Poly4DGS training step against a static 3DGS of the same count;
#   6. the prepared runs, each from a folder written here on CPU (a GPU machine has no Prefect, pycolmap,
#      OpenCV or store) and carried; each runs after the gsplat build, so no timing holds the build:
#      GPU_CLOSEUP=DIR (`python bench/gpu_closeup.py --prepare DIR`, its DIR/gpu carried): the demo's
#        close-up rendered through gsplat and enhanced on CUDA, timed per frame (issue 27; $OUT/closeup.log,
#        timings.json and the parts closeup_exrs.tar.NN, scored here with --score);
#      ZOOM_CURVE=DIR (`python bench/gpu_zoom_curve.py --prepare DIR`): the demo segment at a production-size
#        budget, detail and PSNR per camera role against time, stopped within ZOOM_BUDGET_S (issue 28;
#        $OUT/zoom/: curve.json, sheet.npz, log; read back with --report);
#      P2S=DIR (`python bench/bench_pose2sim_heldout.py ... --gpu-prepare DIR`): issue 30's real capture at full
#        resolution, gpu_zoom_curve's run over the prepared Pose2Sim segment within P2S_BUDGET_S, scored
#        P2S_EVALS times (full-resolution scoring is ~40 s a checkpoint, its floors ~140 s) ($OUT/p2s/);
#      PAIRS=DIR (`python bench/gpu_facerig_pairs.py --prepare DIR`): the Face Rig pair stages' time and GPU
#        memory at 1024² and 4096² within PAIRS_BUDGET_S (issue 29; $OUT/pairs/).
#      PREPARED_ONLY=1 runs the build and the prepared runs alone (what a 15-minute lease holds).
# Results go to $OUT (default /tmp/volcap-gpu). Python packages the machine lacks can travel as
# wheels in .whl/ (installed with --no-deps into /tmp/site). On 2026-11-26 an H200 image with torch
# 2.11 (Python 3.12) lacked pydantic, pydantic_core, annotated_types, typing_inspection, diffusers
# 0.42.1, gsplat 1.5.3 and importlib_metadata (and OpenEXR, for the tests that read EXR); fetch them for it with
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl NAME==VERSION
# (the tests that need OpenEXR, pycolmap or Prefect are not collected there: the first is reported
# as a collection error, the GPU tests run regardless).
#
#   OUT=/tmp/gpu bash bench/gpu_checks.sh
#   OUT=/tmp/gpu GPU_CLOSEUP=.gpu PREPARED_ONLY=1 bash bench/gpu_checks.sh          # the close-up alone
#   OUT=/tmp/gpu P2S=.gpu-p2s PAIRS=.gpu-pairs PREPARED_ONLY=1 bash bench/gpu_checks.sh   # two prepared runs
#   OUT=/tmp/gpu ZOOM_CURVE=.gpu-carry/zoom.tar.xz PREPARED_ONLY=1 bash bench/gpu_checks.sh   # a packed folder
#   # issue 28's production budget to its schedule's end (5 000 steps at ~73 ms on an H200 before the
#   # performers' initial motion, which costs ~1.25x a step on a CPU, and the faces' 2-px Gaussians, ~0.9x
#   # there; 5 scored points; ~480 s with the
#   # build, in one 15-minute lease; prepared with --steps 5000 from a `volcap demo` store of the preset):
#   OUT=/tmp/gpu ZOOM_CURVE=.gpu-carry/zoom.tar.xz ZOOM_ARGS="--evals 5" ZOOM_BUDGET_S=450 ZOOM_S=480 \
#       PREPARED_ONLY=1 bash bench/gpu_checks.sh
set -u
OUT=${OUT:-/tmp/volcap-gpu}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
# Installed once per machine. On 2026-11-28 a second call on the warm machine, which reinstalled the
# wheels, built gsplat's extension again (98 s): the install rewrites gsplat's sources, and its JIT
# build (ninja) goes by file times (the likely cause; not checked further).
if compgen -G ".whl/*.whl" > /dev/null; then
    wheels=$(ls .whl/*.whl | sort | md5sum | cut -c1-32)
    if [ "$(cat /tmp/site/.wheels 2>/dev/null)" != "$wheels" ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
            || { echo "wheel install failed"; exit 1; }
        echo "$wheels" > /tmp/site/.wheels
    fi
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch, diffusers; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'diffusers', diffusers.__version__)"

# gsplat's CUDA extension, built before any prepared run is timed
build_gsplat() {
    export MAX_JOBS=${MAX_JOBS:-14} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
    timeout "${GSPLAT_BUILD_S:-400}" python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat extension:', _C, f'{time.time() - t:.0f} s')"
}

# A prepared folder travels as itself or, where the working tree would pass the 64 MiB a call carries
# (with the demo preset's zoom points, velocities and footprints .gpu-zoom is 51.0 MiB), as a tar.xz holding it at its
# top (`tar cJf .gpu-carry/zoom.tar.xz .gpu-zoom`, 34.4 MiB; carry .gpu-carry, pass ZOOM_CURVE=.gpu-carry/zoom.tar.xz):
# unpacked here under /tmp/prepared, its folder's path printed.
unpacked() {
    case "$1" in
        *.tar.xz)
            mkdir -p /tmp/prepared && tar xJf "$1" -C /tmp/prepared || { echo "cannot unpack $1" >&2; return 1; }
            echo "/tmp/prepared/$(tar tJf "$1" | head -1 | cut -d/ -f1)" ;;
        *) echo "$1" ;;
    esac
}

# 6. the prepared runs (each stops itself within its budget; the timeout is the backstop)
prepared() {
    if [ -n "${GPU_CLOSEUP:-}" ]; then
        timeout "${CLOSEUP_S:-300}" python3 bench/gpu_closeup.py --run "$(unpacked "$GPU_CLOSEUP")" --out "$OUT" --device cuda \
            2>&1 | tee "$OUT/closeup.log" | tail -40
    fi
    if [ -n "${ZOOM_CURVE:-}" ]; then
        mkdir -p "$OUT/zoom"
        # ZOOM_ARGS: more --run options (e.g. "--evals 5 --mcmc gradient_weight=2")
        timeout "${ZOOM_S:-300}" python3 bench/gpu_zoom_curve.py --run "$(unpacked "$ZOOM_CURVE")" --out "$OUT/zoom" --device cuda \
            --budget-s "${ZOOM_BUDGET_S:-250}" ${ZOOM_ARGS:-} 2>&1 | tee "$OUT/zoom/log" | tail -40
    fi
    if [ -n "${P2S:-}" ]; then
        mkdir -p "$OUT/p2s"
        timeout "${P2S_S:-230}" python3 bench/gpu_zoom_curve.py --run "$(unpacked "$P2S")" --out "$OUT/p2s" --device cuda \
            --budget-s "${P2S_BUDGET_S:-200}" --evals "${P2S_EVALS:-8}" 2>&1 | tee "$OUT/p2s/log" | tail -40
    fi
    if [ -n "${PAIRS:-}" ]; then
        mkdir -p "$OUT/pairs"
        timeout "${PAIRS_S:-180}" python3 bench/gpu_facerig_pairs.py --run "$(unpacked "$PAIRS")" --out "$OUT/pairs" --device cuda \
            --budget-s "${PAIRS_BUDGET_S:-150}" 2>&1 | tee "$OUT/pairs/log" | tail -40
    fi
}
if [ -n "${PREPARED_ONLY:-}" ]; then
    build_gsplat
    prepared
    exit
fi

# 1. gsplat's extension, in the background (CPU-bound: it overlaps the GPU-bound enhancer bench)
build_gsplat > "$OUT/gsplat_build.log" 2>&1 &
build=$!

# 2. the enhancer at full size
timeout "${ENHANCE_S:-330}" python3 bench/bench_enhance_gpu.py --json "$OUT/enhance_gpu.json" 2>&1 | tee "$OUT/enhance_gpu.log"

wait $build
tail -3 "$OUT/gsplat_build.log"

# 3. the CUDA tests
timeout "${TESTS_S:-200}" python3 -m pytest -q -p no:cacheprovider -m gpu -rA --continue-on-collection-errors tests/splat tests/enhance 2>&1 \
    | tee "$OUT/gpu_tests.log" | tail -40

# 4. the rasterizer on CUDA (the torch back-end only at the smaller size: its pairs are tensors)
timeout "${RASTER_S:-120}" python3 bench/bench_rasterizer.py --device cuda --backends gsplat torch \
    --gaussians 100000 --sizes 256 1024 --tile-sizes 16 --json "$OUT/raster_small.json" 2>&1 | tee "$OUT/raster.log"
timeout "${RASTER_S:-120}" python3 bench/bench_rasterizer.py --device cuda --backends gsplat \
    --gaussians 1000000 --sizes 1024 2048 --json "$OUT/raster_large.json" 2>&1 | tee -a "$OUT/raster.log"

# 5. Poly4DGS's step against a static 3DGS's, through gsplat (the paper: "no visible overhead")
timeout "${STEP_S:-150}" python3 bench/bench_poly4dgs_step.py --device cuda --frames 1 8 \
    --json "$OUT/poly4dgs_step.json" 2>&1 | tee "$OUT/poly4dgs_step.log"
prepared
echo done
