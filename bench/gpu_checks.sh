#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one run (a lent GPU is a few minutes of machine time):
#   1. gsplat's CUDA extension builds (JIT, sm_90 only) while
#   2. bench/bench_enhance_gpu.py times the full-size enhancer (FLUX.1-dev architecture, random
#      weights): denoising steps at 1024² and 4K, VAE, a whole 4K frame, bf16 LoRA training;
#   3. the CUDA tests (pytest -m gpu): gsplat against the torch back-end (forward, gradients,
#      rendered flow), Poly4DGS training through gsplat, RAFT with torchvision;
#   4. bench/bench_rasterizer.py on CUDA, gsplat beside the torch back-end;
#   5. bench/bench_poly4dgs_step.py: a Poly4DGS training step against a static 3DGS of the same count;
#   6. with GPU_CLOSEUP=DIR (a folder from `python bench/gpu_closeup.py --prepare DIR`, its DIR/gpu
#      carried): the demo's close-up rendered through gsplat and enhanced on CUDA, timed per frame
#      (bench/gpu_closeup.py --run; its files come back to be scored with --score). CLOSEUP_ONLY=1
#      runs it alone (after the gsplat build): $OUT then holds gpu.txt, closeup.log, timings.json
#      and the parts closeup_exrs.tar.NN.
#   7. with ZOOM_CURVE=DIR (a folder from `python bench/gpu_zoom_curve.py --prepare DIR`, carried): the
#      demo segment at a production-size budget trained through gsplat, detail and PSNR per camera
#      role against time (bench/gpu_zoom_curve.py --run, stopped within ZOOM_BUDGET_S, default 250 s;
#      read it back with --report). ZOOM_ONLY=1 runs it alone (after the gsplat build): $OUT then
#      holds gpu.txt, zoom.log, curve.json and sheet.npz.
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
#   OUT=/tmp/gpu GPU_CLOSEUP=.gpu CLOSEUP_ONLY=1 bash bench/gpu_checks.sh   # the close-up alone
#   OUT=/tmp/gpu ZOOM_CURVE=.gpu-zoom ZOOM_ONLY=1 bash bench/gpu_checks.sh   # the zoom curve alone
set -u
OUT=${OUT:-/tmp/volcap-gpu}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || { echo "wheel install failed"; exit 1; }
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch, diffusers; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'diffusers', diffusers.__version__)"

# 6. the demo's close-up (issue 27): the extension built first, so no frame's time holds the build
closeup() {
    export MAX_JOBS=${MAX_JOBS:-14} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
    {
        timeout "${GSPLAT_BUILD_S:-400}" python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat extension:', _C, f'{time.time() - t:.0f} s')"
        timeout "${CLOSEUP_S:-300}" python3 bench/gpu_closeup.py --run "$GPU_CLOSEUP" --out "$OUT" --device cuda
    } 2>&1 | tee "$OUT/closeup.log" | tail -40
}
if [ -n "${GPU_CLOSEUP:-}" ] && [ -n "${CLOSEUP_ONLY:-}" ]; then
    closeup
    exit
fi

# 7. the demo segment at a production-size budget (issue 28): the extension built first, so no step's
# time holds the build; the run stops itself within ZOOM_BUDGET_S, the timeout is the backstop
zoom() {
    export MAX_JOBS=${MAX_JOBS:-14} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
    {
        timeout "${GSPLAT_BUILD_S:-400}" python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat extension:', _C, f'{time.time() - t:.0f} s')"
        timeout "${ZOOM_S:-300}" python3 bench/gpu_zoom_curve.py --run "$ZOOM_CURVE" --out "$OUT" --device cuda \
            --budget-s "${ZOOM_BUDGET_S:-250}"
    } 2>&1 | tee "$OUT/zoom.log" | tail -40
}
if [ -n "${ZOOM_CURVE:-}" ] && [ -n "${ZOOM_ONLY:-}" ]; then
    zoom
    exit
fi

# 1. gsplat's extension, in the background (CPU-bound: it overlaps the GPU-bound enhancer bench)
(
    export MAX_JOBS=${MAX_JOBS:-14} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
    timeout "${GSPLAT_BUILD_S:-400}" python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat extension:', _C, f'{time.time() - t:.0f} s')"
) > "$OUT/gsplat_build.log" 2>&1 &
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
if [ -n "${GPU_CLOSEUP:-}" ]; then
    closeup
fi
if [ -n "${ZOOM_CURVE:-}" ]; then
    zoom
fi
echo done
