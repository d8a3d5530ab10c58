#!/usr/bin/env bash
# Reproduce BENCHMARKS.md: record ray sets, run the traversal and scaling benchmarks, the
# error-vs-time run, and generate the report (about 40 minutes on 2 cores). Run after
# scripts/bootstrap.sh (or scripts/test.sh) has created .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
mkdir -p out/rays
$PY scripts/gen_stress.py spheres --triangles 1000000 --out out/stress_spheres_1m --force
$PY scripts/record_rays.py scenes/paper_mix.xml --out out/rays/paper_mix.npz --res 512 512 --spp 4
$PY scripts/record_rays.py out/stress_spheres_1m/scene.xml --out out/rays/stress_spheres_1m.npz --res 512 512 --spp 4
$PY scripts/bench_traversal.py --rays-file out/rays/paper_mix.npz --rays-file out/rays/stress_spheres_1m.npz \
    --heights 4,8,12 --runs 5 --json docs/bench/bench.json
$PY scripts/bench_scaling.py --heights 4,8 --json docs/bench/scaling.json
.venv/bin/layerbvh converge scenes/paper_mix.xml --budget 40 --res 128 128 --ref-spp 4096 \
    --configs stock,per_ray,layer_sorted:8,auto --out docs/converge/paper_mix
$PY scripts/report.py --bench docs/bench/bench.json --scaling docs/bench/scaling.json \
    --converge docs/converge/paper_mix --readme
