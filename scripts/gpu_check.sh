#!/usr/bin/env bash
# The GPU check of the locality model (issue 27): measured layer_sorted x per_ray on a GPU beside
# what the model predicts for its preset, on paper_mix's recorded rays.
#
# Here (CPU, .venv from scripts/bootstrap.sh): record the rays, replay them through the model for
# the GPU's preset, and write out/gpu_check/{rays.npz,model.json} (about a minute). Then, on the
# device (this workplace's `device` tool: its image has numpy and numba but not drjit, and no
# network; carry the drjit wheel and the folder):
#   echo /.whl/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 -d .whl drjit==1.5.0          # 5 MB
#   run(command="python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl &&
#       PYTHONPATH=/tmp/site python3 scripts/gpu_check_device.py out/gpu_check --backend cuda",
#       carry=[".whl", "out/gpu_check"], timeout_s=480)
# The device half needs only the engine; it prints, per (K, H) and kind, both modes' Mrays/s, the
# measured ratio, the model's, and how many hits differ from the LLVM replay (CUDA's rcp is
# approximate), then the sphere soup's rows; `--kernels 16000000` lists each launch's GPU time.
# Copy what it wrote (measured_cuda.json, the --kernels output as kernels_*.log) with model.json into
# docs/bench/gpu_<name>/ and run `python -m layerbvh_mitsuba.tools.bench.gpu_report` for
# BENCHMARKS.md's GPU section. On the H200 the device half took under a minute.
# BACKEND=llvm runs the device half here too (a dry run of the whole check on the CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
PRESET=${PRESET:-h200}
OUT=${OUT:-out/gpu_check}
mkdir -p "$OUT"
lscpu | grep -m1 'Model name' || true
timeout 300 $PY -m layerbvh_mitsuba.tools.bench.gpu_check --scene scenes/paper_mix.xml --out "$OUT" --preset "$PRESET"
du -sh "$OUT"
if [ -n "${BACKEND:-}" ]; then
  timeout 480 $PY scripts/gpu_check_device.py "$OUT" --backend "$BACKEND"
fi
