#!/usr/bin/env bash
# The GPU check of the locality model (issue 27), at most ~8 minutes on a machine with an NVIDIA
# GPU: the engine's exactness tests on CUDA, the traversal benchmark on paper_mix's recorded rays
# with --backend cuda, and the model's prediction for that GPU's preset on the same rays, printed
# side by side (measured layer_sorted x per_ray against the model's per_ray / sorted traffic).
# Needs .venv (scripts/bootstrap.sh). BACKEND=llvm runs the same steps on the CPU (a dry run);
# PRESET names the GPU's preset (default h200).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
BACKEND=${BACKEND:-cuda}
PRESET=${PRESET:-h200}
OUT=${OUT:-out/gpu_check}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi (BACKEND=$BACKEND)"
lscpu | grep -m1 'Model name' || true
# 1. Exactness on the device: every mode against per_ray and Embree (about a minute).
LAYERBVH_BACKEND=$BACKEND timeout 240 $PY -m pytest -q -p no:xdist -x tests/test_engine_hits.py tests/test_engine_exact.py
# 2. Rays of a real scene (recorded on the CPU: the same rays for both sides of the check).
timeout 120 $PY scripts/record_rays.py scenes/paper_mix.xml --out "$OUT/rays.npz" --res 512 512 --spp 1
# 3. Measured: per_ray and layer_sorted on the device, median of 5 after a warm-up.
timeout 120 $PY scripts/bench_traversal.py --rays-file "$OUT/rays.npz" --kinds camera,first_bounce_diffuse,diffuse \
    --heights 8 --runs 5 --backend "$BACKEND" --procedural-tris 0 --json "$OUT/bench.json"
# 4. Modelled for the GPU's preset, printed beside the measurement.
timeout 120 $PY -m layerbvh_mitsuba.bench.gpu_check --rays "$OUT/rays.npz" --bench "$OUT/bench.json" \
    --preset "$PRESET" --json "$OUT/gpu_check.json"
